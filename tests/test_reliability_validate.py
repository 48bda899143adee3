"""Issue 18: validate must not pass scenes that cannot train.

Each corruption below is applied with h5py to a small valid scene (written by schema.write); validate, read and
the `ev3dgs validate` / `info` / `train` commands must all refuse it with one line naming the path inside the
file. Odd-but-trainable scenes get a SchemaWarning and still train. The valid scenes the other test modules
build must still validate.
"""
from __future__ import annotations

import re
import shutil
import warnings

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ev3dgs import schema, schema_validate
from ev3dgs.cli import ingest
from ev3dgs.cli import main as cli
from ev3dgs.errors import InputError, SchemaError, SchemaWarning
from ev3dgs.events import Events
from ev3dgs.geometry import look_at, rotvec_to_matrix
from ev3dgs.io.davis import DavisOptions

from cli_exit import exit_code
from test_stability import tiny_scene  # noqa: E402,F401  (a fixture: the scene test_stability trains on)

from h5_edits import set_attr, set_value

W, H, VIEWS, S = 16, 12, 3, 3


def build_scene(rng: np.random.Generator, t_events: np.ndarray | None = None) -> schema.Scene:
    """3 views x 3 rigid pose samples over 10 ms exposures, 400 events inside them, every optional part."""
    K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    starts = np.arange(VIEWS, dtype=np.int64) * 50_000
    exposure = np.stack([starts, starts + 10_000], axis=1)
    pose_t = exposure[:, :1] + np.array([0, 5_000, 10_000])
    eyes = [3.0 * np.array([np.cos(a), np.sin(a), 0.4]) for a in np.linspace(0, 1.5, VIEWS)]
    poses = np.stack([[look_at(e + 0.05 * k, [0, 0, 0]) for k in range(S)] for e in eyes])
    n = 400
    if t_events is None:
        t_events = np.sort(rng.integers(0, VIEWS, n) * 50_000 + rng.integers(0, 10_000, n))
    ev = Events(t_events, rng.integers(0, W, n), rng.integers(0, H, n), rng.choice([-1, 1], n))
    img = lambda m: rng.integers(0, 256, (m, H, W, 3), dtype=np.uint8)  # noqa: E731
    return schema.Scene(
        name="r", source="test", camera=schema.Camera(W, H, K=K, background=(0.0, 0.0, 0.0)), events=ev,
        sensor=schema.EventSensor(0.2, 0.25, "none", 0, log_knee=0.05),
        train=schema.Train(img(VIEWS), exposure, poses, pose_t, img(VIEWS), poses[:, 1].copy()),
        test=schema.Test(img(2), np.stack([look_at([3.0, 1.0, 1.0], [0, 0, 0]), look_at([-3.0, 1, 1], [0, 0, 0])])),
        points=schema.Points(rng.normal(size=(30, 3)).astype(np.float32), rng.integers(0, 256, (30, 3), np.uint8)),
        bounds=np.array([[-1.0] * 3, [1.0] * 3]))


@pytest.fixture(scope="module")
def valid_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("valid") / "scene.h5"
    schema.write(build_scene(np.random.default_rng(0)), path)
    return path


# ------------------------------------------------------------------------------------- corruptions



def _empty(group, names):
    def fn(f):
        for n in names:
            a = f[f"{group}/{n}"][()]
            del f[f"{group}/{n}"]
            f.create_dataset(f"{group}/{n}", data=a[:0])
    return fn


def _scale_rotation(f):
    a = f["/train/poses"][()]
    a[1, 2, :3, :3] *= 1e6
    f["/train/poses"][...] = a


def _reflect(f):
    a = f["/train/poses"][()]
    a[0, 1, :3, 0] *= -1
    f["/train/poses"][...] = a


def _unsort_pose_t(f):
    a = f["/train/pose_t"][()]
    a[1, [0, 1]] = a[1, [1, 0]]
    f["/train/pose_t"][...] = a


def _shear(f):
    a = f["/test/poses"][()]
    a[1, 0, 1] += 1e-3
    f["/test/poses"][...] = a


TRAIN_PARTS = ("images", "exposure", "poses", "pose_t", "sharp", "sharp_poses")
ERRORS = [
    ("empty train", _empty("/train", TRAIN_PARTS), "/train/images: no views (N = 0)"),
    ("empty test", _empty("/test", ("images", "poses")), "/test/images: no views (M = 0)"),
    ("all-zero poses", set_value("/train/poses", 0.0), "/train/poses: pose [0, 0] is not rigid"),
    ("rotation x1e6", _scale_rotation, "/train/poses: pose [1, 2] is not rigid: its rotation part is not orthonormal"),
    ("reflection", _reflect, "/train/poses: pose [0, 1] is not rigid: its rotation part is a reflection"),
    ("last row", set_value("/train/poses", 0.5, (2, 0, 3, 0)), "/train/poses: pose [2, 0] is not rigid: last row"),
    ("translation 1e300", set_value("/train/poses", 1e300, (1, 1, 0, 3)), "/train/poses: pose [1, 1] has translation"),
    ("sharp pose scaled", set_value("/train/sharp_poses", 2.0, (2, 1, 1)), "/train/sharp_poses: pose [2] is not rigid"),
    ("test pose sheared", _shear, "/test/poses: pose [1] is not rigid"),
    ("log_knee 0", set_attr("/events", "log_knee", 0.0), "/events: attr log_knee must be a finite number > 0"),
    ("log_knee negative", set_attr("/events", "log_knee", -0.1), "/events: attr log_knee must be a finite number > 0"),
    ("log_knee nan", set_attr("/events", "log_knee", np.nan), "/events: attr log_knee must be a finite number > 0"),
    ("threshold 0", set_attr("/events", "neg_threshold", 0.0), "/events: attr neg_threshold must be a finite number > 0"),
    ("threshold inf", set_attr("/events", "pos_threshold", np.inf), "/events: attr pos_threshold must be a finite"),
    ("K zeros", set_value("/camera/K", 0.0), "/camera/K: focal lengths must be > 0"),
    ("negative fx", set_value("/camera/K", -20.0, (0, 0)), "/camera/K: focal lengths must be > 0"),
    ("fy zero", set_value("/camera/K", 0.0, (1, 1)), "/camera/K: focal lengths must be > 0"),
    ("K row 2", set_value("/camera/K", 2.0, (2, 2)), "/camera/K: not a pinhole matrix"),
    ("K lower", set_value("/camera/K", 0.3, (1, 0)), "/camera/K: not a pinhole matrix"),
    ("principal point nan", set_value("/camera/K", np.nan, (0, 2)), "/camera/K: non-finite value at index [0, 2]"),
    ("skew inf", set_value("/camera/K", np.inf, (0, 1)), "/camera/K: non-finite value at index [0, 1]"),
    ("pose_t unsorted", _unsort_pose_t, "/train/pose_t: view 1 pose times are not increasing"),
    ("pose_t repeated", set_value("/train/pose_t", 55_000, (1, 2)), "/train/pose_t: view 1 pose times are not increasing"),
    ("pose_t outside", set_value("/train/pose_t", 200_000, (2, 2)), "/train/pose_t: sample [2, 2] at t=200000 is outside"),
    ("exposure empty", set_value("/train/exposure", 50_000, (1, 1)), "/train/exposure: view 1 has start 50000 >= end"),
    ("exposure reversed", set_value("/train/exposure", 0, (2, 1)), "/train/exposure: view 2 has start 100000 >= end 0"),
    ("points 1e30", set_value("/points/xyz", 1e30, (4, 1)), "/points/xyz: value at index [4, 1] exceeds"),
    ("bounds 1e300", set_attr("/", "bounds", np.array([[-1e300] * 3, [1.0] * 3])), "/: attr bounds exceed"),
]


@pytest.mark.parametrize("name,corrupt,message", ERRORS, ids=[e[0] for e in ERRORS])
def test_corruption_is_a_named_error_everywhere(scene_copy, tmp_path, capsys, name, corrupt, message):
    with h5py.File(scene_copy, "r+") as f:
        corrupt(f)
    with pytest.raises(SchemaError) as info:
        schema.validate(scene_copy)
    assert str(info.value).startswith(message), str(info.value)
    with pytest.raises(SchemaError) as again:
        schema.read(scene_copy, require_complete=False)
    assert str(again.value) == str(info.value)
    capsys.readouterr()
    for argv in (["validate", str(scene_copy)], ["info", str(scene_copy)],
                 ["train", str(scene_copy), "--out", str(tmp_path / "run"), "--iterations", "1", "--quiet"]):
        assert cli.main(argv) == 2, argv
        out, err = capsys.readouterr()
        assert err == f"error: {info.value}\n" and out == "", (argv, out, err)
    assert ingest.main(["info", str(scene_copy)]) == 2


# ---------------------------------------------------------------------------------------- warnings

def _shift_events(f):
    f["/events/t"][...] = f["/events/t"][()] + 10**9


def _one_time(f):
    f["/events/t"][...] = 55_000


def _no_events(f):
    for name in ("t", "x", "y", "p"):
        a = f[f"/events/{name}"][()]
        del f[f"/events/{name}"]
        f.create_dataset(f"/events/{name}", data=a[:0])


WARNINGS = [
    ("events outside every exposure", _shift_events, "/events: no event lies inside any /train/exposure window"),
    ("all events at one time", _one_time, "/events/t: all 400 events have the same time 55000 us"),
    ("no events", _no_events, "/events: no event lies inside any /train/exposure window; the event loss has "
                              "nothing to use (the file has no events)"),
]


@pytest.mark.parametrize("name,corrupt,message", WARNINGS, ids=[w[0] for w in WARNINGS])
def test_odd_but_trainable_is_a_warning(scene_copy, capsys, name, corrupt, message):
    with h5py.File(scene_copy, "r+") as f:
        corrupt(f)
    with pytest.warns(SchemaWarning, match="^" + re.escape(message)):
        notes = schema.validate(scene_copy)
    assert len(notes) == 1 and notes[0].startswith(message), notes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert schema.validate(scene_copy, warn=False) == notes
    capsys.readouterr()
    assert cli.main(["validate", str(scene_copy)]) == 0
    out, err = capsys.readouterr()
    assert err == f"warning: {notes[0]}\n" and out == f"{scene_copy}: valid\n"
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # info shows it as a summary line, not as a Python warning
        assert cli.main(["info", str(scene_copy)]) == 0
    out, err = capsys.readouterr()
    assert out.splitlines()[-1] == f"warning  {notes[0]}" and err == ""


@pytest.mark.parametrize("corrupt", [None, _shift_events, _one_time], ids=["valid", "outside", "one time"])
def test_what_validate_passes_trains(scene_copy, tmp_path, capsys, corrupt):
    """Warnings are for scenes that train: two steps run and give a finite loss."""
    if corrupt is not None:
        with h5py.File(scene_copy, "r+") as f:
            corrupt(f)
    argv = ["train", str(scene_copy), "--out", str(tmp_path / "run"), "--iterations", "2", "--set", "init_points=50",
            "--set", "sh_degree=0", "--threads", "1", "--backend", "reference", "--set", "device=cpu"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SchemaWarning)
        assert cli.main(argv) == 0, capsys.readouterr().err
    assert "loss nan" not in capsys.readouterr().out


# ------------------------------------------------------------------------------------- rigid poses

def _write_poses(path, poses):
    with h5py.File(path, "r+") as f:
        f["/train/poses"][...] = poses


@st.composite
def rotations(draw):
    """Rotation vectors: generic, near identity (|v| ~ 1e-12..1e-3) and near pi (|v| = pi - 1e-12..1e-3)."""
    axis = np.array(draw(st.tuples(*[st.floats(-1, 1)] * 3)))
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    kind = draw(st.sampled_from(["generic", "identity", "pi"]))
    eps = 10.0 ** draw(st.floats(-12, -3))
    angle = {"generic": draw(st.floats(0, np.pi)), "identity": eps, "pi": np.pi - eps}[kind]
    return axis * angle


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rot=st.lists(rotations(), min_size=VIEWS * S, max_size=VIEWS * S),
       t=st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3),
       storage=st.sampled_from(["float64", "float32", "composed"]))
def test_rigid_poses_always_pass(scene_copy, rot, t, storage):
    m = np.tile(np.eye(4), (VIEWS, S, 1, 1))
    m[..., :3, :3] = rotvec_to_matrix(np.array(rot).reshape(VIEWS, S, 3))
    m[..., :3, 3] = t
    if storage == "float32":       # E2NeRF / Blender: float32 matrices stored as float64
        m = m.astype(np.float32).astype(np.float64)
    elif storage == "composed":    # 20 float32 products of rotations (a deep parent chain)
        R = m[..., :3, :3].astype(np.float32)
        for _ in range(20):
            R = R @ rotvec_to_matrix(np.full(3, 0.3)).astype(np.float32)
        m[..., :3, :3] = R
    _write_poses(scene_copy, m)
    schema.validate(scene_copy)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rot=rotations(), view=st.integers(0, VIEWS - 1), sample=st.integers(0, S - 1),
       kind=st.sampled_from(["scale", "shear", "reflect", "random"]),
       size=st.floats(1e-4, 1e6), seed=st.integers(0, 2**32 - 1))
def test_non_rigid_poses_always_fail(valid_file, tmp_path_factory, rot, view, sample, kind, size, seed):
    path = tmp_path_factory.mktemp("nonrigid") / "s.h5"
    shutil.copy(valid_file, path)
    rng = np.random.default_rng(seed)
    with h5py.File(path, "r") as f:
        m = f["/train/poses"][()]
    R = rotvec_to_matrix(rot)
    if kind == "scale":
        R = R * (1 + min(size, 10.0) * rng.choice([-0.09, 1.0]))   # x1.0009..x11 or x0.9999..x0.1
    elif kind == "shear":
        i, j = rng.choice(3, 2, replace=False)
        E = np.eye(3)
        E[i, j] = min(size, 1e3) * rng.choice([-1, 1])
        R = R @ E
    elif kind == "reflect":
        d = np.ones(3)
        d[rng.integers(3)] = -1.0
        R = R @ np.diag(d)
    else:
        R = rng.normal(size=(3, 3)) * size
    m[view, sample, :3, :3] = R
    _write_poses(path, m)
    with pytest.raises(SchemaError, match=rf"^/train/poses: pose \[{view}, {sample}\] is not rigid"):
        schema.validate(path)


def test_tolerance_bounds():
    """The documented sources of round-off stay well inside RIGID_TOL; a 1e-4 scale is well outside."""
    rng = np.random.default_rng(0)
    R = rotvec_to_matrix(rng.normal(size=(2000, 3)) * 2)
    err = lambda R: np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max()  # noqa: E731
    assert err(R.astype(np.float32).astype(np.float64)) < schema_validate.RIGID_TOL / 20
    assert err(np.round(R, 6)) < schema_validate.RIGID_TOL / 3            # six decimals of text
    assert err(R * (1 + 1e-4)) > schema_validate.RIGID_TOL * 10


# ------------------------------------------------------------------ existing producers still validate

def test_fixture_scenes_still_validate(tmp_path):
    import test_schema
    from test_e2nerf import make_real, make_synthetic

    from ev3dgs.io.e2nerf import import_e2nerf

    rng = np.random.default_rng(0)
    for i, full in enumerate((True, False)):
        path = schema.write(test_schema.make_scene(rng, full=full), tmp_path / f"schema{i}.h5")
        schema.validate(path)
    schema.write(test_schema.events_only(rng), tmp_path / "ev.h5")
    schema.validate(tmp_path / "ev.h5", require_complete=False)
    make_synthetic(tmp_path / "lego", rng)
    make_real(tmp_path / "real", rng)
    for name in ("lego", "real"):
        with warnings.catch_warnings():
            warnings.simplefilter("error", SchemaWarning)
            out = import_e2nerf(tmp_path / name, tmp_path / f"{name}.h5")
            assert schema.validate(out) == []


def test_training_fixture_scene_still_validates(tiny_scene):
    """The scene test_stability trains on (its fixture, imported above; test_train's is built the same way)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", SchemaWarning)
        assert schema.validate(tiny_scene) == []


def test_davis_recording_still_validates(tmp_path):
    from test_davis import SHARED

    from ev3dgs.io.davis import ingest_davis

    if not SHARED.exists():
        pytest.skip("shared recording not present")
    out = tmp_path / "davis.h5"
    ingest_davis(SHARED, out, DavisOptions(poses=False, events="margin", event_margin_ms=1.0, max_views=2))
    assert schema.validate(out) == []


# ------------------------------------------------------------------------------- ingest margin

@pytest.mark.parametrize("margin", ["-50", "-0.001", "nan", "inf", "-inf"])
def test_bad_event_margin_is_an_input_error(tmp_path, capsys, margin):
    with pytest.raises(InputError, match="^--event-margin-ms must be a finite number >= 0"):
        DavisOptions(event_margin_ms=float(margin))
    capsys.readouterr()
    rec = tmp_path / "rec.aedat4"
    rec.write_bytes(b"not read: the options are checked first")
    # argparse may refuse non-finite numbers itself (SystemExit 2), the library refuses the rest
    code = exit_code(ingest.main, ["davis", str(rec), "--out", str(tmp_path / "o.h5"), "--event-margin-ms", margin])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: ") and "event-margin-ms" in err, err
    assert not (tmp_path / "o.h5").exists()
