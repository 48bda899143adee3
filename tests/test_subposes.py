"""Per-view sub-pose counts from the image motion (--subpose-px): the motion against closed forms, the counts'
defining inequality, and the per-view data against the uniform loader run on one view at a time."""
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs import schema
from ev3dgs.errors import InputError
from ev3dgs.geometry import interpolate_pose, intrinsics
from ev3dgs.train.data import load_train_data
from ev3dgs.train.events import bin_polarity_events, sub_pose_times
from ev3dgs.train.subposes import GRID, exposure_motion, motion_points, subpose_counts

from test_train import scene_path  # noqa: F401  (the trainer tests' synthetic scene)

W, H = 64, 48
K = intrinsics(W, H, 60)


def _pose(R=np.eye(3), c=(0.0, 0.0, 0.0)):
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, c
    return out


def _rot_y(a):
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def test_a_sideways_translation_moves_each_point_by_f_d_over_z():
    """A camera sliding D along its x axis moves a point at depth Z by fx D / Z pixels (pinhole, exact); the
    nearest point seen sets the view's motion, points behind the camera or outside the image do not count."""
    D = 0.2
    poses = np.stack([_pose(c=(0, 0, 0)), _pose(c=(D, 0, 0))])[None]
    pose_t = np.array([[0, 100_000]])
    pts = np.array([[0.0, 0.0, 4.0], [0.3, -0.2, 2.5], [0.1, 0.1, 8.0],
                    [0.0, 0.0, -1.0],          # behind the camera
                    [3.0, 0.0, 1.0]])          # far outside the image at mid-exposure
    m = exposure_motion(poses, pose_t, np.array([[0, 100_000]]), K, W, H, pts)
    assert m[0] == pytest.approx(K[0, 0] * D / 2.5, rel=1e-12)
    # a view that sees none of the points has no motion
    assert exposure_motion(poses, pose_t, np.array([[0, 100_000]]), K, W, H, pts[3:])[0] == 0.0


@settings(max_examples=50, deadline=None)
@given(st.floats(-0.3, 0.3), st.lists(st.floats(-0.35, 0.35), min_size=1, max_size=6),
       st.integers(2, 9))
def test_a_pan_moves_a_point_by_the_change_of_its_tangent(alpha, phis, samples):
    """Panning by alpha about the camera's y axis moves a point at bearing phi on the horizon from
    fx tan(phi) to fx tan(phi - alpha): monotone, so the sampled path length is exact for any number of pose
    samples (slerp turns at a constant rate), and the view's motion is the largest over the points."""
    t = np.linspace(0, 50_000, samples).astype(np.int64)
    poses = np.stack([_pose(_rot_y(alpha * (ti - t[0]) / (t[-1] - t[0]))) for ti in t])[None]
    pts = np.array([[5 * math.sin(p), 0.0, 5 * math.cos(p)] for p in phis])
    m = exposure_motion(poses, t[None], np.array([[0, 50_000]]), K, W, H, pts)[0]
    fx, cx = K[0, 0], K[0, 2]
    mid = [fx * math.tan(p - alpha / 2) + cx for p in phis]
    seen = [abs(fx * (math.tan(p - alpha) - math.tan(p))) for p, u in zip(phis, mid) if -0.5 <= u <= W - 0.5]
    assert m == pytest.approx(max(seen, default=0.0), rel=1e-9, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.floats(0, 1e4), st.floats(1e-3, 1e3), st.integers(2, 64))
def test_counts_are_the_fewest_within_the_spacing(motion, px, cap):
    k = int(subpose_counts(np.array([motion]), px, cap)[0])
    assert 2 <= k <= cap
    eps = 1e-12 * max(1.0, motion / px)
    if k < cap:   # the spacing holds ...
        assert motion / (k - 1) <= px * (1 + eps)
    if k > 2:     # ... and one sub-pose fewer would break it
        assert motion / (k - 2) > px * (1 - eps)


@pytest.mark.parametrize("px", [0.0, -1.0, float("nan"), float("inf")])
def test_counts_refuse_a_spacing_that_is_not_positive(px):
    with pytest.raises(ValueError, match="positive"):
        subpose_counts(np.array([3.0]), px, 9)


def test_motion_points_prefer_the_scenes_points_and_fill_the_bounds_otherwise():
    xyz = np.arange(12.0).reshape(4, 3)
    assert np.array_equal(motion_points(xyz, None), xyz)
    box = np.array([[-1.0, 0.0, 2.0], [1.0, 0.5, 3.0]])
    g = motion_points(None, box)
    assert g.shape == (GRID ** 3, 3) and np.array_equal(g.min(0), box[0]) and np.array_equal(g.max(0), box[1])
    with pytest.raises(InputError, match="points or /bounds"):
        motion_points(None, None)


def test_each_view_gets_its_own_sub_poses_and_events(scene_path):  # noqa: F811
    """Every view's rows equal what the uniform loader gives that view alone with its own count: poses at its
    own sub-pose times, its events binned between them (all of them kept), zero padding after."""
    sc = schema.read(scene_path)
    tr = sc.train
    d = load_train_data(scene_path, 9, subpose_px=0.5)
    motion = exposure_motion(tr.poses, tr.pose_t, tr.exposure, sc.camera.K, sc.camera.width, sc.camera.height,
                             motion_points(None, sc.bounds))
    assert np.array_equal(d.motion_px, motion) and np.array_equal(d.n_sub, subpose_counts(motion, 0.5, 9))
    assert len(set(d.n_sub.tolist())) > 1, "the fixture's views should need different counts"
    ev = sc.events.load()
    full = load_train_data(scene_path, 9)
    assert full.n_sub is None and all(full.sub_count(v) == 9 for v in range(full.n_views))
    for v in range(d.n_views):
        k = d.sub_count(v)
        times = sub_pose_times(np.asarray(tr.exposure)[v:v + 1], k)
        assert np.array_equal(d.sub_times[v, :k], times[0])
        expect = np.stack([interpolate_pose(tr.poses[v], tr.pose_t[v], t) for t in times[0]])
        assert torch.allclose(d.viewmats[v, :k].double(), torch.as_tensor(np.linalg.inv(expect)), atol=1e-6)
        bins = bin_polarity_events(ev.t, ev.x, ev.y, ev.p, times, sc.camera.height, sc.camera.width)[0]
        assert torch.equal(d.bins[v, :k - 1], torch.from_numpy(bins))
        assert not d.bins[v, k - 1:].any()
        assert d.bins[v].sum() == full.bins[v].sum()   # the same events, only binned differently


def test_training_renders_each_view_at_its_own_count(scene_path, tmp_path):  # noqa: F811
    """The log records each step's count, which is its view's; where every view needs the cap, the run is
    bitwise the run with that fixed count."""
    import json

    from ev3dgs.train.trainer import Trainer
    from test_train import cfg

    tr = Trainer(cfg(scene_path, iterations=20, subposes=9, subpose_px=0.5), tmp_path / "a", quiet=True)
    tr.fit()
    log = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["subposes"] for r in log] == [int(tr.data.n_sub[r["view"]]) for r in log]
    assert len({r["subposes"] for r in log}) > 1
    capped = Trainer(cfg(scene_path, iterations=20, subposes=3, subpose_px=1e-3), tmp_path / "b", quiet=True)
    fixed = Trainer(cfg(scene_path, iterations=20, subposes=3), tmp_path / "c", quiet=True)
    capped.fit()
    fixed.fit()
    assert capped.data.n_sub.tolist() == [3] * capped.data.n_views
    for name, p in fixed.model.params.items():
        assert torch.equal(p, capped.model.params[name]), name
