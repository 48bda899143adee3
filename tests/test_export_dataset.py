"""`ev3dgs export-dataset` (issue 19): every format checked against something independent of the exporter: a
loader written here from the published layout rules, our importer (`ingest e2nerf`), dv-processing, h5py
with DSEC's documented ms_to_idx definition, and binning done here with np.add.at.

Precision of the conversions (why the comparisons below are exact):
- images: the scene's images are uint8 and PNG is lossless, so every pixel comes back bit-exact;
- poses: JSON (Python's repr of float64) and .npy float64 round-trip a double exactly, and the OpenCV <->
  OpenGL/LLFF axis changes only permute columns and flip signs (exact in floating point). The fixture's pose
  samples lie exactly at the bin-edge / mid-exposure times, where the exporter's interpolation returns the
  stored sample itself;
- events: counts per (view, bin, pixel) are integers, exact in float64; what the E2NeRF layout loses (the
  times inside a bin, ON/OFF pairs cancelling inside a bin, events outside the exposures) is by design and
  checked to be exactly that;
- intrinsics through camera_angle_x: fx -> 2 atan(W / 2fx) -> W / (2 tan(angle / 2)) is a few float64
  roundings of O(1) quantities, so 1e-12 relative (conftest's tolerance policy).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from ev3dgs import schema
from ev3dgs.cli.main import main
from ev3dgs.events import Events
from ev3dgs.exporters import export_dataset
from ev3dgs.event_file import EventFile
from ev3dgs.exporters.torch_file import save_streamed
from ev3dgs.geometry import intrinsics, rotvec_to_matrix
from ev3dgs.io.e2nerf import import_e2nerf

W, H, N, M, S = 12, 9, 4, 3, 9          # views, novel views, pose samples per view (8 intervals)
PERIOD, SPAN, START = 10_000, 8_000, 500  # us: view v exposes [v*PERIOD + START, + SPAN]
GL = np.diag([1.0, -1.0, -1.0, 1.0])      # OpenCV <-> OpenGL camera axes (written out here on purpose)


def _rigid(rng, n):
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = rotvec_to_matrix(rng.normal(size=(n, 3)))
    m[:, :3, 3] = rng.normal(size=(n, 3)) * 2
    return m


def make_scene(path, seed=0, n_events=4000, source="blender", pos=0.25, neg=0.2):
    rng = np.random.default_rng(seed)
    exposure = np.array([[v * PERIOD + START, v * PERIOD + START + SPAN] for v in range(N)], np.int64)
    pose_t = exposure[:, :1] + np.arange(S, dtype=np.int64)[None] * (SPAN // (S - 1))
    t = np.sort(rng.integers(0, N * PERIOD + 2000, n_events))
    t[:N] = exposure[:, 0]                    # events exactly at an exposure start ...
    t[N:2 * N] = exposure[:, 1]               # ... and end (the last bin is closed)
    t = np.sort(t)
    ev = Events(t, rng.integers(0, W, n_events), rng.integers(0, H, n_events), rng.choice([-1, 1], n_events))
    img = lambda n: rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8)  # noqa: E731
    sc = schema.Scene(
        name="fixture", source=source, camera=schema.Camera(W, H, intrinsics(W, H, 50.0), background=(1.0, 1.0, 1.0)),
        events=ev, sensor=schema.EventSensor(pos, neg, count_convention="random_phase"),
        train=schema.Train(images=img(N), exposure=exposure, poses=np.stack([_rigid(rng, S) for _ in range(N)]),
                           pose_t=pose_t, sharp=img(N), sharp_poses=_rigid(rng, N), transfer="srgb"),
        test=schema.Test(img(M), _rigid(rng, M)),
        points=schema.Points(rng.normal(size=(50, 3)).astype(np.float32),
                             rng.integers(0, 256, (50, 3), dtype=np.uint8)),
        bounds=np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    return schema.write(sc, path), sc


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    path, sc = make_scene(d / "scene.h5")
    return path, sc


def edges_here(b=4):
    """Bin edges written out from the layout rule: b+1 evenly spread over [start, end] (SPAN divisible by b)."""
    start = np.arange(N, dtype=np.int64)[:, None] * PERIOD + START
    return start + np.arange(b + 1, dtype=np.int64)[None] * (SPAN // b)


def counts_here(ev, edges):
    """(N, b, H*W) signed counts with edges[v,k] <= t < edges[v,k+1], the last bin closed."""
    out = np.zeros((len(edges), edges.shape[1] - 1, H * W))
    for v, row in enumerate(edges):
        for k in range(len(row) - 1):
            last = k == len(row) - 2
            m = (ev.t >= row[k]) & ((ev.t <= row[k + 1]) if last else (ev.t < row[k + 1]))
            np.add.at(out[v, k], ev.y[m].astype(np.int64) * W + ev.x[m], ev.p[m])
    return out


def _rgb(path):
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


# ------------------------------------------------------------------------------------------ e2nerf

def load_e2nerf_synthetic(d: Path):
    """An E2NeRF synthetic-layout loader written from the layout rules (load_blender.py / E2GS), not ours."""
    meta = json.loads((d / "transform_train.json").read_text())
    test = json.loads((d / "transform_test.json").read_text())
    imgs, poses = [], []
    for num, frame in zip(range(0, 200 * 2, 2), meta["frames"][0:200:2]):
        rgba = _rgb(d / f"train/r_{num}.png")
        assert rgba.shape[2] == 4 and np.all(rgba[..., 3] == 255)
        imgs.append(rgba[..., 2::-1])
        poses.append(np.array([frame["transform_matrix"][i] for i in (1, 5, 9, 13, 17)]))
    test_imgs = [_rgb(d / f"test/r_{i}.png")[..., 2::-1] for i in range(len(test["frames"][0:200]))]
    test_poses = [np.array(f["transform_matrix"][1]) for f in test["frames"][0:200]]
    fl = 0.5 * imgs[0].shape[1] / np.tan(0.5 * float(meta["camera_angle_x"]))
    events = torch.load(d / "events.pt", weights_only=True)
    return dict(imgs=np.array(imgs), poses=np.array(poses), test_imgs=np.array(test_imgs),
                test_poses=np.array(test_poses), focal=fl, events=events)


def test_e2nerf_independent_loader(scene, tmp_path):
    path, sc = scene
    out = tmp_path / "e2"
    export_dataset(path, "e2nerf", out, quiet=True)
    got = load_e2nerf_synthetic(out)
    assert np.array_equal(got["imgs"], sc.train.images)
    # sub-frames 1, 5, .., 17 sit at the bin edges = pose samples 0, 2, .., 8 of the fixture
    assert np.array_equal(got["poses"], sc.train.poses[:, ::2] @ GL)
    K = sc.camera.K
    assert got["focal"] == pytest.approx(K[0, 0], rel=1e-12)
    assert got["events"].dtype == torch.float64 and tuple(got["events"].shape) == (N, 4, H * W)
    assert np.array_equal(got["events"].numpy(), counts_here(sc.events, edges_here()))
    # test split: even = blur view (sharp frame of training view k), odd = novel view k; K = min(N, M) pairs
    assert np.array_equal(got["test_imgs"][0::2], sc.train.sharp[:M])
    assert np.array_equal(got["test_imgs"][1::2], sc.test.images)
    assert np.array_equal(got["test_poses"][0::2], sc.train.sharp_poses[:M] @ GL)
    assert np.array_equal(got["test_poses"][1::2], sc.test.poses @ GL)
    readme = (out / "README.txt").read_text()
    assert "asymmetric" in readme and "random_phase" in readme and "sRGB" in readme


def test_e2nerf_importer_gives_the_scene_back(scene, tmp_path):
    from ev3dgs.train.events import bin_signed_events

    path, sc = scene
    export_dataset(path, "e2nerf", tmp_path / "e2", quiet=True)
    back = schema.read(import_e2nerf(tmp_path / "e2", tmp_path / "back.h5", 0.25, 0.2))
    assert np.array_equal(np.asarray(back.train.images), sc.train.images)
    assert np.array_equal(back.train.poses, sc.train.poses[:, ::2])          # exact, see module doc
    assert np.allclose(back.camera.K, sc.camera.K, rtol=1e-12, atol=0)
    ev = back.events.load()
    rebinned = bin_signed_events(ev.t, ev.x, ev.y, ev.p, back.train.pose_t, H, W).reshape(N, 4, H * W)
    expected = counts_here(sc.events, edges_here())
    assert np.array_equal(rebinned, expected)
    # what the layout loses is exactly ON/OFF cancellation and the out-of-exposure events
    assert len(ev) == int(np.abs(expected).sum()) < len(sc.events)
    test = np.asarray(back.test.images)
    assert np.array_equal(test[1::2], sc.test.images) and np.array_equal(test[0::2], sc.train.sharp[:M])
    assert np.array_equal(back.test.poses[1::2], sc.test.poses)


def test_e2nerf_more_bins(scene, tmp_path):
    path, sc = scene
    export_dataset(path, "e2nerf", tmp_path / "e8", quiet=True, bins=8)
    got = torch.load(tmp_path / "e8" / "events.pt", weights_only=True).numpy()
    assert np.array_equal(got, counts_here(sc.events, edges_here(8)))
    meta = json.loads((tmp_path / "e8" / "transform_train.json").read_text())
    mats = np.array(meta["frames"][0]["transform_matrix"])
    assert mats.shape == (34, 4, 4)
    assert np.array_equal(mats[1::4], sc.train.poses[0] @ GL)                 # 9 edges = the 9 samples


def test_e2nerf_llff_layout(scene, tmp_path):
    path, sc = scene
    out = tmp_path / "llff"
    export_dataset(path, "e2nerf", out, quiet=True, layout="llff")
    # independent reading of the LLFF rules: 3x5 [down, right, back | t | hwf] per row, then near, far
    arr = np.load(out / "poses_bounds.npy")
    assert arr.shape == (N * 5, 17) and arr.dtype == np.float64
    m = arr[:, :15].reshape(-1, 3, 5)
    c2w = np.zeros((len(m), 4, 4))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = m[:, :, 1], m[:, :, 0], -m[:, :, 2], m[:, :, 3]
    c2w[:, 3, 3] = 1
    assert np.array_equal(c2w.reshape(N, 5, 4, 4), sc.train.poses[:, ::2])
    assert np.array_equal(m[0, :, 4], [H, W, sc.camera.K[0, 0]])
    near, far = arr[0, 15:]
    assert 0 < near < far
    files = sorted(p for p in (out / "images").iterdir())
    assert [p.name for p in files] == [f"{5 * i:03d}.png" for i in range(N)]
    assert np.array_equal(np.array([_rgb(p)[..., ::-1] for p in files]), sc.train.images)
    ev = torch.load(out / "events.pt", weights_only=True).numpy()
    assert np.array_equal(ev, counts_here(sc.events, edges_here()))
    back = schema.read(import_e2nerf(out, tmp_path / "back.h5"))
    assert np.array_equal(back.train.poses, sc.train.poses[:, ::2])
    assert np.array_equal(np.asarray(back.train.images), sc.train.images)
    assert "test views (3)" in (out / "README.txt").read_text()


def test_e2nerf_needs_poses(tmp_path):
    rng = np.random.default_rng(3)
    sc = schema.Scene(name="np", source="davis", camera=schema.Camera(W, H, intrinsics(W, H, 50.0)),
                      events=Events(np.arange(10), rng.integers(0, W, 10), rng.integers(0, H, 10),
                                    np.ones(10)),
                      sensor=schema.EventSensor(),
                      train=schema.Train(images=rng.integers(0, 256, (2, H, W, 3), dtype=np.uint8),
                                         exposure=np.array([[0, 5], [5, 9]])))
    p = schema.write(sc, tmp_path / "np.h5")
    assert main(["export-dataset", str(p), "--format", "e2nerf", "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
    # the events need no poses
    assert main(["export-dataset", str(p), "--format", "events-h5", "--out", str(tmp_path / "o"), "--quiet"]) == 0


# ------------------------------------------------------------------------------------------ events-h5

def test_events_h5_dsec_layout(scene, tmp_path):
    path, sc = scene
    out = tmp_path / "h5"
    export_dataset(path, "events-h5", out, quiet=True)
    with h5py.File(out / "events.h5", "r") as f:
        x, y, t, p = (f[f"events/{n}"][()] for n in "xytp")
        assert (x.dtype, y.dtype, t.dtype, p.dtype) == (np.uint16, np.uint16, np.uint32, np.uint8)
        off = int(f["t_offset"][()])
        ms_to_idx = f["ms_to_idx"][()]
    ev = sc.events
    assert off % 1000 == 0 and off <= ev.t[0]
    assert np.array_equal(t.astype(np.int64) + off, ev.t) and np.array_equal(x, ev.x) and np.array_equal(y, ev.y)
    assert np.array_equal(p, (ev.p > 0).astype(np.uint8))
    # DSEC's definition: t[ms_to_idx[ms]] >= 1000 ms and t[ms_to_idx[ms] - 1] < 1000 ms
    for ms, i in enumerate(ms_to_idx.astype(np.int64)):
        assert i == len(t) or t[i] >= 1000 * ms
        assert i == 0 or t[i - 1] < 1000 * ms
    assert ms_to_idx[-1] == len(t) and ms_to_idx[0] == 0
    exp = np.loadtxt(out / "images" / "exposure_timestamps.txt", delimiter=",", dtype=np.int64)
    assert np.array_equal(exp, sc.train.exposure)
    imgs = sorted((out / "images").glob("*.png"))
    assert np.array_equal(np.array([_rgb(q)[..., ::-1] for q in imgs]), sc.train.images)


@settings(max_examples=25, deadline=None)
@given(ts=st.lists(st.integers(0, 50_000), max_size=300), chunk=st.integers(1, 64),
       queries=st.lists(st.integers(-10, 60_000), min_size=1, max_size=20))
def test_event_stream_searchsorted_matches_numpy(tmp_path_factory, ts, chunk, queries):
    t = np.sort(np.asarray(ts, np.int64))
    path = tmp_path_factory.mktemp("es") / "e.h5"
    with h5py.File(path, "w") as f:
        for n, a in (("t", t), ("x", np.zeros(len(t), np.uint16)), ("y", np.zeros(len(t), np.uint16)),
                     ("p", np.ones(len(t), np.int8))):
            f.create_dataset(f"events/{n}", data=a)
    with EventFile(path, chunk=chunk) as es:
        for side in ("left", "right"):
            assert np.array_equal(es.searchsorted(queries, side), np.searchsorted(t, queries, side))
        assert np.array_equal(np.concatenate([b.t for b in es.blocks()] or [np.zeros(0, np.int64)]), t)


def test_outputs_do_not_depend_on_the_chunk_size(scene, tmp_path, monkeypatch):
    path, _ = scene
    export_dataset(path, "events-h5", tmp_path / "a", quiet=True)
    export_dataset(path, "e2nerf", tmp_path / "c", quiet=True)
    monkeypatch.setattr(EventFile.__init__, "__defaults__", (7,))      # 7-event blocks
    export_dataset(path, "events-h5", tmp_path / "b", quiet=True)
    export_dataset(path, "e2nerf", tmp_path / "d", quiet=True)
    with h5py.File(tmp_path / "a" / "events.h5") as fa, h5py.File(tmp_path / "b" / "events.h5") as fb:
        for n in ("events/x", "events/y", "events/t", "events/p", "ms_to_idx", "t_offset"):
            assert np.array_equal(fa[n][()], fb[n][()])
    a = torch.load(tmp_path / "c" / "events.pt", weights_only=True)
    b = torch.load(tmp_path / "d" / "events.pt", weights_only=True)
    assert torch.equal(a, b)


# ------------------------------------------------------------------------------------------ aedat4

def test_aedat4_read_back_by_dv_processing(scene, tmp_path):
    dv = pytest.importorskip("dv_processing")
    path, sc = scene
    out = tmp_path / "a4"
    export_dataset(path, "aedat4", out, quiet=True)
    r = dv.io.MonoCameraRecording(str(out / "recording.aedat4"))
    assert tuple(r.getEventResolution()) == (W, H)
    parts = []
    while (b := r.getNextEventBatch()) is not None:
        parts.append(b.numpy())
    got = np.concatenate(parts)
    ev = sc.events
    assert np.array_equal(got["timestamp"], ev.t) and np.array_equal(got["x"], ev.x)
    assert np.array_equal(got["y"], ev.y) and np.array_equal(got["polarity"].astype(bool), ev.p > 0)
    frames = []
    while (f := r.getNextFrame()) is not None:
        frames.append(f)
    assert len(frames) == N
    for i, f in enumerate(frames):
        assert np.array_equal(f.image[..., ::-1], sc.train.images[i])
        assert f.timestamp == sc.train.exposure[i, 0]
        assert f.exposure.total_seconds() * 1e6 == pytest.approx(SPAN, abs=0.5)


# ------------------------------------------------------------------------------------------ transforms

@pytest.mark.parametrize("images", ["blurry", "sharp", "both"])
def test_transforms_poses_back_to_opencv(scene, tmp_path, images):
    path, sc = scene
    out = tmp_path / images
    export_dataset(path, "transforms", out, quiet=True, images=images)
    meta = json.loads((out / "transforms.json").read_text())
    K = sc.camera.K
    assert (meta["fl_x"], meta["fl_y"], meta["w"], meta["h"]) == (K[0, 0], K[1, 1], W, H)
    assert (meta["cx"], meta["cy"]) == (K[0, 2] + 0.5, K[1, 2] + 0.5)      # pixel corner at 0, as COLMAP
    frames = {f["file_path"]: np.array(f["transform_matrix"]) @ GL for f in meta["frames"]}
    expect = {}
    if images in ("blurry", "both"):   # mid-exposure = pose sample 4 of 8 intervals
        expect.update({f"blurry/{i:03d}.png": (sc.train.poses[i, S // 2], sc.train.images[i]) for i in range(N)})
    if images in ("sharp", "both"):
        expect.update({f"sharp/{i:03d}.png": (sc.train.sharp_poses[i], sc.train.sharp[i]) for i in range(N)})
    tests = {f"test/{i:03d}.png": (sc.test.poses[i], sc.test.images[i]) for i in range(M)}
    assert set(frames) == set(expect) | set(tests)
    assert sorted(meta["train_filenames"]) == sorted(expect) and meta["test_filenames"] == sorted(tests)
    for name, (pose, img) in {**expect, **tests}.items():
        assert np.array_equal(frames[name], pose), name
        assert np.array_equal(_rgb(out / name)[..., ::-1], img)
    blender = json.loads((out / "transforms_train.json").read_text())
    assert blender["camera_angle_x"] == pytest.approx(2 * np.arctan(W / (2 * K[0, 0])), rel=1e-12)
    for f in blender["frames"]:        # NeRF/3DGS Blender loaders append ".png"
        assert (out / (f["file_path"] + ".png")).is_file()
        assert np.array_equal(np.array(f["transform_matrix"]) @ GL, frames[f["file_path"][2:] + ".png"])
    assert meta["ply_file_path"] == "points3d.ply" and (out / "points3d.ply").is_file()


# ------------------------------------------------------------------------------------------ CLI and folder

def _cli(*args):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    return subprocess.run([sys.executable, "-m", "ev3dgs.cli.main", *map(str, args)], capture_output=True,
                          text=True, env=env)


def test_non_empty_out_needs_force(scene, tmp_path):
    path, _ = scene
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = _cli("export-dataset", path, "--format", "transforms", "--out", out)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and r.stderr.startswith("error: ")
    assert "--force" in r.stderr and (out / "keep.txt").read_text() == "mine"
    assert main(["export-dataset", str(path), "--format", "transforms", "--out", str(out), "--force",
                 "--quiet"]) == 0
    assert not (out / "keep.txt").exists() and (out / "transforms.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]        # no staging folder left behind
    (tmp_path / "f").write_text("x")
    assert main(["export-dataset", str(path), "--format", "transforms", "--out", str(tmp_path / "f")]) == 2
    # an empty folder is fine without --force
    (tmp_path / "empty").mkdir()
    assert main(["export-dataset", str(path), "--format", "aedat4", "--out", str(tmp_path / "empty"),
                 "--quiet"]) == 0


def test_interrupted_export_leaves_nothing(scene, tmp_path, monkeypatch):
    import ev3dgs.exporters.events_h5 as m

    path, _ = scene
    real = m.write_png

    def boom(p, *a, **k):
        if p.name.endswith("2.png"):
            raise KeyboardInterrupt
        return real(p, *a, **k)

    monkeypatch.setattr(m, "write_png", boom)
    assert main(["export-dataset", str(path), "--format", "events-h5", "--out", str(tmp_path / "o")]) == 130
    assert list(tmp_path.iterdir()) == []
    # an existing export survives a failed --force re-export
    monkeypatch.setattr(m, "write_png", real)
    export_dataset(path, "events-h5", tmp_path / "o", quiet=True)
    monkeypatch.setattr(m, "write_png", boom)
    assert main(["export-dataset", str(path), "--format", "events-h5", "--out", str(tmp_path / "o"), "--force"]) == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"] and (tmp_path / "o" / "events.h5").is_file()


def test_stale_stage_of_a_dead_process_is_removed(scene, tmp_path):
    path, _ = scene
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    stale = tmp_path / f".o.tmp-{p.pid}"
    stale.mkdir()
    (stale / "half.png").write_bytes(b"x")
    export_dataset(path, "transforms", tmp_path / "o", quiet=True)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["o"]


def test_out_containing_the_scene_is_refused(tmp_path):
    path, _ = make_scene(tmp_path / "s.h5", n_events=50)
    assert main(["export-dataset", str(path), "--format", "aedat4", "--out", str(tmp_path), "--force"]) == 2
    assert path.is_file()


def test_cli_prints_one_summary_and_no_bar_when_piped(scene, tmp_path):
    path, _ = scene
    r = _cli("export-dataset", path, "--format", "e2nerf", "--out", tmp_path / "e")
    assert r.returncode == 0 and r.stderr == "" and "README.txt" in r.stdout   # no bar when not a TTY


# ------------------------------------------------------------------------------------------ torch file

@settings(max_examples=20, deadline=None)
@given(shape=st.tuples(st.integers(1, 5), st.integers(1, 4), st.integers(1, 30)),
       dtype=st.sampled_from([np.float64, np.float32, np.int8]), step=st.integers(1, 5))
def test_streamed_torch_file_loads_like_torch_save(tmp_path_factory, shape, dtype, step):
    rng = np.random.default_rng(0)
    a = rng.integers(-100, 100, shape).astype(dtype)
    p = tmp_path_factory.mktemp("pt") / "x.pt"
    save_streamed(p, shape, dtype, (a[i:i + step] for i in range(0, shape[0], step)))
    for kw in ({"weights_only": True}, {"weights_only": True, "mmap": True}):
        t = torch.load(p, **kw)
        assert t.dtype == torch.from_numpy(a).dtype and tuple(t.shape) == shape
        assert np.array_equal(t.numpy(), a)


@settings(max_examples=30, deadline=None)
@given(shape=st.lists(st.integers(1, 6), min_size=1, max_size=4).map(tuple),
       dtype=st.sampled_from([np.float64, np.float32, np.int8, np.int16, np.int32, np.int64, np.uint8]))
def test_tensor_pickle_is_torchs_own(shape, dtype):
    """Our data.pkl is byte-for-byte what torch.save pickles for the same contiguous tensor."""
    import io
    import zipfile

    from ev3dgs.exporters.torch_file import tensor_pickle

    buf = io.BytesIO()
    torch.save(torch.zeros(shape, dtype=torch.from_numpy(np.zeros(1, dtype)).dtype), buf)
    z = zipfile.ZipFile(buf)
    name = next(n for n in z.namelist() if n.endswith("/data.pkl"))
    assert z.read(name) == tensor_pickle(shape, dtype)


def test_e2nerf_events_pt_is_never_whole_in_memory(tmp_path):
    """tracemalloc (numpy and torch.save's buffers included) stays far below the size of events.pt: the
    tensor is streamed one view at a time. 100 views x 4 bins x 128x128 float64 = 52 MB; one view's counts
    and binning temporaries are ~1 MB, the rest (scene metadata, PNG encoding, h5py reads) a few MB."""
    import tracemalloc

    from ev3dgs.geometry import look_at

    views, h, w = 100, 128, 128
    rng = np.random.default_rng(5)
    n = views * 500
    t = np.sort(rng.integers(0, views * 1000, n))
    exposure = np.array([[v * 1000, v * 1000 + 800] for v in range(views)], np.int64)
    pose = look_at([0, -4, 1], [0, 0, 0])
    sc = schema.Scene(name="m", source="blender", camera=schema.Camera(w, h, intrinsics(w, h, 40.0)),
                      events=Events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n)),
                      sensor=schema.EventSensor(),
                      train=schema.Train(images=np.zeros((views, h, w, 3), np.uint8), exposure=exposure,
                                         poses=np.tile(pose, (views, 2, 1, 1)), pose_t=exposure))
    p = schema.write(sc, tmp_path / "m.h5")
    pt_bytes = views * 4 * h * w * 8
    tracemalloc.start()
    try:
        export_dataset(p, "e2nerf", tmp_path / "o", quiet=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert (tmp_path / "o" / "events.pt").stat().st_size > pt_bytes
    assert peak < pt_bytes / 4, f"peak {peak / 2**20:.1f} MB for a {pt_bytes / 2**20:.1f} MB events.pt"


@pytest.mark.parametrize("fmt", ["e2nerf", "events-h5", "aedat4", "transforms"])
def test_scene_without_events(tmp_path, fmt):
    from ev3dgs.geometry import look_at

    exposure = np.array([[0, 10], [20, 30]])
    sc = schema.Scene(name="z", source="blender", camera=schema.Camera(8, 6, intrinsics(8, 6, 50.0)), events=Events(),
                      sensor=schema.EventSensor(),
                      train=schema.Train(images=np.zeros((2, 6, 8, 3), np.uint8), exposure=exposure,
                                         poses=np.tile(look_at([0, -3, 0], [0, 0, 0]), (2, 2, 1, 1)), pose_t=exposure))
    with pytest.warns(Warning):
        p = schema.write(sc, tmp_path / "z.h5")
    with pytest.warns(Warning):
        export_dataset(p, fmt, tmp_path / "o", quiet=True)
    if fmt == "events-h5":
        with h5py.File(tmp_path / "o" / "events.h5") as f:
            assert f["events/t"].shape == (0,) and list(f["ms_to_idx"][()]) == [0, 0]
    if fmt == "e2nerf":
        assert not torch.load(tmp_path / "o" / "events.pt", weights_only=True).any()
