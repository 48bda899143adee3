"""AEDAT 2.0 / 3.1 readers against fixtures built byte by byte from the documented layouts
(shared/reference/aedat-formats.md §2), with an encoder written here independently of the readers."""
from __future__ import annotations

import struct
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ev3dgs.io.jaer.aedat2 import Aedat2Reader
from ev3dgs.io.jaer.aedat3 import Aedat3Reader
from ev3dgs.io.types import AedatError

from aedat2_build import aps as a2_aps, dvs as a2_dvs, imu_word as a2_imu  # the jAER DAVIS address encoders

W, H = 346, 260
AEDAT4_SAMPLE = Path(__file__).resolve().parents[2] / "shared/data/aedat/aestream_davis.aedat4"

# ---------------------------------------------------------------- AEDAT 2.0 encoder (jAER DAVIS, big-endian)
A2_HEADER = (b"#!AER-DAT2.0\r\n# This is a raw AE data file created by AEOutputStream\r\n"
             b"# AEChip: eu.seebetter.ini.chips.davis.Davis346red\r\n"
             b"#      <entry key=\"ImuAccelScale\" value=\"ImuAccelScaleG8\"/>\r\n"
             b"#      <entry key=\"ImuGyroScale\" value=\"GyroFullScaleDegPerSec1000\"/>\r\n"
             b"#End Of ASCII Header\r\n")


def build_aedat2(seed=0, roi=True):
    """-> (bytes, expected dict). Every record's end offset is kept so truncated files have exact expectations."""
    rng = np.random.default_rng(seed)
    recs = []                                         # (address, true timestamp)
    exp = dict(ev=[], frames=[], imu=[], trig=[])
    t = [2**31 - 4000]                                # crosses the int32 overflow and the uint32 wrap below

    def add(addr, dt):
        t[0] += dt
        recs.append((addr, t[0]))
        return len(recs)                              # 1-based index of this record = records needed to hold it

    def dvs_burst(n, big=False):
        for _ in range(n):
            x, y, p = int(rng.integers(0, W)), int(rng.integers(0, H)), int(rng.integers(0, 2))
            k = add(a2_dvs(x, y, p), int(rng.integers(1 << 23, 1 << 25)) if big else int(rng.integers(0, 50)))
            exp["ev"].append((t[0], x, H - 1 - y, 1 if p else -1, k))

    dvs_burst(60)
    for code, kind in ((2, 2), (3, 1), (4, 3), (0, -1)):        # external input: excluded from events
        k = add((1 << 10) | code, 7)
        exp["trig"].append((t[0], kind, k))
    dvs_burst(150, big=True)                          # ~2.5e9 us: passes 2^32
    # APS frame: ROI 4x3 at x 10..13, y 20..22 (or full sensor), reset reads then signal reads, in jAER's
    # Davis346 readout order: from the first pixel address (W-1, H-1) to the last (0, 0)
    xs, ys = (range(13, 9, -1), range(22, 19, -1)) if roi else (range(W - 1, -1, -1), range(H - 1, -1, -1))
    reset = {(x, y): int(rng.integers(300, 1024)) for y in ys for x in xs}
    signal = {(x, y): int(rng.integers(0, 700)) for y in ys for x in xs}
    signal[(xs[0], ys[0])] = 1023                     # signal above reset -> clipped to 0
    fs = None
    for (x, y), v in reset.items():
        add(a2_aps(x, y, 0, v), 1)
        fs = t[0] if fs is None else fs
    soe = t[0]
    dvs_burst(20)                                     # DVS events during the exposure
    eoe = None
    for (x, y), v in signal.items():
        k = add(a2_aps(x, y, 1, v), 1)
        eoe = t[0] if eoe is None else eoe
    img = np.zeros((len(ys), len(xs)), np.uint16)
    for (x, y) in reset:
        img[max(ys) - y, x - min(xs)] = np.clip(reset[(x, y)] - signal[(x, y)], 0, 1023) << 6
    exp["frames"].append(dict(fs=fs, soe=soe, eoe=eoe, fe=t[0], img=img, pos=(min(xs), H - 1 - max(ys)), k=k))
    for s in range(3):                                # IMU samples: 7 words, same timestamp
        raw = [int(v) for v in rng.integers(-30000, 30000, 7)]
        for kind, v in enumerate(raw):
            k = add(a2_imu(kind, v), 5 if kind == 0 else 0)
        exp["imu"].append((t[0], raw, k))
        dvs_burst(10)
    dvs_burst(40)
    body = b"".join(struct.pack(">II", a, ts % 2**32) for a, ts in recs)
    return A2_HEADER + body, exp


def imu_expected(raw):
    r = np.array(raw, float)
    # camera frame (x right, y down, z forward) = diag(-1, 1, -1) x the MPU's raw axes, both sensors
    return np.array([-r[0], r[1], -r[2]]) / 4096, np.array([-r[4], r[5], -r[6]]) / 32.8, r[3] / 340 + 35


def read_all(reader):
    ev = list(reader.events())
    t = np.concatenate([e.t for e in ev]) if ev else np.zeros(0, np.int64)
    return dict(t=t, x=np.concatenate([e.x for e in ev]) if ev else t, y=np.concatenate([e.y for e in ev]) if ev else t,
                p=np.concatenate([e.p for e in ev]) if ev else t, frames=list(reader.frames()), imu=reader.imu(),
                trig=reader.triggers(), info=reader.info())


def check_aedat2(got, exp, k_max=10**9):
    ev = [e for e in exp["ev"] if e[4] <= k_max]
    assert got["t"].tolist() == [e[0] for e in ev]
    assert got["x"].tolist() == [e[1] for e in ev]
    assert got["y"].tolist() == [e[2] for e in ev]
    assert got["p"].tolist() == [e[3] for e in ev]
    frames = [f for f in exp["frames"] if f["k"] <= k_max]
    assert len(got["frames"]) == len(frames)
    for g, f in zip(got["frames"], frames):
        assert (g.frame_start, g.exposure_start, g.exposure_end, g.frame_end) == (f["fs"], f["soe"], f["eoe"], f["fe"])
        assert g.timestamp == (f["soe"] + f["eoe"]) // 2
        assert g.position == f["pos"] and g.image.dtype == np.uint16
        np.testing.assert_array_equal(g.image, f["img"])
    imu = [s for s in exp["imu"] if s[2] <= k_max]
    assert got["imu"].t.tolist() == [s[0] for s in imu]
    for i, s in enumerate(imu):
        a, g, temp = imu_expected(s[1])
        np.testing.assert_allclose(got["imu"].accel[i], a, rtol=1e-6)
        np.testing.assert_allclose(got["imu"].gyro[i], g, rtol=1e-6)
        np.testing.assert_allclose(got["imu"].temperature[i], temp, rtol=1e-6)
    trig = [s for s in exp["trig"] if s[2] <= k_max]
    assert got["trig"].t.tolist() == [s[0] for s in trig]
    assert got["trig"].kind.tolist() == [s[1] for s in trig]
    assert got["info"]["events"] == len(ev) and got["info"]["frames"] == len(frames)


@pytest.fixture(scope="module")
def a2(tmp_path_factory):
    data, exp = build_aedat2()
    p = tmp_path_factory.mktemp("a2") / "rec.aedat"
    p.write_bytes(data)
    return p, data, exp


def test_aedat2_exact_values(a2):
    p, data, exp = a2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with Aedat2Reader(p) as r:
            assert r.format == "aedat2" and r.sensor_size() == (W, H)
            got = read_all(r)
            assert r.warnings == []
    check_aedat2(got, exp)
    assert got["t"].max() > 2**32 and np.all(np.diff(got["t"]) >= 0)     # unwrapped past the uint32 wrap
    info = got["info"]
    assert info["file_size"] == len(data) and info["triggers"] == 4 and info["imu_samples"] == 3
    assert "special" not in info and all("packets" not in s for s in info["streams"])
    assert info["time_range"] == (int(got["t"].min()), int(got["t"].max()))
    assert [s.kind for s in Aedat2Reader(p).streams()] == ["events", "frames", "imu", "triggers"]


@pytest.mark.parametrize("chunk", [1, 3, 7, 64])
def test_aedat2_chunk_boundaries(a2, chunk):
    p, _, exp = a2
    with Aedat2Reader(p, chunk_records=chunk) as r:
        check_aedat2(read_all(r), exp)


def test_aedat2_window_and_streams(a2):
    p, _, exp = a2
    ts = [e[0] for e in exp["ev"]]
    lo, hi = ts[100], ts[200]
    with Aedat2Reader(p) as r:
        got = np.concatenate([e.t for e in r.events("events", lo, hi)])
        assert got.tolist() == [t for t in ts if lo <= t < hi]
        with pytest.raises(AedatError):
            list(r.events("imu"))
        with pytest.raises(AedatError):
            r.imu(7)


def test_aedat2_full_frame_and_31bit_wrap(tmp_path):
    data, exp = build_aedat2(seed=3, roi=False)
    p = tmp_path / "full.aedat"
    p.write_bytes(data)
    with Aedat2Reader(p) as r:
        got = read_all(r)
    check_aedat2(got, exp)
    assert got["frames"][0].image.shape == (H, W) and got["frames"][0].position == (0, 0)
    # a 31-bit counter wrapping back to 0 (no int32 overflow): +2^31
    body = b"".join(struct.pack(">II", a2_dvs(1, 2, 1), ts) for ts in (2**31 - 100, 2**31 - 1, 5, 9))
    p.write_bytes(A2_HEADER + body)
    with Aedat2Reader(p) as r:
        assert np.concatenate([e.t for e in r.events()]).tolist() == [2**31 - 100, 2**31 - 1, 2**31 + 5, 2**31 + 9]


def test_aedat2_truncation_every_record_and_random(a2, tmp_path):
    p0, data, exp = a2
    n = (len(data) - len(A2_HEADER)) // 8
    rng = np.random.default_rng(1)
    cuts = [len(A2_HEADER) + 8 * k for k in range(n + 1)] + list(rng.integers(len(A2_HEADER), len(data), 40))
    p = tmp_path / "cut.aedat"
    for c in cuts:
        p.write_bytes(data[:c])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Aedat2Reader(p, chunk_records=97) as r:
                got = read_all(r)
                if (c - len(A2_HEADER)) % 8:
                    assert any("trailing bytes" in w for w in r.warnings)
        check_aedat2(got, exp, k_max=(c - len(A2_HEADER)) // 8)


# ---------------------------------------------------------------- AEDAT 3.1 encoder (cAER, little-endian)
A3_HEADER = (b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS346B\r\n"
             b"#Start-Time: 2020-01-01 00:00:00 (TZ+0000)\r\n#!END-HEADER\r\n")


def a3_packet(typ, size, ovf, events, capacity=None, src=1):
    cap = len(events) if capacity is None else capacity
    valid = sum(1 for e in events if struct.unpack_from("<I", e)[0] & 1)
    return (struct.pack("<hhiiiiii", typ, src, size, 4, ovf, cap, len(events), valid)
            + b"".join(events) + bytes((cap - len(events)) * size))


def a3_polarity(x, y, p, ts, valid=1):
    return struct.pack("<Ii", valid | (p << 1) | (y << 2) | (x << 17), ts)


def a3_frame(ts4, img, pos, channels):
    ly, lx = img.shape[:2]
    info = 1 | (channels << 1) | (0 << 4) | (5 << 8)
    return struct.pack("<9i", info, *ts4, lx, ly, *pos) + img.astype("<u2").tobytes()


def build_aedat3(seed=0):
    """-> (bytes, expected); each expected item carries the byte offset where its event ends."""
    rng = np.random.default_rng(seed)
    out = bytearray(A3_HEADER)
    exp = dict(ev=[], frames=[], imu=[], trig=[])

    def packet(typ, size, ovf, items, capacity=None):
        """items: (bytes, expected list name or None, value)."""
        start = len(out) + 28
        out.extend(a3_packet(typ, size, ovf, [b for b, _, _ in items], capacity))
        for j, (_, name, val) in enumerate(items):
            if name:
                exp[name].append((*val, start + (j + 1) * size))

    for ovf, n in ((0, 120), (1, 150)):
        items, base = [], int(rng.integers(2**31 - 10**6, 2**31 - 1000)) if ovf == 0 else 500
        for j in range(n):
            x, y, p, ts = int(rng.integers(0, W)), int(rng.integers(0, H)), int(rng.integers(0, 2)), base + 3 * j
            valid = int(j % 17 != 5)
            items.append((a3_polarity(x, y, p, ts, valid), "ev" if valid else None,
                          ((ovf << 31) | ts, x, y, 1 if p else -1)))
        packet(1, 8, ovf, items, capacity=n + 5 if ovf else None)
        # special events: trigger kinds follow AEDAT 4's TriggerType; wrap/row-only are excluded
        sp = []
        for ctype, kind in ((2, 1), (3, 2), (0, None), (14, 6), (17, 9), (5, None), (1, 0)):
            ts = base + 7
            sp.append((struct.pack("<Ii", 1 | (ctype << 1) | (42 << 8), ts), "trig" if kind is not None else None,
                       ((ovf << 31) | ts, kind)))
        packet(0, 8, ovf, sp)
        imu = []
        for s in range(2):
            v = [float(f) for f in np.float32(rng.normal(size=7))]
            ts = base + 11 * s
            imu.append((struct.pack("<Ii7f", 1, ts, *v), "imu", ((ovf << 31) | ts, v)))
        packet(3, 36, ovf, imu)
    gray = rng.integers(0, 65536, (3, 4)).astype(np.uint16)
    rgb = rng.integers(0, 65536, (2, 2, 3)).astype(np.uint16)
    size = 36 + 4 * 3 * 3 * 2
    frames = []
    for img, ch, pos in ((gray, 1, (7, 9)), (rgb, 3, (0, 0))):
        ts4 = [int(v) for v in np.sort(rng.integers(1000, 9000, 4))]
        ev = a3_frame(ts4, img, pos, ch)
        ev += bytes(size - len(ev))
        want = img if ch == 1 else img[:, :, ::-1]
        frames.append((ev, "frames", ([(1 << 31) | v for v in ts4], want, pos)))
    packet(2, size, 1, frames)
    return bytes(out), exp


def check_aedat3(r, exp, cut=10**12):
    got = read_all(r)
    ev = [e for e in exp["ev"] if e[-1] <= cut]
    assert got["t"].tolist() == [e[0] for e in ev]
    assert got["x"].tolist() == [e[1] for e in ev] and got["y"].tolist() == [e[2] for e in ev]
    assert got["p"].tolist() == [e[3] for e in ev]
    tr = [e for e in exp["trig"] if e[-1] <= cut]
    assert got["trig"].t.tolist() == [e[0] for e in tr] and got["trig"].kind.tolist() == [e[1] for e in tr]
    imu = [e for e in exp["imu"] if e[-1] <= cut]
    assert got["imu"].t.tolist() == [e[0] for e in imu]
    for i, e in enumerate(imu):
        v = np.array(e[1], np.float32)
        np.testing.assert_array_equal(got["imu"].accel[i], v[0:3])
        np.testing.assert_array_equal(got["imu"].gyro[i], v[3:6])
        assert got["imu"].temperature[i] == v[6]
    fr = [e for e in exp["frames"] if e[-1] <= cut]
    assert len(got["frames"]) == len(fr)
    for g, (ts4, img, pos, _) in zip(got["frames"], fr):
        assert [g.frame_start, g.frame_end, g.exposure_start, g.exposure_end] == ts4
        assert g.timestamp == (ts4[2] + ts4[3]) // 2 and g.position == pos
        np.testing.assert_array_equal(g.image, img)
    assert got["info"]["events"] == len(ev)
    return got


@pytest.fixture(scope="module")
def a3(tmp_path_factory):
    data, exp = build_aedat3()
    p = tmp_path_factory.mktemp("a3") / "rec.aedat"
    p.write_bytes(data)
    return p, data, exp


def test_aedat3_exact_values(a3):
    p, data, exp = a3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with Aedat3Reader(p) as r:
            assert r.format == "aedat3.1" and r.sensor_size() == (W, H)
            got = check_aedat3(r, exp)
            assert r.warnings == []
            assert [s.kind for s in r.streams()] == ["events", "frames", "imu", "triggers"]
            assert r.streams()[0].source == "DAVIS346B" and r.streams()[0].packets == 2
    assert got["t"].max() > 2**31 and got["info"]["file_size"] == len(data)
    assert got["info"]["time_range"] == (int(got["t"].min()), int(got["t"].max()))


def test_aedat3_two_sources(tmp_path):
    hdr = A3_HEADER.replace(b"#!END", b"#Source 2: DAVIS240C\r\n#!END")
    body = a3_packet(1, 8, 0, [a3_polarity(1, 2, 1, 10)], src=1) + a3_packet(1, 8, 0, [a3_polarity(3, 4, 0, 20)], src=2)
    p = tmp_path / "two.aedat"
    p.write_bytes(hdr + body)
    with Aedat3Reader(p) as r:
        assert [s.name for s in r.streams()] == ["events_1", "events_2"]
        assert [int(e.t[0]) for e in r.events("events_2")] == [20]
        assert [int(e.x[0]) for e in r.events()] == [1]


def test_aedat3_truncation_and_corrupt_header(a3, tmp_path):
    p0, data, exp = a3
    rng = np.random.default_rng(2)
    p = tmp_path / "cut.aedat"
    ends = sorted({e[-1] for k in exp for e in exp[k]})
    with Aedat3Reader(p0) as r:
        bounds = {pk[0] for pk in r._packets()} | {len(data)}
    cuts = sorted(set(ends) | set(rng.integers(len(A3_HEADER), len(data), 60).tolist()) | {len(A3_HEADER)})
    for c in cuts:
        p.write_bytes(data[:c])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Aedat3Reader(p) as r:
                check_aedat3(r, exp, cut=c)
                if c not in bounds:
                    assert any("truncated" in w for w in r.warnings)
    bad = bytearray(data)
    off = len(A3_HEADER)
    struct.pack_into("<i", bad, off + 4, 12)                      # eventSize 12 for polarity events
    p.write_bytes(bytes(bad))
    with pytest.raises(AedatError, match=f"byte {off}"):
        list(Aedat3Reader(p).events())


# ---------------------------------------------------------------- wrong formats and byte flips
def test_wrong_formats(tmp_path, a2, a3):
    a4 = tmp_path / "x.aedat4"
    a4.write_bytes(AEDAT4_SAMPLE.read_bytes()[:4096] if AEDAT4_SAMPLE.exists() else b"#!AER-DAT4.0\r\n" + bytes(100))
    junk = tmp_path / "junk.bin"
    junk.write_bytes(np.random.default_rng(0).bytes(5000))
    empty = tmp_path / "empty.aedat"
    empty.write_bytes(b"")
    for path in (a4, junk, empty, a3[0]):
        with pytest.raises(AedatError, match="not an AEDAT 2.0 file"):
            Aedat2Reader(path)
    for path in (a4, junk, empty, a2[0]):
        with pytest.raises(AedatError, match="not an AEDAT 3.1 file"):
            Aedat3Reader(path)
    with pytest.raises(AedatError, match="cannot open"):
        Aedat2Reader(tmp_path / "missing.aedat")


def consume(cls, path):
    t0 = time.perf_counter()
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                with cls(path) as r:
                    read_all(r)
                    r.streams()
            except AedatError:
                pass
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 10
    assert peak < 256 << 20


flips = st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8)


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips)
def test_aedat2_byte_flips(tmp_path, a2, fl):
    data = bytearray(a2[1])
    for f, v in fl:
        data[int(f * len(data))] ^= v
    p = tmp_path / "flip2.aedat"
    p.write_bytes(bytes(data))
    consume(Aedat2Reader, p)


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips, st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=3))
def test_aedat3_byte_flips(tmp_path, a3, fl, hot):
    data = bytearray(a3[1])
    with Aedat3Reader(a3[0]) as r:      # packet headers and frame-event headers, where flips matter most
        spots = [pk[0] + i for pk in r._packets() for i in range(28 + (36 if pk[1] == 2 else 0))]
    for f, v in fl:
        data[int(f * len(data))] ^= v
    for i, v in hot:
        data[spots[i % len(spots)]] ^= v
    p = tmp_path / "flip3.aedat"
    p.write_bytes(bytes(data))
    consume(Aedat3Reader, p)


def test_aedat2_chip_sizes_and_dvs_only(tmp_path):
    p = tmp_path / "d240.aedat"
    hdr = A2_HEADER.replace(b"Davis346red", b"DAVIS240C")
    p.write_bytes(hdr + struct.pack(">II", a2_dvs(239, 0, 0), 10) + struct.pack(">II", a2_dvs(240, 0, 1), 11))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat2Reader(p) as r:
            assert r.sensor_size() == (240, 180)
            [ev] = list(r.events())
            assert (ev.x.tolist(), ev.y.tolist(), ev.p.tolist()) == ([239], [179], [-1])   # x=240 is off-sensor
            assert any("outside" in w for w in r.warnings)
            assert [s.kind for s in r.streams()] == ["events"] and len(r.imu()) == 0 and list(r.frames()) == []
