"""The trainer end to end on a small synthetic scene made without Blender."""
import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs import schema
from ev3dgs.cli import main as cli
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.sim.isp import linear_to_srgb, srgb_to_linear
from ev3dgs.splat.model import GaussianModel
from ev3dgs.splat.rasterize import rasterization
from ev3dgs.train.config import TrainConfig, sh_interval_for
from ev3dgs.train.evaluate import evaluate
from ev3dgs.train.export import load_ply
from ev3dgs.train.trainer import Trainer, TrainingError

from cli_exit import exit_code

W, H = 40, 30


def _truth():
    rng = np.random.default_rng(0)
    n = 300
    xyz = rng.uniform(-0.6, 0.6, (n, 3))
    m = GaussianModel.from_points(xyz, rng.integers(30, 255, (n, 3)).astype(np.uint8), sh_degree=0,
                                  init_opacity=0.8)
    return m


def _draw(model, c2w, K):
    vm = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
    with torch.no_grad():
        img, _, _ = rasterization(model.means, model.quats_normalised, model.scales, model.opacities, model.sh,
                                  vm, K, W, H, sh_degree=0, background=torch.ones(3), backend="cpu")
    return img.clamp(0, 1).numpy()


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    """6 shaky views (5 sub-frames over 100 ms) + 2 test views of a Gaussian blob cloud; events from the
    simulator on the linear sub-frames, blurry frames averaged in linear light."""
    truth = _truth()
    K = intrinsics(W, H, 50)
    Kt = torch.as_tensor(K, dtype=torch.float32)
    rng = np.random.default_rng(1)
    views, S = 6, 5
    imgs, sharp, sharp_poses, poses, pose_t, exposure, linear, times = [], [], [], [], [], [], [], []
    for v in range(views):
        az = 2 * np.pi * v / views
        eye = 3.0 * np.array([np.cos(az), np.sin(az), 0.5])
        start = v * 150_000
        t = start + np.linspace(0, 100_000, S).astype(np.int64)
        drift = rng.normal(0, 0.3, 3)
        ps = [look_at(eye + drift * (k / (S - 1) - 0.5), [0, 0, 0]) for k in range(S)]
        frames = np.stack([_draw(truth, p, Kt) for p in ps])
        lin = srgb_to_linear(frames)
        linear.append(lin)
        times.append(t)
        imgs.append((linear_to_srgb(lin.mean(0)) * 255 + 0.5).astype(np.uint8))
        sharp.append((frames[S // 2] * 255 + 0.5).astype(np.uint8))
        sharp_poses.append(ps[S // 2])
        poses.append(np.stack(ps))
        pose_t.append(t)
        exposure.append((t[0], t[-1]))
    parts = []
    from ev3dgs.sim import DVSSimulator

    sim = DVSSimulator(H, W)
    for lin, t in zip(linear, times):
        sim.restart()
        parts.append(sim.feed(lin.astype(np.float32), t))
    from ev3dgs.events import Events

    ev = Events.concatenate(parts)
    test_poses = [look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.4]), [0, 0, 0]) for a in (0.5, 2.5)]
    sc = schema.Scene(
        name="blobs", source="test", camera=schema.Camera(W, H, K=K, background=(1.0, 1.0, 1.0)), events=ev,
        sensor=schema.EventSensor(), bounds=np.array([[-0.7] * 3, [0.7] * 3]),
        train=schema.Train(images=np.stack(imgs), exposure=np.array(exposure), poses=np.stack(poses),
                           pose_t=np.stack(pose_t), sharp=np.stack(sharp), sharp_poses=np.stack(sharp_poses)),
        test=schema.Test(images=np.stack([(_draw(truth, p, Kt) * 255 + 0.5).astype(np.uint8) for p in test_poses]),
                         poses=np.stack(test_poses)))
    path = tmp_path_factory.mktemp("scene") / "blobs.h5"
    schema.write(sc, path)
    assert len(ev) > 100
    return str(path)


def cfg(scene, **kw):
    base = dict(scene=scene, iterations=60, init_points=800, checkpoint_every=20, threads=1, seed=3, sh_degree=1,
                sh_interval=20)
    base.update(kw)
    return TrainConfig(**base)


def test_training_improves_the_sharp_views(scene_path, tmp_path):
    tr = Trainer(cfg(scene_path, iterations=150), tmp_path / "run", quiet=True)
    tr.save_model()
    before = evaluate(tmp_path / "run", write_images=False)
    tr.fit()
    after = evaluate(tmp_path / "run")
    assert after["train_sharp"]["psnr"] > before["train_sharp"]["psnr"] + 3
    assert after["test"]["psnr"] > before["test"]["psnr"] + 2
    assert after["lpips"] is None and "lpips" in after["lpips_reason"].lower()
    assert (tmp_path / "run" / "training.png").stat().st_size > 1000
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert len(log) == 150 and all(np.isfinite(r["loss"]) for r in log) and log[-1]["event"] > 0


@pytest.mark.parametrize("extra", [{}, {"threshold_map": True}, {"hdr": True},
                                   {"edi_prior": 0.05, "edi_anneal": 1.0}, {"subposes": 9, "subpose_px": 0.5},
                                   {"learn_response": True, "hdr": True}, {"frame_noise": 80.0}])
def test_resume_matches_an_uninterrupted_run(scene_path, tmp_path, extra):
    class Stop(Exception):
        pass

    def stop_at_40(trainer, rec):
        if trainer.step == 40:
            raise Stop

    full = Trainer(cfg(scene_path, **extra), tmp_path / "a", quiet=True)
    full.fit()
    part = Trainer(cfg(scene_path, **extra), tmp_path / "b", quiet=True)
    with pytest.raises(Stop):
        part.fit(on_step=stop_at_40)
    resumed = Trainer(cfg(scene_path, **extra), tmp_path / "b", quiet=True)
    resumed.fit(resume=True)
    for name, p in full.model.params.items():
        assert torch.equal(p, resumed.model.params[name]), name
    assert resumed.step == full.step == 60
    if "threshold_map" in extra:
        assert torch.equal(full.term("threshold_map").map.multiplier, resumed.term("threshold_map").map.multiplier)
        saved = torch.load(tmp_path / "a" / "model.pt", weights_only=False)["threshold_map"]
        assert saved.shape == (2, H, W) and torch.equal(saved, full.term("threshold_map").map.multiplier)
        assert not torch.equal(saved, torch.ones_like(saved))    # the events moved it
    if "learn_response" in extra:
        assert torch.equal(full.term("response").curve.logits, resumed.term("response").curve.logits)
        learned = full.term("response").curve.logits
        assert not torch.equal(learned, torch.zeros_like(learned))  # it was learned
        table = json.loads((tmp_path / "a" / "response.json").read_text())
        assert table["decoded_as"] == [float(v) for v in full.term("response").curve.values().detach().double()]
    if "frame_noise" in extra:
        assert resumed.term("events").blur_mse == full.term("events").blur_mse is not None


def test_frame_noise_weighs_the_events_up_as_the_blur_error_comes_down_to_the_noise(scene_path, tmp_path):
    """--frame-noise 0 leaves the blur weight at 1, so the event weight is omega / 1.0 = omega to
    the bit (IEEE division by 1 is exact). A noise larger than the blur term's error (80 levels: sigma^2 =
    0.098; a 30-step fit of this scene is at 0.06) drives the weight to its bound and the run away from the
    one with 0; auto (the default) finds under one level of noise in this noise-free scene's frames (0.33), which is
    taken as none: the run is the one with 0, bit for bit."""
    from ev3dgs.train.frame_noise import blur_weight
    from ev3dgs.train.frame_noise import W_MIN

    runs = {}
    for name, fn in (("off", 0.0), ("loud", 80.0), ("auto", None)):
        tr = Trainer(cfg(scene_path, iterations=30, frame_noise=fn), tmp_path / name, quiet=True)
        tr.fit()
        runs[name] = tr
    assert runs["off"].term("events").frame_noise_var == 0.0 and runs["off"].term("events").blur_mse is None
    assert blur_weight(runs["loud"].term("events").frame_noise_var, runs["loud"].term("events").blur_mse) == W_MIN
    assert not torch.equal(runs["off"].model.params["means"], runs["loud"].model.params["means"])
    assert TrainConfig(scene=scene_path).frame_noise is None and runs["auto"].term("events").frame_noise_var == 0.0
    for n, p in runs["auto"].model.params.items():
        assert torch.equal(p, runs["off"].model.params[n]), n
    log = [json.loads(line) for line in (tmp_path / "loud" / "log.jsonl").read_text().splitlines()]
    assert log[-1]["event_weight"] == pytest.approx(TrainConfig(scene=scene_path).omega / W_MIN)
    assert log[-1]["frame_noise"] == pytest.approx(80.0)
    assert "event_weight" not in json.loads((tmp_path / "off" / "log.jsonl").read_text().splitlines()[-1])


def test_frame_noise_that_is_not_auto_or_a_number_is_one_line_exit_2(scene_path, tmp_path, capsys):
    assert cli.main(["train", scene_path, "--out", str(tmp_path / "r"), "--set", "events.frame_noise=loud"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and 'events.frame_noise: expected "auto" or a number' in err


def test_threshold_map_is_inert_without_mismatch_and_needs_the_noise_norm(scene_path, tmp_path):
    """With --event-mismatch 0 there is no pattern to fit: the run is bitwise the one without the map; the
    count norm has no noise model to weigh the map with and is refused."""
    plain = Trainer(cfg(scene_path, iterations=15, event_mismatch=0.0), tmp_path / "a", quiet=True)
    plain.fit()
    mapped = Trainer(cfg(scene_path, iterations=15, event_mismatch=0.0, threshold_map=True), tmp_path / "b",
                     quiet=True)
    mapped.fit()
    assert mapped.term("threshold_map") is None
    for name, p in plain.model.params.items():
        assert torch.equal(p, mapped.model.params[name]), name
    from ev3dgs.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\[threshold_map\] needs events.norm noise"):
        cfg(scene_path, threshold_map=True, event_norm="count")


def test_map_weights_prior_weighs_the_first_step_as_without_a_map_and_posterior_no_less(scene_path, tmp_path):
    """The map starts at the nominal thresholds (multipliers 1) with the prior's spread s everywhere. With
    --map-weights prior the events' variance is the noise norm's, so the first step's event term is the one
    without a map, to the bit. With posterior the mismatch variance is (s theta n_on)^2 + (s theta n_off)^2,
    never above the noise norm's (s theta (n_on + n_off))^2 (a^2 + b^2 <= (a + b)^2 for a, b >= 0; the forms
    themselves: test_threshold_map), so the term is no smaller. After the first step the map moves the
    thresholds (prior leaves plain) and shrinks the spread where the counts inform it (posterior leaves
    prior)."""
    first, runs = {}, {}
    for name, extra in (("plain", {}), ("prior", {"threshold_map": True}),
                        ("posterior", {"threshold_map": True, "map_weights": "posterior"})):
        # the mean floor: a floor of this step's residuals that does not depend on the weighting (the chi-square
        # floor is solved again for each weighting, which makes every first step's term about 1)
        runs[name] = tr = Trainer(cfg(scene_path, iterations=8, event_mismatch=0.3, event_floor="mean",
                                      event_huber=0.0, **extra), tmp_path / name, quiet=True)
        tr.fit()
        log = [json.loads(line) for line in (tmp_path / name / "log.jsonl").read_text().splitlines()]
        first[name] = log[0]["event"]
    assert first["prior"] == first["plain"] > 0
    assert first["posterior"] >= first["prior"]
    means = {name: tr.model.params["means"] for name, tr in runs.items()}
    assert not torch.equal(means["prior"], means["plain"])
    assert not torch.equal(means["posterior"], means["prior"])


def test_a_saved_config_without_map_weights_loads_as_the_posterior_weighting_it_was_made_with(tmp_path):
    """Runs saved before --map-weights existed weighed a threshold map's events by its posterior spread:
    resuming one keeps that (config.LEGACY_VALUES); a new config defaults to the prior."""
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"scene": "s.h5", "event_norm": "noise", "threshold_map": True}))
    assert TrainConfig.load(path).map_weights == "posterior"
    assert TrainConfig(scene="s.h5", threshold_map=True).map_weights == "prior"


def test_map_weights_without_a_map_or_unknown_is_one_line_exit_2(scene_path, tmp_path, capsys):
    for argv, msg in ((["--set", "threshold_map.weights=fitted"], "threshold_map.weights must be one of"),
                      (["--set", "threshold_map.wieghts=prior"], "unknown config key threshold_map.wieghts")):
        assert exit_code(cli.main, ["train", scene_path, "--out", str(tmp_path / "r"), *argv]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and msg in err
    assert not (tmp_path / "r").exists()


def test_the_sh_degree_rises_every_sh_interval_steps(scene_path, tmp_path):
    """Degree 0 for the first interval, one more per interval after, capped at --sh-degree."""
    seen = []
    tr = Trainer(cfg(scene_path, iterations=14, sh_degree=2, sh_interval=4), tmp_path / "run", quiet=True)
    tr.fit(on_step=lambda trainer, rec: seen.append(trainer.model.active_sh_degree))
    # the degree a step renders with is raised at its start: steps 1-4 use 0, 5-8 use 1, 9-14 use 2
    assert seen == [0] * 4 + [1] * 4 + [2] * 6


@settings(deadline=None)
@given(st.integers(1, 10 ** 7))
def test_the_auto_sh_schedule_is_the_3dgs_one_scaled_to_the_run(n):
    """3DGS raises the degree every 1000 of 30 000 steps, so degree 3 from a tenth of the run: auto gives
    every n / 30 steps, rounded down, at least 1; 1000 at 30 000 steps, and never later than 3DGS would."""
    every = sh_interval_for(n)
    assert every >= 1 and (every == 1 or 30 * every <= n < 30 * (every + 1))
    assert TrainConfig(scene="x.h5", iterations=n).sh_interval == every
    assert TrainConfig(scene="x.h5", iterations=n, sh_interval=7).sh_interval == 7


def test_the_auto_sh_schedule_at_known_lengths():
    assert [sh_interval_for(n) for n in (1, 29, 30, 1000, 1500, 3000, 30000)] == [1, 1, 1, 33, 50, 100, 1000]


def test_hdr_needs_the_linear_light_blur_model(scene_path, tmp_path):
    from ev3dgs.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\[hdr\] needs the linear-light blur model"):
        cfg(scene_path, hdr=True, blur_space="srgb")
    sc = schema.read(scene_path)   # frames blurred in display values (E2NeRF's data): their blur model is sRGB
    sc.train.transfer = "display"
    schema.write(sc, tmp_path / "display.h5")
    with pytest.raises(ConfigError, match=r"\[hdr\] needs the linear-light blur model"):
        Trainer(cfg(str(tmp_path / "display.h5"), hdr=True), tmp_path / "run", quiet=True)


def test_learn_response_is_refused_where_the_frames_are_not_decoded_with_srgb(scene_path, tmp_path):
    from ev3dgs.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\[response\] needs the linear-light blur model"):
        cfg(scene_path, learn_response=True, blur_space="srgb")
    with pytest.raises(ConfigError, match=r"\[response\] needs the blur model"):
        cfg(scene_path, learn_response=True, oracle=True)
    with pytest.raises(ConfigError, match=r"\[response\] with edi_prior.weight"):
        cfg(scene_path, learn_response=True, edi_prior=0.05)
    sc = schema.read(scene_path)
    sc.train.transfer = "display"
    schema.write(sc, tmp_path / "display.h5")
    with pytest.raises(ConfigError, match=r"\[response\] needs a scene whose frames are decoded with sRGB"):
        Trainer(cfg(str(tmp_path / "display.h5"), learn_response=True), tmp_path / "run", quiet=True)
    # off, a run leaves no curve behind, not even an older run's
    (tmp_path / "r2").mkdir()
    (tmp_path / "r2" / "response.json").write_text("{}")
    Trainer(cfg(scene_path, iterations=2), tmp_path / "r2", quiet=True).fit()
    assert not (tmp_path / "r2" / "response.json").exists()


def test_edi_prior_moves_the_fit_while_it_fades_and_is_refused_where_it_has_no_meaning(scene_path, tmp_path):
    """The prior's term is logged and positive until its anneal point (a short run's fade lasts at least
    MIN_EDI_ANNEAL_STEPS = 100 steps: all 20 steps here); it changes the run; it needs
    the noise norm and the events, and a blur model in which the frame's event intensity is the mean of the
    sub-poses' (sRGB events averaged as display values are refused)."""
    from ev3dgs.errors import ConfigError

    tr = Trainer(cfg(scene_path, iterations=20, edi_prior=0.05, edi_anneal=0.5), tmp_path / "a", quiet=True)
    tr.fit()
    log = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert all(r["edi"] > 0 for r in log)
    plain = Trainer(cfg(scene_path, iterations=20), tmp_path / "b", quiet=True)
    plain.fit()
    assert not torch.equal(plain.model.params["means"], tr.model.params["means"])
    for kw, match in (({"event_norm": "count"}, "needs events.norm noise"),
                      ({"event_loss": False}, "needs the event loss"), ({"oracle": True}, "needs the event loss"),
                      ({"edi_anneal": 0.0}, "edi_prior.anneal"), ({"edi_prior": -1.0}, "edi_prior.weight must be")):
        with pytest.raises(ConfigError, match=match):
            cfg(scene_path, **{"edi_prior": 0.05, **kw})
    with pytest.raises(ConfigError, match=r"\[edi_prior\]: the blurry frame's event intensity"):
        Trainer(cfg(scene_path, edi_prior=0.05, blur_space="srgb"), tmp_path / "c", quiet=True)


def test_nan_guard_stops_and_keeps_the_checkpoint(scene_path, tmp_path, monkeypatch):
    import ev3dgs.train.terms.blur as T

    real = T.average_loss

    def poisoned(*a, **k):
        out = real(*a, **k)
        return out * float("nan") if poisoned.calls >= 25 else out

    poisoned.calls = 0

    def counting(*a, **k):
        poisoned.calls += 1
        return poisoned(*a, **k)

    monkeypatch.setattr(T, "average_loss", counting)
    tr = Trainer(cfg(scene_path), tmp_path / "run", quiet=True)
    with pytest.raises(TrainingError, match="non-finite loss.*step 25.*ckpt.pt"):
        tr.fit()
    ckpt = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)
    assert ckpt["step"] == 20 and all(torch.isfinite(v).all() for k, v in ckpt["model"].items()
                                      if isinstance(v, torch.Tensor))


@pytest.mark.parametrize("flags", [["--naive"], ["--no-event-loss"],
                                   ["--set", "blur.space=linear", "--set", "events.learn_thresholds=true",
                                    "--set", "events.pairs=3", "--set", "threshold_map=true",
                                    "--set", "threshold_map.weights=posterior", "--set", "hdr=true",
                                    "--set", "sh_interval=4", "--set", "edi_prior.weight=0.02", "--set",
                                    "blur.subposes=7", "--set", "blur.subpose_px=0.5"],
                                   ["--set", "hdr=true", "--set", "response=true", "--set", "events.pairs=2",
                                    "--set", "events.frame_noise=2.5"],
                                   pytest.param(["--refine-poses", "--set", "blur.subposes=9", "--set",
                                                 "blur.subpose_px=0.5"], marks=pytest.mark.slow)])
def test_cli_variants_train_eval_export_render(scene_path, tmp_path, flags, capsys):
    run = tmp_path / "run"
    assert cli.main(["train", scene_path, "--out", str(run), "--iterations", "12", "--set", "init_points=300",
                     "--threads", "1", "--quiet", *flags]) == 0
    assert cli.main(["eval", str(run)]) == 0
    assert "PSNR" in capsys.readouterr().out
    m = json.loads((run / "metrics.json").read_text())
    assert {"test", "train_sharp", "blurry_input"} <= set(m)
    saved = json.loads((run / "config.json").read_text())
    # --sh-interval auto at 12 steps: every 12 / 30 steps, at least 1
    assert saved["hdr"] == ("hdr=true" in flags) and saved["sh_interval"] == (4 if "sh_interval=4" in flags else 1)
    assert saved["edi_prior"] == (0.02 if "edi_prior.weight=0.02" in flags else 0.0)
    assert saved["subpose_px"] == (0.5 if "blur.subpose_px=0.5" in flags else 0.0)
    assert saved["learn_response"] == ("response=true" in flags)
    assert saved["frame_noise"] == (2.5 if "events.frame_noise=2.5" in flags else None)
    assert (run / "trajectory.npz").exists() == ("--refine-poses" in flags)
    assert cli.main(["export", str(run), "--ply", str(tmp_path / "m.ply")]) == 0
    assert len(load_ply(tmp_path / "m.ply")) > 0
    assert cli.main(["render", str(run), "--out", str(tmp_path / "frames"), "--frames", "3"]) == 0
    assert len(list((tmp_path / "frames").glob("*.png"))) == 3


@pytest.mark.parametrize("args,match", [
    (["train", "/nonexistent.h5", "--out", "X"], "no such file"),
    (["train", "SCENE", "--out", "X", "--set", "blur.subposes=0"], "subposes"),
    (["train", "SCENE", "--out", "X", "--iterations", "0"], "iterations"),
    (["train", "SCENE", "--out", "X", "--set", "events.pairs=11"], "events.pairs"),
    (["train", "SCENE", "--out", "X", "--set", "sh_interval=0"], "sh_interval"),
    (["train", "SCENE", "--out", "X", "--set", "sh_interval=fast"], 'sh_interval: expected "auto" or an integer'),
    (["train", "SCENE", "--out", "X", "--set", "hdr=true", "--set", "blur.space=srgb"], "hdr.*needs the linear-light"),
    (["train", "SCENE", "--out", "X", "--set", "edi_prior.weight=0.05", "--set", "edi_prior.anneal=0"],
     "edi_prior.anneal"),
    (["train", "SCENE", "--out", "X", "--set", "edi_prior.anneal=0.3"], r"\[edi_prior\] needs weight"),
    (["train", "SCENE", "--out", "X", "--set", "response=true", "--naive"], "response.*needs the blur model"),
    (["train", "SCENE", "--out", "X", "--set", "blur.subpose_px=-1"], "blur.subpose_px must be a number >= 0"),
    (["train", "SCENE", "--out", "X", "--set", "events.frame_noise=-1"], "events.frame_noise must be auto or a sigma"),
    (["train", "SCENE", "--out", "X", "--set", "edi_prior.weight=0.1", "--no-event-loss"],
     "edi_prior.weight needs the event loss"),
    (["train", "SCENE", "--out", "X", "--set", "device=cuda"], "CUDA|cuda"),
    (["train", "SCENE", "--out", "X", "--event-huber", "3"], "--set events.huber=VALUE"),
    (["train", "SCENE", "--out", "X", "--resume"], "no checkpoint"),
    (["eval", "/nonexistent_run"], "not a finished training run"),
])
def test_bad_input_is_one_line_exit_2(scene_path, tmp_path, capsys, args, match):
    if "device=cuda" in args and torch.cuda.is_available():
        pytest.skip("CUDA present")
    args = [a.replace("SCENE", scene_path).replace("X", str(tmp_path / "r")) for a in args]
    assert exit_code(cli.main, args) == 2   # also argparse's own refusals (a value its type rejects)
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    import re

    assert re.search(match, err)


def test_scene_without_poses_is_refused(scene_path, tmp_path, capsys):
    sc = schema.read(scene_path)
    tr = sc.train
    sc.train = schema.Train(images=np.asarray(tr.images), exposure=tr.exposure)
    sc.events = sc.events.load()
    sc.test = None
    schema.write(sc, tmp_path / "noposes.h5")
    assert cli.main(["train", str(tmp_path / "noposes.h5"), "--out", str(tmp_path / "r")]) == 2
    assert "/train/poses is missing" in capsys.readouterr().err


def test_bench_train_scaling_step_and_plot(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
    from bench_train_scaling import plot, step_ms

    ms = step_ms(300, 24, 18, threads=1, repeats=1)
    assert 0 < ms < 60_000
    rows = lambda key, xs: [{"width": 24, "height": 18, "pixels": x if key == "p" else 432,  # noqa: E731
                             "gaussians": x if key == "g" else 300, "ms": float(x) ** 0.5} for x in xs]
    plot({"threads": 1, "subposes": 5, "by_pixels": rows("p", [100, 400]), "by_gaussians": rows("g", [100, 1000]),
          "slope_pixels": 0.5, "slope_gaussians": 0.5}, str(tmp_path / "s.png"))
    assert (tmp_path / "s.png").stat().st_size > 0


def test_bench_train_speed_worker_fixed_count(scene_path):
    """bench_train.py --speed --no-densify: the worker trains without densification, so the Gaussian count
    stays the init's at every timed step, and the per-1000-Gaussians figure is the per-step one scaled by
    that count (an independent recomputation from the record's own fields)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
    import math
    from bench_train_speed import worker

    rec = worker(str(scene_path), 4, 1, 0, densify=False)
    assert rec["densify"] is False and rec["gaussians"] == 5000 and rec["mean_gaussians"] == 5000
    assert rec["cpu_ms_per_step"] > 0
    assert math.isclose(rec["cpu_ms_per_step_per_1k"], rec["cpu_ms_per_step"] * 1000 / 5000, rel_tol=1e-12)


def test_bench_train_options_times_every_variant_at_its_sh_degree(scene_path, tmp_path):
    """tools/bench/bench_train_options.py: each variant timed, the SH variants at degree 3 when timing starts
    and the others at 0, ratios against the default's median."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
    from bench_train_options import VARIANTS, main

    out = tmp_path / "o.json"
    assert main(["--scene", scene_path, "--rounds", "2", "--init-points", "200", "--json", str(out),
                 "--plot", str(tmp_path / "o.png")]) == 0
    res = json.loads(out.read_text())
    assert set(res["ms_per_step"]) == set(VARIANTS) and res["ratio_to_default"]["default"] == 1.0
    assert res["sh_degree"] == {"default": 0, "--hdr": 0, "SH degree 3": 3, "--hdr, SH degree 3": 3,
                                "--edi-prior": 0, "17 sub-poses": 0, "--subpose-px 2": 0, "--learn-response": 0}
    assert set(res["ms_mean"]) == set(VARIANTS) and res["mean_ratio_to_default"]["default"] == 1.0
    assert all(v > 0 for v in res["ms_per_step"].values()) and (tmp_path / "o.png").stat().st_size > 1000
