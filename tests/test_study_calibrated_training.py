"""The calibrated-training study's scene copies: the one with a sensor carries that sensor's thresholds and noise
model to the trainer's event noise model, the one without gives the trainer's defaults (not the simulator's
provenance, which a file without the model attrs would otherwise fall back to)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import h5py
import pytest

ROOT = Path(__file__).resolve().parents[1]
for sub in ("tools", "tools/studies", "tools/bench"):
    if str(ROOT / sub) not in sys.path:
        sys.path.insert(0, str(ROOT / sub))

import study_calibrated_training as sct  # noqa: E402

from ev3dgs import schema  # noqa: E402
from ev3dgs.blob_scene import blob_scene  # noqa: E402
from ev3dgs.train.terms.events import DEFAULT_NOISE_RATE_HZ, DEFAULT_REL_MISMATCH  # noqa: E402


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A small scene file that looks simulated with a 40 % mismatch sensor: the /events model attrs and the
    simulator's provenance (/config sim.dvs) both say so."""
    path = blob_scene(tmp_path_factory.mktemp("sct") / "scene.h5", 16, 12, views=2, subframes=3, n=40)
    with h5py.File(path, "r+") as f:
        f["events"].attrs.update(mismatch_sigma=0.08, leak_rate_hz=0.1, shot_noise_rate_hz=1.0)
        config = json.loads(f.attrs.get("config", "{}"))
        config["sim"] = {"dvs": {"pos_threshold": 0.2, "neg_threshold": 0.2, "reference": "random",
                                 "threshold_mismatch": {"sigma": 0.08}, "leak": {"rate_hz": 0.1},
                                 "shot_noise": {"rate_hz": 1.0}}}
        f.attrs["config"] = json.dumps(config)
    return path


def test_truth_file_gives_its_sensor(simulated):
    m = sct.noise_model(simulated)
    assert m["rel_mismatch"] == pytest.approx(0.08 / 0.2) and m["noise_rate_hz"] == pytest.approx(1.1)
    assert m["rel_mismatch_from"] == "scene"


def test_default_copy_gives_the_trainers_defaults(simulated, tmp_path):
    dst = sct.with_sensor(simulated, tmp_path / "default.h5", None)
    m = sct.noise_model(dst)
    assert (m["rel_mismatch"], m["noise_rate_hz"]) == (DEFAULT_REL_MISMATCH, DEFAULT_NOISE_RATE_HZ)
    assert m["rel_mismatch_from"] == m["noise_rate_from"] == "default"
    sc = schema.read(dst)   # the rest of the file is untouched: thresholds and count convention stay
    assert (sc.sensor.pos_threshold, sc.sensor.neg_threshold) == (0.2, 0.2)
    assert sc.sensor.count_convention == schema.read(simulated).sensor.count_convention


def test_calibrated_copy_gives_the_calibrated_sensor(simulated, tmp_path):
    cal = schema.EventSensor(pos_threshold=0.18, neg_threshold=0.19, refractory_us=502.0, mismatch_sigma=0.06,
                             leak_rate_hz=0.0, shot_noise_rate_hz=1.01)
    dst = sct.with_sensor(simulated, tmp_path / "calibrated.h5", cal)
    m = sct.noise_model(dst)
    assert m["rel_mismatch"] == pytest.approx(0.06 / 0.185) and m["noise_rate_hz"] == pytest.approx(1.01)
    assert m["rel_mismatch_from"] == m["noise_rate_from"] == "scene"
    sc = schema.read(dst)
    assert (sc.sensor.pos_threshold, sc.sensor.neg_threshold, sc.sensor.refractory_us) == (0.18, 0.19, 502.0)
    assert not (tmp_path / "calibrated.tmp.h5").exists()
