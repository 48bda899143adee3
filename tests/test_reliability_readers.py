"""Damaged recordings never give silent garbage (issue 18): every decoded value the file itself contradicts is
dropped with a warning naming stream, packet and byte, or (strict) raises AedatError; intact files are read
exactly as before."""
from __future__ import annotations

import struct
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ev3dgs.events import Events
from ev3dgs.io.jaer.aedat2 import Aedat2Reader
from ev3dgs.io.jaer.aedat3 import Aedat3Reader
from ev3dgs.io.aedat4 import Aedat4Reader
from ev3dgs.io.types import AedatError

sys.path.insert(0, str(Path(__file__).parent))
from test_aedat_legacy import A2_HEADER, A3_HEADER, a2_dvs, a3_packet, a3_polarity, build_aedat2  # noqa: E402

SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="shared AEDAT sample not present")
N_EVENTS, W, H = 117_667, 346, 260


def read4(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat4Reader(path, **kw) as r:
            return dict(ev=Events.concatenate(list(r.events())), frames=list(r.frames()), imu=r.imu(),
                        trig=r.triggers(), warnings=list(r.warnings))


@pytest.fixture(scope="module")
def shared():
    if not SHARED.exists():
        pytest.skip("shared AEDAT sample not present")
    with Aedat4Reader(SHARED) as r:
        pt, tp = r.packet_table(), r.table_position
    return SHARED.read_bytes(), pt, tp


def assert_within_file(got, pt):
    """Every value is within what the (intact) file states: sensor size, polarity, per-stream time range
    and order."""
    ev = got["ev"]
    rng = {s: (int(pt["t_start"][pt["stream"] == s].min()), int(pt["t_end"][pt["stream"] == s].max())) for s in range(4)}
    if len(ev):
        assert int(ev.x.max()) < W and int(ev.y.max()) < H and set(np.unique(ev.p).tolist()) <= {-1, 1}
        assert rng[0][0] <= ev.t.min() and ev.t.max() <= rng[0][1] and (np.diff(ev.t) >= 0).all()
    for f in got["frames"]:
        assert f.image.shape[:2] == (H, W) and rng[1][0] <= f.timestamp <= rng[1][1]
    for k, s in (("imu", 2), ("trig", 3)):
        t = got[k].t
        assert len(t) == 0 or (rng[s][0] <= t.min() and t.max() <= rng[s][1] and (np.diff(t) >= 0).all())
    assert len(got["trig"]) == 0 or got["trig"].kind.max() <= 9
    lost = N_EVENTS - len(ev) + 3 - len(got["frames"]) + 130 - len(got["imu"]) + 15 - len(got["trig"])
    if lost:
        assert got["warnings"], "data dropped without a warning"


def mutate(data: bytes, flips) -> bytes:
    b = bytearray(data)
    for pos, v in flips:
        b[pos] ^= v
    return bytes(b)


# ---------------------------------------------------------------- the two byte flips from the probe
@needs_shared
@pytest.mark.parametrize("pos,val,what", [(1_000_775, 0x97, "t outside the packet's FileDataTable range"),
                                          (791_496, 0x64, "x/y outside the 346x260 sensor")])
def test_probe_flips_caught(shared, tmp_path, pos, val, what):
    data, pt, _ = shared
    p = tmp_path / "m.aedat4"
    p.write_bytes(mutate(data, [(pos, val)]))
    got = read4(p)
    assert_within_file(got, pt)
    assert len(got["ev"]) < N_EVENTS and any(what in w and "stream 0 (events) packet" in w for w in got["warnings"])
    with pytest.raises(AedatError, match=r"^byte \d+: stream 0 \(events\) packet \d+ \(file packet \d+\): .*" + what):
        read4(p, strict=True)


@needs_shared
@settings(max_examples=50, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=3))
def test_mutant_sweep_clean_error_or_within_file(shared, tmp_path_factory, flips):
    data, pt, tp = shared
    lo = int(pt["offset"][0]) - 8                        # the packets (the header and table are fuzzed elsewhere)
    p = tmp_path_factory.getbasetemp() / "sweep.aedat4"
    p.write_bytes(mutate(data, [(lo + int(f * (tp - lo)), v) for f, v in flips]))
    try:
        got = read4(p)
    except AedatError as e:
        assert "byte" in str(e)
        return
    assert_within_file(got, pt)


@needs_shared
def test_intact_file_unchanged_and_silent(shared):
    data, pt, _ = shared
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = read4(SHARED, strict=True)
    ev = got["ev"]
    assert len(ev) == N_EVENTS and int(ev.x.sum()) == 17_676_033 and int(ev.y.sum()) == 10_498_046
    assert int((ev.t - ev.t[0]).sum()) == 7_327_758_848 and ev.on_count == 72_363
    assert len(got["frames"]) == 3 and len(got["imu"]) == 130 and len(got["trig"]) == 15 and not got["warnings"]


# ---------------------------------------------------------------- a duplicated packet without a FileDataTable
@needs_shared
@pytest.mark.parametrize("packet", [7, 6])                 # an events packet, an IMU packet
def test_duplicated_packet_without_table(shared, tmp_path, packet):
    data, pt, tp = shared
    k = data.find(struct.pack("<q", tp), 0, int(pt["offset"][0]))
    data = data[:k] + struct.pack("<q", -1) + data[k + 8:]  # IOHeader: no FileDataTable
    a, b = int(pt["offset"][packet]) - 8, int(pt["offset"][packet]) + int(pt["size"][packet])
    p = tmp_path / "dup.aedat4"
    p.write_bytes(data[:b] + data[a:b] + data[b:tp])
    got = read4(p)
    assert len(got["ev"]) == N_EVENTS and len(got["imu"]) == 130
    assert any(f"a duplicate of file packet {packet}" in w for w in got["warnings"])
    assert_within_file(got, pt)
    with pytest.raises(AedatError, match="duplicate"):
        read4(p, strict=True)


# ---------------------------------------------------------------- AEDAT 2.0 timestamps
def a2_file(tmp_path, ts, name="a.aedat"):
    p = tmp_path / name
    p.write_bytes(A2_HEADER + b"".join(struct.pack(">II", a2_dvs(1 + i % 5, 2, i % 2), t) for i, t in enumerate(ts)))
    return p


def a2_times(p, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat2Reader(p, **kw) as r:
            return np.concatenate([e.t for e in r.events()] or [np.zeros(0, np.int64)]).tolist(), r.warnings


@pytest.mark.parametrize("ts,want", [
    ((10, 0xFFFFFFFF, 20, 30), [10, 20, 30]),                                  # the probe's case
    ((10, 20, 0xFFFFFFF0, 0xFFFFFFF5, 30, 40), [10, 20, 30, 40]),              # a run of two
    ((2**32 - 100, 5, 2**32 - 90, 2**32 - 80), [2**32 - 100, 2**32 - 90, 2**32 - 80]),   # a dip near the boundary
    ((1000, 1000 + 2**31, 1010), [1000, 1010]),                               # bit 31 flipped
])
def test_aedat2_outlier_timestamp_is_not_a_wrap(tmp_path, ts, want):
    p = a2_file(tmp_path, ts)
    got, warns = a2_times(p)
    assert got == want and any("outliers" in w and "byte" in w for w in warns)
    with pytest.raises(AedatError, match=r"byte \d+: .*outliers"):
        a2_times(p, strict=True)


@pytest.mark.parametrize("ts,want", [((2**31 - 100, 2**31 - 1, 5, 9), [2**31 - 100, 2**31 - 1, 2**31 + 5, 2**31 + 9]),
                                     ((2**32 - 100, 2**32 - 50, 5, 9), [2**32 - 100, 2**32 - 50, 2**32 + 5, 2**32 + 9])])
def test_aedat2_plausible_wraps_kept(tmp_path, ts, want):
    assert a2_times(a2_file(tmp_path, ts), strict=True) == (want, [])


def test_aedat2_outlier_across_chunks_and_backwards(tmp_path):
    ts = list(range(100, 140)) + [0xFFFFFFFF] + list(range(140, 180))
    p = a2_file(tmp_path, ts)
    for chunk in (1, 7, 40, 41, 1000):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Aedat2Reader(p, chunk_records=chunk) as r:
                assert np.concatenate([e.t for e in r.events()]).tolist() == list(range(100, 180)), chunk
    got, warns = a2_times(a2_file(tmp_path, (100, 200, 150, 300)))     # one event going back: dropped, said
    assert got in ([100, 200, 300], [100, 150, 300]) and any("going back in time" in w for w in warns)


# ---------------------------------------------------------------- AEDAT 3.1
def test_aedat3_overflow_outlier_and_negative_ts(tmp_path):
    pk = [a3_packet(1, 8, ovf, [a3_polarity(1 + j, 2, 1, 100 * k + j) for j in range(3)]) for k, ovf in
          enumerate((0, 0, 9, 0, 1))]
    pk[3] = a3_packet(1, 8, 0, [a3_polarity(1, 2, 1, 300), a3_polarity(2, 2, 1, -5), a3_polarity(3, 2, 1, 302)])
    p = tmp_path / "a3.aedat"
    p.write_bytes(A3_HEADER + b"".join(pk))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat3Reader(p) as r:
            t = np.concatenate([e.t for e in r.events()]).tolist()
            warns = r.warnings
    assert t == [0, 1, 2, 100, 101, 102, 300, 302, 2**31 + 400, 2**31 + 401, 2**31 + 402]
    assert any("eventTSOverflow 9" in w for w in warns) and any("negative 32-bit timestamp" in w for w in warns)
    with pytest.raises(AedatError, match="byte .*eventTSOverflow 9"):
        with Aedat3Reader(p, strict=True) as r:
            list(r.events())


# ---------------------------------------------------------------- --strict through the CLI
@needs_shared
@pytest.mark.parametrize("cmd", ["info", "davis"])
def test_cli_strict(shared, tmp_path, capsys, cmd):
    from ev3dgs.cli.ingest import main

    data, _, _ = shared
    p = tmp_path / "m.aedat4"
    p.write_bytes(mutate(data, [(791_496, 0x64)]))
    extra = ["--out", str(tmp_path / "s.h5"), "--no-poses", "--events", "all"] if cmd == "davis" else []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main([cmd, str(p), "--strict", *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "byte 760230" in err[0] and "outside the 346x260 sensor" in err[0]
    assert not (tmp_path / "s.h5").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main([cmd, str(p), *extra, *(["--scan"] if cmd == "info" else [])])
    out = capsys.readouterr()
    assert code == 0 and "x/y outside the 346x260 sensor" in out.out + out.err
    if cmd == "info":   # without --scan, info reads the header and the FileDataTable only: nothing decoded
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            code = main([cmd, str(p)])
        out = capsys.readouterr()
        scanned = ["scanned:", "no"] in [ln.split() for ln in out.out.splitlines()]
        assert code == 0 and scanned and "outside" not in out.out + out.err


@pytest.mark.parametrize("bit", range(20, 31))
@pytest.mark.parametrize("where", [0, 1, 150, 298, 299])
def test_aedat2_one_flipped_timestamp_bit_is_an_outlier_not_a_reset(tmp_path, bit, where):
    """One record's timestamp with one high bit set (a forward spike of 2^bit us, 1 s to 18 min) between two
    in-order neighbours: that record alone is dropped, the rest of the file is read as it is (no reset split,
    no bad timestamp kept). Record 0 has no neighbour before it: it is dropped either way. Record 299 is the
    last one: nothing comes back after it, so it is kept or dropped
    as the monotonic check decides, but never splits the file."""
    base = [2_000_000 + 37 * i for i in range(300)]          # 2 s in: a 'reset' back to here would be < 2^24
    ts = list(base)
    ts[where] |= 1 << bit
    if ts[where] == base[where]:
        pytest.skip("bit already set")
    got, warns = a2_times(a2_file(tmp_path, ts))
    if where == 0:      # nothing before it: a first record far ahead of the rest reads as an older clock's
        assert got == base[1:]
        return
    assert not any("timestamp reset" in w for w in warns), warns
    if where < 299:
        assert got == base[:where] + base[where + 1:]
        assert any("outliers" in w for w in warns)
    else:
        assert got[:299] == base[:299] and len(got) in (299, 300)


def test_aedat2_pause_then_resume_is_not_an_outlier(tmp_path):
    """A real pause (a 5 s gap forward, the clock going on from there) keeps every record."""
    ts = [1000 + 10 * i for i in range(50)] + [6_000_000 + 10 * i for i in range(50)]
    assert a2_times(a2_file(tmp_path, ts), strict=True) == (ts, [])


# ---------------------------------------------------------------- AEDAT 2.0: header/data boundary shifted
def _a2_events(p, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat2Reader(p, **kw) as r:
            ev = list(r.events())
            return (np.concatenate([e.t for e in ev]), np.concatenate([e.x for e in ev])), r.warnings


@pytest.mark.parametrize("shift", [1, 2, 3, 4, 5, 6, 7, -1, -3, -7])
def test_aedat2_shifted_boundary_finds_the_record_alignment(tmp_path, shift):
    """Bytes inserted (shift > 0) or removed (< 0) where the header meets the data: the reader finds where the
    records really start (a warning; strict: an error) and reads every record that survived, unchanged."""
    data, _ = build_aedat2(seed=1)
    head = len(A2_HEADER)
    (tmp_path / "good.aedat").write_bytes(data)
    (want_t, want_x), _ = _a2_events(tmp_path / "good.aedat")
    bad = data[:head] + b"\x5a" * shift + data[head:] if shift > 0 else data[:head] + data[head - shift:]
    p = tmp_path / "shifted.aedat"
    p.write_bytes(bad)
    (t, x), warns = _a2_events(p)
    assert any("records start" in w for w in warns), warns
    if shift > 0:
        assert t.tolist() == want_t.tolist() and x.tolist() == want_x.tolist()
    else:            # the first record lost bytes: it is gone, every later one is read as it was
        assert t.tolist() == want_t.tolist()[len(want_t) - len(t):] and len(want_t) - len(t) <= 1
    assert t.max() < 2**33              # no t = 8.6e9 garbage
    with pytest.raises(AedatError, match="records start"):
        _a2_events(p, strict=True)


def test_aedat2_data_with_no_plausible_alignment_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    p = tmp_path / "noise.aedat"
    p.write_bytes(A2_HEADER + rng.integers(0, 256, 8 * 5000, dtype=np.uint8).tobytes())
    with pytest.raises(AedatError, match="no 8-byte record alignment"):
        _a2_events(p)


@pytest.mark.parametrize("rec,bit", [(338, 28), (338, 26), (348, 29), (200, 31)])
def test_aedat2_a_cleared_bit_after_real_gaps_drops_that_record_only(tmp_path, rec, bit):
    """The jAER fixture's events come up to 33 s apart (real forward steps). One record's timestamp with a high
    bit flipped (cleared: it falls back below records seconds before it): only that record goes, never the
    run of real steps before it (which held the file's only APS frame and its IMU samples)."""
    data, _ = build_aedat2()
    good = tmp_path / "good.aedat"
    good.write_bytes(data)
    (want_t, _), _ = _a2_events(good)
    head = data.index(b"#End Of ASCII Header\r\n") + len(b"#End Of ASCII Header\r\n")
    b = bytearray(data)
    b[head + 8 * rec + 4 + (3 - bit // 8)] ^= 1 << (bit % 8)    # big-endian timestamp word of record `rec`
    p = tmp_path / "flip.aedat"
    p.write_bytes(bytes(b))
    (t, _), warns = _a2_events(p)
    assert not any("timestamp reset" in w for w in warns)
    assert len(want_t) - len(t) <= 1 and set(t.tolist()) <= set(want_t.tolist()), (len(t), len(want_t), warns)
