"""The calibrated sensor into the scene file: `ev3dgs-ingest davis --sensor` stores the TOML's sensor model in
/events (read back through the schema), and the sensor TOML `record` writes beside its recording is one that
--sensor and the simulator's loader accept."""
from __future__ import annotations

import tomllib

import pytest

from ev3dgs import schema
from ev3dgs.calib.synth import Truth, make_recording
from ev3dgs.sim.config import SimConfig, load_sim_config


def _ingest(argv):
    from ev3dgs.cli.ingest import main

    return main(argv)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    p = tmp_path_factory.mktemp("rec") / "syn.aedat4"
    make_recording(p, Truth(), seed=2, seconds=0.6)
    return p


def test_ingest_sensor_round_trip_of_calibrate_toml(recording, tmp_path):
    from ev3dgs.calib.report import calibrate_recording, to_toml

    text = to_toml(calibrate_recording(recording, boot=5))
    (tmp_path / "sensor.toml").write_text(text)
    want = tomllib.loads(text)["dvs"]
    out = tmp_path / "scene.h5"
    assert _ingest(["davis", str(recording), "--out", str(out), "--no-poses", "--events", "all",
                    "--sensor", str(tmp_path / "sensor.toml"), "--quiet"]) == 0
    s = schema.read(out).sensor
    assert s.pos_threshold == want["pos_threshold"] and s.neg_threshold == want["neg_threshold"]
    assert s.mismatch_sigma == want.get("threshold_mismatch", {}).get("sigma", 0.0)
    assert s.refractory_us == want.get("refractory", {}).get("period_us", 0.0)
    assert s.leak_rate_hz == want.get("leak", {}).get("rate_hz", 0.0)
    assert s.shot_noise_rate_hz == want.get("shot_noise", {}).get("rate_hz", 0.0)
    assert s.count_convention == "random_phase"
    # the synthetic sensor has every effect on and a 0.6 s recording shows at least the thresholds and mismatch
    assert s.mismatch_sigma > 0


def test_record_sensor_toml_is_what_ingest_sensor_reads(recording, tmp_path):
    """record's sensor file for a sensor with every effect on -> --sensor -> the same numbers in /events."""
    from ev3dgs.sim.record import sensor_toml

    cfg = SimConfig(dvs=Truth(pos_threshold=0.15, neg_threshold=0.25, sigma=0.12, leak_hz=0.05, shot_hz=5.0,
                              refractory_us=1000.0).dvs())
    path = tmp_path / "rec.sensor.toml"
    path.write_text(sensor_toml(cfg))
    assert load_sim_config(path) == cfg                 # the simulator reads back exactly what was simulated
    out = tmp_path / "scene.h5"
    assert _ingest(["davis", str(recording), "--out", str(out), "--no-poses", "--sensor", str(path),
                    "--quiet"]) == 0
    s = schema.read(out).sensor
    assert (s.pos_threshold, s.neg_threshold, s.mismatch_sigma, s.refractory_us, s.leak_rate_hz,
            s.shot_noise_rate_hz) == (0.15, 0.25, 0.12, 1000.0, 0.05, 5.0)


def test_ingest_without_sensor_leaves_the_model_unknown(recording, tmp_path):
    out = tmp_path / "scene.h5"
    assert _ingest(["davis", str(recording), "--out", str(out), "--no-poses", "--quiet"]) == 0
    s = schema.read(out).sensor
    assert s.mismatch_sigma is None and s.leak_rate_hz is None and s.pos_threshold == 0.2


@pytest.mark.parametrize("text,extra,words", [
    (None, [], "no such file"),
    ("[dvs]\npos_threshold = -1\n", [], "pos_threshold"),
    ("not toml [", [], "invalid TOML"),
    ("[isp]\n", [], "no [dvs] table"),
    ("[dvs]\npos_threshold = 0.3\n", ["--pos-threshold", "0.3"], "drop --pos-threshold"),
])
def test_ingest_sensor_bad_input_one_line(recording, tmp_path, capsys, text, extra, words):
    p = tmp_path / "s.toml"
    if text is not None:
        p.write_text(text)
    out = tmp_path / "scene.h5"
    assert _ingest(["davis", str(recording), "--out", str(out), "--no-poses", "--sensor", str(p), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and words in err and "\n" not in err
    assert not out.exists()
