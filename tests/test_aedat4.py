"""AEDAT 4.0 reader: the shared real DAVIS346 file, dv-processing-written fixtures (all compressions, frame
formats, IMU, triggers, several streams), truncation, byte flips and bounded memory."""
from __future__ import annotations

import datetime
import os
import struct
import tempfile
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ev3dgs.events import Events
from ev3dgs.io.aedat4 import Aedat4Reader, AedatWarning, info
from ev3dgs.io.types import AedatError

dv = pytest.importorskip("dv_processing")

SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="shared AEDAT sample not present")
COMPRESSIONS = {"none": "NONE", "lz4": "LZ4", "lz4-high": "LZ4_HIGH", "zstd": "ZSTD", "zstd-high": "ZSTD_HIGH"}


def read_all(path, **kw):
    """Everything the reader returns, as plain arrays (used to compare truncated/corrupt reads)."""
    with Aedat4Reader(path, **kw) as r:
        out = {"events": Events.concatenate(list(r.events())) if any(s.kind == "events" for s in r.streams())
               else Events(), "frames": [], "imu": None, "triggers": None, "warnings": r.warnings}
        kinds = {s.kind for s in r.streams()}
        if "frames" in kinds:
            out["frames"] = list(r.frames())
        if "imu" in kinds:
            out["imu"] = r.imu()
        if "triggers" in kinds:
            out["triggers"] = r.triggers()
        out["info"] = r.info()
    return out


# ---------------------------------------------------------------- the shared real recording (EXPECTED.md)
@needs_shared
def test_shared_file_expected_values():
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # an intact file gives no warning
        with Aedat4Reader(SHARED) as r:
            assert r.format == "aedat4" and r.data_start == 3126 and r.table_position == 1190063 and r.has_table
            assert [(s.id, s.name, s.type_identifier, s.kind) for s in r.streams()] == [
                (0, "events", "EVTS", "events"), (1, "frames", "FRME", "frames"),
                (2, "imu", "IMUS", "imu"), (3, "triggers", "TRIG", "triggers")]
            assert [s.packets for s in r.streams()] == [13, 3, 13, 11]
            assert {s.compression for s in r.streams()} == {"lz4"}
            assert r.streams()[0].source == "DAVIS346_00000104" and r.sensor_size() == (346, 260)
            chunks = list(r.events())
            ev = Events.concatenate(chunks)
            frames = list(r.frames())
            imu, trig = r.imu(), r.triggers()
            pt = r.packet_table()
            inf = r.info()
            assert r.warnings == []
    assert (pt["stream"] == 0).sum() == 13 and sum(len(c) for c in chunks) == int(pt["elements"][pt["stream"] == 0].sum())
    assert len(ev) == 117667 and ev.on_count == 72363 and ev.off_count == 45304
    assert ev.t[0] == 1633953690975950 and ev.t[-1] == 1633953691105949 and np.all(np.diff(ev.t) >= 0)
    assert int(ev.x.astype(np.int64).sum()) == 17676033 and int(ev.y.astype(np.int64).sum()) == 10498046
    assert int((ev.t - ev.t[0]).sum()) == 7327758848
    assert ev.x.max() == 345 and ev.y.max() == 259
    first3 = [(int(t), int(x), int(y), int(p > 0)) for t, x, y, p in zip(ev.t[:3], ev.x[:3], ev.y[:3], ev.p[:3])]
    assert first3 == [(1633953690975950, 218, 15, 1), (1633953690975950, 306, 76, 1), (1633953690975954, 178, 73, 0)]
    assert set(np.unique(ev.p)) == {-1, 1}
    assert len(frames) == 3
    f0 = frames[0]
    assert f0.image.shape == (260, 346) and f0.image.dtype == np.uint8 and f0.position == (0, 0)
    assert (f0.timestamp, f0.frame_start, f0.frame_end, f0.exposure_start, f0.exposure_end) == (
        1633953690978904, 1633953690967091, 1633953690990743, 1633953690976518, 1633953690981291)
    assert f0.exposure_end - f0.exposure_start == 4773 and frames[-1].timestamp == 1633953691058904
    assert int(f0.image.astype(np.int64).sum()) == 4587151 and abs(f0.image.mean() - 50.991) < 1e-3
    assert sum(int(f.image.astype(np.int64).sum()) for f in frames) == 13809230
    assert len(imu) == 130 and imu.t[0] == 1633953690976628 and imu.t[-1] == 1633953691105605
    assert imu.temperature[0] == pytest.approx(27.752941, abs=1e-5)
    np.testing.assert_allclose(imu.accel[0], [-0.060425, -0.991211, -0.097412], atol=1e-5)
    np.testing.assert_allclose(imu.gyro[0], [6.454467, 2.578735, -0.167847], atol=1e-5)
    assert len(trig) == 15 and trig.t[0] == 1633953690976518 and trig.t[-1] == 1633953691110744
    assert dict(zip(*[a.tolist() for a in np.unique(trig.kind, return_counts=True)])) == {6: 3, 7: 4, 8: 4, 9: 4}
    # FileDataTable: 40 packets, 26 start before the latest end of the earlier ones (cross-stream disorder)
    assert len(pt["offset"]) == 40 and pt["offset"][0] == 3134
    assert int(np.sum(pt["t_start"][1:] < np.maximum.accumulate(pt["t_end"])[:-1])) == 26
    assert inf["compression"] == "lz4" and inf["file_size"] == 1191471 and inf["packets"] == 40
    assert [(d["packets"], d["elements"]) for d in inf["streams"]] == [(13, 117667), (3, 3), (13, 130), (11, 15)]
    assert inf["t_start"] == 1633953690975950 and inf["t_end"] == 1633953691110744


@needs_shared
def test_shared_file_window_and_dv_reference():
    with Aedat4Reader(SHARED) as r:
        full = Events.concatenate(list(r.events()))
        a, b = 1633953691000000, 1633953691050000
        win = Events.concatenate(list(r.events(start_us=a, end_us=b)))
        assert len(list(r.events(start_us=0, end_us=1))) == 0
    ref = full.window(a, b)
    assert np.array_equal(win.t, ref.t) and np.array_equal(win.x, ref.x) and np.array_equal(win.p, ref.p)
    rec = dv.io.MonoCameraRecording(str(SHARED))
    parts = []
    while (b := rec.getNextEventBatch()) is not None:
        parts.append(b.numpy())
    dref = np.concatenate(parts)
    assert np.array_equal(full.t, dref["timestamp"]) and np.array_equal(full.x, dref["x"])
    assert np.array_equal(full.y, dref["y"]) and np.array_equal(full.p > 0, dref["polarity"] > 0)


# ---------------------------------------------------------------- fixtures written by dv-processing
def _events(t0, n, res=(640, 480), seed=0):
    return dv.data.generate.uniformEventsWithinTimeRange(t0, datetime.timedelta(microseconds=4 * n), res, n, seed)


def write_fixture(path, compression="LZ4"):
    """Events (several packets), GRAY, BGR, BGRA and 16-bit frames (one with an ROI offset), IMU, triggers."""
    rng = np.random.default_rng(1)
    cfg = dv.io.MonoCameraWriter.Config("DAVIS346_test", getattr(dv.CompressionType, compression))
    cfg.addEventStream((640, 480))
    cfg.addFrameStream((64, 48))
    cfg.addImuStream()
    cfg.addTriggerStream()
    w = dv.io.MonoCameraWriter(str(path), cfg)
    w.setPackagingCount(4)
    stores = [_events(1000 + k * 100000, 12000, seed=k) for k in range(3)]
    images = [rng.integers(0, 256, (48, 64), dtype=np.uint8), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),
              rng.integers(0, 256, (48, 64, 4), dtype=np.uint8), rng.integers(0, 1024, (48, 64), dtype=np.uint16),
              rng.integers(0, 256, (10, 20, 3), dtype=np.uint8)]
    frames = [(5000 + 20000 * i, 300 + i, (2, 3) if i == 4 else (0, 0), img) for i, img in enumerate(images)]
    imu = rng.normal(size=(10, 7)).astype(np.float32)
    for k, s in enumerate(stores):
        w.writeEvents(s)
        fr = frames[k]
        w.writeFrame(dv.Frame(fr[0], fr[1], fr[2][0], fr[2][1], fr[3], dv.FrameSource.SENSOR))
    for fr in frames[3:]:
        w.writeFrame(dv.Frame(fr[0], fr[1], fr[2][0], fr[2][1], fr[3], dv.FrameSource.SENSOR))
    for i in range(10):
        w.writeImu(dv.IMU(2000 + 10 * i, *map(float, imu[i]), 0.0, 0.0, 0.0))
        w.writeTrigger(dv.Trigger(2000 + 7 * i, dv.TriggerType(i % 10)))
    del w
    ev = np.concatenate([s.numpy() for s in stores])
    return {"events": ev, "frames": frames, "imu": imu, "imu_t": 2000 + 10 * np.arange(10),
            "trig_t": 2000 + 7 * np.arange(10), "trig_kind": np.arange(10) % 10}


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    d = tmp_path_factory.mktemp("aedat4")
    out = {}
    for name, comp in COMPRESSIONS.items():
        p = d / f"fx_{name}.aedat4"
        out[name] = (p, write_fixture(p, comp))
    return out


@pytest.mark.parametrize("name", list(COMPRESSIONS))
def test_roundtrip_all_compressions(fixtures, name):
    path, exp = fixtures[name]
    got = read_all(path)
    assert got["warnings"] == [] and got["info"]["compression"] == name and got["info"]["has_table"]
    ev, e = got["events"], exp["events"]
    assert np.array_equal(ev.t, e["timestamp"]) and np.array_equal(ev.x, e["x"]) and np.array_equal(ev.y, e["y"])
    assert np.array_equal(ev.p, np.where(e["polarity"] > 0, 1, -1))
    assert len(got["frames"]) == len(exp["frames"])
    for f, (ts, expo, pos, img) in zip(got["frames"], exp["frames"]):
        assert f.image.dtype == img.dtype and f.image.shape == img.shape and np.array_equal(f.image, img)
        assert f.timestamp == ts and f.exposure_start == ts and f.exposure_end - f.exposure_start == expo
        assert f.position == pos and f.source == "DAVIS346_test"
    imu = got["imu"]
    assert np.array_equal(imu.t, exp["imu_t"]) and np.array_equal(imu.temperature, exp["imu"][:, 0])
    assert np.array_equal(imu.accel, exp["imu"][:, 1:4]) and np.array_equal(imu.gyro, exp["imu"][:, 4:7])
    assert np.array_equal(got["triggers"].t, exp["trig_t"]) and np.array_equal(got["triggers"].kind, exp["trig_kind"])
    with Aedat4Reader(path) as r:
        assert r.sensor_size() == (640, 480)
        assert [s.name for s in r.streams()] == ["events", "frames", "imu", "triggers"]


def test_several_event_streams(tmp_path):
    left = dv.io.MonoCameraWriter.Config("camL", dv.CompressionType.ZSTD)
    left.addEventStream((100, 80))
    left.addEventStream((100, 80), "events2")
    right = dv.io.MonoCameraWriter.Config("camR", dv.CompressionType.ZSTD)
    right.addEventStream((120, 90))
    right.addTriggerStream()
    p = tmp_path / "stereo.aedat4"
    w = dv.io.StereoCameraWriter(str(p), left, right)
    sl, sl2, sr = _events(1000, 500, (100, 80), 1), _events(1000, 300, (100, 80), 2), _events(1000, 700, (120, 90), 3)
    w.left.writeEvents(sl)
    w.left.writeEvents(sl2, "events2")
    w.right.writeEvents(sr)
    del w
    with Aedat4Reader(p) as r:
        ss = r.streams()
        assert [(s.name, s.source, s.kind) for s in ss] == [("events", "camL", "events"), ("events2", "camL", "events"),
                                                            ("events", "camR", "events"), ("triggers", "camR", "triggers")]
        cat = lambda **kw: Events.concatenate(list(r.events(**kw)))  # noqa: E731
        assert np.array_equal(cat().t, sl.numpy()["timestamp"])
        assert np.array_equal(cat(stream="events2").x, sl2.numpy()["x"])
        for sel in ("camR", "camR/events", ss[2].id, ss[2]):
            assert np.array_equal(cat(stream=sel).y, sr.numpy()["y"])
        assert r.sensor_size("camR") == (120, 90) and r.sensor_size() == (100, 80)
        assert len(r.triggers("camR")) == 0
        with pytest.raises(AedatError, match="holds triggers"):
            next(r.events(stream=3))
        with pytest.raises(AedatError, match="no events stream"):
            next(r.events(stream="nope"))
        with pytest.raises(AedatError, match="no frames stream"):
            next(r.frames())


def test_not_aedat4_and_missing(tmp_path):
    p = tmp_path / "x.aedat4"
    p.write_bytes(b"#!AER-DAT2.0\r\n" + bytes(100))
    with pytest.raises(AedatError, match="byte 0"):
        Aedat4Reader(p)
    with pytest.raises(AedatError, match="cannot open"):
        Aedat4Reader(tmp_path / "missing.aedat4")
    p.write_bytes(b"#!AER-DAT4.0\r\n" + struct.pack("<I", 0xFFFFFFFF) + bytes(10))
    with pytest.raises(AedatError, match="byte 14: IOHeader size 4294967295 runs past the end"):
        Aedat4Reader(p)


def test_corrupt_packet_size_names_byte(tmp_path, fixtures):
    path, _ = fixtures["lz4"]
    data = bytearray(path.read_bytes())
    with Aedat4Reader(path) as r:
        first, tp = int(r.packet_table()["offset"][0]) - 8, r.table_position
    data[first + 4:first + 8] = struct.pack("<I", 0xFFFFFFFF)
    data[tp:] = b""                                        # no table: force the packet walk
    p = tmp_path / "bad.aedat4"
    p.write_bytes(bytes(data))
    with pytest.warns(AedatWarning), pytest.raises(AedatError, match=f"byte {first}: packet size 4294967295 runs past"):
        Aedat4Reader(p)


def test_absent_table_walks_packets(tmp_path, fixtures):
    path, exp = fixtures["zstd"]
    full = read_all(path)
    with Aedat4Reader(path) as r:
        tp = r.table_position
    p = tmp_path / "notable.aedat4"
    p.write_bytes(path.read_bytes()[:tp])
    with pytest.warns(AedatWarning, match="FileDataTable position"):
        got = read_all(p)
    assert np.array_equal(got["events"].t, full["events"].t) and len(got["frames"]) == 5
    assert not got["info"]["has_table"]
    assert [(d["packets"], d["elements"], d["t_start"], d["t_end"]) for d in got["info"]["streams"]] == \
        [(d["packets"], d["elements"], d["t_start"], d["t_end"]) for d in full["info"]["streams"]]


def test_unreadable_xml_and_corrupt_table_fall_back(tmp_path, fixtures):
    path, _ = fixtures["none"]
    full = read_all(path)
    data = bytearray(path.read_bytes())
    i = data.index(b"<dv version")
    data[i:i + 3] = b"<<v"                                  # same length: the IOHeader stays valid
    p = tmp_path / "badxml.aedat4"
    p.write_bytes(bytes(data))
    with pytest.warns(AedatWarning, match="unreadable infoNode XML"):
        got = read_all(p)
    assert [(s["kind"], s["type_identifier"]) for s in got["info"]["streams"]] == [
        ("events", "EVTS"), ("frames", "FRME"), ("imu", "IMUS"), ("triggers", "TRIG")]
    assert np.array_equal(got["events"].t, full["events"].t) and len(got["frames"]) == 5
    data = bytearray(path.read_bytes())
    tp = full["info"]["table_position"]
    data[tp + 12:] = bytes(len(data) - tp - 12)               # zero the FileDataTable body
    p.write_bytes(bytes(data))
    with pytest.warns(AedatWarning, match="FileDataTable"):
        got = read_all(p)
    assert not got["info"]["has_table"] and np.array_equal(got["events"].x, full["events"].x)
    assert np.array_equal(got["imu"].gyro, full["imu"].gyro)


# ---------------------------------------------------------------- truncation and corruption
def _check_prefix(got, full):
    """Salvaged data must be a prefix of the full data, per stream."""
    n = len(got["events"])
    assert n <= len(full["events"])
    assert np.array_equal(got["events"].t, full["events"].t[:n]) and np.array_equal(got["events"].x, full["events"].x[:n])
    assert len(got["frames"]) <= len(full["frames"])
    for a, b in zip(got["frames"], full["frames"]):
        assert np.array_equal(a.image, b.image) and a.timestamp == b.timestamp
    for k in ("imu", "triggers"):
        if got[k] is not None:
            m = len(got[k])
            assert np.array_equal(got[k].t, full[k].t[:m])


def _truncation_offsets(path, n_random, seed):
    with Aedat4Reader(path) as r:
        pt, tp, ds = r.packet_table(), r.table_position, r.data_start
    size = path.stat().st_size
    bounds = [int(o) - 8 for o in pt["offset"]] + [int(o) + 3 for o in pt["offset"]] + [tp, tp + 5, ds, ds - 1, 10]
    rng = np.random.default_rng(seed)
    return sorted(set(bounds) | set(rng.integers(1, size, n_random).tolist()))


@pytest.mark.parametrize("which", ["fixture", "shared"])
def test_truncation_salvages_prefix(tmp_path, fixtures, which):
    path = fixtures["lz4"][0] if which == "fixture" else SHARED
    if not path.exists():
        pytest.skip("shared AEDAT sample not present")
    full = read_all(path)
    data = path.read_bytes()
    salvaged = 0
    for cut in _truncation_offsets(path, 40, 7):
        p = tmp_path / "cut.aedat4"
        p.write_bytes(data[:cut])
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                got = read_all(p)
            except AedatError as e:
                assert "byte" in str(e)
                continue
        assert caught and got["warnings"], f"cut at {cut}: data lost without a warning"
        _check_prefix(got, full)
        salvaged += 1
    assert salvaged >= 30


def _flip_and_read(data: bytes, flips, limit_s=5.0, limit_mb=200):
    buf = bytearray(data)
    for pos, val in flips:
        buf[pos % len(buf)] ^= val
    fd, name = tempfile.mkstemp(suffix=".aedat4")
    try:
        os.write(fd, bytes(buf))
        os.close(fd)
        tracemalloc.start()
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for skip in (False, True):
                try:
                    read_all(name, skip_corrupt=skip)
                except AedatError as e:
                    assert "byte" in str(e) or "stream" in str(e)
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        os.unlink(name)
    assert elapsed < limit_s, f"took {elapsed:.1f} s"
    assert peak < limit_mb * 2**20, f"peak {peak / 2**20:.0f} MB"


_flips = st.lists(st.tuples(st.integers(0, 2**31), st.integers(1, 255)), min_size=1, max_size=6)
_fuzz = settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@_fuzz
@given(flips=_flips, structural=st.booleans())
def test_byte_flips_uncompressed_fixture(fixtures, flips, structural):
    path = fixtures["none"][0]
    if structural:  # aim at the IOHeader, each packet's header and flatbuffer head, and the FileDataTable
        with Aedat4Reader(path) as r:
            pt, tp = r.packet_table(), r.table_position
        spots = np.concatenate([np.arange(14, 200), (pt["offset"][:, None] + np.arange(-8, 56)).ravel(),
                                np.arange(tp, path.stat().st_size)])
        flips = [(int(spots[p % len(spots)]), v) for p, v in flips]
    _flip_and_read(path.read_bytes(), flips)


@needs_shared
@_fuzz
@given(flips=_flips, in_header=st.booleans())
def test_byte_flips_shared_file(flips, in_header):
    data = SHARED.read_bytes()
    if in_header:   # aim at the IOHeader, packet headers near the start, and the FileDataTable
        flips = [(p % 4000 if i % 2 else len(data) - 1 - p % 1400, v) for i, (p, v) in enumerate(flips)]
    _flip_and_read(data, flips)


def test_decompression_bomb_refused(tmp_path):
    import zstandard
    hdr = b"#!AER-DAT4.0\r\n"
    xml = b'<dv version="2.0"><node name="outInfo"><node name="0"><attr key="typeIdentifier" type="string">EVTS</attr></node></node></dv>'
    # IOHeader table by hand: root uoffset, vtable (3 slots), table: soffset, compression int32, xml offset
    vt = struct.pack("<HHHHH", 10, 12, 4, 0, 8)
    body = struct.pack("<I", 4 + len(vt)) + vt
    tab_pos = len(body)
    body += struct.pack("<iiI", tab_pos - 4, 3, 0)
    body = bytearray(body)
    struct.pack_into("<I", body, tab_pos + 8, len(body) - (tab_pos + 8))
    body += struct.pack("<I", len(xml)) + xml + b"\0"
    payload = zstandard.ZstdCompressor().compress(struct.pack("<I", 2**31) + b"\0" * (20 << 20))
    data = hdr + struct.pack("<I", len(body)) + bytes(body) + struct.pack("<iI", 0, len(payload)) + payload
    p = tmp_path / "bomb.aedat4"
    p.write_bytes(data)
    with pytest.raises(AedatError, match="no FileDataTable"):
        Aedat4Reader(p, strict=True)              # strict: walking the packets is a repair, and fails
    with pytest.warns(AedatWarning, match="no FileDataTable"):
        r = Aedat4Reader(p)
    tracemalloc.start()
    try:
        with pytest.warns(AedatWarning, match=r"claims 2147483652 decompressed bytes"):
            assert list(r.events()) == []         # the bomb is skipped, never inflated
        assert tracemalloc.get_traced_memory()[1] < 50 << 20
    finally:
        tracemalloc.stop()
        r.close()


# ---------------------------------------------------------------- bounded memory on a larger file
@pytest.fixture(scope="module")
def big_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("big") / "big5m.aedat4"
    cfg = dv.io.MonoCameraWriter.Config("big", dv.CompressionType.LZ4)
    cfg.addEventStream((640, 480))
    w = dv.io.MonoCameraWriter(str(p), cfg)
    for k in range(50):
        w.writeEvents(_events(1000 + k * 400000, 100000, seed=k))
    del w
    return p


@pytest.mark.parametrize("threads", [1, 2])
def test_memory_bounded_and_throughput(big_file, capsys, threads):
    with Aedat4Reader(big_file, threads=threads) as r:
        assert r.streams()[0].packets >= 400
        pt_elements = r.packet_table()["elements"]
        tracemalloc.start()
        t0 = time.perf_counter()
        n = sx = 0
        for ev in r.events():
            n += len(ev)
            sx += int(ev.x.sum(dtype=np.int64))
        ours = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert n == 5_000_000
    # what the reader holds does not grow with the file: per decoding thread a read buffer and a decompression
    # buffer (_SCRATCH0 each, packets here are smaller), and at most 16 reused blocks of unpacked events, each
    # the largest packet's 17 bytes per event rounded up to a power of two; 1 MiB for Python objects
    from ev3dgs.io.aedat4.packets import _SCRATCH0, BlockPool
    block = max(BlockPool.MIN_BLOCK, 1 << (17 * int(pt_elements.max()) - 1).bit_length())
    bound = threads * 2 * _SCRATCH0 + 16 * block + (1 << 20)
    assert peak < bound < 16 * n // 8, f"peak {peak / 2**20:.1f} MB for {16 * n / 2**20:.0f} MB of decoded events"
    t0 = time.perf_counter()
    rec = dv.io.MonoCameraRecording(str(big_file))
    m = sy = 0
    while (b := rec.getNextEventBatch()) is not None:
        a = b.numpy()
        m += len(a)
        sy += int(a["x"].sum(dtype=np.int64))
    theirs = time.perf_counter() - t0
    assert (m, sy) == (n, sx)
    with capsys.disabled():
        print(f"\n5M events: ev3dgs ({threads} threads) {n / ours / 1e6:.1f} M ev/s, dv-processing {m / theirs / 1e6:.1f} M ev/s, "
              f"tracemalloc peak {peak / 2**20:.1f} MB")


def test_info_function(fixtures):
    d = info(fixtures["zstd-high"][0])
    assert d["format"] == "aedat4" and d["compression"] == "zstd-high"
    assert [(s["kind"], s["elements"]) for s in d["streams"]] == [("events", 36000), ("frames", 5), ("imu", 10),
                                                                  ("triggers", 10)]
