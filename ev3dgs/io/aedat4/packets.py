"""AEDAT 4.0 packet decoding: bounded decompression into reused buffers, flatbuffer parsing of the four packet
types, and the optional read-ahead thread.

A packet payload is one LZ4 or zstd frame (or raw bytes) holding a size-prefixed flatbuffer. An events packet
whose element count the FileDataTable gives is decompressed straight into a reused block sized from that count
(aedat4_codec: one C call of the LZ4 / zstd library per packet, GIL released); any other packet into a
per-thread scratch buffer reused from packet to packet, through cramjam when the C libraries are not found. A
packet larger than the buffer takes the bounded streaming path once and the buffer grows to fit it. t, x, y
are strided views of the Event structs in the block; p is computed next to them from the polarity bytes
gathered in one strided pass, together with the statistics the per-packet checks need (largest x and y, bad
polarity bytes, backward time steps), so the checks themselves cost a few scalar comparisons on intact data.

Threads: reading and decompressing a packet (`fetch`) is GIL-free C work with a few microseconds of Python
around it; unpacking (`finish`) is a handful of numpy calls. With threads > 1, threads - 1 workers fetch
groups of consecutive packets (GROUP_BYTES compressed bytes each) ahead of the consumer, which unpacks and
checks them: the two stages overlap on two cores with one GIL hand-over per packet or so. (The earlier pool
ran whole decodes, numpy passes included, on two workers plus the consumer: three threads for two cores,
handing the GIL over at every numpy call.) Memory stays bounded by `threads` groups in flight and one read and
one scratch buffer per thread.
"""
from __future__ import annotations

import os
import struct
import sys
import threading
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cramjam
import lz4.frame
import numpy as np
import zstandard

from . import codec as native
from .flatbuf import FlatbufError, root, table_vector
from ..types import AedatError, FrameData

COMPRESSIONS = {0: "none", 1: "lz4", 2: "lz4-high", 3: "zstd", 4: "zstd-high"}
KINDS = {"EVTS": "events", "FRME": "frames", "IMUS": "imu", "TRIG": "triggers"}
IDENTS = {v: k for k, v in KINDS.items()}
# flatbuffer Event struct: int64 timestamp, int16 x, int16 y, bool polarity, 3 bytes padding (16 bytes)
EVENT_DTYPE = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<i2", "<i2", "u1"],
                        "offsets": [0, 8, 10, 12], "itemsize": 16})
MAX_DECOMPRESSED = 1 << 30          # no packet may claim more than 1 GiB once decompressed
_SCRATCH0 = 1 << 20                 # first size of a thread's scratch buffer (grows to the largest packet)
GROUP_BYTES = 256 << 10             # thread pool: consecutive packets decoded by one task, in compressed bytes
_CHUNK = 8 << 20
HDR = struct.Struct("<iI")
_U32 = struct.Struct("<I")
IMU_FIELDS = {"t": (0, "<i8"), "temp": (1, "<f4"), "ax": (2, "<f4"), "ay": (3, "<f4"), "az": (4, "<f4"),
              "gx": (5, "<f4"), "gy": (6, "<f4"), "gz": (7, "<f4")}
TRIG_FIELDS = {"t": (0, "<i8"), "kind": (1, "i1")}


class Skip(Exception):
    """A packet that is valid but not supported (e.g. an unknown frame format): skipped with a warning, also
    under strict reading."""


# ------------------------------------------------------------------ decompression
def _cap(data) -> int:
    """Most bytes one packet may decompress to: MAX_DECOMPRESSED and 1024x its compressed size (16 MiB at
    least), so that a corrupt size cannot make the reader allocate without bound."""
    return min(MAX_DECOMPRESSED, max(16 << 20, 1024 * len(data)))


def _inflate_stream(data, comp: int, at: int) -> bytearray:
    """Decompress a frame holding a size-prefixed flatbuffer by streaming: the output is bounded by the size
    prefix and _cap, and allocated only as it is really produced (a decompression bomb stops at the cap)."""
    cap = _cap(data)
    if comp in (1, 2):
        dec, src = lz4.frame.LZ4FrameDecompressor(), [data]

        def read(k: int) -> bytes:
            if dec.eof or (not src and dec.needs_input):
                return b""
            return dec.decompress(src.pop() if src else b"", max_length=k)
    else:
        read = zstandard.ZstdDecompressor().stream_reader(data).read
    out = bytearray()
    while len(out) < 4:
        chunk = read(4 - len(out))
        if not chunk:
            raise AedatError(f"byte {at}: packet decompresses to {len(out)} bytes, too short for a flatbuffer")
        out += chunk
    total = 4 + struct.unpack_from("<I", out)[0]
    if total > cap:
        raise AedatError(f"byte {at}: packet claims {total} decompressed bytes from {len(data)} compressed "
                         f"bytes (limit {cap})")
    while len(out) < total:
        chunk = read(min(total - len(out), _CHUNK))
        if not chunk:
            break
        out += chunk
    if len(out) < total:
        raise AedatError(f"byte {at}: packet decompresses to {len(out)} bytes but its flatbuffer size prefix "
                         f"says {total}")
    return out


_local = threading.local()


def decompress(data, comp: int, at: int, out: np.ndarray | None = None, data_addr: int | None = None,
               out_addr: int | None = None) -> np.ndarray:
    """The decompressed payload of one packet as a uint8 array. For compressed packets it is a view of `out`
    when the payload fits there, else of this thread's scratch buffer, valid only until this thread's next call
    (copy what must outlive it). data_addr / out_addr: the buffers' addresses when the caller knows them
    (saves looking them up per packet)."""
    if comp == 0:
        return np.frombuffer(data, np.uint8)
    fast = native.available(comp)
    if out is not None and fast:
        n = native.decompress_into(data, comp, out, data_addr, out_addr)
        if n is not None:
            return _checked(out, n, at)
    codec = cramjam.lz4 if comp in (1, 2) else cramjam.zstd
    if out is not None and not fast:
        try:
            n = codec.decompress_into(data, out)
        except cramjam.DecompressionError:
            pass                            # too small for this packet, or corrupt: the scratch path says which
        else:
            return _checked(out, n, at)
    buf = getattr(_local, "buf", None)
    if buf is None:
        buf = _local.buf = np.empty(_SCRATCH0, np.uint8)
    if fast:
        n = native.decompress_into(data, comp, buf, data_addr)
        if n is not None:
            return _checked(buf, n, at)
    try:
        n = codec.decompress_into(data, buf)
    except cramjam.DecompressionError as e:
        if "whole buffer" not in str(e):      # corrupt data (not merely a buffer too small for this packet)
            raise AedatError(f"byte {at}: {COMPRESSIONS[comp]} decompression failed: {e}") from None
        try:
            out = _inflate_stream(data, comp, at)
        except AedatError:
            raise
        except Exception as e:   # lz4 raises RuntimeError, zstandard ZstdError: both mean corrupt data
            raise AedatError(f"byte {at}: {COMPRESSIONS[comp]} decompression failed: {e}") from None
        _local.buf = np.empty(1 << (len(out) - 1).bit_length(), np.uint8)   # fits the largest packet so far
        return np.frombuffer(out, np.uint8)
    return _checked(buf, n, at)


def _checked(buf: np.ndarray, n: int, at: int) -> np.ndarray:
    if n < 4:
        raise AedatError(f"byte {at}: packet decompresses to {n} bytes, too short for a flatbuffer")
    total = 4 + _U32.unpack_from(buf)[0]
    if n < total:
        raise AedatError(f"byte {at}: packet decompresses to {n} bytes but its flatbuffer size prefix says {total}")
    return buf[:n]


# ------------------------------------------------------------------ flatbuffer payloads
def parse(payload, kind: str, at: int):
    """(root table, flatbuffer body) of a payload checked to be a `kind` packet; AedatError names the byte."""
    try:
        tab, ident, body = root(payload)
    except FlatbufError as e:
        raise AedatError(f"byte {at}: {kind} packet: corrupt flatbuffer ({e} of the decompressed payload)") from None
    name = ident.decode("ascii", "replace")
    if name in KINDS and kind in IDENTS and name != IDENTS[kind]:
        raise AedatError(f"byte {at}: packet identifier {name} in a {kind} stream (expected {IDENTS[kind]})")
    return tab, body


@dataclass
class EventArrays:
    """One events packet unpacked: t (int64), x, y (uint16; a negative int16 coordinate reads as >= 32768;
    strided views of the packet's own copy of the Event structs), pol (int8 +1/-1, -128 for a stored byte
    other than 0/1) and the statistics the checks use."""
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    pol: np.ndarray
    max_x: int
    max_y: int
    bad_polarity: int           # events whose stored polarity byte is not 0 or 1
    backward: int               # k with t[k] < t[k-1]


_I8, _U2, _S8 = np.dtype("<i8"), np.dtype("<u2"), np.dtype(np.int8)
_max = np.maximum.reduce                    # ndarray.max() adds ~1 us of Python wrapper per call


def _fresh(nbytes: int) -> np.ndarray:
    return np.empty(nbytes, np.uint8)


def decode_events(payload, at: int, alloc=_fresh, pol_out: np.ndarray | None = None) -> EventArrays:
    """Unpack an events packet: t, x, y are strided views of the Event structs and pol is computed into
    pol_out (n bytes) when given: the payload then already lives in memory of its own (a BlockPool block).
    Otherwise the structs are first copied out of the (scratch) payload in one memcpy into memory from
    alloc(bytes). The statistics for the checks take a few vectorised passes (numpy releases the GIL)."""
    tab, body = parse(payload, "events", at)
    start, n = tab.vector(0, EVENT_DTYPE.itemsize)
    size = EVENT_DTYPE.itemsize * n
    if pol_out is not None and len(pol_out) == n:
        b = np.frombuffer(body, np.uint8, count=size, offset=start)
        mem = pol_out
        size = 0
    else:
        mem = alloc(size + n)
        b = mem[:size]
        b[:] = np.frombuffer(body, np.uint8, count=size, offset=start)
    u16 = b.view(_U2)
    t, x, y = b.view(_I8)[0::2], u16[4::8], u16[5::8]
    q = mem[size:size + n]                  # the stored polarity bytes (0 OFF, 1 ON), gathered contiguously:
    np.copyto(q, b[12::16])                 # the one strided pass for polarity; the rest is contiguous
    bad_p = 0
    if n and _max(q) > 1:
        bad = q > 1
        bad_p = int(np.count_nonzero(bad))
    pol = q.view(_S8)
    np.add(pol, pol, out=pol)
    pol -= 1                                # 0 -> -1, 1 -> +1
    if bad_p:
        pol[bad] = -128
    back = int(np.count_nonzero(np.less(t[1:], t[:-1]))) if n > 1 else 0
    return EventArrays(t, x, y, pol, int(_max(x)) if n else 0, int(_max(y)) if n else 0, bad_p, back)


class BlockPool:
    """Memory for unpacked event packets, reused once nothing references a block any more (CPython reference
    counts: every array unpacked into a block is a view whose base is the block). Streaming a file then touches
    the same few blocks over and over instead of having the allocator map, fault in and return fresh pages for
    every packet (measured: ~100 page faults and a third of the read time per 20 000-event packet). At most
    `keep` blocks are kept; a consumer that holds on to its chunks simply gets fresh memory."""

    MIN_BLOCK = 64 << 10

    def __init__(self, keep: int) -> None:
        self._blocks: list[np.ndarray] = []
        self._addr: list[int] = []
        self._keep = keep
        self._lock = threading.Lock()

    def __call__(self, nbytes: int) -> np.ndarray:
        return self.claim(nbytes)[0]

    def claim(self, nbytes: int) -> tuple[np.ndarray, int]:
        """A block's first nbytes (a view) and its address."""
        with self._lock:                    # a block found free is claimed (viewed) before the lock is let go
            blocks = self._blocks
            for k in range(len(blocks)):
                if blocks[k].size >= nbytes and sys.getrefcount(blocks[k]) == 2:   # the list's + the argument's
                    return blocks[k][:nbytes], self._addr[k]
            blk = np.empty(max(self.MIN_BLOCK, 1 << (nbytes - 1).bit_length()), np.uint8)
            addr = native.address(blk)
            if len(blocks) < self._keep:
                blocks.append(blk)
                self._addr.append(addr)
            return blk[:nbytes], addr


def decode_frame(payload, at: int, source: str) -> FrameData:
    tab, body = parse(payload, "frames", at)
    ts = [tab.scalar(k, "q", 0) for k in range(5)]
    code, w, h = tab.scalar(5, "b", 0), tab.scalar(6, "h", 0), tab.scalar(7, "h", 0)
    depth, ch = code & 7, (code >> 3) + 1
    if depth not in (0, 2) or code < 0:
        raise Skip(f"byte {at}: frame with unsupported OpenCV type {code} skipped")
    if w < 0 or h < 0:
        raise AedatError(f"byte {at}: frame size {w}x{h} is negative")
    start, n = tab.vector(10, 1)
    dt = np.dtype(np.uint8 if depth == 0 else "<u2")
    if n != w * h * ch * dt.itemsize:
        raise AedatError(f"byte {at}: frame holds {n} pixel bytes, {w}x{h}x{ch}x{dt.itemsize} expected")
    img = np.frombuffer(body, dt, count=w * h * ch, offset=start).astype(dt.newbyteorder("="))   # a copy
    img = img.reshape((h, w) if ch == 1 else (h, w, ch))
    return FrameData(timestamp=ts[0], frame_start=ts[1], frame_end=ts[2], exposure_start=ts[3],
                     exposure_end=ts[4], image=img, position=(tab.scalar(8, "h", 0), tab.scalar(9, "h", 0)),
                     source=source)


def decode_vector(payload, at: int, kind: str) -> dict[str, np.ndarray]:
    """IMU or trigger samples: one array per field (fresh arrays: they do not keep the payload alive)."""
    tab, body = parse(payload, kind, at)
    start, n = tab.vector(0, 4)
    return table_vector(body, start, n, IMU_FIELDS if kind == "imu" else TRIG_FIELDS)


def summary(payload, at: int, kind: str) -> tuple[int, int, int]:
    """(elements, first t, last t) of a packet (used when there is no FileDataTable)."""
    tab, body = parse(payload, kind, at)
    if kind == "frames":
        t = tab.scalar(0, "q", 0)
        return 1, t, t
    start, n = tab.vector(0, 16 if kind == "events" else 4)
    if not n:
        return 0, -1, -1
    if kind == "events":
        t = np.frombuffer(body, "<i8", count=2 * n, offset=start)[::2]
    else:
        t = table_vector(body, start, n, {"t": (0, "<i8")})["t"]
    return n, int(t.min()), int(t.max())


# ------------------------------------------------------------------ reading packets
class PacketReader:
    """Reads packet i of an indexed file (positioned reads: safe from worker threads) and decodes it."""

    def __init__(self, f, off: np.ndarray, size: np.ndarray, sid: np.ndarray, compression: int, path: str,
                 elements: np.ndarray | None = None) -> None:
        self.f, self.off, self.size, self.sid, self.comp, self.path = f, off, size, sid, compression, path
        self.elements = elements            # per packet, from the FileDataTable (None without one)
        self._where = list(zip(off.tolist(), size.tolist(), sid.tolist()))    # Python ints: cheap per packet
        self.blocks = BlockPool(keep=16)
        self._pool: ThreadPoolExecutor | None = None      # kept while the reader is open: its threads keep
        self._pool_threads = 0                              # their grown scratch buffers from read to read

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def _executor(self, threads: int) -> ThreadPoolExecutor:
        if self._pool is None or self._pool_threads != threads:
            self.close()
            self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="aedat4")
            self._pool_threads = threads
        return self._pool

    def raw(self, i: int) -> tuple[memoryview, int]:
        """Packet i's header and payload as read from the file, in this thread's reused read buffer (valid
        until this thread's next call), and the payload's offset."""
        off, n, sid = self._where[i]
        if self.f.closed:
            raise AedatError(f"{self.path}: the reader is closed")
        buf = getattr(_local, "raw", None)
        if buf is None or len(buf) < n + 8:
            buf = _local.raw = bytearray(max(_SCRATCH0, 1 << (n + 7).bit_length()))
            _local.raw_addr = native.address(buf)
        mv = memoryview(buf)[:n + 8]
        got = os.preadv(self.f.fileno(), [mv], off - 8)
        if got < n + 8:
            raise AedatError(f"byte {off - 8}: file ends inside the packet ({n} bytes): was it truncated since "
                             "opening?")
        if HDR.unpack_from(mv) != (sid, n):
            hs, hn = HDR.unpack_from(mv)
            raise AedatError(f"byte {off - 8}: packet header (stream {hs}, {hn} bytes) does not match the "
                             f"FileDataTable (stream {sid}, {n} bytes)")
        return mv, off

    def payload(self, i: int) -> bytes:
        """The decompressed payload of packet i as its own bytes object."""
        raw, off = self.raw(i)
        return bytes(decompress(memoryview(raw)[8:], self.comp, off))

    def fetch(self, i: int, kind: str, source: str = ""):
        """Stage 1 of decoding packet i (safe in a worker thread): read and decompress it. An events packet with
        a FileDataTable count is decompressed straight into a reused block sized from that count (a
        size-prefixed EVTS flatbuffer is 16 bytes per event plus < 64) with room for its polarity after it, and
        returned as (payload, polarity memory) for `finish`; anything else is decoded completely (EventArrays,
        FrameData or a dict of sample arrays)."""
        raw, off = self.raw(i)
        try:
            if kind == "events":
                if self.comp and self.elements is not None and 17 * int(self.elements[i]) < _cap(raw) // 2:
                    k = int(self.elements[i])
                    need = 16 * k + 64
                    mem, addr = self.blocks.claim(need + k)
                    payload = decompress(raw[8:], self.comp, off, mem[:need], _local.raw_addr + 8, addr)
                    if np.shares_memory(payload, mem):
                        return payload, mem[need:], off
                    return decode_events(payload, off, self.blocks)
                return decode_events(decompress(memoryview(raw)[8:], self.comp, off), off, self.blocks)
            payload = decompress(memoryview(raw)[8:], self.comp, off)
            if kind == "frames":
                return decode_frame(payload, off, source)
            return decode_vector(payload, off, kind)
        except FlatbufError as e:
            raise AedatError(f"byte {off}: corrupt {kind} packet ({e})") from None

    def finish(self, got, kind: str):
        """Stage 2 (in the consuming thread): unpack what `fetch` left decompressed in place."""
        if type(got) is not tuple:
            return got
        payload, pol, off = got
        try:
            return decode_events(payload, off, self.blocks, pol)   # a wrong table count: copied to a block
        except FlatbufError as e:
            raise AedatError(f"byte {off}: corrupt {kind} packet ({e})") from None

    def decode(self, i: int, kind: str, source: str = ""):
        """Packet i decoded as `kind`: EventArrays, FrameData or a dict of sample arrays."""
        return self.finish(self.fetch(i, kind, source), kind)

    def _attempt(self, i: int, kind: str, source: str):
        try:
            return self.fetch(i, kind, source)
        except (AedatError, Skip) as e:
            return e

    def _attempt_group(self, group: list[int], kind: str, source: str) -> list:
        return [self._attempt(i, kind, source) for i in group]

    def _finish(self, got, kind: str):
        if isinstance(got, Exception):
            return got
        try:
            return self.finish(got, kind)
        except (AedatError, Skip) as e:
            return e

    def iterate(self, todo: list[int], kind: str, source: str, threads: int):
        """Yield (i, decoded packet or the AedatError/Skip it raised) for i in `todo`, in order. With
        threads > 1, threads - 1 workers fetch (read and decompress) groups of consecutive packets (GROUP_BYTES
        compressed bytes at least, so that small packets do not pay a task each) at most `threads` groups ahead,
        and the calling thread unpacks them; errors still surface in order, and abandoning the iteration cancels
        what was queued. A stream of at most `threads` groups is decoded in the calling thread."""
        groups, cur, acc = [], [], 0
        for i in (todo if threads > 1 else ()):
            cur.append(i)
            acc += int(self.size[i])
            if acc >= GROUP_BYTES:
                groups.append(cur)
                cur, acc = [], 0
        if cur:
            groups.append(cur)
        if len(groups) <= threads:          # too little to share out: decode in the calling thread
            for i in todo:
                yield i, self._finish(self._attempt(i, kind, source), kind)
            return
        workers = threads - 1
        pool = self._executor(workers)
        queued: deque = deque()
        nxt = iter(groups)
        try:
            for g in nxt:
                queued.append((g, pool.submit(self._attempt_group, g, kind, source)))
                if len(queued) > workers:
                    break
            while queued:
                g, fut = queued.popleft()
                h = next(nxt, None)
                if h is not None:
                    queued.append((h, pool.submit(self._attempt_group, h, kind, source)))
                for i, got in zip(g, fut.result()):
                    yield i, self._finish(got, kind)
        finally:
            for _, fut in queued:
                fut.cancel()
