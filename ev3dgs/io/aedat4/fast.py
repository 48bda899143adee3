"""AEDAT 4.0 events streams read by the C fast path (`_fast.c`), falling back packet by packet.

For a stream indexed by a FileDataTable (element counts and time ranges known), one C call reads, decompresses
(the LZ4 frame / zstd functions that `aedat4_codec` loads, called by address), parses and unpacks packet after
packet into a chunk of output arrays, with the GIL released and no Python work per packet. It commits a packet
only when every check the general path (`aedat4_packets` + `checks.StreamChecks`) would make passes on it; at
the first packet that does not, it stops, that one packet goes through the general path (which reports it with
the same warning or error as before), and the fast path resumes after it. So the events, warnings and errors
are those of the general path, on intact and on damaged files (tests compare the two).

Chunks hold up to CHUNK_EVENTS events (a packet larger than that gets a chunk of its own size) in blocks that
are reused once the caller has let go of them; the read and decompression buffers (one pair per thread, reused
from read to read) are sized from the largest packet in the table and capped at MAX_BUFFER (a larger packet
takes the general path). Memory stays bounded.

Used when the extension was built (`pip install` compiles it; without a C compiler the package still installs
and reads through the general path: `available()` says which) and FAST is True.
"""
from __future__ import annotations

import ctypes
import threading

import numpy as np

from ...events import Events
from . import codec as native
from .packets import BlockPool

try:
    from . import _fast as _c
except ImportError:                         # built without a C compiler: the general path reads everything
    _c = None

FAST = True                                 # switch for tests and for comparing the two paths
CHUNK_EVENTS = 1 << 17                      # events per yielded chunk (13 bytes each in the output block)
MAX_BUFFER = 64 << 20                       # largest read / decompression buffer the fast path allocates
LZ4_SLACK = 4 << 20                         # room for one more LZ4 block of the largest size in the scratch buffer
_ST_FULL, _ST_SLOW = 1, 2


MAX_THREADS = 64                            # as in _fast.c
_POOL = BlockPool(keep=4)                   # output chunks, reused once their consumer has let go of them
_local = threading.local()


def _buffer(name: str, nbytes: int) -> np.ndarray:
    """This thread's reused read / decompression buffer, grown to at least nbytes. Safe to share between
    readers: nothing in it outlives one `_c.events` call."""
    buf = getattr(_local, name, None)
    if buf is None or len(buf) < nbytes:
        buf = np.empty(int(nbytes), np.uint8)
        setattr(_local, name, buf)
    return buf


class _Contexts(threading.local):
    """Per Python thread: decompression contexts for the C worker threads (never shared by two calls at once)."""

    def __init__(self) -> None:
        self.lz4: list[int] = []
        self.zstd: list[int] = []
        self._free = (native.free_lz4_context, native.free_zstd_context)    # kept: module globals may be gone

    def __del__(self) -> None:
        for c in self.lz4:
            self._free[0](c)
        for c in self.zstd:
            self._free[1](c)


_ctxs = _Contexts()


def _contexts(comp: int, threads: int) -> tuple[np.ndarray, np.ndarray]:
    """int64 arrays of `threads` LZ4F and zstd decompression context addresses (zeros for the codec not used;
    created on first use, kept for the thread's lifetime)."""
    lz4 = zstd = np.zeros(threads, np.int64)
    if comp in (1, 2):
        while len(_ctxs.lz4) < threads:
            _ctxs.lz4.append(native.new_lz4_context())
        lz4 = np.array(_ctxs.lz4[:threads], np.int64)
    elif comp in (3, 4):
        while len(_ctxs.zstd) < threads:
            _ctxs.zstd.append(native.new_zstd_context())
        zstd = np.array(_ctxs.zstd[:threads], np.int64)
    return lz4, zstd


def _address(lib, name: str) -> int:
    return ctypes.cast(getattr(lib, name), ctypes.c_void_p).value if lib is not None else 0


_LZ4 = (_address(native._lz4, "LZ4F_decompress"), _address(native._lz4, "LZ4F_resetDecompressionContext"))
_ZSTD = (_address(native._zstd, "ZSTD_decompressDCtx"), _address(native._zstd, "ZSTD_isError"))


def available(compression: int) -> bool:
    """Whether events packets of this compression can take the fast path here."""
    return FAST and _c is not None and (compression == 0 or native.available(compression))


def usable(reader) -> bool:
    """Whether `reader` (an Aedat4Reader) can read its events streams through the fast path."""
    return reader._nel is not None and reader._t0 is not None and available(reader.compression)


_TABLE_FIELDS = ("offset", "stream", "size", "elements", "t_start", "t_end")


def table(body, start: int, count: int) -> dict[str, np.ndarray] | None:
    """The FileDataTable's PacketHeader vector (`count` tables at `start` of the flatbuffer `body`) as int64
    arrays, decoded in C; None when the fast path is off or anything is out of place (the caller then decodes
    it with flatbuf.table_vector, which names the problem)."""
    if not FAST or _c is None:
        return None
    out = {k: np.empty(count, np.int64) for k in _TABLE_FIELDS}
    return out if _c.table(body, start, count, *out.values()) else None


class _Chunk:
    """Output arrays for up to `cap` events, views of one pooled block: t | x | y | p."""

    def __init__(self, pool: BlockPool, cap: int) -> None:
        blk = pool(13 * cap)
        self.cap = cap
        self.t = blk[:8 * cap].view(np.int64)
        self.x = blk[8 * cap:10 * cap].view(np.uint16)
        self.y = blk[10 * cap:12 * cap].view(np.uint16)
        self.p = blk[12 * cap:13 * cap].view(np.int8)

    def events(self, n: int) -> Events:
        return Events(self.t[:n], self.x[:n], self.y[:n], self.p[:n])


def iterate(reader, stream, chk, todo: list[int], threads: int = 1):
    """Yield, in file order, Events chunks read by the fast path and, for a packet it leaves to the general
    path, that packet's file index (an int): the caller decodes and checks it before asking for more. `chk` is
    the stream's StreamChecks; its state (last time kept, packet signatures seen) is kept up to date.
    threads > 1: that many C threads decode the packets of a chunk at once (each into its own place)."""
    if not todo:
        return
    if reader._f.closed:                    # the general path says so, packet by packet
        yield from todo
        return
    idx = np.asarray(todo, np.int64)
    off, size = reader._off[idx].astype(np.int64), reader._size[idx].astype(np.int64)
    nel = reader._nel[idx].astype(np.int64)
    lo, hi = reader._t0[idx].astype(np.int64), reader._t1[idx].astype(np.int64)
    comp = reader.compression
    threads = max(1, min(int(threads), MAX_THREADS, len(idx)))
    rb_len = min(max(int(size.max()), 0) + 8, MAX_BUFFER)
    # LZ4F decodes a block straight into the output only where a whole block (up to 4 MiB, as the frame says)
    # still fits; else through its own buffer with a slower dictionary path. The slack is never touched
    # (np.empty: no pages are faulted in that are not written).
    sc_len = min(16 * max(int(nel.max()), 0) + 64, MAX_BUFFER) + LZ4_SLACK if comp else 1
    readbuf = _buffer("read", threads * rb_len)[:threads * rb_len]
    scratch = _buffer("scratch", threads * sc_len)[:threads * sc_len]
    sig = np.zeros(3 * len(idx), np.int64)
    lz4_ctx, zstd_ctx = _contexts(comp, threads)
    w, h = max(stream.width, 0), max(stream.height, 0)
    pool = _POOL
    fd = reader._f.fileno()
    chunk = _Chunk(pool, CHUNK_EVENTS)
    k, total = 0, len(idx)
    seen = chk.seen
    while k < total:
        last = chk.last
        k2, nout, has_last, last, status = _c.events(
            fd, comp, _LZ4[0], _LZ4[1], lz4_ctx, _ZSTD[0], _ZSTD[1], zstd_ctx, stream.id, off, size, nel, lo, hi,
            k, total, readbuf, scratch, chunk.t, chunk.x, chunk.y, chunk.p, sig, w, h, last is not None,
            0 if last is None else last)
        for j, (c, t0, t1) in enumerate(sig[3 * k:3 * k2].reshape(-1, 3).tolist(), k):
            if c:
                seen.setdefault((c, t0, t1), todo[j])
        if has_last:
            chk.last = last
        if nout:
            yield chunk.events(nout)
            chunk = _Chunk(pool, CHUNK_EVENTS)
        k = k2
        if status == _ST_FULL and not nout:
            need = int(nel[k])
            if 16 * need <= sc_len - LZ4_SLACK if comp else 16 * need <= rb_len - 8:
                chunk = _Chunk(pool, need)          # a packet larger than a chunk: a chunk of its own size
                continue
            status = _ST_SLOW
        if status == _ST_SLOW:
            yield todo[k]
            k += 1
