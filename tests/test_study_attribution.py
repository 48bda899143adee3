"""tools/studies/study_attribution.py: the scene files it derives from a render cache and its table arithmetic.

A tiny cell is made the way make_dataset makes one (the blurry frame through blur_frames, the sharp one through
the same ISP without noise) from random linear sub-frames, beside a render cache of those sub-frames; the derived
files are checked against a second implementation (the simulator's numpy sRGB functions, not the trainer's torch
ones) and against the sub-frames themselves.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
for sub in ("tools", "tools/bench", "tools/studies"):
    sys.path.insert(0, str(ROOT / sub))

import study_attribution as sa  # noqa: E402

from ev3dgs import schema  # noqa: E402
from ev3dgs.events import Events  # noqa: E402
from ev3dgs.geometry import intrinsics, look_at  # noqa: E402
from ev3dgs.sim.blur import blur_frames  # noqa: E402
from ev3dgs.sim.dataset import _to_srgb  # noqa: E402
from ev3dgs.sim.isp import linear_to_srgb, srgb_to_linear  # noqa: E402
from ev3dgs.sim.scenes import load_scene  # noqa: E402

# the tiny cells have no events (the derived files do not need them)
pytestmark = pytest.mark.filterwarnings("ignore::ev3dgs.errors.SchemaWarning")
S = sa.SUBFRAMES
W, H, VIEWS = 10, 8, 3


def make_cell(tmp_path: Path, scene: str, seed: int = 0,
              highlight: bool = False) -> tuple[Path, list[np.ndarray], list[np.ndarray]]:
    spec = load_scene(scene)
    rng = np.random.default_rng(seed)
    cell = tmp_path / "cell" / "scene.h5"
    cache = cell.parent / ".scene.cache-0123"
    cache.mkdir(parents=True)
    frames_all, poses_all = [], []
    imgs, sharp, sharp_poses, poses, pose_t, exposure = [], [], [], [], [], []
    for v in range(VIEWS):
        frames = rng.uniform(0.02, 0.9, (S, H, W, 3)).astype(np.float32)
        if highlight and v == 0:      # a 3x3 highlight at 5x full scale for 4 of the 17 sub-frames of view 0
            frames[3:7, 2:5, 4:7] = 5.0
        eye = np.array([3.0 * np.cos(v), 3.0 * np.sin(v), 0.5])
        ps = np.stack([look_at(eye + [0.01 * k, 0, 0], [0, 0, 0]) for k in range(S)])
        np.savez(cache / f"view_{v:04d}.npz", frames=frames, poses=ps)
        t = v * 150_000 + np.linspace(0, 100_000, S).astype(np.int64)
        imgs.append(blur_frames(frames, spec.sensor.isp, spec.sensor.sensor_noise, seed=v))
        sharp.append(_to_srgb(frames[S // 2], spec))
        sharp_poses.append(ps[S // 2])
        poses.append(ps)
        pose_t.append(t)
        exposure.append((t[0], t[-1]))
        frames_all.append(frames)
        poses_all.append(ps)
    sc = schema.Scene(
        name=scene, source="blender", camera=schema.Camera(W, H, K=intrinsics(W, H, 50), background=(0, 0, 0)),
        events=Events.concatenate([]), sensor=schema.EventSensor(), bounds=np.array([[-1.0] * 3, [1.0] * 3]),
        train=schema.Train(images=np.stack(imgs), exposure=np.array(exposure), poses=np.stack(poses),
                           pose_t=np.stack(pose_t), sharp=np.stack(sharp), sharp_poses=np.stack(sharp_poses),
                           transfer="srgb"),
        test=schema.Test(images=np.stack(sharp[:1]), poses=np.stack(sharp_poses[:1])))
    schema.write(sc, cell)
    return cell, frames_all, poses_all


def test_info_oracle_holds_every_sub_frame_at_its_pose(tmp_path):
    cell, frames, poses = make_cell(tmp_path, "materials")
    paths = sa.derived_scenes("materials", cell, tmp_path / "derived")
    assert set(paths) == {"info", "ideal"}          # materials has no frame noise: no clean/noisy files
    info = schema.read(paths["info"])
    spec = load_scene("materials")
    assert len(info.train) == VIEWS * S
    for v in range(VIEWS):
        for k in (0, S // 2, S - 1):
            np.testing.assert_array_equal(np.asarray(info.train.sharp[v * S + k]), _to_srgb(frames[v][k], spec))
            np.testing.assert_allclose(info.train.sharp_poses[v * S + k], poses[v][k])


def test_ideal_blur_is_the_trainers_blur_model_of_the_sharp_sub_frames(tmp_path):
    cell, frames, _ = make_cell(tmp_path, "materials")
    paths = sa.derived_scenes("materials", cell, tmp_path / "derived")
    ideal = np.asarray(schema.read(paths["ideal"]).train.images).astype(int)
    spec = load_scene("materials")
    for v in range(VIEWS):
        srgb = np.stack([_to_srgb(f, spec) for f in frames[v]]).astype(np.float64) / 255.0
        want = linear_to_srgb(srgb_to_linear(srgb).mean(axis=0)) * 255.0   # numpy path, not the trainer's torch one
        # the two implementations agree to float rounding (~1e-12 DN); the stored frame is rounded once
        assert np.abs(ideal[v] - want).max() <= 0.5 + 1e-6
    # and it is not simply the scene's blurry frame (the ISP is not the sRGB transfer the trainer models)
    real = np.asarray(schema.read(cell).train.images).astype(int)
    assert np.abs(real - ideal).max() > 0


def test_noisy_scene_adds_clean_blur_and_noisy_sharp_frames(tmp_path):
    cell, frames, _ = make_cell(tmp_path, "lowlight")
    paths = sa.derived_scenes("lowlight", cell, tmp_path / "derived")
    assert set(paths) == {"info", "ideal", "clean", "noisy"}
    spec = load_scene("lowlight")
    sc, clean, noisy = (schema.read(p).train for p in (cell, paths["clean"], paths["noisy"]))
    for v in range(VIEWS):
        np.testing.assert_array_equal(np.asarray(clean.images[v]), blur_frames(frames[v], spec.sensor.isp, None))
    # the noisy oracle frames: the clean sharp frames plus noise (ISO 1600: several DN at these levels)
    a, b = np.asarray(sc.sharp).astype(float), np.asarray(noisy.sharp).astype(float)
    assert (b - a).std() > 1.0
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9
    np.testing.assert_array_equal(np.asarray(noisy.images), np.asarray(sc.images))  # only the sharp frames change


def test_a_render_cache_of_other_frames_is_refused(tmp_path):
    cell, frames, poses = make_cell(tmp_path, "materials")
    cache = next(cell.parent.glob(".scene.cache-*"))
    np.savez(cache / "view_0001.npz", frames=frames[2], poses=poses[1])   # another view's sub-frames
    with pytest.raises(SystemExit, match="view 1"):
        sa.derived_scenes("materials", cell, tmp_path / "derived")


def test_blur_model_residual_sits_where_a_sub_frame_exceeds_full_scale(tmp_path):
    cell, _, _ = make_cell(tmp_path, "materials", highlight=True)
    paths = sa.derived_scenes("materials", cell, tmp_path / "derived")
    r = sa.blur_model_residual(cell, paths["ideal"])
    assert r["pixels_above_full_scale"] == pytest.approx(9 / (VIEWS * H * W))
    # there the blurry frame integrates 4/17 of 5x full scale (+~1 linear, saturating), the model of clipped
    # sub-frames at most 4/17 of 1: tens of DN; everywhere else the two differ by the sub-frames' 8-bit
    # rounding and the ISP's gamut clip, a few DN at most
    assert r["share_above_full_scale"] > 0.9
    assert r["share_saturated"] > 0.5
    assert 10 < r["psnr_db"] < 60


def test_attribution_pairs_seeds():
    summary = {"oracle": {"blur_view": [30.0, 31.0], "novel_view": [28.0, 28.5], "seeds": [0, 1]},
               "info-oracle": {"blur_view": [32.0, 32.5, 40.0], "novel_view": [29.0, 29.0, 40.0],
                               "seeds": [0, 1, 2]}}
    rows = sa.attribution(summary)
    assert len(rows) == 1 and rows[0]["without"] == "info-oracle" and rows[0]["with"] == "oracle"
    assert rows[0]["blur_view"] == [1.75, 1.5, 2.0, 2]      # seed 2 has no oracle run: not paired
    assert rows[0]["novel_view"] == [0.75, 0.5, 1.0, 2]


def test_run_one_keys_its_cache_on_the_file_scored_on(tmp_path):
    """A model trained on one file and scored on another (the study's derived scenes) is cached with that file:
    the same call returns the cached scores, another scoring file scores again without retraining."""
    import shutil

    from bench_fidelity import run_one

    from ev3dgs.blob_scene import blob_scene

    train = blob_scene(tmp_path / "train.h5", 24, 18, views=3, subframes=3, n=60, backend="reference")
    other = tmp_path / "other.h5"
    shutil.copy(train, other)
    out = tmp_path / "run"
    kw = dict(overrides=dict(oracle=True, sh_degree=0, backend="reference"), seed=0, iterations=3, init_points=50,
              out=out)
    first = run_one(train, eval_scene=other, **kw)
    assert first["scored_on"] == str(other) and first["scene"] == str(other.resolve())
    model = (out / "model.pt").stat().st_mtime_ns
    assert run_one(train, eval_scene=other, **kw) == first                 # cached
    again = run_one(train, **kw)                                           # scored on the training file
    assert "scored_on" not in again and again["scene"] == str(train.resolve())
    assert (out / "model.pt").stat().st_mtime_ns == model                  # scored again, not trained again
    assert again["blur_view"]["psnr"] == first["blur_view"]["psnr"]        # the same frames in both files


def test_bench_merge_adds_earlier_runs_once_and_refuses_a_foreign_file(tmp_path):
    """bench_fidelity --merge: runs of earlier summaries join, first file first, never twice for one
    (scene, variant, seed), never over a run of this invocation; a file without runs is a one-line usage error."""
    import argparse
    import json

    from bench_fidelity import merged_runs

    def run(scene, variant, seed, psnr):
        return {"scene": scene, "variant": variant, "seed": seed, "metrics": {"blur_view": {"psnr": psnr}}}

    a, b, bad = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "bad.json"
    a.write_text(json.dumps({"runs": [run("lego", "oracle", 0, 1.0), run("lego", "blur+event", 0, 2.0)]}))
    b.write_text(json.dumps({"runs": [run("lego", "oracle", 0, 9.0), run("ficus", "oracle", 1, 3.0)]}))
    bad.write_text(json.dumps({"summary": {}}))
    ap = argparse.ArgumentParser()
    got = merged_runs([a, b], {("lego", "blur+event", 0)}, ap)
    assert [(r["scene"], r["variant"], r["seed"], r["metrics"]["blur_view"]["psnr"]) for r in got] == \
        [("lego", "oracle", 0, 1.0), ("ficus", "oracle", 1, 3.0)]
    with pytest.raises(SystemExit):
        merged_runs([bad], set(), ap)


def test_bench_sh_interval_fills_only_variants_without_their_own_and_keeps_its_own_run_folders(tmp_path):
    """bench_fidelity --sh-interval N: every variant that does not set the SH schedule trains with N, one that
    does keeps its own; the runs go to folders of their own, so the default's cached runs are not retrained."""
    from bench_fidelity import VARIANTS, make_jobs

    variants = {k: VARIANTS[k] for k in ("blur+event", "oracle-sh")}
    paths = {"lego": tmp_path / "lego_96x72.h5"}
    plain = make_jobs(["lego"], paths, variants, 2, tmp_path, None, iterations=10)
    fixed = make_jobs(["lego"], paths, variants, 2, tmp_path, dict(sh_interval=1000), iterations=10)
    assert [(j["seed"], j["variant"]) for j in plain] == [(0, "blur+event"), (0, "oracle-sh"), (1, "blur+event"),
                                                          (1, "oracle-sh")]
    assert [j["overrides"].get("sh_interval") for j in plain] == [None, 33, None, 33]
    assert [j["overrides"].get("sh_interval") for j in fixed] == [1000, 33, 1000, 33]
    assert all(j["iterations"] == 10 for j in plain + fixed)
    assert not {j["out"] for j in plain} & {j["out"] for j in fixed}
    assert fixed[0]["out"] == str(tmp_path / "runs" / "lego_96x72" / "blur_event_sh1000_s0")
    # the studies keep the schedule and the event floor their tables were trained with, unless a variant sets
    # its own
    from bench_fidelity import study_overrides
    from study_event_term import ROBUST, VARIANTS as TERM_VARIANTS

    mean = dict(event_floor="mean", event_huber=0.0, densify_from="all")
    assert study_overrides(VARIANTS["blur+event"]) == {"sh_interval": 1000, **mean}
    assert study_overrides(VARIANTS["oracle-sh"]) == {"oracle": True, "sh_interval": 33, **mean}
    robust = study_overrides(TERM_VARIANTS["blur+event-sh-robust"])
    assert {k: robust[k] for k in ROBUST} == ROBUST and robust["sh_interval"] == 33


def test_event_term_plot_draws_every_variant_or_the_ones_asked_for(tmp_path):
    """study_event_term.plot: a variant without a fixed style (here a sub-pose variant) gets one and is
    drawn; --plot-variants restricts the event variants, not the sensor-free lines."""
    import study_event_term as se

    summary = {"sensor_free": {"oracle": {"blur_view": [31.0, 0.0, 2], "novel_view": [28.0, 0.0, 2]}},
               "t0.05_m0.1": {"blur+event": {"blur_view": [27.0, 0.1, 2], "novel_view": [26.0, 0.1, 2]},
                              "blur+event-px2": {"blur_view": [28.0, 0.1, 2], "novel_view": [26.5, 0.1, 2]}},
               "t0.1_m0.1": {"blur+event": {"blur_view": [27.1, 0.1, 2], "novel_view": [26.1, 0.1, 2]}}}
    png = tmp_path / "p.png"
    labels = se.plot(summary, [0.05, 0.1], [0.1], png)
    assert labels == ["oracle", "blur+event, mismatch 0.1", "blur+event-px2, mismatch 0.1"]
    assert png.stat().st_size > 1000
    assert se.plot(summary, [0.05, 0.1], [0.1], png, ["blur+event-px2", "absent"]) == [
        "oracle", "blur+event-px2, mismatch 0.1"]


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.2, 5.0))
def test_response_study_contrast_curve_and_its_inverse(x, c):
    import study_response as sr

    # S(S^-1(y)) = y, the curve is monotone and fixes 0, 1/2 and 1 (closed form: x/(1-x) -> (x/(1-x))^c)
    y = sr.contrast_curve(x, c)
    assert abs(sr.contrast_curve(sr.inverse_contrast_curve(y, c), c) - y) <= 1e-12
    assert sr.contrast_curve(0.0, c) == 0.0 and sr.contrast_curve(1.0, c) == 1.0
    assert abs(sr.contrast_curve(0.5, c) - 0.5) <= 1e-15
    assert sr.contrast_curve(min(x + 1e-3, 1.0), c) >= y


def test_response_study_tone_scene_curves_every_frame_and_keeps_the_rest(tmp_path):
    import study_response as sr

    from dataclasses import replace

    cell, _, _ = make_cell(tmp_path, "ficus")
    sc = schema.read(cell)
    schema.write(replace(sc, camera=replace(sc.camera, background=(0.3, 0.5, 0.9))), cell)
    out = sr.tone_scene(cell, 1.5, tmp_path / "derived" / "tone.h5")
    a, b = schema.read(cell), schema.read(out)
    want = lambda img: np.clip(np.rint(sr.contrast_curve(np.asarray(img) / 255.0, 1.5) * 255), 0, 255)  # noqa: E731
    for got, src in ((b.train.images, a.train.images), (b.train.sharp, a.train.sharp),
                     (b.test.images, a.test.images)):
        assert np.array_equal(np.asarray(got), want(src))
    assert np.allclose(b.camera.background, sr.contrast_curve(np.asarray(a.camera.background), 1.5), rtol=0,
                       atol=1e-15)
    assert np.array_equal(b.train.poses, a.train.poses) and len(b.events) == len(a.events)
    assert b.train.transfer == "srgb"       # the file still declares sRGB: the curve is the camera's secret
    mtime = out.stat().st_mtime_ns
    assert sr.tone_scene(cell, 1.5, out) == out and out.stat().st_mtime_ns == mtime   # made once


def test_band_split_of_white_noise_follows_the_low_pass_kernels_energy():
    """An error of white noise (variance s²) leaves s²·Σk² in the low-pass part and s²·Σ(δ − k)² =
    s²·(1 − 2k(0) + Σk²) in the rest, with the 2-D Gaussian kernel's Σk² = κ = 1 / (4πσ²) and centre
    k(0) = 1 / (2πσ²) = 2κ: s²·κ and s²·(1 − 3κ) (continuous forms; the sampled kernel differs by far less
    than the tolerance at σ = 1.5). Tolerances: the low-pass noise is correlated over about 4πσ² ≈ 28 px,
    so 400 x 400 x 3 samples are worth ~17 000 independent ones, a relative spread of sqrt(2 / 17 000) ≈ 1.1 %;
    the reflected border (3 % of the pixels within 2σ of it) adds up to 3 %: 10 % on the low part, 2 % on the
    high part (its samples are nearly independent). The truth is white noise too (variance t²), so the
    renders' fine detail is (t² + s²)(1 − 3κ) against t²(1 − 3κ): a ratio of 1 + s²/t²."""
    rng = np.random.default_rng(7)
    s, t = 0.05, 0.1
    truth = rng.normal(0.5, t, (1, 400, 400, 3))
    pred = truth + rng.normal(0.0, s, truth.shape)
    out = sa.band_split(pred, truth, sigma=1.5)
    kappa = 1.0 / (4 * np.pi * 1.5 ** 2)
    assert 10 ** (-out["low_psnr"] / 10) == pytest.approx(s ** 2 * kappa, rel=0.10)
    assert 10 ** (-out["high_psnr"] / 10) == pytest.approx(s ** 2 * (1 - 3 * kappa), rel=0.02)
    assert out["fine_energy_ratio"] == pytest.approx(1 + s ** 2 / t ** 2, rel=0.02)


def test_band_split_puts_a_smooth_error_in_the_low_part_and_a_blurred_render_below_one():
    """A constant offset is all low-pass (the Gaussian keeps a constant; reflected borders too); a render that
    is the truth blurred has less fine detail than the truth."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(3)
    truth = rng.uniform(0, 1, (2, 40, 50, 3))
    out = sa.band_split(truth + 0.01, truth)
    assert out["low_psnr"] == pytest.approx(40.0, abs=1e-6)
    assert out["high_psnr"] > 200        # rounding only
    blurred = np.stack([gaussian_filter(im, (2, 2, 0)) for im in truth])
    assert sa.band_split(blurred, truth)["fine_energy_ratio"] < 0.2


def test_bench_event_norm_fills_only_variants_without_their_own_in_run_folders_of_its_own(tmp_path):
    """bench_fidelity --event-norm count (the docs' event-weight table) and --frame-noise 0 (the lowlight rows
    of the option tables): every variant that does not set its own trains with it; the runs go to folders of
    their own, so the default's cached runs stay."""
    from bench_fidelity import make_jobs

    variants = {"blur+event@4": {"event_weight": 4 / 625}, "own": {"event_norm": "noise"}}
    paths = {"lego": tmp_path / "lego_96x72.h5"}
    plain = make_jobs(["lego"], paths, variants, 1, tmp_path, None, iterations=10)
    count = make_jobs(["lego"], paths, variants, 1, tmp_path, dict(sh_interval=1000, event_norm="count"),
                      iterations=10)
    assert [j["overrides"].get("event_norm") for j in plain] == [None, "noise"]
    assert [j["overrides"] for j in count] == [{"sh_interval": 1000, "event_norm": "count", "event_weight": 4 / 625},
                                              {"sh_interval": 1000, "event_norm": "noise"}]
    assert count[0]["out"] == str(tmp_path / "runs" / "lego_96x72" / "blur_event_w4_sh1000_count_s0")
    assert not {j["out"] for j in plain} & {j["out"] for j in count}
    quiet = make_jobs(["lego"], paths, variants, 1, tmp_path, dict(frame_noise=0.0), iterations=10)
    assert [j["overrides"] for j in quiet] == [{"frame_noise": 0.0, "event_weight": 4 / 625},
                                              {"frame_noise": 0.0, "event_norm": "noise"}]
    assert quiet[0]["out"] == str(tmp_path / "runs" / "lego_96x72" / "blur_event_w4_fn0_s0")
    fixed = make_jobs(["lego"], paths, {"own": {"frame_noise": 5.0}}, 1, tmp_path, dict(frame_noise=0.0))
    assert fixed[0]["overrides"] == {"frame_noise": 5.0}
    # --event-floor mean --event-huber 0 --densify-from all (what the option tables were measured with): the
    # same filling; the blur+event-mean variant sets all three itself
    from bench_fidelity import MEAN_FLOOR, VARIANTS

    opts = dict(event_floor="mean", event_huber=0.0, densify_from="all")
    mean = make_jobs(["lego"], paths, {**variants, "blur+event-mean": VARIANTS["blur+event-mean"]}, 1, tmp_path,
                     opts, iterations=10)
    assert [j["overrides"] for j in mean] == [{**opts, "event_weight": 4 / 625}, {**opts, "event_norm": "noise"},
                                             MEAN_FLOOR]
    assert mean[0]["out"] == str(tmp_path / "runs" / "lego_96x72" / "blur_event_w4_floormean_huber0_densifyall_s0")
    some = make_jobs(["lego"], paths, {"own": {"event_floor": "chi2"}}, 1, tmp_path,
                     dict(event_floor="mean", event_huber=None, densify_from=None))
    assert some[0]["overrides"] == {"event_floor": "chi2"} and some[0]["out"].endswith("own_floormean_s0")
    with pytest.raises(ValueError, match="threads"):   # a setting without a run-folder suffix
        make_jobs(["lego"], paths, variants, 1, tmp_path, dict(threads=2))
