"""validate checks what it used to pass (issue 53, item 8): sensor values outside their physical range, lens
distortion no lens has, /imu with non-finite values or going back in time, a bounds box without volume, views
exposed far longer than the whole event stream; train refuses a distortion it cannot model."""
from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.cli import main as cli
from ev3dgs.errors import SchemaError

from h5_edits import set_attr, set_value
from test_reliability_validate import build_scene


@pytest.fixture(scope="module")
def valid_file(tmp_path_factory):
    sc = build_scene(np.random.default_rng(0))
    t = np.arange(50, dtype=np.int64) * 2_000
    sc = dataclasses.replace(sc, imu=schema.Imu(t=t, accel=np.tile(np.float32([0, -1, 0]), (50, 1)),
                                                gyro=np.zeros((50, 3), np.float32),
                                                temperature=np.full(50, 30.0, np.float32)))
    path = tmp_path_factory.mktemp("valid53") / "scene.h5"
    schema.write(sc, path)
    return path


def _imu_back(f):
    t = f["/imu/t"][()]
    t[10] = t[9] - 1
    f["/imu/t"][...] = t


def _long_exposures(f):
    e = f["/train/exposure"][()]
    e[:, 1] = e[:, 0] + 30 * 60 * 10**6                  # every view exposed 30 minutes; events span 0.11 s
    f["/train/exposure"][...] = e


def _distortion(d):
    def fn(f):
        if "distortion" in f["camera"]:
            del f["camera/distortion"]
        f["camera"].create_dataset("distortion", data=np.asarray(d, np.float64))
    return fn


ERRORS = [
    ("threshold 1e300", set_attr("/events", "pos_threshold", 1e300), "/events: attr pos_threshold = 1e+300"),
    ("threshold 1e-6", set_attr("/events", "neg_threshold", 1e-6), "/events: attr neg_threshold = 1e-06"),
    ("knee 1e-300", set_attr("/events", "log_knee", 1e-300), "/events: attr log_knee = 1e-300"),
    ("refractory 1e300", set_attr("/events", "refractory_us", 1e300), "/events: attr refractory_us = 1e+300"),
    ("leak 1e6", set_attr("/events", "leak_rate_hz", 1e6), "/events: attr leak_rate_hz = 1e+06"),
    ("k1 1e6", _distortion([1e6, 0, 0, 0, 0]), "/camera/distortion: [1000000.0, 0.0, 0.0, 0.0, 0.0]"),
    ("k1 -50", _distortion([-50.0, 0, 0, 0, 0]), "/camera/distortion: [-50.0"),
    ("p1 5", _distortion([0, 0, 5.0, 0, 0]), "/camera/distortion: [0.0, 0.0, 5.0"),
    ("imu accel nan", set_value("/imu/accel", np.nan, (7, 1)), "/imu/accel: value at index [7, 1] is not finite"),
    ("imu gyro inf", set_value("/imu/gyro", np.inf, (3, 0)), "/imu/gyro: value at index [3, 0] is not finite"),
    ("imu time back", _imu_back, "/imu/t: not in time order (t[10]"),
    ("bounds zero", set_attr("/", "bounds", np.zeros((2, 3))), "/: attr bounds must be finite (2, 3) [min, max] "
                                                             "with min < max"),
    ("bounds flat", set_attr("/", "bounds", np.array([[-1.0, -1, 0], [1.0, 1, 0]])), "/: attr bounds must be"),
    ("exposure 30 min", _long_exposures, "/train/exposure: the median view is exposed for 1800 s"),
]


@pytest.mark.parametrize("name,corrupt,message", ERRORS, ids=[e[0] for e in ERRORS])
def test_impossible_scene_is_a_named_error(scene_copy, capsys, name, corrupt, message):
    with h5py.File(scene_copy, "r+") as f:
        corrupt(f)
    with pytest.raises(SchemaError) as info:
        schema.validate(scene_copy)
    assert str(info.value).startswith(message), str(info.value)
    capsys.readouterr()
    assert cli.main(["validate", str(scene_copy)]) == 2
    out, err = capsys.readouterr()
    assert err == f"error: {info.value}\n" and out == ""


@pytest.mark.parametrize("d", [[-0.2, 0.05, 0.0, 0.0, 0.0], [0.1, -0.01, 0.001, 0.002, 0.0]])
def test_real_lens_distortion_validates_and_train_refuses_it(scene_copy, tmp_path, capsys, d):
    """A DAVIS lens's coefficients (tests/test_davis.py) are valid data; the trainer's pinhole renderer cannot
    model them, so train says so instead of training as if they were 0."""
    with h5py.File(scene_copy, "r+") as f:
        _distortion(d)(f)
    schema.validate(scene_copy)
    assert cli.main(["train", str(scene_copy), "--out", str(tmp_path / "run"), "--iterations", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1 and "cannot model lens distortion" in err
    assert not (tmp_path / "run" / "model.pt").exists()


def test_valid_scene_with_imu_passes(valid_file):
    schema.validate(valid_file)
