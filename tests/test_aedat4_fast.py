"""The C fast path for AEDAT 4.0 events (ev3dgs.io.aedat4.fast) against the general numpy path, which is the
second implementation here: on intact files, on every compression, on packets at chunk and time boundaries,
and on damaged files (hypothesis byte flips) the events, the warnings and the strict-mode errors must be the
same. The FileDataTable decoder in C against flatbuf.table_vector, also on damaged tables."""
from __future__ import annotations

import struct
import warnings
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ev3dgs.events import Events
from ev3dgs.io.aedat4 import fast as aedat4_fast
from ev3dgs.io.aedat4 import Aedat4Reader
from ev3dgs.io.aedat4.container import _FTAB_FIELDS
from ev3dgs.io.aedat4.packets import decompress
from ev3dgs.io.aedat4.writer import write_aedat4
from ev3dgs.io.aedat4.flatbuf import FlatbufError, root, table_vector
from ev3dgs.io.types import AedatError

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "aedat" / "aestream_davis.aedat4"
needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="shared DAVIS346 recording not present")


def test_extension_is_built():
    # `pip install` (make setup) compiles it wherever a C compiler exists, as on every machine we test on;
    # without it the readers still work (general path), only slower.
    assert aedat4_fast._c is not None, "ev3dgs.io.aedat4._fast was not built: run `pip install -e .` again"


def read(path, fast: bool, strict: bool = False, threads: int = 1, **window):
    """(events, chunk count, warnings) or the AedatError message, through one path (threads: the fast path's
    C threads)."""
    with warnings.catch_warnings(), mock.patch.object(aedat4_fast, "FAST", fast):
        warnings.simplefilter("ignore")
        try:
            with Aedat4Reader(path, strict=strict, threads=threads if fast else 1) as r:
                chunks = list(r.events(**window))
                return Events.concatenate(chunks), len(chunks), list(r.warnings)
        except AedatError as e:
            return str(e)


def assert_same(path, strict: bool = False, **window):
    """The fast path with 1 and with 3 C threads gives what the general path gives."""
    b = read(path, False, strict, **window)
    for threads in (3, 1):
        a = read(path, True, strict, threads, **window)
        if isinstance(a, str) or isinstance(b, str):
            assert a == b
            continue
        for k in "txyp":
            assert np.array_equal(getattr(a[0], k), getattr(b[0], k)), k
            assert getattr(a[0], k).dtype == getattr(b[0], k).dtype
        assert a[2] == b[2]
    return a


def synthetic(n: int, seed: int = 0, w: int = 64, h: int = 48, t0: int = 1_000_000) -> Events:
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, 50 * n, n))
    return Events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n))


# ---------------------------------------------------------------- intact files
@needs_shared
def test_shared_file_same_through_both_paths():
    ev, chunks, warns = assert_same(SHARED)
    assert len(ev) == 117_667 and not warns and chunks == 1        # 13 packets merged into one chunk


@pytest.mark.parametrize("compression", ["none", "lz4", "lz4-high", "zstd", "zstd-high"])
def test_every_compression(tmp_path, compression):
    p = tmp_path / "c.aedat4"
    write_aedat4(p, 64, 48, synthetic(30_000), compression=compression, packet_events=4_000)
    ev, _, warns = assert_same(p)
    assert len(ev) == 30_000 and not warns


def test_chunks_split_and_oversized_packets(tmp_path, monkeypatch):
    """Chunks fill up to CHUNK_EVENTS; a packet larger than a chunk gets one of its own; any chunking gives the
    same events."""
    p = tmp_path / "big.aedat4"
    ev = synthetic(25_000)
    write_aedat4(p, 64, 48, ev, packet_events=3_000)           # 9 packets: 8 x 3000 + 1000
    monkeypatch.setattr(aedat4_fast, "CHUNK_EVENTS", 7_000)
    got, chunks, _ = assert_same(p)
    assert np.array_equal(got.t, ev.t) and chunks == 4         # 2 + 2 + 2 + (2 + the short last one)
    monkeypatch.setattr(aedat4_fast, "CHUNK_EVENTS", 1_000)    # every packet larger than a chunk
    got, chunks, _ = assert_same(p)
    assert np.array_equal(got.t, ev.t) and chunks == 9
    # chunks the consumer keeps are never overwritten; chunks it drops at once have their blocks reused
    with Aedat4Reader(p, threads=2) as r:
        kept = list(r.events())
        streamed = [(int(e.t.sum()), int(e.x.astype(np.int64).sum()), int(e.p.sum())) for e in r.events()]
    assert [(int(e.t.sum()), int(e.x.astype(np.int64).sum()), int(e.p.sum())) for e in kept] == streamed
    assert np.array_equal(Events.concatenate(kept).t, ev.t)


def test_time_window(tmp_path):
    p = tmp_path / "w.aedat4"
    ev = synthetic(20_000)
    write_aedat4(p, 64, 48, ev, packet_events=1_500)
    lo, hi = int(ev.t[4_321]), int(ev.t[15_000])
    got, _, _ = assert_same(p, start_us=lo, end_us=hi)
    keep = (ev.t >= lo) & (ev.t < hi)
    assert np.array_equal(got.t, ev.t[keep]) and np.array_equal(got.x, ev.x[keep])


def test_equal_times_across_packets(tmp_path):
    """Time ties across packet boundaries are kept, also a packet whose events all sit at the last time kept
    (the fast path leaves that one to the general path, which tells it from a duplicate)."""
    def ev(t):
        t = np.asarray(t)
        return Events(t, np.arange(len(t)) % 64, np.ones(len(t)), np.ones(len(t)))
    chunks = [ev(np.full(10, 500)), ev(np.arange(500, 510)), ev(np.full(10, 509)), ev(np.arange(509, 519))]
    p = tmp_path / "ties.aedat4"
    write_aedat4(p, 64, 48, chunks, packet_events=10)
    got, _, warns = assert_same(p)
    assert len(got) == 40 and not warns


def _edit_events(path: Path, edit) -> None:
    """Edit the Event structs of an uncompressed file in place: edit(k, structs) for events packet k."""
    from ev3dgs.io.aedat4.packets import EVENT_DTYPE
    with Aedat4Reader(path) as r:
        pt = r.packet_table()
    data = bytearray(path.read_bytes())
    for k, (off, size) in enumerate(zip(pt["offset"][pt["stream"] == 0], pt["size"][pt["stream"] == 0])):
        tab, _, _ = root(bytes(data[int(off):int(off + size)]))
        start, n = tab.vector(0, 16)
        at = int(off) + 4 + start                   # positions in the body count from after the size prefix
        edit(k, np.frombuffer(data, EVENT_DTYPE, count=n, offset=at))
    path.write_bytes(bytes(data))


def test_duplicate_packet_and_bad_values_reported_alike(tmp_path):
    p = tmp_path / "dup.aedat4"
    write_aedat4(p, 64, 48, synthetic(4_000, seed=5), compression="none", packet_events=500)
    first = {}

    def edit(k, s):
        if k == 0:
            first["s"] = s.copy()
        elif k == 1:
            s[:] = first["s"]                       # packet 1 repeats packet 0: a duplicate
        elif k == 3:
            s["x"][17] = 64                         # one column past the sensor
        elif k == 4:
            s["p"][3] = 7                           # a polarity byte other than 0/1
        elif k == 5:
            s["t"][100], s["t"][101] = s["t"][101], s["t"][100] - 1     # time goes backwards
    _edit_events(p, edit)
    got, _, warns = assert_same(p)
    text = " ".join(warns)
    for what in ("duplicate", "outside the 64x48 sensor", "polarity byte other than 0/1"):
        assert what in text
    assert len(got) < 4_000
    assert assert_same(p, strict=True).startswith("byte ")


# ---------------------------------------------------------------- damaged files
def _flipped(data: bytes, lo: int, hi: int, flips) -> bytes:
    b = bytearray(data)
    for f, v in flips:
        b[lo + int(f * (hi - lo))] ^= v
    return bytes(b)


@needs_shared
@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=3),
       st.booleans())
def test_flipped_bytes_same_through_both_paths(tmp_path_factory, flips, strict):
    data = SHARED.read_bytes()
    with Aedat4Reader(SHARED) as r:
        pt, tp = r.packet_table(), r.table_position
    lo = int(pt["offset"][0]) - 8                   # packet headers and payloads (the table: test below)
    p = tmp_path_factory.getbasetemp() / "flip.aedat4"
    p.write_bytes(_flipped(data, lo, tp, flips))
    assert_same(p, strict=strict)


@settings(max_examples=30, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=2),
       st.sampled_from(["none", "zstd"]), st.integers(0, 2_000))
def test_flipped_and_truncated_synthetic(tmp_path_factory, flips, compression, cut):
    base = tmp_path_factory.getbasetemp()
    src = base / f"src-{compression}.aedat4"
    if not src.exists():
        write_aedat4(src, 64, 48, synthetic(12_000, seed=3), compression=compression, packet_events=1_000)
    data = src.read_bytes()
    with Aedat4Reader(src) as r:
        lo, tp = int(r.packet_table()["offset"][0]) - 8, r.table_position
    p = base / "mut.aedat4"
    p.write_bytes(_flipped(data, lo, tp, flips)[:len(data) - cut])
    assert_same(p)


# ---------------------------------------------------------------- the FileDataTable decoder
def _ftab_body():
    with Aedat4Reader(SHARED) as r:
        tp, comp = r.table_position, r.compression
    raw = SHARED.read_bytes()[tp:]
    return bytearray(bytes(decompress(memoryview(raw), comp, tp)))


@needs_shared
@settings(max_examples=80, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), max_size=3))
def test_table_decoder_matches_table_vector(flips):
    buf = _ftab_body()
    for f, v in flips:
        buf[4 + int(f * (len(buf) - 4))] ^= v          # inside the flatbuffer, after the size prefix
    try:
        tab, _, body = root(bytes(buf))
        start, count = tab.vector(0, 4)
    except FlatbufError:
        return                                        # the fast decoder is only called past these checks
    try:
        want = table_vector(body, start, count, _FTAB_FIELDS)
    except FlatbufError:
        want = None
    got = aedat4_fast.table(body, start, count)
    if want is None:
        assert got is None
        return
    assert got is not None
    for k, v in want.items():
        assert np.array_equal(got[k], v.astype(np.int64)), k


def test_table_decoder_rejects_what_runs_past_the_buffer():
    # one PacketHeader table whose uoffset points past the end: None (table_vector raises)
    body = struct.pack("<II", 8, 1) + struct.pack("<I", 1000)
    assert aedat4_fast.table(memoryview(body), 8, 1) is None


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 502), st.sampled_from(["t", "x", "y", "p"]),
                          st.integers(0, 2**16)), min_size=1, max_size=4),
       st.sampled_from([None, (64, 48)]))
def test_edited_event_fields_same_through_both_paths(tmp_path_factory, edits, sensor):
    """Any field of any event (every position inside the 4-event SIMD blocks and the scalar tail of a
    503-event packet) set to another value: both paths keep and drop the same events with the same words."""
    base = tmp_path_factory.getbasetemp()
    p = base / "edit.aedat4"
    write_aedat4(p, 64, 48, synthetic(6 * 503, seed=7), compression="none", packet_events=503)

    def edit(k, s):
        for kk, j, f, v in edits:
            if kk == k:
                u16 = v % 2**16 - (2**16 if v % 2**16 >= 2**15 else 0)     # the int16 with these 16 bits
                s[f][j] = {"t": int(s["t"][j]) + v - 2**15, "x": u16, "y": u16, "p": v % 256}[f]
    _edit_events(p, edit)
    if sensor is None:                              # no sensor size in the XML: no coordinate check
        data = p.read_bytes()
        assert b'key="sizeX" type="int">64<' in data
        p.write_bytes(data.replace(b'key="sizeX" type="int">64<', b'key="sizeX" type="int">00<'))
    assert_same(p)
