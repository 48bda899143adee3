"""Sensor configs and calibrate/compare inputs that used to pass and then blow up (issue 53, items 3, 5-7, 9):
one place loads and bounds a sensor TOML (UTF-8 and nesting errors, a physical range per numeric key, checked
before any render), the noise effects' memory is estimated before they run, recordings with impossible exposure
times are refused, compare reads the APS dark level from a key, and option values are bounded."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from ev3dgs.calib.synth import Truth, make_recording
from ev3dgs.cli import sim as sim_cli
from ev3dgs.errors import ConfigError
from ev3dgs.sim.config import load_sim_config


def one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, err
    return err


# ------------------------------------------------------------------ item 5: undecodable and nested files
def bad_files(tmp_path):
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"[dvs]\npos_threshold = 0.2\n# \xff\xfe\x00\x81 not UTF-8\n")
    nested = tmp_path / "nested.toml"
    nested.write_text("x = " + "[" * 5000 + "]" * 5000 + "\n")
    return {"binary": (binary, "not UTF-8"), "nested": (nested, "nested too deeply")}


@pytest.mark.parametrize("which", ["binary", "nested"])
def test_undecodable_or_nested_config_one_line_everywhere(tmp_path, capsys, monkeypatch, which):
    path, why = bad_files(tmp_path)[which]
    with pytest.raises(ConfigError, match=why):
        load_sim_config(path)
    assert sim_cli.main(["events", str(tmp_path / "in.npz"), "--config", str(path), "--out",
                         str(tmp_path / "e.h5")]) == 2
    one_line_error(capsys, why)
    assert sim_cli.main(["compare", str(tmp_path / "in.aedat4"), "--config", str(path), "--out",
                         str(tmp_path / "rep")]) == 2
    one_line_error(capsys, why)


def test_bad_config_fails_make_dataset_before_blender(tmp_path, capsys, monkeypatch):
    """make-dataset loads and bounds the config before it renders: the render entry is never reached."""
    import ev3dgs.sim.dataset as dataset

    calls = []
    monkeypatch.setattr(sim_cli, "require_blender", lambda command: None)     # as if Blender were installed
    monkeypatch.setattr(dataset, "make_dataset", lambda *a, **k: calls.append(a))
    hostile = tmp_path / "hostile.toml"
    hostile.write_text("[dvs.shot_noise]\nrate_hz = 1e300\n")
    for cfg, why in ((hostile, "physical range"), bad_files(tmp_path)["binary"]):
        assert sim_cli.main(["make-dataset", "--scene", "lego", "--config", str(cfg), "--out",
                             str(tmp_path / "d.h5")]) == 2
        one_line_error(capsys, why)
    assert calls == [] and not (tmp_path / "d.h5").exists()


def test_noise_that_would_not_fit_in_memory_fails_make_dataset_before_blender(tmp_path, capsys, monkeypatch):
    """The noise effects' events over every exposure are estimated before the render: a dataset whose noise
    would not fit is refused in one line, and Blender's render entry is never reached."""
    import ev3dgs.sim.dataset as dataset

    calls = []
    monkeypatch.setattr(sim_cli, "require_blender", lambda command: None)
    monkeypatch.setattr(dataset, "render_all", lambda *a, **k: calls.append(a))
    monkeypatch.setenv("EV3DGS_MAX_MEMORY", "1M")
    noisy = tmp_path / "noisy.toml"
    noisy.write_text("[dvs.shot_noise]\nrate_hz = 1000\n")   # in range: 1e3 Hz x 6912 px x 1 s x 48 B > 1 MiB
    assert sim_cli.main(["make-dataset", "--scene", "lego", "--quick", "--config", str(noisy), "--out",
                         str(tmp_path / "d.h5")]) == 2
    one_line_error(capsys, "would make about")
    assert calls == [] and not (tmp_path / "d.h5").exists()


# ------------------------------------------------------------------ item 6: a physical range per key
HOSTILE = [("dvs", "pos_threshold", 1e-300), ("dvs", "pos_threshold", 1e-6), ("dvs", "neg_threshold", 1e300),
           ("dvs", "log_knee", 1e-300), ("dvs.threshold_mismatch", "min_threshold", 1e-300),
           ("dvs.threshold_mismatch", "sigma", 50.0), ("dvs.leak", "rate_hz", 1e6), ("dvs.leak", "rate_hz", 1e300),
           ("dvs.shot_noise", "rate_hz", 1e5), ("dvs.shot_noise", "rate_hz", 1e300),
           ("dvs.refractory", "period_us", 1e300), ("dvs.lowpass", "cutoff_hz", 1e300),
           ("dvs.lowpass", "dark_intensity", 1e300), ("dvs.lowpass", "dark_intensity", 1e-300),
           ("sensor_noise", "iso", 1e300), ("sensor_noise", "full_well_electrons", 1e-300),
           ("sensor_noise", "read_noise_electrons", 1e300), ("isp", "white_balance", [1e300, 1.0, 1.0]),
           ("aps", "dark_dn", 1e300)]


@pytest.mark.parametrize("table,key,value", HOSTILE)
def test_every_numeric_key_has_a_physical_range(tmp_path, table, key, value):
    p = tmp_path / "c.toml"
    p.write_text(f"[{table}]\n{key} = {value!r}\n".replace("'", '"'))
    with pytest.raises(ConfigError, match="outside its physical range"):
        load_sim_config(p)


def test_range_ends_load(tmp_path):
    """The stated ends are inside: the ranges refuse nothing a sensor can have."""
    from ev3dgs.sensor import RANGES

    lo_t, hi_t = RANGES["threshold"]
    lo_k, hi_k = RANGES["intensity"]
    p = tmp_path / "ends.toml"
    p.write_text(f"[dvs]\npos_threshold = {lo_t}\nneg_threshold = {hi_t}\nlog_knee = {lo_k}\n"
                 f"[dvs.shot_noise]\nrate_hz = {RANGES['rate_hz'][1]}\n[dvs.leak]\nrate_hz = 1e-9\n"
                 f"[dvs.lowpass]\ndark_intensity = {hi_k}\n[dvs.refractory]\nperiod_us = {RANGES['period_us'][1]}\n")
    cfg = load_sim_config(p)
    assert cfg.dvs.pos_threshold == lo_t and cfg.dvs.shot_noise.rate_hz == RANGES["rate_hz"][1]


def test_noise_memory_estimate_is_an_upper_bound_and_refuses(monkeypatch):
    """Expected leak + shot events = rate x pixels x seconds (Poisson, dark frames: the shot-noise rate's
    maximum): the simulator's count stays within 5 sigma below it; a run whose estimate exceeds the memory
    available is refused in one line before any event is made."""
    from ev3dgs.sim.budget import EVENT_BYTES, noise_events
    from ev3dgs.sim.config import DVSConfig, ShotNoise
    from ev3dgs.sim.dvs import DVSSimulator

    cfg = DVSConfig(shot_noise=ShotNoise(rate_hz=50.0))
    frames = np.zeros((11, 20, 30), np.float32)
    t = np.arange(11, dtype=np.int64) * 100_000                                   # 1 s
    n = len(DVSSimulator(20, 30, cfg, seed=1).feed(frames, t))
    expect = noise_events(cfg, 600, 1.0)
    assert expect == 50.0 * 600 and abs(n - expect) < 5 * math.sqrt(expect)
    monkeypatch.setenv("EV3DGS_MAX_MEMORY", str(int(expect * EVENT_BYTES * 0.5)))
    with pytest.raises(ConfigError, match="more than the .* GiB of memory available"):
        DVSSimulator(20, 30, cfg, seed=1).feed(frames, t)
    monkeypatch.delenv("EV3DGS_MAX_MEMORY")
    big = DVSConfig(shot_noise=ShotNoise(rate_hz=1e4))             # in range; 1e4 Hz x 90k pixels x 1e5 s
    with pytest.raises(ConfigError, match="noise effects would make about 9e\\+13 events"):
        DVSSimulator(260, 346, big).feed(np.zeros((2, 260, 346), np.float32), np.array([0, 10**11]))


# ------------------------------------------------------------------ item 7: the dark level key, options
@pytest.fixture(scope="module")
def small_rec(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec53")
    make_recording(d / "r.aedat4", Truth(hot=((3, 5),)), seed=3, seconds=0.6, width=32, height=24, warmup_s=0.2)
    return d / "r.aedat4"


def test_calibrate_writes_the_dark_level_as_a_key(small_rec):
    import tomllib

    from ev3dgs.calib.report import calibrate_recording, to_toml

    cal = calibrate_recording(small_rec, boot=2, seed=0)
    text = to_toml(cal)
    data = tomllib.loads(text)
    assert data["aps"]["dark_dn"] == pytest.approx(cal.thresholds.dark.value, rel=1e-5)
    assert "# aps_dark_dn" not in text


@pytest.mark.parametrize("value", ["-", "e", "1.2.3", "1e400"])
def test_compare_old_comment_bad_value_one_line(small_rec, tmp_path, capsys, value):
    cfg = tmp_path / "old.toml"
    cfg.write_text(f"# aps_dark_dn = {value}   (read by ev3dgs-sim compare)\n[dvs]\npos_threshold = 0.2\n")
    assert sim_cli.main(["compare", str(small_rec), "--config", str(cfg), "--out", str(tmp_path / "rep")]) == 2
    one_line_error(capsys, "aps_dark_dn", "[aps] dark_dn")


def test_compare_old_comment_still_loads_with_a_note(small_rec, tmp_path):
    from ev3dgs.calib.compare import dark_from_toml

    cfg = tmp_path / "old.toml"
    cfg.write_text("# aps_dark_dn = 12.5   (read by ev3dgs-sim compare)\n[dvs]\npos_threshold = 0.2\n")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert dark_from_toml(cfg, load_sim_config(cfg)) == 12.5
    assert len(w) == 1 and "older calibrate file" in str(w[0].message)
    new = tmp_path / "new.toml"
    new.write_text("# aps_dark_dn = 99\n[aps]\ndark_dn = 7.25\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert dark_from_toml(new, load_sim_config(new)) == 7.25          # the key wins, no note


@pytest.mark.parametrize("argv,needle", [(["--seed", "-1"], "--seed"), (["--bootstrap", "-1"], "--bootstrap"),
                                         (["--bootstrap", "0"], "--bootstrap"), (["--bootstrap", "1"], "--bootstrap"),
                                         (["--bootstrap", "2"], "--bootstrap"),
                                         (["--bootstrap", "10001"], "--bootstrap")])
def test_calibrate_options_bounded(small_rec, tmp_path, capsys, argv, needle):
    with pytest.raises(SystemExit) as e:
        sim_cli.main(["calibrate", str(small_rec), "--out", str(tmp_path / "s.toml"), *argv])
    assert e.value.code == 2
    one_line_error(capsys, needle)
    assert not (tmp_path / "s.toml").exists()


def test_compare_on_a_tiny_sensor_fails_before_simulating(tmp_path, capsys, monkeypatch):
    import ev3dgs.calib.compare as compare

    from ev3dgs.events import Events
    from ev3dgs.io.aedat4.writer import write_aedat4
    from ev3dgs.io.types import FrameData

    rec = tmp_path / "tiny.aedat4"
    frames = [FrameData(timestamp=40_000 * i, exposure_start=40_000 * i, exposure_end=40_000 * i + 5_000,
                        frame_start=40_000 * i, frame_end=40_000 * i + 5_500,
                        image=np.full((1, 1), 60 + 15 * i, np.uint8), source="T") for i in range(10)]
    t = np.arange(2_000, 360_000, 9_000, dtype=np.int64)
    write_aedat4(rec, 1, 1, events=Events(t, np.zeros(len(t), np.int16), np.zeros(len(t), np.int16),
                                          np.ones(len(t), np.int8)), frames=frames)
    monkeypatch.setattr(compare, "resimulate", lambda *a, **k: pytest.fail("simulated"))
    assert sim_cli.main(["compare", str(rec), "--out", str(tmp_path / "rep")]) == 2
    one_line_error(capsys, "too small to compare")
    assert not (tmp_path / "rep").exists()


# ------------------------------------------------------------------ item 3: implausible exposure times
def rewrite(src, dst, edit):
    """A copy of an AEDAT 4.0 recording whose APS frames went through edit(list of FrameData)."""
    from dataclasses import replace

    from ev3dgs.events import Events
    from ev3dgs.io.aedat4.writer import write_aedat4
    from ev3dgs.io.recording import open_recording

    with open_recording(src) as r:
        w, h = r.sensor_size()
        ev = Events.concatenate(list(r.events()))
        frames = [replace(f) for f in r.frames()]
    write_aedat4(dst, w, h, events=ev, frames=edit(frames))


def _set(frames, i, **kw):
    from dataclasses import replace

    frames[i] = replace(frames[i], **kw)
    return frames


def test_exposure_checks_against_hand_made_windows():
    from ev3dgs.calib.checks import check_exposures
    from ev3dgs.errors import InputError

    s = np.arange(5) * 40_000
    ev = np.arange(0, 200_000, 100)
    check_exposures("r", s, s + 5_000, ev)
    with pytest.raises(InputError, match="frame 2 has no exposure window .*ends before it starts"):
        check_exposures("r", s, np.where(np.arange(5) == 2, s - 1, s + 5_000), ev)
    with pytest.raises(InputError, match="frame 1 is exposed for 225 s, longer than the whole recording"):
        check_exposures("r", s, np.where(np.arange(5) == 1, s + 225_000_000, s + 5_000), ev)
    with pytest.raises(InputError, match="frames 3 .* and 4 .* overlap"):
        check_exposures("r", s, np.where(np.arange(5) == 3, s + 45_000, s + 5_000), ev)


@pytest.mark.parametrize("case,needle", [
    ("hour", "longer than the whole recording"),      # the 225,000,500 us in a 0.6 s recording
    ("overlap", "overlap")])
def test_calibrate_and_compare_refuse_impossible_exposures(small_rec, tmp_path, capsys, case, needle):
    def edit(fr):
        if case == "hour":
            return _set(fr, 3, exposure_end=fr[3].exposure_start + 225_000_500)
        return _set(fr, 3, exposure_end=fr[4].exposure_start + 10)

    bad = tmp_path / f"{case}.aedat4"
    rewrite(small_rec, bad, edit)
    assert sim_cli.main(["calibrate", str(bad), "--out", str(tmp_path / "s.toml"), "--bootstrap", "3"]) == 2
    one_line_error(capsys, needle)
    assert sim_cli.main(["compare", str(bad), "--out", str(tmp_path / "rep")]) == 2
    one_line_error(capsys, needle)
    assert not (tmp_path / "s.toml").exists() and not (tmp_path / "rep").exists()


def test_suspicious_exposure_warns(small_rec, tmp_path):
    from ev3dgs.calib.aps import load_recording

    bad = tmp_path / "long.aedat4"
    # frame 2 exposed from just after frame 1's exposure to just before frame 3's: ~75 ms where the frames are
    # 40 ms apart and expose 5 ms; possible (nothing overlaps), but not what a camera set to 5 ms does
    rewrite(small_rec, bad, lambda fr: _set(fr, 2, exposure_start=fr[1].exposure_end + 1,
                                            exposure_end=fr[3].exposure_start - 1))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        load_recording(bad)
    assert any("exposed longer than the median frame interval" in str(x.message) for x in w)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_recording(small_rec)                                      # the intact recording: no warning


# ------------------------------------------------------------------ item 9: the full-disk message's units
def test_full_disk_message_units(tmp_path, monkeypatch):
    import shutil
    from collections import namedtuple

    from ev3dgs.outputs import OutputError, check_output_file

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 1234, 1234))
    with pytest.raises(OutputError) as e:
        check_output_file(tmp_path / "x.h5", 5000)
    msg = str(e.value)
    assert "needs about 5 kB, 1.23 kB free" in msg and "0.0 MB" not in msg
    with pytest.raises(OutputError, match="needs about 2.5 GB, 1.23 kB free"):
        check_output_file(tmp_path / "x.h5", 2_500_000_000)
