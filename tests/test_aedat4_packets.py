"""AEDAT 4.0 packet decoding (ev3dgs.io.aedat4.packets) and the reader's threads / cheap info: the event
unpacking against numpy's structured-dtype reading of the same bytes, decompression into reused buffers against
the lz4 and zstandard packages, identical results and warnings with 1 and 2 decoding threads (intact and damaged
files), and info() reading only the header and the FileDataTable unless asked to scan."""
from __future__ import annotations

import struct
import threading
import warnings
from unittest import mock
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.events import Events
from ev3dgs.io.aedat4 import fast as aedat4_fast
from ev3dgs.io.aedat4 import packets as P
from ev3dgs.io.aedat4 import Aedat4Reader
from ev3dgs.io.aedat4.writer import event_packet, write_aedat4
from ev3dgs.io.types import AedatError

SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="shared AEDAT sample not present")


def _payload(t, x, y, pbyte) -> bytes:
    """An EVTS flatbuffer from our writer, with the stored polarity bytes then overwritten by `pbyte` (the
    writer stores 0/1; corrupt files may hold anything)."""
    buf = bytearray(event_packet(t, x.astype(np.uint16), y.astype(np.uint16), np.where(pbyte > 0, 1, -1)))
    tab, body = P.parse(buf, "events", 0)
    start, n = tab.vector(0, 16)
    for k in range(n):
        buf[4 + start + 16 * k + 12] = int(pbyte[k])
    return bytes(buf)


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_decode_events_matches_structured_dtype(data):
    n = data.draw(st.integers(0, 300))
    ints = lambda lo, hi: np.array(data.draw(st.lists(st.integers(lo, hi), min_size=n, max_size=n)), np.int64)
    t, x, y = ints(-2**62, 2**62), ints(-2**15, 2**15 - 1), ints(-2**15, 2**15 - 1)
    pbyte = np.array(data.draw(st.lists(st.sampled_from([0, 1, 1, 0, 2, 255]), min_size=n, max_size=n)), np.uint8)
    payload = _payload(t, x, y, pbyte)
    got = P.decode_events(payload, 0)
    # reference: numpy's structured dtype over the same bytes (an independent reading of the Event struct)
    tab, body = P.parse(payload, "events", 0)
    start, m = tab.vector(0, 16)
    ref = np.frombuffer(body, P.EVENT_DTYPE, count=m, offset=start)
    assert m == n
    assert np.array_equal(got.t, ref["t"]) and np.array_equal(got.t, t)
    assert np.array_equal(got.x, ref["x"].astype(np.int64) % 65536)      # int16 read as uint16
    assert np.array_equal(got.y, ref["y"].astype(np.int64) % 65536)
    want_pol = np.where(ref["p"] == 0, -1, np.where(ref["p"] == 1, 1, -128))
    assert np.array_equal(got.pol, want_pol) and got.pol.dtype == np.int8
    assert got.max_x == (int((x % 65536).max()) if n else 0) and got.max_y == (int((y % 65536).max()) if n else 0)
    assert got.bad_polarity == int(np.count_nonzero(pbyte > 1))
    assert got.backward == int(np.count_nonzero(t[1:] < t[:-1]))     # (np.diff would overflow at +-2^62)


@pytest.mark.parametrize("comp", [1, 3])
def test_decompress_grows_scratch_and_matches_reference(comp):
    """A packet larger than the first scratch buffer takes the bounded path once; later ones reuse the grown
    buffer. Both give exactly what the lz4 / zstandard packages decompress."""
    rng = np.random.default_rng(comp)
    n = 3 * P._SCRATCH0 // 16                           # 3 MiB of events: larger than the first scratch buffer
    t = np.cumsum(rng.integers(0, 5, n))
    payload = event_packet(t, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.choice([-1, 1], n))
    small = event_packet(t[:10], t[:10] % 346, t[:10] % 260, np.ones(10))
    pack = (lambda b: lz4.frame.compress(b)) if comp == 1 else zstandard.ZstdCompressor(level=3).compress
    out = {}

    def run():                                          # a fresh thread: a fresh scratch buffer
        out["small"] = bytes(P.decompress(pack(small), comp, 0))
        out["big1"] = bytes(P.decompress(pack(payload), comp, 0))
        out["big2"] = bytes(P.decompress(pack(payload), comp, 0))
        out["size"] = len(P._local.buf)

    th = threading.Thread(target=run)
    th.start()
    th.join()
    assert out["small"] == small and out["big1"] == payload and out["big2"] == payload
    assert out["size"] >= len(payload)


def test_decompress_errors_name_the_byte():
    good = lz4.frame.compress(struct.pack("<I", 100) + bytes(100))
    with pytest.raises(AedatError, match="byte 77: lz4 decompression failed"):
        P.decompress(good[:-7] + b"\xff" * 7, 1, 77)
    short = lz4.frame.compress(struct.pack("<I", 100) + bytes(50))     # size prefix says 104 bytes, 54 present
    with pytest.raises(AedatError, match="byte 5: packet decompresses to 54 bytes but its flatbuffer size prefix "
                                         "says 104"):
        P.decompress(short, 1, 5)


def _read(path, threads, fast_path=False):
    """Everything in the file, read through the general path (fast_path False: threads apply to events too) or
    with the events through the C fast path."""
    with warnings.catch_warnings(), mock.patch.object(aedat4_fast, "FAST", fast_path):
        warnings.simplefilter("ignore")
        with Aedat4Reader(path, threads=threads) as r:
            ev = Events.concatenate(list(r.events()))
            pooled = r._reader._pool is not None         # the events stream was shared out to the pool
            return ev, list(r.frames()), r.imu(), r.triggers(), list(r.warnings), pooled


@needs_shared
@pytest.mark.parametrize("damage", [None, "coordinate", "frames"])
def test_threads_give_identical_results(tmp_path, damage):
    data = bytearray(SHARED.read_bytes())
    if damage == "coordinate":          # an event's y byte: outside the sensor (tests/test_reliability_readers.py)
        data[791_496] = 0x64
    elif damage == "frames":            # the LZ4 frame magic of the 3rd and 8th events packets: packets skipped
        with Aedat4Reader(SHARED) as r:
            pt = r.packet_table()
        for k in (2, 7):
            data[int(pt["offset"][pt["stream"] == 0][k])] ^= 0xFF
    p = tmp_path / "s.aedat4"
    p.write_bytes(bytes(data))
    one, two = _read(p, 1), _read(p, 2)
    assert not one[5] and two[5]
    for other in (two, _read(p, 1, fast_path=True)):     # 2 threads; the C fast path for the events
        for a, b in zip((one[0].t, one[0].x, one[0].y, one[0].p), (other[0].t, other[0].x, other[0].y, other[0].p)):
            assert np.array_equal(a, b)
        assert [f.timestamp for f in one[1]] == [f.timestamp for f in other[1]]
        assert np.array_equal(one[2].t, other[2].t) and np.array_equal(one[3].t, other[3].t)
        assert one[4] == other[4]
    if damage is None:
        assert len(one[0]) == 117_667 and one[4] == []
    else:
        assert one[4]                                    # the damage is reported, the same way by both


@needs_shared
def test_abandoned_iteration_with_threads(tmp_path):
    with Aedat4Reader(SHARED, threads=2) as r:
        it = r.events()
        first = next(it)
        it.close()                                       # cancels what the pool had queued
        again = next(r.events())
    assert np.array_equal(first.t, again.t)
    with pytest.raises(ValueError, match="threads"):
        Aedat4Reader(SHARED, threads=0)


def test_info_reads_only_header_and_table(tmp_path, monkeypatch):
    p = tmp_path / "f.aedat4"
    t = np.arange(50_000) * 3 + 1_000
    write_aedat4(p, 64, 48, Events(t, t % 64, t % 48, np.where(t % 2, 1, -1)), packet_events=7_000)
    with Aedat4Reader(p) as r:
        scanned = r.info(scan=True)

    def no_decode(*a, **k):
        raise AssertionError("info() without scan decoded a packet")

    monkeypatch.setattr(P.PacketReader, "decode", no_decode)
    monkeypatch.setattr(P.PacketReader, "payload", no_decode)
    with Aedat4Reader(p) as r:
        cheap = r.info()
    assert cheap["scanned"] is False and scanned["scanned"] is True
    assert cheap["streams"] == scanned["streams"]
    ev = cheap["streams"][0]
    assert (ev["packets"], ev["elements"], ev["t_start"], ev["t_end"]) == (8, 50_000, 1_000, int(t[-1]))


def test_block_pool_reuses_only_unreferenced_blocks():
    pool = P.BlockPool(keep=2)
    a = pool(1000)
    a[:] = 1
    b = pool(1000)                                       # a is still referenced: a different block
    assert not np.shares_memory(a, b)
    view = a[10:20].view(np.int16)                       # a view keeps a's block busy after a is dropped
    del a
    c = pool(1000)
    assert not np.shares_memory(c, view) and not np.shares_memory(c, b)
    assert (view == 0x0101).all()                        # untouched
    del view, c
    d = pool(900)                                        # now a free block is handed out again
    assert any(np.shares_memory(d, blk) for blk in pool._blocks)
    big = pool(5 * P.BlockPool.MIN_BLOCK)                # larger than every kept block: fresh memory
    assert big.size == 5 * P.BlockPool.MIN_BLOCK and len(pool._blocks) == 2


@needs_shared
def test_chunks_kept_by_the_consumer_stay_intact():
    """Holding every chunk (no block can be reused) and dropping each at once (blocks reused) give the same."""
    with Aedat4Reader(SHARED, threads=1) as r:
        kept = list(r.events())
        sums = [(int(e.t.sum()), int(e.x.astype(np.int64).sum()), int(e.p.sum())) for e in r.events()]
    assert [(int(e.t.sum()), int(e.x.astype(np.int64).sum()), int(e.p.sum())) for e in kept] == sums
    ev = Events.concatenate(kept)
    assert len(ev) == 117_667 and int(ev.x.astype(np.int64).sum()) == 17_676_033


@pytest.mark.parametrize("delta", [-1, 0, 5])
def test_inplace_decompression_with_wrong_table_counts(tmp_path, delta):
    """Packets are decompressed straight into a block sized from the FileDataTable's element count; a count
    that is too small (the packet does not fit) or too large falls back to the scratch buffer with the same
    events (the checks then report the count mismatch)."""
    p = tmp_path / "f.aedat4"
    t = np.arange(30_000) * 2 + 500
    write_aedat4(p, 64, 48, Events(t, t % 64, (t // 64) % 48, np.where(t % 3, 1, -1)), packet_events=4_000)
    with warnings.catch_warnings(), mock.patch.object(aedat4_fast, "FAST", False):   # the general path's blocks
        warnings.simplefilter("ignore")
        with Aedat4Reader(p, threads=1) as r:
            r._reader.elements = r._reader.elements + delta     # what the reader uses to size the block
            ev = Events.concatenate(list(r.events()))
    assert np.array_equal(ev.t, t) and np.array_equal(ev.x, t % 64) and np.array_equal(ev.y, (t // 64) % 48)
    assert np.array_equal(ev.p, np.where(t % 3, 1, -1))


@pytest.mark.parametrize("cores, load, want", [(4, 0.2, 4), (4, 2.4, 2), (4, 2.6, 1), (2, 0.4, 2), (2, 0.6, 1),
                                               (2, 9.0, 1), (1, 0.0, 1), (16, 0.0, 4)])
def test_default_threads_follow_idle_cores(monkeypatch, cores, load, want):
    import ev3dgs.io.aedat4.reader as A

    monkeypatch.setattr(A.os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    monkeypatch.setattr(A.os, "getloadavg", lambda: (load, load, load))
    assert A.default_threads() == want


@pytest.mark.parametrize("dtype_name, vt, size", [("IMU_DTYPE", [4, 12, 16, 20, 24, 28, 32, 36, 40, 44, 48], 52),
                                                  ("TRIG_DTYPE", [4, 12], 13),
                                                  ("FTAB_DTYPE", [4, 36, 12, 20, 28], 44)])
def test_table_rows_padding_written_as_zeros(dtype_name, vt, size):
    """The same rows give the same bytes whatever memory the rows' padding (IMU rows: 52 of 56 bytes are fields)
    lands on, in the caller's array or in a copy numpy fills field by field: the padding is written as zeros,
    so a recording written twice is the same file."""
    from ev3dgs.io.aedat4 import writer

    dtype = getattr(writer, dtype_name)
    rng = np.random.default_rng(7)
    clean = np.zeros(5, dtype)
    dirty = np.frombuffer(bytearray(b"\xa5" * (5 * dtype.itemsize)), dtype)   # writable, padding 0xa5
    for name in dtype.names:
        vals = rng.integers(0, 100, clean[name].shape).astype(dtype[name].base)
        clean[name], dirty[name] = vals, vals
    assert clean.tobytes() != dirty.tobytes()   # the fields agree, the padding does not
    for rows in (dirty, clean):
        # a freed buffer of the rows' size filled with 0xa5: numpy's small-buffer cache hands it to the next
        # array of that size (an array left uninitialised where no field is written shows 0xa5 there)
        junk = np.full(rows.nbytes, 0xA5, np.uint8)
        del junk
        out = writer._vector_table("TEST", vt, size, rows)
        assert out == writer._vector_table("TEST", vt, size, clean)
    assert b"\xa5" not in out
