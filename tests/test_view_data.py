"""`ev3dgs view`'s data preparation (ev3dgs/view/data.py) against the scene file and closed forms; the --png
figure and the one-line errors. No browser and no viser here (tests/test_view_server.py, test_view_browser.py).
"""
import json
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ev3dgs import palette, schema
from ev3dgs.cli import main as cli
from ev3dgs.errors import Ev3dgsError, InputError, SchemaError
from ev3dgs.event_file import EventFile
from ev3dgs.geometry import quat_to_matrix, rotvec_to_matrix
from ev3dgs.splat.model import GaussianModel
from ev3dgs.view import data

from cli_exit import exit_code
from view_scene import EXPOSURE_US, N, OMEGA_DPS, PERIOD_US, S, H, W, make_scene, pose_at, view_events

import numpy.random as npr


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("view") / "scene.h5",
                      registration=[{"frame": 2, "exposure": [1000, 2000]}])


@pytest.fixture(scope="module")
def content(scene_path):
    return data.load_scene(scene_path)


# ------------------------------------------------------------------------------- trajectories

def test_polylines_are_the_pose_samples_centres_in_time_order(content):
    lines = content.polylines()
    assert lines.shape == (N, S, 3)
    for v in range(N):
        for s in range(S):
            t = v * PERIOD_US + np.linspace(0, EXPOSURE_US, S).astype(np.int64)[s]
            np.testing.assert_allclose(lines[v, s], pose_at(t)[:3, 3], atol=1e-12)  # closed form, few ops


def test_polylines_sort_samples_given_out_of_order():
    t = np.array([[30, 10, 20]])
    poses = np.tile(np.eye(4), (1, 3, 1, 1))
    poses[0, :, 0, 3] = [3.0, 1.0, 2.0]
    np.testing.assert_array_equal(data.trajectory_polylines(poses, t)[0, :, 0], [1.0, 2.0, 3.0])
    with pytest.raises(InputError):
        data.trajectory_polylines(poses, t[:, :2])


def test_frustum_matches_the_pinhole(content):
    c2w = content.mid_poses()[1]
    K = content.scene.camera.K
    f = data.frustum(c2w, K, W, H)
    # vertical FOV of a pinhole: the rays through the top and bottom image edges
    assert f.fov_y == pytest.approx(2 * np.arctan(H / 2 / K[1, 1]), abs=1e-12)
    assert f.aspect == W / H
    np.testing.assert_allclose(quat_to_matrix(f.wxyz), c2w[:3, :3], atol=1e-12)
    np.testing.assert_allclose(f.position, c2w[:3, 3])
    corners = data.image_corners(c2w, K, W, H, depth=2.5)
    cam = (corners - c2w[:3, 3]) @ c2w[:3, :3]      # world -> camera
    np.testing.assert_allclose(cam[:, 2], 2.5, atol=1e-12)
    uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    np.testing.assert_allclose(uv, [[0, 0], [W, 0], [W, H], [0, H]], atol=1e-9)


def test_top_view_looks_down_the_cameras_up():
    # an orbit in the world xy plane, z up: the top view's plane is xy
    from ev3dgs.geometry import look_at

    rots = np.stack([look_at([3 * np.cos(a), 3 * np.sin(a), 0], [0, 0, 0])[:3, :3] for a in np.linspace(0, 6, 8)])
    np.testing.assert_allclose(data.world_up(rots), [0, 0, 1], atol=1e-12)
    b = data.top_view_basis(rots)
    np.testing.assert_allclose(b @ b.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(b[:, 2], 0, atol=1e-12)


# ------------------------------------------------------------------------------------ events

def test_event_counts_are_the_exposure_window(scene_path, content):
    per_view, _ = view_events(npr.default_rng(7))
    with EventFile(scene_path) as r:
        for v in range(N):
            on, off = content.event_counts(r, v, 1.0)
            x, y, p, t = per_view[v]
            ref_on, ref_off = np.zeros((H, W), int), np.zeros((H, W), int)
            for xi, yi, pi in zip(x, y, p):   # independent: one event at a time
                (ref_on if pi > 0 else ref_off)[yi, xi] += 1
            np.testing.assert_array_equal(on, ref_on)
            np.testing.assert_array_equal(off, ref_off)
            # half way: only the events before start + EXPOSURE/2
            on_h, off_h = content.event_counts(r, v, 0.5)
            assert on_h.sum() + off_h.sum() == int(np.sum(t < v * PERIOD_US + EXPOSURE_US // 2))
            on_0, off_0 = content.event_counts(r, v, 0.0)
            assert on_0.sum() == off_0.sum() == 0


@settings(max_examples=40, deadline=None)
@given(a=st.integers(-50_000, 900_000), b=st.integers(-50_000, 900_000))
def test_event_window_matches_searchsorted(scene_path, a, b):
    lo, hi = min(a, b), max(a, b)
    t_all = np.asarray(schema.read(scene_path).events.t)
    with EventFile(scene_path) as r:
        t, x, y, p = r.window(lo, hi)
    i, j = np.searchsorted(t_all, [lo, hi], side="left")
    np.testing.assert_array_equal(t, t_all[i:j])
    assert len(x) == len(y) == len(p) == j - i


@settings(max_examples=60, deadline=None)
@given(on=st.integers(0, 20), off=st.integers(0, 20), sat=st.integers(1, 10))
def test_event_image_colours(on, off, sat):
    img = data.event_image(np.array([[on]]), np.array([[off]]), saturation=sat)[0, 0].astype(float)
    a, b = min(on / sat, 1), min(off / sat, 1)
    expect = 255 + a * (np.array(palette.ON_RGB) - 255.0) + b * (np.array(palette.OFF_RGB) - 255.0)
    np.testing.assert_allclose(img, np.clip(np.rint(expect), 0, 255), atol=0)


def test_event_image_two_colours_and_default_saturation():
    on = np.array([[0, 3, 0, 1000]])
    off = np.array([[0, 0, 3, 0]])
    img = data.event_image(on, off)            # 99th percentile of (3, 1000, 3) is about 980
    np.testing.assert_array_equal(img[0, 0], palette.BACKGROUND_RGB)
    np.testing.assert_array_equal(img[0, 3], palette.ON_RGB)
    assert img[0, 1, 0] > img[0, 1, 2] and img[0, 2, 2] > img[0, 2, 0]   # ON reddish, OFF bluish
    assert data.accumulation_time(np.array([100, 300]), 0.25) == 150
    assert data.accumulation_time(np.array([100, 300]), 2.0) == 300


# --------------------------------------------------------------------------------------- IMU

def test_gyro_integration_closed_forms():
    t = np.arange(0, 1_000_001, 5000, dtype=np.int64)
    # constant rate about a tilted axis: exp(w T) exactly (the midpoint rule is exact for a constant)
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    w = np.tile(40.0 * axis, (len(t), 1))
    R = data.integrate_gyro(t, w, np.array([0, 250_000, 1_000_000]))
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(R[2], rotvec_to_matrix(np.deg2rad(40.0) * 1.0 * axis), atol=1e-12)
    # 200 steps of a few u each: 1e-12
    np.testing.assert_allclose(R[1], rotvec_to_matrix(np.deg2rad(40.0) * 0.25 * axis), atol=1e-12)
    # a rate growing linearly about a fixed axis: angle alpha T^2 / 2 (the midpoint of a linear rate is exact)
    ramp = np.outer(100.0 * t * 1e-6, [0, 0, 1])
    R = data.integrate_gyro(t, ramp, np.array([0, 1_000_000]))
    np.testing.assert_allclose(R[1], rotvec_to_matrix(np.deg2rad([0, 0, 100.0 / 2])), atol=1e-12)
    # the rotation from a later start: R(t1 -> t2) = R(0 -> t1)^T R(0 -> t2)
    full = data.integrate_gyro(t, ramp, np.array([0, 300_000, 800_000]))
    part = data.integrate_gyro(t, ramp, np.array([300_000, 800_000]))
    np.testing.assert_allclose(part[1], full[1].T @ full[2], atol=1e-12)
    # outside the IMU's time span: NaN
    assert np.isnan(data.integrate_gyro(t, w, np.array([0, 2_000_000]))[1]).all()


def test_imu_rotation_beside_the_poses(content):
    imu = content.imu
    assert imu is not None and imu.rotations.shape == (N, S, 3, 3)
    # the fixture's poses follow the gyro exactly: float32 gyro (6e-8 relative) over < 1 rad -> < 1e-5 deg
    assert np.nanmax(imu.angle_deg) < 1e-4
    for v in range(N):
        np.testing.assert_allclose(imu.rotations[v], content.train_poses[v, :, :3, :3], atol=1e-6)


def test_scene_without_imu_has_no_imu_rotation(tmp_path):
    c = data.load_scene(make_scene(tmp_path / "noimu.h5", with_imu=False))
    assert c.imu is None


def test_failed_registrations(content):
    assert content.failed == ["frame 2 (exposure 1000-2000 us)"]
    sc = content.scene
    old = schema.Scene(**{**sc.__dict__, "config": {"registered_latent_frames": N * S + 3,
                                                     "options": {"subposes": S}}})
    assert "3 registered latent frames" in data.failed_registrations(old)[0]
    assert data.failed_registrations(schema.Scene(**{**sc.__dict__, "config": {}})) == []


# ------------------------------------------------------------------------------------ splats

def _model(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    params = {"means": torch.randn(n, 3, generator=g), "log_scales": torch.randn(n, 3, generator=g) - 2,
              "quats": torch.randn(n, 4, generator=g), "opacity_logits": torch.randn(n, generator=g),
              "sh0": torch.randn(n, 1, 3, generator=g) * 0.5, "shN": torch.randn(n, 3, 3, generator=g)}
    return GaussianModel(params, sh_degree=1, active_sh_degree=1)


def test_splat_arrays_against_scipy():
    m = _model()
    a = data.splat_arrays(m)
    assert a["centers"].shape == (50, 3) and a["covariances"].shape == (50, 3, 3)
    assert a["rgbs"].shape == (50, 3) and a["opacities"].shape == (50, 1)
    assert all(v.dtype == np.float32 for v in a.values())
    q = m.params["quats"].detach().numpy().astype(np.float64)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()          # scipy: x y z w
    s = np.exp(m.params["log_scales"].detach().numpy().astype(np.float64))
    cov = np.einsum("nij,nj,nkj->nik", R, s ** 2, R)
    # float32 output of O(s^2) values: 1e-6 relative to the largest entry
    np.testing.assert_allclose(a["covariances"], cov, rtol=1e-5, atol=1e-6 * np.abs(cov).max())
    op = 1 / (1 + np.exp(-m.params["opacity_logits"].detach().numpy().astype(np.float64)))
    np.testing.assert_allclose(a["opacities"][:, 0], op, rtol=1e-6)
    C0 = 0.28209479177387814                                      # Y_0^0 = 1 / (2 sqrt(pi))
    rgb = np.clip(m.params["sh0"].detach().numpy()[:, 0].astype(np.float64) * C0 + 0.5, 0, 1)
    np.testing.assert_allclose(a["rgbs"], rgb, atol=1e-6)
    np.testing.assert_array_equal(a["centers"], m.params["means"].detach().numpy())


def test_splat_colours_of_points_and_the_exported_ply(tmp_path):
    rgb = np.array([[255, 0, 0], [10, 200, 30], [128, 128, 128], [0, 0, 255]], np.uint8)
    m = GaussianModel.from_points(np.eye(4, 3), rgb, sh_degree=0)
    np.testing.assert_allclose(data.splat_arrays(m)["rgbs"], rgb / 255.0, atol=1e-6)
    # the same arrays from the parameters `ev3dgs export` writes
    from ev3dgs.train.export import load_ply, save_ply

    m2 = _model(30, seed=1)
    save_ply(m2, tmp_path / "m.ply")
    a, b = data.splat_arrays(m2), data.splat_arrays(load_ply(tmp_path / "m.ply"))
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


# ------------------------------------------------------------------------------ runs, errors

def _run(tmp_path, scene_path, model=True, trajectory=None):
    from ev3dgs.train.config import TrainConfig

    run = tmp_path / "run"
    run.mkdir()
    TrainConfig(scene=scene_path, iterations=10).save(run / "config.json")
    if model:
        torch.save({"model": _model().state_dict()}, run / "model.pt")
    if trajectory is not None:
        np.savez(run / "trajectory.npz", **trajectory)
    return run


def test_run_content_with_refined_trajectory(tmp_path, scene_path, content):
    refined = content.train_poses.copy()
    refined[..., :3, 3] += 0.01
    run = _run(tmp_path, scene_path, trajectory={"poses": refined, "pose_t": content.pose_t})
    rc = data.load(run)
    assert isinstance(rc, data.RunContent) and len(rc.model) == 50 and rc.source == "model.pt"
    np.testing.assert_array_equal(rc.refined_poses, refined)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "config.json").write_text((run / "config.json").read_text())
    torch.save({"model": _model().state_dict()}, bad / "model.pt")
    np.savez(bad / "trajectory.npz", poses=refined[:2], pose_t=content.pose_t[:2])
    with pytest.raises(InputError, match="do not match"):
        data.load(bad)


def test_png_of_scene_and_run(tmp_path, scene_path, capsys):
    import matplotlib.image as mpimg

    out = tmp_path / "figs" / "scene.png"
    assert cli.main(["view", scene_path, "--png", str(out), "--rows", "3"]) == 0
    img = mpimg.imread(out)
    assert img.shape[0] > 300 and img.shape[1] > 600 and img[..., :3].std() > 0.05
    run = _run(tmp_path, scene_path)
    assert cli.main(["view", str(run), "--png", str(tmp_path / "run.png")]) == 0
    assert mpimg.imread(tmp_path / "run.png").shape[1] > img.shape[1]   # one more column: the model render
    assert not list(tmp_path.glob("**/.*.tmp-*"))


@pytest.mark.parametrize("case", ["missing", "text", "folder", "no_checkpoint", "select", "port", "rows"])
def test_bad_input_is_one_line_exit_2(tmp_path, scene_path, capsys, case):
    args = {"missing": [str(tmp_path / "nope.h5")],
            "text": [str(tmp_path / "a.txt")],
            "folder": [str(tmp_path)],
            "no_checkpoint": [None],
            "select": [scene_path, "--select", "9"],
            "port": [scene_path, "--port", "70000"],
            "rows": [scene_path, "--rows", "0"]}[case]
    (tmp_path / "a.txt").write_text("not a scene\n")
    if case == "no_checkpoint":
        args = [str(_run(tmp_path, scene_path, model=False))]
    rc = exit_code(cli.main, ["view", *args, "--png", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert not (tmp_path / "x.png").exists()
    if case == "no_checkpoint":
        assert "no checkpoint" in err


def test_without_viser_the_error_names_the_extra(monkeypatch, scene_path, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)      # import viser -> ImportError, as when not installed
    rc = cli.main(["view", scene_path])
    err = capsys.readouterr().err
    assert rc == 2 and "pip install ev3dgs[view]" in err and err.count("\n") == 1
    # the static figure needs no viser
    assert cli.main(["view", scene_path, "--png", str(scene_path) + ".png"]) == 0


def test_ingest_records_the_views_that_failed_to_register(tmp_path, monkeypatch):
    """`ingest davis` keeps the views whose latent frames all registered; the others are listed in the config
    (pose estimation replaced by a stand-in that drops the middle view of the shared 3-frame recording)."""
    from types import SimpleNamespace

    from ev3dgs.io import davis

    from test_davis import SHARED as shared

    if not shared.exists():
        pytest.skip("shared recording not present")

    def fake_estimate(images, ev, views, K, opts, progress=None):
        kept = [0, len(views) - 1]
        t = np.stack([np.linspace(views[i].exposure_start, views[i].exposure_end, opts.subposes).astype(np.int64)
                      for i in kept])
        poses = np.tile(np.eye(4), (len(kept), opts.subposes, 1, 1))
        poses[1, :, 0, 3] = 1.0
        K = np.array([[200.0, 0, 173], [0, 200.0, 130], [0, 0, 1]])
        return kept, poses, t, K, SimpleNamespace(points_xyz=None), len(kept) * opts.subposes

    monkeypatch.setattr(davis, "estimate_view_poses", fake_estimate)
    out = tmp_path / "rec.h5"
    davis.ingest_davis(shared, out, davis.DavisOptions(events="all"))
    sc = schema.read(out)
    rows = sc.config["unregistered_views"]
    assert [r["frame"] for r in rows] == [1] and len(sc.train) == 2
    assert data.failed_registrations(sc) == [f"frame 1 (exposure {rows[0]['exposure'][0]}-{rows[0]['exposure'][1]} us)"]
