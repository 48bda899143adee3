"""Readers against what real jAER / cAER recordings look like (issue 15): IMU full scale and axes, rolling-shutter
APS frames, DVS128 / DAVIS240 / unknown chips, the header/data boundary, timestamp resets, decode-once slicing and
the CLI's messages. Every fixture is built byte by byte here from the public format rules (jAER's DavisChip.java,
DVS128.java, IMUSample.java; libcaer's event headers), independently of the readers."""
from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from aedat2_build import aps, dvs, imu_word   # the jAER DAVIS address encoders

from ev3dgs.io.jaer.aedat2 import Aedat2Reader
from ev3dgs.io.jaer.aedat3 import Aedat3Reader
from ev3dgs.io.types import AedatError

SHARED = Path(__file__).resolve().parents[2] / "shared/data/aedat/aestream_davis.aedat4"
IMU_PREFS = (b"#      <entry key=\"ImuAccelScale\" value=\"ImuAccelScaleG8\"/>\r\n"
             b"#      <entry key=\"ImuGyroScale\" value=\"GyroFullScaleDegPerSec1000\"/>\r\n"
             b"#      <entry key=\"DAVIS240C.imu3_GYRO_CONFIG\" value=\"16\"/>\r\n"
             b"#      <entry key=\"DAVIS240C.imu4_ACCEL_CONFIG\" value=\"16\"/>\r\n")


def header(chip: bytes | None = b"eu.seebetter.ini.chips.davis.DAVIS240C", prefs: bytes = IMU_PREFS) -> bytes:
    h = b"#!AER-DAT2.0\r\n# This is a raw AE data file created by AEOutputStream\r\n"
    if chip:
        h += b"# AEChip: " + chip + b"\r\n"
    return h + prefs + b"#End Of ASCII Header\r\n"


def body(recs) -> bytes:
    a = np.array(recs, np.int64)
    out = np.empty((len(a), 2), ">u4")
    out[:, 0], out[:, 1] = a[:, 0] & 0xFFFFFFFF, a[:, 1] & 0xFFFFFFFF
    return out.tobytes()


def read(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = Aedat2Reader(path, **kw)
        ev = list(r.events())
        return r, ev


# ------------------------------------------------------------------ 1 + 2: IMU scale and axes
def roll_recording(rate_hz=1000, seconds=1.0, roll_deg=90.0):
    """An upright DAVIS240C at rest, then rolled clockwise (seen from behind) by roll_deg about its optical axis at
    a constant rate, then at rest. Raw words follow jAER's documented signs: raw accel x is positive towards the
    camera's left (IMUSample.getAccelX negates it for 'right'), an upright camera at rest reads raw ay = -1 g, and
    a clockwise roll is a negative raw gz (getGyroRollZ = -gz). Scale: +-8 g (4096 LSB/g), +-1000 deg/s (32.8)."""
    n_rest, n_turn = 100, int(rate_hz * seconds)
    rate = roll_deg / seconds                                        # deg/s, clockwise
    recs, t = [], 1000
    for i in range(n_rest + n_turn + n_rest):
        k = min(max(i - n_rest, 0), n_turn)
        ang = np.deg2rad(rate * k / rate_hz)                          # roll so far
        turning = n_rest <= i < n_rest + n_turn
        # specific force (1 g, pointing up) in the camera's (left, down) raw axes: up = -down rotated by the roll
        ax_left, ay_down = np.sin(ang), -np.cos(ang)
        raw = [ax_left * 4096, ay_down * 4096, 0, 1700, 0, 0, -rate * 32.8 if turning else 0]
        for kind, v in enumerate(raw):
            recs.append((imu_word(kind, round(v)), t))
        recs.append((dvs(5, 6, 1), t + 3))
        t += 1_000_000 // rate_hz
    return recs


def integrate(t_us, gyro_dps):
    R = np.eye(3)
    for k in range(1, len(t_us)):
        w = np.deg2rad(gyro_dps[k - 1]) * (t_us[k] - t_us[k - 1]) * 1e-6
        th = np.linalg.norm(w)
        if th:
            a = w / th
            K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            R = R @ (np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K)
    return R


def angle(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_imu_scale_from_header_and_camera_axes(tmp_path):
    p = tmp_path / "roll.aedat"
    p.write_bytes(header() + body(roll_recording()))
    r, _ = read(p)
    imu = r.imu()
    assert r.warnings == [] and len(imu) == 1200
    assert (r.accel_lsb_per_g, r.gyro_lsb_per_dps) == (4096.0, 32.8)
    # gravity reads 1 g; upright camera at rest: specific force up = -y in the camera frame (x right, y down, z fwd)
    np.testing.assert_allclose(np.linalg.norm(imu.accel, axis=1), 1.0, atol=2e-3)
    np.testing.assert_allclose(imu.accel[0], [0, -1, 0], atol=2e-3)
    # the gyro integrates to the 90-degree roll (the old 65.5 LSB scale gave 45)
    assert abs(float(np.sum(imu.gyro[:-1, 2] * np.diff(imu.t) * 1e-6)) - 90.0) < 0.5
    # a clockwise roll puts the camera's right side down: up is now -x
    np.testing.assert_allclose(imu.accel[-1], [-1, 0, 0], atol=2e-3)
    # the two sensors share one right-handed frame: integrating the gyro predicts the accelerometer's gravity
    R = integrate(imu.t, imu.gyro.astype(np.float64))
    assert angle(R.T @ imu.accel[0], imu.accel[-1]) < 1.0
    # (the old axes, accel x negated only, put the sensors in frames of opposite handedness: the check fails)
    old_acc, old_gyr = imu.accel * [1, 1, -1], imu.gyro * [-1, 1, -1]
    assert angle(integrate(imu.t, old_gyr.astype(np.float64)).T @ old_acc[0], old_acc[-1]) > 90


def test_imu_scale_config_bytes_and_default_warning(tmp_path):
    p = tmp_path / "cfg.aedat"
    prefs = (b"#   <entry key=\"DAVIS240C.imu3_GYRO_CONFIG\" value=\"8\"/>\r\n"       # FS_SEL 1: 500 deg/s
             b"#   <entry key=\"DAVIS240C.imu4_ACCEL_CONFIG\" value=\"24\"/>\r\n")    # AFS_SEL 3: 16 g
    p.write_bytes(header(prefs=prefs) + body(roll_recording(seconds=0.1, roll_deg=9)))
    r, _ = read(p)
    assert (r.accel_lsb_per_g, r.gyro_lsb_per_dps) == (2048.0, 65.5) and r.warnings == []
    p.write_bytes(header(prefs=b"") + body(roll_recording(seconds=0.1, roll_deg=9)))
    r, _ = read(p)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r.imu()
    assert (r.accel_lsb_per_g, r.gyro_lsb_per_dps) == (4096.0, 32.8)
    assert any("does not state the IMU full scale" in w for w in r.warnings)


def test_aedat4_and_aedat31_imu_units():
    if not SHARED.exists():
        pytest.skip("shared DAVIS346 recording not present")
    from ev3dgs.io.aedat4 import Aedat4Reader

    with Aedat4Reader(SHARED) as r:
        imu = r.imu()
    # DV stores g in the camera frame already: gravity 1 g along -y for the resting, upright camera
    g = np.linalg.norm(imu.accel, axis=1)
    assert abs(np.median(g) - 1.0) < 0.03 and np.median(imu.accel[:, 1]) < -0.95


# ------------------------------------------------------------------ 3: rolling shutter
def rolling_frames(W=240, H=180, n_frames=2, row_us=20, exposure=3000, t0=10_000):
    """DAVIS240C readout order (first pixel (0, H-1), last (W-1, 0), raw jAER coordinates): each row is reset,
    then read out `exposure` us later, rows `row_us` apart, so reset and signal reads of different rows interleave."""
    rng = np.random.default_rng(5)
    recs, exp = [], []
    for f in range(n_frames):
        start = t0 + f * (H * row_us + exposure + 5000)
        reset = rng.integers(400, 1024, (H, W))
        signal = rng.integers(0, 400, (H, W))
        items = []
        for i, y in enumerate(range(H - 1, -1, -1)):
            tr, ts = start + i * row_us, start + i * row_us + exposure
            for x in range(W):
                items.append((tr, 0, aps(x, y, 0, int(reset[y, x]))))
                items.append((ts, 1, aps(x, y, 1, int(signal[y, x]))))
        items.sort(key=lambda it: (it[0], it[1]))
        recs += [(a, t) for t, _, a in items]
        img = (np.clip(reset - signal, 0, 1023).astype(np.uint16) << 6)[::-1]      # image row 0 = top = raw y H-1
        rows = np.array([[start + i * row_us, start + i * row_us + exposure] for i in range(H)])
        exp.append((img, rows))
    return recs, exp


def test_rolling_shutter_frames(tmp_path):
    recs, exp = rolling_frames()
    p = tmp_path / "rolling.aedat"
    p.write_bytes(header() + body(recs))
    for chunk in (1 << 19, 5000):                      # frame state across chunk boundaries
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Aedat2Reader(p, chunk_records=chunk) as r:
                frames = list(r.frames())
                assert r.warnings == []
        assert len(frames) == 2                        # not 234 strips
        for fr, (img, rows) in zip(frames, exp):
            assert fr.image.shape == (180, 240) and fr.position == (0, 0) and fr.rolling_shutter
            np.testing.assert_array_equal(fr.image, img)
            np.testing.assert_array_equal(fr.row_exposure, rows)
            # jAER's frame times: exposure from the first row's reset to its signal read
            assert (fr.exposure_start, fr.exposure_end) == tuple(rows[0])
            assert fr.frame_start == rows[0, 0] and fr.frame_end == rows[-1, 1]


# ------------------------------------------------------------------ 4: other chips
def test_dvs128_layout(tmp_path):
    rng = np.random.default_rng(0)
    x, y, on = rng.integers(0, 128, 1000), rng.integers(0, 128, 1000), rng.integers(0, 2, 1000)
    # DVS128.java: x = 127 - bits 7-1, y = bits 14-8 (origin bottom-left), raw bit 0 = 0 is ON; bit 15 = sync
    addr = ((127 - x) << 1) | (y << 8) | (1 - on)
    recs = [(int(a), 100 + 10 * i) for i, a in enumerate(addr)] + [(1 << 15, 20_000)]
    p = tmp_path / "dvs128.aedat"
    p.write_bytes(header(b"ch.unizh.ini.jaer.chip.retina.DVS128", b"") + body(recs))
    r, ev = read(p)
    assert r.sensor_size() == (128, 128) and r.warnings == []
    e = ev[0] if len(ev) == 1 else None
    assert e is not None and len(e) == 1000
    assert e.x.tolist() == x.tolist() and e.y.tolist() == (127 - y).tolist()
    assert e.p.tolist() == np.where(on == 1, 1, -1).tolist()
    assert len(r.triggers()) == 1 and len(r.imu()) == 0 and list(r.frames()) == []


def test_unknown_chip_refused_and_missing_chip_inferred(tmp_path):
    p = tmp_path / "x.aedat"
    p.write_bytes(header(b"ch.unizh.ini.jaer.chip.cochlea.CochleaAMS1c", b"") + body([(5, 10)]))
    with pytest.raises(AedatError, match="unsupported AEChip 'ch.unizh.ini.jaer.chip.cochlea.CochleaAMS1c'"):
        Aedat2Reader(p)
    recs = [(dvs(239, 179, 1), 10), (dvs(0, 0, 0), 20), (dvs(120, 50, 1), 30)]
    p.write_bytes(header(None, b"") + body(recs))
    r, ev = read(p)
    assert r.sensor_size() == (240, 180) and any("no AEChip line" in w for w in r.warnings)
    assert ev[0].y.tolist() == [0, 179, 129]                        # not off by 80 rows (346x260)
    r, ev = read(p, sensor_size=(240, 180))
    assert r.warnings == [] and ev[0].y.tolist() == [0, 179, 129]


# ------------------------------------------------------------------ 5: header/data boundary
def test_header_boundary(tmp_path):
    # the first record's address starts with byte 0x23 ('#'): a DVS event at y = 140 on a DAVIS346
    first = dvs(0x13, 140, 1) | (1 << 29)
    assert first >> 24 == 0x23
    recs = [(first, 5)] + [(dvs(i % 300, i % 200, i & 1), 10 + i) for i in range(2000)]
    p = tmp_path / "hash.aedat"
    p.write_bytes(header(b"eu.seebetter.ini.chips.davis.Davis346red", b"") + body(recs))
    r, ev = read(p)
    assert sum(len(e) for e in ev) == 2001 and r.warnings == []
    # without the end-of-header line, the binary first byte still ends the header
    p.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.Davis346red\r\n" + body(recs))
    r, ev = read(p)
    assert sum(len(e) for e in ev) == 2001 and r.warnings == []
    # a header line cut mid-line (binary data follows without a line end) is an error
    p.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.Davis346red\r\n# HardwareInterf"
                  + body(recs))
    with pytest.raises(AedatError, match="header line cut"):
        Aedat2Reader(p)
    # data that is not a whole number of records: a warning with the remainder
    p.write_bytes(header(b"eu.seebetter.ini.chips.davis.Davis346red", b"") + body(recs) + b"\x00\x01\x02")
    r, ev = read(p)
    assert sum(len(e) for e in ev) == 2001 and any("3 trailing bytes" in w for w in r.warnings)


# ------------------------------------------------------------------ 6: timestamp resets
def test_jaer_timestamp_reset(tmp_path):
    before = [(dvs(1, 1, 1), 1_800_000_000 + 100 * i) for i in range(100)]     # 30 min in: not near a wrap
    after = [(dvs(2, 2, 0), 7 + 50 * i) for i in range(300)]
    p = tmp_path / "reset.aedat"
    p.write_bytes(header(b"eu.seebetter.ini.chips.davis.DAVIS240C", b"") + body(before + after))
    r, ev = read(p)
    t = np.concatenate([e.t for e in ev])
    assert t.tolist() == [7 + 50 * i for i in range(300)]            # no invented 351 s gap, no mixing
    assert any("timestamp reset" in w and "segment 2" in w for w in r.warnings)
    with pytest.raises(AedatError, match="timestamp reset"):
        Aedat2Reader(p, strict=True)
    # a small reset (5 s in, back to 0) is also a reset, not events left out of order
    p.write_bytes(header(b"eu.seebetter.ini.chips.davis.DAVIS240C", b"")
                  + body([(dvs(1, 1, 1), 5_000_000 + i) for i in range(300)] + after[:100]))
    r, ev = read(p)
    assert np.concatenate([e.t for e in ev]).tolist() == [5_000_000 + i for i in range(300)]
    assert any("timestamp reset" in w for w in r.warnings)


def a3_packet(typ, size, ovf, events):
    return struct.pack("<hhiiiiii", typ, 1, size, 4, ovf, len(events), len(events), len(events)) + b"".join(events)


def test_aedat31_timestamp_reset(tmp_path):
    pol = lambda x, y, ts: struct.pack("<Ii", 1 | (1 << 1) | (y << 2) | (x << 17), ts)       # noqa: E731
    hdr = b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS240C\r\n#!END-HEADER\r\n"
    data = (a3_packet(1, 8, 0, [pol(3, 4, 9_000_000 + i) for i in range(50)])
            + a3_packet(0, 8, 0, [struct.pack("<Ii", 1 | (1 << 1), 9_000_100)])            # TIMESTAMP_RESET
            + a3_packet(1, 8, 0, [pol(5, 6, 10 + i) for i in range(200)]))
    p = tmp_path / "reset.aedat3"
    p.write_bytes(hdr + data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat3Reader(p) as r:
            t = np.concatenate([e.t for e in r.events()])
            assert t.tolist() == [10 + i for i in range(200)]
            assert any("TIMESTAMP_RESET" in w for w in r.warnings)
    with pytest.raises(AedatError, match="TIMESTAMP_RESET"):
        with Aedat3Reader(p, strict=True) as r:
            r.streams()


# ------------------------------------------------------------------ 7: decode once, slice per view
def test_events_decoded_once_and_sliced(tmp_path):
    rng = np.random.default_rng(2)
    recs = [(dvs(int(rng.integers(240)), int(rng.integers(180)), int(rng.integers(2))), 1000 + 7 * i)
            for i in range(50_000)]
    p = tmp_path / "many.aedat"
    p.write_bytes(header(b"eu.seebetter.ini.chips.davis.DAVIS240C", b"") + body(recs))
    windows = [(1000 + 7 * k, 1000 + 7 * k + 5000) for k in range(0, 50_000, 2500)]
    ts = np.array([t for _, t in recs])
    for kw in ({}, {"cache_records": 0, "chunk_records": 4096}):     # in-memory, and the per-chunk time index
        with Aedat2Reader(p, **kw) as r:
            list(r.events())                                       # the one decoding pass
            calls = []
            scan = r._scan
            r._scan = lambda *a, **k: (calls.append(1), scan(*a, **k))[1]
            for lo, hi in windows:
                got = np.concatenate([e.t for e in r.events(None, lo, hi)])
                assert got.tolist() == ts[(ts >= lo) & (ts < hi)].tolist()
            assert len(calls) == (0 if not kw else len(windows))
            if kw:                                                 # the index decodes 1-2 chunks, not the file
                assert len(r._index) > 10


# ------------------------------------------------------------------ 8: messages
def test_cli_messages(tmp_path, capsys):
    from ev3dgs.cli.ingest import main

    p = tmp_path / "w.aedat"
    p.write_bytes(header(b"eu.seebetter.ini.chips.davis.DAVIS240C", b"") + body(roll_recording(seconds=0.05))
                  + b"\x01\x02")
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr()
    text = out.out + out.err
    assert text.count("does not state the IMU full scale") == 1 and text.count("trailing bytes") == 1
    assert "UserWarning" not in text and "AedatWarning" not in text and "special" not in text
    assert "packets" not in text
    empty = tmp_path / "empty.aedat"
    empty.write_bytes(b"")
    assert main(["info", str(empty)]) == 2
    assert "empty file" in capsys.readouterr().err
    assert main(["davis", str(p), "--out", str(tmp_path / "s.h5"), "--no-poses"]) == 2
    err = capsys.readouterr().err
    assert "no APS frames (0 frames)" in err and "UserWarning" not in err
