"""Tests of the scene file schema: round trips, laziness, compression, atomic writes, validation errors."""
from __future__ import annotations

import os

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ev3dgs import schema
from ev3dgs.errors import SchemaError
from ev3dgs.events import Events
from ev3dgs.geometry import rotvec_to_matrix
from ev3dgs.schema import Test as Views  # noqa: E402  (not a pytest class)
from ev3dgs.schema import (Camera, EventSensor, Imu, LazyArray, LazyEvents, Points, Scene, Train,
                           read, validate, write)

from h5_edits import replace, set_attr, set_value

W, H = 12, 8


def random_events(rng, n, w=W, h=H):
    t = np.sort(rng.integers(0, 100_000, n))
    return Events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n))


def random_poses(rng, shape):
    """Rigid camera-to-world poses (validate rejects anything else): random rotations and translations."""
    m = np.tile(np.eye(4), shape + (1, 1))
    m[..., :3, :3] = rotvec_to_matrix(rng.normal(size=shape + (3,)))
    m[..., :3, 3] = rng.normal(size=shape + (3,))
    return m


def make_scene(rng, n_events=500, n_views=3, samples=2, full=True, w=W, h=H):
    cam = Camera(w, h, K=np.array([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]]),
                 distortion=rng.normal(size=5) * 0.02, background=(0.0, 0.5, 1.0) if full else None)
    starts = np.arange(n_views, dtype=np.int64) * 10_000
    exposure = np.stack([starts, starts + 5_000], axis=1)
    pose_t = exposure[:, :1] + np.linspace(0, 5_000, samples).astype(np.int64)[None, :]
    poses = random_poses(rng, (n_views, samples))
    train = Train(rng.integers(0, 256, (n_views, h, w, 3), dtype=np.uint8), exposure, poses, pose_t,
                  rng.integers(0, 256, (n_views, h, w, 3), dtype=np.uint8) if full else None,
                  random_poses(rng, (n_views,)) if full else None)
    scene = Scene(name="cube", source="blender", camera=cam, events=random_events(rng, n_events, w, h),
                  sensor=EventSensor(0.25, 0.3, "RGGB", 100, log_knee=0.05 if full else None), train=train,
                  config={"seed": 3, "nested": {"a": [1, 2]}, "np": np.float32(1.5)})
    if full:
        scene.test = Views(rng.integers(0, 256, (2, h, w, 3), dtype=np.uint8), random_poses(rng, (2,)))
        scene.points = Points(rng.normal(size=(40, 3)).astype(np.float32),
                              rng.integers(0, 256, (40, 3), dtype=np.uint8))
        scene.imu = Imu(np.arange(20, dtype=np.int64) * 1000, rng.normal(size=(20, 3)).astype(np.float32),
                        rng.normal(size=(20, 3)).astype(np.float32), rng.normal(size=20).astype(np.float32))
        scene.bounds = np.array([[-1.0, -2, -3], [1, 2, 3]])
    return scene


def events_only(rng, n=300):
    return Scene(name="ev", source="sim", camera=Camera(W, H), events=random_events(rng, n),
                 sensor=EventSensor(0.2, 0.2, "none", 0))


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def scene_file(tmp_path, rng):
    path = tmp_path / "scene.h5"
    write(make_scene(rng), path)
    return path


def eq(a, b):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(a).dtype == np.asarray(b).dtype or not isinstance(a, LazyArray)


def assert_same(s: Scene, r: Scene):
    assert (r.name, r.source) == (s.name, s.source)
    assert r.created and r.created.endswith("+00:00")
    assert (r.camera.width, r.camera.height, r.camera.background) == (s.camera.width, s.camera.height,
                                                                      s.camera.background)
    if s.camera.K is None:
        assert r.camera.K is None
    else:
        eq(r.camera.K, s.camera.K)
    eq(r.camera.distortion, s.camera.distortion)
    assert r.sensor == s.sensor
    assert isinstance(r.events, LazyEvents) and len(r.events) == len(s.events)
    loaded = r.events.load()
    for k, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8)):
        eq(getattr(loaded, k), getattr(s.events, k))
        assert getattr(r.events, k).dtype == dt and getattr(loaded, k).dtype == dt
    for part in ("train", "test", "points", "imu"):
        a, b = getattr(s, part), getattr(r, part)
        assert (a is None) == (b is None), part
        if a is None:
            continue
        for k, v in vars(a).items():
            w = getattr(b, k)
            assert (v is None) == (w is None), (part, k)
            if v is not None:
                eq(w, v)
    if s.bounds is None:
        assert r.bounds is None
    else:
        eq(r.bounds, s.bounds)


def test_full_round_trip(tmp_path, rng):
    s = make_scene(rng)
    out = write(s, tmp_path / "a.h5")
    assert out == tmp_path / "a.h5"
    r = read(out)
    assert_same(s, r)
    assert r.config == {"seed": 3, "nested": {"a": [1, 2]}, "np": 1.5}
    assert s.created == ""                     # write does not mutate its input
    # large arrays are lazy, small ones are numpy
    assert isinstance(r.train.images, LazyArray) and isinstance(r.train.sharp, LazyArray)
    assert isinstance(r.test.images, LazyArray)
    assert isinstance(r.train.exposure, np.ndarray) and isinstance(r.points.xyz, np.ndarray)
    assert r.train.images.shape == (3, H, W, 3) and r.train.images.dtype == np.uint8
    assert len(r.train.images) == 3 and len(r.train) == 3
    eq(r.train.images[1], s.train.images[1])
    eq(r.train.images[0:2, 3:5], s.train.images[0:2, 3:5])
    eq(r.events.t[10:20], s.events.t[10:20])
    eq(r.events.x[[1, 5, 7]], s.events.x[[1, 5, 7]])
    eq(np.asarray(r.train.sharp), s.train.sharp)
    eq(r.test.images.read(), s.test.images)


def test_explicit_created_kept(tmp_path, rng):
    s = make_scene(rng, full=False)
    s.created = "2024-01-02T03:04:05+00:00"
    assert read(write(s, tmp_path / "a.h5")).created == "2024-01-02T03:04:05+00:00"


def test_events_only_round_trip(tmp_path, rng):
    s = events_only(rng)
    path = write(s, tmp_path / "ev.h5")
    with pytest.raises(SchemaError, match="^/camera/K: missing"):
        read(path)
    r = read(path, require_complete=False)
    assert_same(s, r)
    assert r.train is None and r.camera.K is None and r.config == {}
    validate(path, require_complete=False)
    with h5py.File(path) as f:
        assert "distortion" not in f["camera"] and "train" not in f


def test_rewrite_from_lazy(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(schema, "_COPY_BYTES", 64)      # force many small blocks when copying LazyArrays
    s = make_scene(rng)
    r = read(write(s, tmp_path / "a.h5"))
    r2 = read(write(r, tmp_path / "b.h5"))
    assert_same(s, r2)


def test_empty_events(tmp_path, rng):
    s = events_only(rng, 0)
    r = read(write(s, tmp_path / "e.h5"), require_complete=False)
    assert len(r.events) == 0 and len(r.events.load()) == 0


def test_plain_h5py_compressed_chunked(scene_file):
    with h5py.File(scene_file, "r") as f:
        assert f.attrs["format"] == "ev3dgs-scene" and f.attrs["version"] == 1
        for name in ("/events/t", "/events/x", "/events/y", "/events/p", "/train/images", "/train/sharp",
                     "/test/images"):
            assert f[name].compression == "gzip" and f[name].shuffle and f[name].chunks is not None, name
        assert f["/train/images"].chunks == (1, H, W, 3)
        assert f["/train/exposure"].chunks is None and f["/camera/K"].chunks is None
        assert f["/events/t"].dtype == np.int64 and f["/events/p"].dtype == np.int8


def test_atomic_write_failure_keeps_target(tmp_path, rng, monkeypatch):
    path = tmp_path / "scene.h5"
    path.write_bytes(b"previous contents")
    calls = {"n": 0}
    real = schema._put_large

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk on fire")
        return real(*args, **kwargs)

    monkeypatch.setattr(schema, "_put_large", failing)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write(make_scene(rng), path)
    assert path.read_bytes() == b"previous contents"
    assert sorted(os.listdir(tmp_path)) == ["scene.h5"]


def test_invalid_scene_write_keeps_target(tmp_path, rng):
    path = tmp_path / "scene.h5"
    path.write_bytes(b"old")
    s = make_scene(rng)
    s.events.t[5], s.events.t[6] = 90_000_000, 0        # unsorted: refused before writing anything
    with pytest.raises(SchemaError, match=r"^/events/t: not sorted \(first decrease at index 6\)"):
        write(s, path)
    s = make_scene(rng)
    s.train.pose_t = s.train.pose_t + 10**7              # caught by the post-write validation
    with pytest.raises(SchemaError, match="^/train/pose_t"):
        write(s, path)
    s = make_scene(rng)
    s.train.images = s.train.images.astype(np.float32)
    with pytest.raises(SchemaError, match="^/train/images: expected dtype uint8, found float32"):
        write(s, path)
    assert path.read_bytes() == b"old" and sorted(os.listdir(tmp_path)) == ["scene.h5"]


def test_unreadable_files(tmp_path):
    with pytest.raises(SchemaError, match="no such file"):
        read(tmp_path / "nope.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all" * 100)
    with pytest.raises(SchemaError, match="not a readable HDF5 file"):
        read(tmp_path / "junk.h5")
    with pytest.raises(SchemaError):
        read(tmp_path)


def test_truncated_file(tmp_path, rng):
    path = write(make_scene(rng, n_events=20_000), tmp_path / "a.h5")
    data = path.read_bytes()
    for cut in (len(data) // 2, len(data) - 100):
        bad = tmp_path / f"cut{cut}.h5"
        bad.write_bytes(data[:cut])
        with pytest.raises(SchemaError, match="not a readable HDF5 file|truncated"):
            read(bad)


def test_validate_accepts_open_file(scene_file):
    with h5py.File(scene_file, "r") as f:
        validate(f)


def _del(name):
    def fn(f):
        del f[name]
    return fn




def _unsort(f):
    t = f["/events/t"][()]
    t[41] = t[40] - 1
    f["/events/t"][...] = t


CORRUPTIONS = [
    ("missing images", _del("/train/images"), "/train/images: missing"),
    ("missing exposure", _del("/train/exposure"), "/train/exposure: missing"),
    ("missing events x", _del("/events/x"), "/events/x: missing"),
    ("missing camera", _del("/camera"), "/camera: missing"),
    ("missing K", _del("/camera/K"), "/camera/K: missing"),
    ("events t dtype", replace("/events/t", lambda f: f["/events/t"][()].astype(np.float64)),
     "/events/t: expected dtype int64, found float64"),
    ("images dtype", replace("/train/images", lambda f: f["/train/images"][()].astype(np.uint16)),
     "/train/images: expected dtype uint8, found uint16"),
    ("K shape", replace("/camera/K", np.eye(4)), "/camera/K: expected shape (3, 3), found (4, 4)"),
    ("images shape", replace("/train/images", lambda f: f["/train/images"][:, :, :-1]),
     f"/train/images: expected shape (N, H={H}, W={W}, 3), found (3, {H}, {W - 1}, 3)"),
    ("events length", replace("/events/p", lambda f: f["/events/p"][:-1]),
     "/events/p: expected shape (E=500,), found (499,)"),
    ("unsorted", _unsort, "/events/t: not sorted (first decrease at index 41)"),
    ("polarity", set_value("/events/p", 0, 7), "/events/p: value 0 at index 7"),
    ("x range", set_value("/events/x", W, 3), "/events/x: value 12 at index 3 is out of range"),
    ("y range", set_value("/events/y", H + 5, 9), "/events/y: value 13 at index 9 is out of range"),
    ("newer version", set_attr("/", "version", 2), "/: schema version 2 is newer than this reader (1)"),
    ("version not int", set_attr("/", "version", "1"), "/: attr version must be an integer"),
    ("format", set_attr("/", "format", "something-else"), "/: attr format is 'something-else'"),
    ("config", set_attr("/", "config", "{not json"), "/: attr config is not valid JSON"),
    ("config not object", set_attr("/", "config", "[1, 2]"), "/: attr config must be a JSON object"),
    ("bounds", set_attr("/", "bounds", np.array([[1.0, 0, 0], [0, 1, 1]])), "/: attr bounds"),
    ("width", set_attr("/camera", "width", 0), "/camera: attr width must be a positive integer"),
    ("background", set_attr("/camera", "background", np.array([0.0, 1.5, 0.2])), "/camera: attr background"),
    ("threshold", set_attr("/events", "pos_threshold", -0.1), "/events: attr pos_threshold"),
    ("color filter", set_attr("/events", "color_filter", "XYZW"), "/events: attr color_filter"),
    ("refractory", set_attr("/events", "refractory_us", -1), "/events: attr refractory_us"),
    ("poses without pose_t", _del("/train/pose_t"), "/train/pose_t: missing"),
    ("pose_t without poses", _del("/train/poses"), "/train/poses: missing"),
    ("pose_t outside exposure", set_value("/train/pose_t", 10_000_000, (1, 1)),
     "/train/pose_t: sample [1, 1] at t=10000000 is outside the exposure"),
    ("non-finite pose", set_value("/train/poses", np.nan, (2, 0, 1, 3)),
     "/train/poses: non-finite value at index [2, 0, 1, 3]"),
    ("mismatched N", replace("/train/exposure", lambda f: f["/train/exposure"][:2]),
     "/train/exposure: expected shape (N=3, 2), found (2, 2)"),
    ("exposure order", set_value("/train/exposure", 10_000, (1, 1)), "/train/exposure: view 1 has start 10000 >= end 10000"),
    ("sharp without poses", _del("/train/sharp_poses"), "/train/sharp_poses: missing"),
    ("sharp N", replace("/train/sharp", lambda f: f["/train/sharp"][:1]), "/train/sharp: expected shape (N=3,"),
    ("test poses shape", replace("/test/poses", lambda f: f["/test/poses"][:1]),
     "/test/poses: expected shape (M=2, 4, 4), found (1, 4, 4)"),
    ("test missing poses", _del("/test/poses"), "/test/poses: missing"),
    ("points dtype", replace("/points/xyz", lambda f: f["/points/xyz"][()].astype(np.float64)),
     "/points/xyz: expected dtype float32, found float64"),
    ("points rgb shape", replace("/points/rgb", lambda f: f["/points/rgb"][:5]),
     "/points/rgb: expected shape (P=40, 3)"),
    ("imu gyro", replace("/imu/gyro", lambda f: f["/imu/gyro"][:, :2]), "/imu/gyro: expected shape (I=20, 3)"),
    ("imu missing", _del("/imu/temperature"), "/imu/temperature: missing"),
    ("count convention", set_attr("/events", "count_convention", "floor"), "/events: attr count_convention"),
    ("raw matrix shape", set_attr("/events", "camera_raw_matrix", np.eye(2)), "/events: attr camera_raw_matrix"),
    ("raw matrix singular", set_attr("/events", "camera_raw_matrix", np.zeros((3, 3))),
     "/events: attr camera_raw_matrix"),
    ("raw matrix nan", set_attr("/events", "camera_raw_matrix", np.full((3, 3), np.nan)),
     "/events: attr camera_raw_matrix"),
    ("transfer", set_attr("/train", "transfer", "gamma22"), "/train: attr transfer must be one of"),
]


def test_fidelity_attrs_round_trip_and_defaults(tmp_path, rng):
    """count_convention, camera_raw_matrix (/events) and transfer (/train) round-trip; absent they read as
    None and the documented defaults apply."""
    s = make_scene(rng)
    s.sensor.count_convention = "exact_reference"
    s.sensor.camera_raw_matrix = np.array([[0.5, 0.1, 0.0], [0.1, 1.0, 0.1], [0.0, 0.1, 0.6]])
    s.train.transfer = "display"
    write(s, tmp_path / "a.h5")
    r = read(tmp_path / "a.h5")
    assert r.sensor.count_convention == "exact_reference" and r.train.transfer == "display"
    np.testing.assert_array_equal(r.sensor.camera_raw_matrix, s.sensor.camera_raw_matrix)
    old = make_scene(rng)
    write(old, tmp_path / "old.h5")
    r = read(tmp_path / "old.h5")
    assert r.sensor.count_convention is None and r.train.transfer is None and r.sensor.camera_raw_matrix is None
    assert schema.default_transfer("blender") == "srgb" and schema.default_transfer("e2nerf") == "display"
    assert schema.default_count_convention("e2nerf", {}) == "exact_reference"
    assert schema.default_count_convention("davis", {}) == "random_phase"
    assert schema.default_count_convention("blender", {"sim": {"dvs": {"reference": "random"}}}) == "random_phase"
    assert schema.default_count_convention("blender", {"sim": {"dvs": {"pos_threshold": 0.2}}}) == "exact_reference"


@pytest.mark.parametrize("name,corrupt,message", CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS])
def test_validation_errors(scene_file, name, corrupt, message):
    validate(scene_file)
    with h5py.File(scene_file, "r+") as f:
        corrupt(f)
    with pytest.raises(SchemaError) as info:
        validate(scene_file)
    assert str(info.value).startswith(message), str(info.value)
    with pytest.raises(SchemaError):
        read(scene_file)


def test_events_checked_across_scan_blocks(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(schema, "CHECK_ROWS", 64)
    path = write(make_scene(rng), tmp_path / "a.h5")
    with h5py.File(path, "r+") as f:
        t = f["/events/t"][()]
        t[128] = t[127] - 1                     # decrease exactly at a block boundary
        f["/events/t"][...] = t
    with pytest.raises(SchemaError, match=r"^/events/t: not sorted \(first decrease at index 128\)"):
        validate(path)
    with h5py.File(path, "r+") as f:
        f["/events/t"][...] = np.sort(t)
        f["/events/x"][200] = W
    with pytest.raises(SchemaError, match="^/events/x: value 12 at index 200"):
        validate(path)


@pytest.mark.filterwarnings("ignore::ev3dgs.errors.SchemaWarning")  # random events may miss every exposure
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n_events=st.integers(0, 300), n_views=st.integers(1, 4), samples=st.integers(1, 3),
       w=st.integers(1, 9), h=st.integers(1, 9), full=st.booleans(), seed=st.integers(0, 2**32 - 1))
def test_property_round_trip(tmp_path, n_events, n_views, samples, w, h, full, seed):
    s = make_scene(np.random.default_rng(seed), n_events, n_views, samples, full, w, h)
    path = write(s, tmp_path / "p.h5")
    assert_same(s, read(path))
