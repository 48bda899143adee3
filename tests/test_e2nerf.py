"""E2NeRF importer: tiny fake synthetic and real-world (LLFF) layouts."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from ev3dgs import schema
from ev3dgs.errors import InputError
from ev3dgs.geometry import blender_to_opencv, project, rotvec_to_matrix
from ev3dgs.io.e2nerf import import_e2nerf, llff_to_opencv, synthesise_events
from ev3dgs.train.events import bin_signed_events, sub_pose_times

W, H, V, NSUB = 16, 12, 3, 18
ANGLE = 0.69
IDX = [1, 5, 9, 13, 17]


def _rand_c2w(rng, n):
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = rotvec_to_matrix(rng.normal(size=(n, 3)))
    m[:, :3, 3] = rng.normal(size=(n, 3)) * 3
    return m


def _rgba(rng, alpha=255):
    img = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
    img[..., 3] = alpha
    return img


def make_synthetic(root, rng, n_test=4):
    (root / "train").mkdir(parents=True)
    (root / "test").mkdir()
    train = [_rand_c2w(rng, NSUB) for _ in range(2 * V)]
    test = [_rand_c2w(rng, NSUB) for _ in range(n_test)]
    for fname, mats in (("transform_train.json", train), ("transform_test.json", test)):
        frames = [{"file_path": f"./r_{i}", "transform_matrix": m.tolist()} for i, m in enumerate(mats)]
        (root / fname).write_text(json.dumps({"camera_angle_x": ANGLE, "frames": frames}))
    imgs = {}
    for i in range(V):
        img = _rgba(rng, 255 if i else 128)      # view 0 has alpha 128: composited onto black
        cv2.imwrite(str(root / "train" / f"r_{2 * i}.png"), img)
        imgs[i] = img
    for i in range(n_test):
        cv2.imwrite(str(root / "test" / f"r_{i}.png"), _rgba(rng))
    counts = rng.integers(-3, 4, (V, 4, H * W)).astype(np.float64)
    counts[0, 0, 5] = 40                          # many events in one bin
    torch.save(torch.from_numpy(counts), root / "events.pt")
    return train, test, imgs, counts


def make_real(root, rng, h=8, w=10):
    (root / "images").mkdir(parents=True)
    for i in range(V):
        cv2.imwrite(str(root / "images" / f"{i * 5:03d}.jpg"), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    rows = np.zeros((V * 5, 17))
    for r in range(V * 5):
        R = rotvec_to_matrix(rng.normal(size=3))
        m = np.concatenate([R, rng.normal(size=(3, 1)), np.array([[h], [w], [7.5]])], axis=1)
        rows[r, :15] = m.reshape(-1)
        rows[r, 15:] = [0.5, 9.0]
    np.save(root / "poses_bounds.npy", rows)
    counts = rng.integers(-2, 3, (V, 4, h * w)).astype(np.float64)
    torch.save(torch.from_numpy(counts), root / "events.pt")
    return rows, counts


def _rebin(ev, edges, height, width):
    """Signed counts per (view, bin, pixel) with edges[v,k] < t < edges[v,k+1] (strictly inside)."""
    out = np.zeros((len(edges), edges.shape[1] - 1, height * width))
    for v, row in enumerate(edges):
        for k in range(len(row) - 1):
            m = (ev.t > row[k]) & (ev.t < row[k + 1])
            np.add.at(out[v, k], ev.y[m].astype(np.int64) * width + ev.x[m], ev.p[m])
    return out


@pytest.fixture
def synthetic(tmp_path):
    rng = np.random.default_rng(0)
    data = make_synthetic(tmp_path / "lego", rng)
    out = import_e2nerf(tmp_path / "lego", tmp_path / "out" / "scene.h5", pos_threshold=0.25, neg_threshold=0.3)
    return out, data


def test_synthetic_scene(synthetic):
    out, (train, test, imgs, counts) = synthetic
    schema.validate(out, require_complete=True)
    s = schema.read(out)
    assert s.source == "e2nerf" and s.name == "lego"
    assert (s.camera.width, s.camera.height, s.camera.background) == (W, H, (0.0, 0.0, 0.0))
    assert (s.sensor.pos_threshold, s.sensor.neg_threshold) == (0.25, 0.3)
    assert s.config["events"].startswith("synthesised from E2NeRF binned counts")
    assert s.config["thresholds"] == "not stored by E2NeRF; given on the command line"
    assert s.config["train_subframe_indices"] == IDX and s.config["test_novel_views"] == [1, 3]
    # poses: sub-frames 1,5,9,13,17 of json frames 0, 2, 4, in OpenCV axes; test: sub-frame 1
    for i in range(V):
        np.testing.assert_array_equal(s.train.poses[i], blender_to_opencv(train[2 * i][IDX]))
    np.testing.assert_array_equal(s.test.poses, np.stack([blender_to_opencv(m[1]) for m in test]))
    # time line: view i at i*250 ms, poses at +10,50,90,130,170 ms, exposure first..last pose
    start = np.arange(V)[:, None] * 250_000
    np.testing.assert_array_equal(s.train.pose_t, start + np.array(IDX) * 10_000)
    np.testing.assert_array_equal(s.train.exposure, start + np.array([10_000, 170_000]))
    np.testing.assert_array_equal(sub_pose_times(s.train.exposure, 5), s.train.pose_t)
    # images: RGB, alpha composited onto black
    tr = s.train.images.read()
    assert tr.shape == (V, H, W, 3) and tr.dtype == np.uint8 and s.test.images.shape == (4, H, W, 3)
    np.testing.assert_array_equal(tr[1], imgs[1][..., 2::-1])
    np.testing.assert_array_equal(tr[0], np.round(imgs[0][..., 2::-1] * (128 / 255)).astype(np.uint8))


def test_synthetic_events_rebin_exactly(synthetic):
    out, (_, _, _, counts) = synthetic
    s = schema.read(out)
    ev = s.events.load()
    assert len(ev) == int(np.abs(counts).sum())
    assert np.all(np.diff(ev.t) >= 0)
    np.testing.assert_array_equal(_rebin(ev, s.train.pose_t, H, W), counts)   # all strictly inside their bins
    binned = bin_signed_events(ev.t, ev.x, ev.y, ev.p, s.train.pose_t, H, W)  # the trainer's binning agrees
    np.testing.assert_array_equal(binned.reshape(V, 4, -1), counts)


def test_intrinsics_from_camera_angle_x(synthetic):
    out, _ = synthetic
    s = schema.read(out)
    K = s.camera.K
    assert K[0, 0] == pytest.approx(0.5 * W / math.tan(ANGLE / 2)) and K[1, 1] == K[0, 0]
    c2w = s.train.poses[1, 2]
    ahead = c2w[:3, 3] + 3.0 * c2w[:3, 2]          # OpenCV: +z forward
    uv, depth = project(K, c2w, ahead[None])
    np.testing.assert_allclose(uv[0], [(W - 1) / 2, (H - 1) / 2], atol=1e-9)
    assert depth[0] > 0


def test_synthesise_events_inside_bins():
    counts = np.array([[3, -1000, 0], [0, 2, -1]], np.float64)       # |c| > bin width: clipped inside
    edges = np.array([100, 110, 150])
    t, x, y, p = synthesise_events(counts, edges, width=3)
    assert len(t) == 1006 and np.all(np.diff(t) >= 0)
    k = np.searchsorted(edges, t, side="left") - 1
    assert np.all((t > edges[k]) & (t < edges[k + 1]))
    back = np.zeros_like(counts)
    np.add.at(back, (k, y.astype(int) * 3 + x), p)
    np.testing.assert_array_equal(back, counts)
    t3 = t[(x == 0) & (k == 0)]
    np.testing.assert_array_equal(t3, [101, 105, 108])                 # evenly spaced: 100 + (j + .5) * 10/3


def test_real_world_llff(tmp_path):
    rng = np.random.default_rng(1)
    rows, counts = make_real(tmp_path / "toys", rng)
    out = import_e2nerf(tmp_path / "toys", tmp_path / "toys.h5", name="toys-real")
    schema.validate(out, require_complete=True)
    s = schema.read(out)
    assert s.name == "toys-real" and s.test is None and (s.camera.width, s.camera.height) == (10, 8)
    assert s.train.images.shape == (V, 8, 10, 3) and s.train.poses.shape == (V, 5, 4, 4)
    np.testing.assert_allclose(s.camera.K, [[7.5, 0, 4.5], [0, 7.5, 3.5], [0, 0, 1]])
    expected = llff_to_opencv(rows[:, :15].reshape(-1, 3, 5)[:, :, :4])
    np.testing.assert_array_equal(s.train.poses.reshape(-1, 4, 4), expected)
    start = np.arange(V)[:, None] * 250_000
    np.testing.assert_array_equal(s.train.pose_t, start + np.arange(5) * 25_000)
    np.testing.assert_array_equal(s.train.exposure, start + np.array([0, 100_000]))
    ev = s.events.load()
    np.testing.assert_array_equal(_rebin(ev, s.train.pose_t, 8, 10), counts)
    assert len(ev) == int(np.abs(counts).sum())
    assert s.config["near_far"][0] == [0.5, 9.0]


def test_llff_to_opencv_known_pose():
    # LLFF columns [down, right, back]; camera at (1,2,3) looking down world -z, image right = +x, down = +y
    llff = np.array([[0, 1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3.0]])
    c2w = llff_to_opencv(llff)
    np.testing.assert_array_equal(c2w[:3, :3], np.diag([1.0, 1.0, -1.0]))
    np.testing.assert_array_equal(c2w[:3, 3], [1, 2, 3])
    K = np.array([[10.0, 0, 4.5], [0, 10.0, 3.5], [0, 0, 1]])
    uv, depth = project(K, c2w, np.array([[1, 2, -2.0], [2, 3, -2.0]]))
    np.testing.assert_allclose(uv[0], [4.5, 3.5])
    assert uv[1, 0] > 4.5 and uv[1, 1] > 3.5 and np.all(depth == 5)   # +x is right, +y is down
    # a camera looking along world +y with up = +z: forward +y, right +x, down -z; LLFF back = -y
    llff = np.array([[0, 1, 0, 0], [0, 0, -1, 0], [-1, 0, 0, 0.0]])
    c2w = llff_to_opencv(llff)
    np.testing.assert_array_equal(c2w[:3, 2], [0, 1, 0])
    np.testing.assert_array_equal(c2w[:3, 0], [1, 0, 0])
    np.testing.assert_array_equal(c2w[:3, 1], [0, 0, -1])
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1)


def test_event_tensor_variants(tmp_path):
    rng = np.random.default_rng(2)
    root = tmp_path / "s"
    *_, counts = make_synthetic(root, rng, n_test=0)
    (root / "transform_test.json").write_text(json.dumps({"camera_angle_x": ANGLE, "frames": []}))
    t = torch.from_numpy(counts.reshape(V, 4, H, W))                     # (V, b, H, W), legacy format
    torch.save(t, root / "events.pt", _use_new_zipfile_serialization=False)
    s = schema.read(import_e2nerf(root, tmp_path / "s.h5"))
    assert s.test is None
    np.testing.assert_array_equal(_rebin(s.events.load(), s.train.pose_t, H, W), counts)


def _expect(tmp_path, root, match):
    with pytest.raises(InputError, match=match):
        import_e2nerf(root, tmp_path / "bad.h5")
    assert not (tmp_path / "bad.h5").exists()
    assert not list(tmp_path.glob(".bad.h5*"))


def test_bad_synthetic_layouts(tmp_path):
    rng = np.random.default_rng(3)
    root = tmp_path / "s"
    _, _, _, counts = make_synthetic(root, rng)
    _expect(tmp_path, tmp_path / "nothing", "not a directory")
    (tmp_path / "empty").mkdir()
    _expect(tmp_path, tmp_path / "empty", "neither transform_train.json nor poses_bounds.npy")
    torch.save(torch.from_numpy(counts[:, :, :-1]), root / "events.pt")
    _expect(tmp_path, root, r"events\.pt: 191 pixels")
    torch.save(torch.from_numpy(counts[:2]), root / "events.pt")
    _expect(tmp_path, root, r"transform_train\.json: 3 training frames.*2 views")
    torch.save(torch.from_numpy(counts + 0.5), root / "events.pt")
    _expect(tmp_path, root, r"events\.pt: view 0 holds non-integer")
    (root / "events.pt").write_bytes(b"not a torch file")
    _expect(tmp_path, root, r"events\.pt: cannot read")
    (root / "events.pt").unlink()
    _expect(tmp_path, root, r"events\.pt: missing")
    torch.save(torch.from_numpy(counts), root / "events.pt")
    (root / "train" / "r_2.png").unlink()
    _expect(tmp_path, root, r"r_2\.png: missing")
    (root / "transform_test.json").write_text("{not json")
    _expect(tmp_path, root, r"transform_test\.json: unreadable JSON")
    (root / "transform_test.json").write_text(json.dumps({"camera_angle_x": ANGLE, "frames": []}))
    meta = {"camera_angle_x": ANGLE, "frames": [{"transform_matrix": np.eye(4).tolist()}] * 6}
    (root / "transform_train.json").write_text(json.dumps(meta))
    _expect(tmp_path, root, r"transform_train\.json: frame 0 has 1 sub-frame matrices")
    frames = [{"transform_matrix": [np.eye(4).tolist()] * 18}] * 6
    (root / "transform_train.json").write_text(json.dumps({"frames": frames}))
    _expect(tmp_path, root, r"transform_train\.json: missing or invalid camera_angle_x")


def test_bad_real_layouts(tmp_path):
    rng = np.random.default_rng(4)
    root = tmp_path / "r"
    rows, counts = make_real(root, rng)
    np.save(root / "poses_bounds.npy", rows[:-1])
    _expect(tmp_path, root, r"poses_bounds\.npy: 14 poses")
    np.save(root / "poses_bounds.npy", rows[:, :16])
    _expect(tmp_path, root, r"poses_bounds\.npy: expected a finite \(N, 17\)")
    (root / "poses_bounds.npy").write_bytes(b"garbage")
    _expect(tmp_path, root, r"poses_bounds\.npy: cannot read")
    np.save(root / "poses_bounds.npy", rows)
    (root / "images" / "005.jpg").unlink()
    _expect(tmp_path, root, r"images: 2 images but events\.pt has 3 views")
