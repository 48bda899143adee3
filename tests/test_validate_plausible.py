"""What a camera makes impossible is refused, what is merely odd is a warning, and a damaged chunk of data
that only eval or export would read is found by validate (read_data) — each on a small valid scene edited with
h5py. Thresholds are physical: a pinhole's field of view below 180 deg, a frame exposed for less than an
hour, events within days of the frames."""
from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.errors import SchemaError

from test_reliability_validate import W, H, valid_file  # noqa: F401  (valid_file: a fixture; scene_copy is conftest's)


def _K(f, **entries):
    K = f["/camera/K"][()]
    for (i, j), v in {(0, 0): entries.get("fx"), (1, 1): entries.get("fy"), (0, 2): entries.get("cx"),
                      (1, 2): entries.get("cy")}.items():
        if v is not None:
            K[i, j] = v
    f["/camera/K"][...] = K


def _exposure(f, view, length):
    e = f["/train/exposure"][()]
    e[view, 1] = e[view, 0] + length
    f["/train/exposure"][...] = e
    pt = f["/train/pose_t"][()]                              # pose samples stay inside their exposure
    pt[view] = np.linspace(e[view, 0], e[view, 1], pt.shape[1]).astype(np.int64)
    f["/train/pose_t"][...] = pt


def _last_event(f, t):
    ts = f["/events/t"][()]
    ts[-1] = t
    f["/events/t"][...] = ts


ERRORS = [
    ("focal length 1e-9 px", lambda f: _K(f, fx=1e-9), r"/camera/K: fx = 1e-09 px gives a 180 deg field of view"),
    ("focal length 1e9 px", lambda f: _K(f, fx=1e9, fy=1e9), r"/camera/K: fx = 1e\+09 px gives a"),
    ("pixels 20:1", lambda f: _K(f, fx=400.0), r"/camera/K: fx / fy = 20"),
    ("principal point at x = 1e7", lambda f: _K(f, cx=1e7), r"/camera/K: principal point cx = 1e\+07 lies more"),
    ("principal point at y = -2H", lambda f: _K(f, cy=-2.0 * H), r"/camera/K: principal point cy = -24"),
    ("an exposure of 1e15 us", lambda f: _exposure(f, 1, 10**15), r"/train/exposure: view 1 is exposed for 1e\+09 s"),
    ("an event at t = 2^62", lambda f: _last_event(f, 2**62), r"/events/t: the last event .* at t = 4611686018427387904"),
]


@pytest.mark.parametrize("name,edit,message", ERRORS, ids=[e[0] for e in ERRORS])
def test_impossible_camera_or_times_are_errors(scene_copy, name, edit, message):
    with h5py.File(scene_copy, "r+") as f:
        edit(f)
    with pytest.raises(SchemaError, match="^" + message):
        schema.validate(scene_copy)


WARNINGS = [
    ("170 deg field of view", lambda f: _K(f, fx=W / 2 / np.tan(np.radians(85)), fy=W / 2 / np.tan(np.radians(85))),
     "/camera/K: fx = "),
    ("principal point just outside", lambda f: _K(f, cx=W + 3.0), f"/camera/K: principal point cx = {W + 3}"),
    ("pixels 1.5:1", lambda f: _K(f, fx=30.0), "/camera/K: fx / fy = 1.5"),
    ("one exposure 200x the others", lambda f: _exposure(f, 0, 2_000_000),
     "/train/exposure: view 0 is exposed for 2000000 us, over 100x the median"),
    ("an event two hours after the last frame", lambda f: _last_event(f, 7_200_000_000),
     "/events/t: the last event at t = 7200000000 us lies"),
]


@pytest.mark.parametrize("name,edit,message", WARNINGS, ids=[w[0] for w in WARNINGS])
def test_odd_camera_or_times_are_warnings(scene_copy, name, edit, message):
    with h5py.File(scene_copy, "r+") as f:
        edit(f)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        notes = schema.validate(scene_copy)
    assert [n for n in notes if n.startswith(message)], notes


def test_the_valid_scene_has_no_plausibility_notes(valid_file):
    assert schema.validate(valid_file, read_data=True) == []


def _damage_chunk(path, dataset):
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        if ds.chunks is None or not ds.compression:
            pytest.skip(f"{dataset} is not chunked and compressed")
        info = ds.id.get_chunk_info(0)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(b"\xde\xad\xbe\xef" * 4)


@pytest.mark.parametrize("dataset", ["/test/images", "/train/sharp", "/train/images"])
def test_a_damaged_chunk_is_found_by_read_data(scene_copy, dataset):
    _damage_chunk(scene_copy, dataset)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        schema.validate(scene_copy)                          # the structure is intact: the quick check passes
    with pytest.raises(SchemaError, match=f"^{dataset}: rows 0..\\d+ cannot be read"):
        schema.validate(scene_copy, read_data=True)


def test_train_refuses_a_damaged_chunk_before_training(scene_copy, tmp_path, capsys):
    """/test/images is read only by eval: a damaged chunk there must stop `ev3dgs train` at the start, not
    surface after the training."""
    from ev3dgs.cli import main as cli

    _damage_chunk(scene_copy, "/test/images")
    rc = cli.main(["train", str(scene_copy), "--out", str(tmp_path / "run"), "--iterations", "5", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: /test/images: rows 0..") and err.count("\n") == 1, err
    assert not (tmp_path / "run" / "model.pt").exists()
