"""ev3dgs.io.aedat4.codec (LZ4 / zstd frames decoded by the C libraries straight into a buffer) against
the lz4 and zstandard packages' own frame decoders (intact and damaged frames), and the reader's
general path (cramjam) giving the same packets when the native path is unavailable."""
from __future__ import annotations

import struct
import warnings
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.events import Events
from ev3dgs.io.aedat4 import codec as C
from ev3dgs.io.aedat4 import packets as P
from ev3dgs.io.aedat4 import Aedat4Reader
from ev3dgs.io.types import AedatError

SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
needs_native = pytest.mark.skipif(not (C.available(1) and C.available(3)), reason="no liblz4 / libzstd found")

# compressible but not trivial: runs of a few symbols with random literals (LZ4 emits both matches and literals)
_blobs = st.builds(lambda n, k, seed: np.random.default_rng(seed).integers(0, k, n, dtype=np.uint8).tobytes(),
                   st.integers(0, 300_000), st.sampled_from([1, 3, 17, 256]), st.integers(0, 2**32 - 1))


def _ref_lz4(frame: bytes):
    try:
        return lz4.frame.decompress(frame)
    except RuntimeError:
        return None


@needs_native
@settings(max_examples=40, deadline=None)
@given(_blobs, st.sampled_from([lz4.frame.BLOCKSIZE_MAX64KB, lz4.frame.BLOCKSIZE_MAX256KB,
                                lz4.frame.BLOCKSIZE_MAX1MB, lz4.frame.BLOCKSIZE_MAX4MB]),
       st.booleans(), st.booleans(), st.sampled_from([0, 9]))
def test_lz4_matches_lz4_frame(data, block_size, linked, store_size, level):
    frame = lz4.frame.compress(data, block_size=block_size, block_linked=linked, store_size=store_size,
                               compression_level=level)
    out = np.empty(len(data) + (4 << 20), np.uint8)
    n = C.lz4_into(frame, C.address(frame), out)
    assert n == len(data) and bytes(out[:n]) == data


@needs_native
@settings(max_examples=60, deadline=None)
@given(_blobs, st.data())
def test_lz4_damaged_frames_never_disagree(data, draw):
    """A damaged frame is either refused (None: the general path then reports it) or decodes to exactly what
    LZ4's own frame decoder makes of it; nothing is written past the buffer."""
    frame = bytearray(lz4.frame.compress(data, store_size=draw.draw(st.booleans())))
    for _ in range(draw.draw(st.integers(1, 4))):
        k = draw.draw(st.integers(0, len(frame) - 1))
        frame[k] = draw.draw(st.integers(0, 255))
    if draw.draw(st.booleans()):
        frame = frame[:draw.draw(st.integers(0, len(frame)))]
    frame = bytes(frame)
    room = len(data) + 64
    out = np.full(room + 4096, 0xA5, np.uint8)
    n = C.lz4_into(frame, C.address(frame), out[:room])
    assert (out[room:] == 0xA5).all()                   # the guard zone after the buffer is untouched
    if n is not None:
        assert bytes(out[:n]) == _ref_lz4(frame)


@needs_native
def test_lz4_checks_and_refusals():
    """Checksums are verified when the frame carries them; a damaged checksum, a corrupt header checksum, a
    buffer too small, an unfinished frame or trailing bytes give None, and the reader's general path then
    reports the packet as before."""
    data = struct.pack("<I", 256_000) + bytes(range(256)) * 1000     # size-prefixed, as a packet payload is
    out = np.empty(len(data) + 100, np.uint8)
    for kw in ({"content_checksum": True}, {"block_checksum": True}):
        f = lz4.frame.compress(data, **kw)
        assert C.lz4_into(f, C.address(f), out) == len(data) and bytes(out[:len(data)]) == data
    f = bytearray(lz4.frame.compress(data, content_checksum=True))
    f[-1] ^= 1                                              # content checksum
    assert C.lz4_into(bytes(f), C.address(bytes(f)), out) is None
    f = bytearray(lz4.frame.compress(data, store_size=False))
    f[6] ^= 1                                               # header checksum byte
    assert C.lz4_into(bytes(f), C.address(bytes(f)), out) is None
    with pytest.raises(AedatError, match="byte 9: lz4 decompression failed"):
        P.decompress(bytes(f), 1, 9)
    f = lz4.frame.compress(data)
    assert C.lz4_into(f, C.address(f), out[:len(data) - 1]) is None
    assert C.lz4_into(f[:-3], C.address(f[:-3]), out) is None
    assert C.lz4_into(f + f, C.address(f + f), out) is None
    assert C.lz4_into(f, C.address(f), out) == len(data)     # the context was reset after each refusal


@needs_native
@settings(max_examples=30, deadline=None)
@given(_blobs, st.sampled_from([1, 3, 19]), st.booleans())
def test_zstd_matches_zstandard(data, level, size_in_header):
    frame = zstandard.ZstdCompressor(level=level, write_content_size=size_in_header).compress(data)
    out = np.empty(len(data) + 16, np.uint8)
    n = C.zstd_into(frame, C.address(frame), out)
    assert n == len(data) and bytes(out[:n]) == data
    if data:
        assert C.zstd_into(frame, C.address(frame), out[:len(data) - 1]) is None     # too small: refused
        bad = bytearray(frame)
        bad[len(bad) // 2] ^= 0xFF
        n = C.zstd_into(bytes(bad), C.address(bytes(bad)), out)
        if n is not None:                   # zstd without checksum may still decode: as zstandard does
            assert bytes(out[:n]) == zstandard.ZstdDecompressor().decompressobj().decompress(bytes(bad))


@pytest.mark.skipif(not SHARED.exists(), reason="shared AEDAT sample not present")
@pytest.mark.parametrize("threads", [1, 2])
def test_general_path_gives_the_same_events(monkeypatch, threads):
    """With the native path switched off (no C library found) the reader decodes with cramjam: same events."""
    def read():
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with Aedat4Reader(SHARED, threads=threads) as r:
                return Events.concatenate(list(r.events()))

    fast = read()
    monkeypatch.setattr(C, "available", lambda comp: False)
    slow = read()
    for k in "txyp":
        assert np.array_equal(getattr(fast, k), getattr(slow, k))
    assert len(fast) == 117_667 and int(fast.x.astype(np.int64).sum()) == 17_676_033


@pytest.mark.parametrize("comp", ["LZ4", "ZSTD"])
def test_dv_written_file_matches_dv_processing(tmp_path, comp):
    """A file written by dv-processing (uniformly random events: poorly compressible, many LZ4 literals) reads
    exactly as dv-processing reads it, with the decompression in the calling thread and in a worker."""
    dv = pytest.importorskip("dv_processing")
    import datetime

    p = tmp_path / "dv.aedat4"
    cfg = dv.io.MonoCameraWriter.Config("DAVIS346_codec", getattr(dv.CompressionType, comp))
    cfg.addEventStream((346, 260))
    w = dv.io.MonoCameraWriter(str(p), cfg)
    for k in range(4):
        w.writeEvents(dv.data.generate.uniformEventsWithinTimeRange(
            1_000_000 + k * 250_000, datetime.timedelta(microseconds=250_000), (346, 260), 30_000, k))
    del w
    rec = dv.io.MonoCameraRecording(str(p))
    parts = []
    while (b := rec.getNextEventBatch()) is not None:
        parts.append(b.numpy())
    ref = np.concatenate(parts)
    for threads in (1, 2):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with Aedat4Reader(p, threads=threads) as r:
                ev = Events.concatenate(list(r.events()))
        assert np.array_equal(ev.t, ref["timestamp"]) and np.array_equal(ev.x, ref["x"])
        assert np.array_equal(ev.y, ref["y"]) and np.array_equal(ev.p, np.where(ref["polarity"], 1, -1))


@pytest.mark.skipif(not SHARED.exists(), reason="shared AEDAT sample not present")
def test_file_data_table_vectorised_matches_per_table_reads():
    """flatbuf.table_vector (one gather of every table's bytes when the tables share a vtable) against reading
    each FileDataTable entry with the scalar Table API (an independent, per-element path)."""
    import struct as _st

    from ev3dgs.io.aedat4.container import _FTAB_FIELDS
    from ev3dgs.io.aedat4.flatbuf import Table, root, table_vector

    with Aedat4Reader(SHARED) as r:
        tp, size = r.table_position, r.file_size
    blob = SHARED.read_bytes()[tp:size]
    tab, ident, body = root(lz4.frame.decompress(blob))
    assert ident == b"FTAB"
    start, count = tab.vector(0, 4)
    got = table_vector(body, start, count, _FTAB_FIELDS)
    assert count == 40
    for k in range(count):
        e = Table(body, start + 4 * k + _st.unpack_from("<I", body, start + 4 * k)[0])
        stream, nbytes = _st.unpack_from("<iI", body, e.struct_pos(1, 8))
        want = {"offset": e.scalar(0, "q"), "stream": stream, "size": nbytes, "elements": e.scalar(2, "q"),
                "t_start": e.scalar(3, "q"), "t_end": e.scalar(4, "q")}
        assert {name: int(got[name][k]) for name in want} == want
