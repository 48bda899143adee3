"""AEDAT 4.0 packet decompression straight into a caller's buffer with the C libraries' one-shot functions.

DV writes every packet as one LZ4 frame (linked 64 KiB blocks, no checksums, usually no content size) or one
zstd frame. cramjam's `decompress_into` decodes such a frame through a streaming decoder that copies every
block once more; here each LZ4 block is decoded by `LZ4_decompress_safe_usingDict` directly after the previous
one in the output (the previous 64 KiB are its dictionary, as in dv-processing), and a zstd frame by one
`ZSTD_decompressDCtx` call. Both are called through ctypes, which releases the GIL for the call.

The functions come from the C libraries the declared dependencies already ship (the `lz4` package's block
module and the `zstandard` package's cffi module export them), else from a system liblz4 / libzstd; when
neither is found `available()` is False for that codec and callers keep using cramjam.

Safety: every LZ4 block size is checked against the frame's block maximum and the input's end, and the C
decoder (the bounds-checked "safe" variant) is given the room left in the buffer, so it never writes past it;
the frame descriptor's header checksum is verified as LZ4's own frame decoder does. Anything these fast paths do not handle (checksums, dictionary ids, skippable
or concatenated frames, a buffer too small, corrupt data) returns None: the caller then takes its general
path, which reports the error exactly as before.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import importlib.util
import struct
import threading

import numpy as np

_U32 = struct.Struct("<I")
_LZ4_MAGIC = 0x184D2204
_BLOCK_MAX = {4: 64 << 10, 5: 256 << 10, 6: 1 << 20, 7: 4 << 20}
_DICT = 64 << 10                    # LZ4 linked blocks refer back at most 64 KiB


def _load(candidates, symbol):
    for name in candidates:
        if not name:
            continue
        try:
            lib = ctypes.CDLL(name)
            getattr(lib, symbol)
        except (OSError, AttributeError):
            continue
        return lib
    return None


def _module_file(modname: str) -> str | None:
    """Path of an installed extension module's shared object, found without importing the module itself."""
    try:
        spec = importlib.util.find_spec(modname)
    except (ImportError, ValueError):
        return None
    return spec.origin if spec is not None and spec.has_location else None


_lz4 = _load([_module_file("lz4.block._block"), ctypes.util.find_library("lz4")], "LZ4_decompress_safe_usingDict")
if _lz4 is not None:
    _lz4_block = _lz4.LZ4_decompress_safe_usingDict
    _lz4_block.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_void_p,
                           ctypes.c_int]
    _lz4_block.restype = ctypes.c_int

_zstd = _load([_module_file("zstandard._cffi"), ctypes.util.find_library("zstd")], "ZSTD_decompressDCtx")
if _zstd is not None:
    _zstd.ZSTD_createDCtx.restype = ctypes.c_void_p
    _zstd.ZSTD_createDCtx.argtypes = []
    _zstd.ZSTD_freeDCtx.argtypes = [ctypes.c_void_p]
    _zstd.ZSTD_decompressDCtx.restype = ctypes.c_size_t
    _zstd.ZSTD_decompressDCtx.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p,
                                          ctypes.c_size_t]
    _zstd.ZSTD_isError.restype = ctypes.c_uint
    _zstd.ZSTD_isError.argtypes = [ctypes.c_size_t]


def available(comp: int) -> bool:
    """Whether packets of compression `comp` (1/2 LZ4, 3/4 zstd) can take the fast path here."""
    return (_lz4 is not None) if comp in (1, 2) else (_zstd is not None) if comp in (3, 4) else False


def address(buf) -> int:
    """Address of the first byte of a writable or read-only contiguous buffer (bytes, bytearray, memoryview,
    numpy array)."""
    return np.frombuffer(buf, np.uint8).ctypes.data if not isinstance(buf, np.ndarray) else buf.ctypes.data


def lz4_into(src, src_addr: int, out: np.ndarray) -> int | None:
    """Decode the LZ4 frame in `src` (a buffer whose first byte is at src_addr) into `out` (a contiguous uint8
    array); the number of bytes written, or None when this path does not apply (see the module docstring)."""
    n = len(src)
    if n < 7 or _U32.unpack_from(src, 0)[0] != _LZ4_MAGIC:
        return None
    flg, bd = src[4], src[5]
    if flg >> 6 != 1 or flg & 0b10111 or bd & 0x8F or (bd >> 4) not in _BLOCK_MAX:   # checksums, dict id,
        return None                                                                     # reserved bits
    pos = 7 + (8 if flg & 8 else 0)
    if n < pos or not _header_ok(bytes(src[4:pos])):
        return None
    bmax = _BLOCK_MAX[bd >> 4]
    cap, dst, o = len(out), out.ctypes.data, 0
    while True:
        if pos + 4 > n:
            return None
        sz = _U32.unpack_from(src, pos)[0]
        pos += 4
        if sz == 0:
            break
        raw = sz & 0x80000000
        sz &= 0x7FFFFFFF
        room = cap - o if cap - o < bmax else bmax
        if sz > bmax or pos + sz > n or (raw and sz > room):
            return None
        if raw:
            ctypes.memmove(dst + o, src_addr + pos, sz)
            got = sz
        else:                               # the safe decoder writes at most `room` bytes (fails otherwise)
            d = o if o < _DICT else _DICT
            got = _lz4_block(src_addr + pos, dst + o, sz, room, dst + o - d, d)
            if got < 0:
                return None
        o += got
        pos += sz
    if pos != n or (flg & 8 and struct.unpack_from("<Q", src, 6)[0] != o):
        return None                         # trailing bytes (a second frame, garbage), or not the stated size
    return o


_P1, _P2, _P3, _P4, _P5, _M = 2654435761, 2246822519, 3266489917, 668265263, 374761393, 0xFFFFFFFF


def xxh32_short(data: bytes) -> int:
    """XXH32 with seed 0 of fewer than 16 bytes (what an LZ4 frame descriptor's header checksum hashes)."""
    assert len(data) < 16
    h = (_P5 + len(data)) & _M
    k = 0
    while k + 4 <= len(data):
        h = (h + _U32.unpack_from(data, k)[0] * _P3) & _M
        h = (((h << 17) | (h >> 15)) & _M) * _P4 & _M
        k += 4
    for b in data[k:]:
        h = (h + b * _P5) & _M
        h = (((h << 11) | (h >> 21)) & _M) * _P1 & _M
    h ^= h >> 15
    h = h * _P2 & _M
    h ^= h >> 13
    h = h * _P3 & _M
    return h ^ (h >> 16)


_seen_headers: set[bytes] = set()


def _header_ok(desc: bytes) -> bool:
    """Whether an LZ4 frame descriptor (FLG, BD, optional content size, then the header checksum byte) is
    intact; DV's descriptors repeat from packet to packet, so each distinct one is hashed once."""
    if desc in _seen_headers:
        return True
    if (xxh32_short(desc[:-1]) >> 8) & 0xFF != desc[-1]:
        return False
    if len(_seen_headers) < 4096:
        _seen_headers.add(desc)
    return True


_local = threading.local()


class _DCtx:
    """One zstd decompression context per thread (freed with the thread's locals)."""

    def __init__(self) -> None:
        self._free = _zstd.ZSTD_freeDCtx          # kept: module globals may be gone when this is collected
        self.ptr = _zstd.ZSTD_createDCtx()
        if not self.ptr:
            raise MemoryError("ZSTD_createDCtx failed")

    def __del__(self) -> None:
        if self.ptr:
            self._free(self.ptr)
            self.ptr = None


def zstd_into(src, src_addr: int, out: np.ndarray) -> int | None:
    """Decode the zstd frame(s) in `src` into `out`; bytes written, or None (buffer too small, corrupt)."""
    ctx = getattr(_local, "dctx", None)
    if ctx is None:
        ctx = _local.dctx = _DCtx()
    got = _zstd.ZSTD_decompressDCtx(ctx.ptr, out.ctypes.data, len(out), src_addr, len(src))
    return None if _zstd.ZSTD_isError(got) else got


def decompress_into(src, comp: int, out: np.ndarray) -> int | None:
    """Bytes of `src` (compression comp) decoded into `out`, or None: take the general path."""
    if comp in (1, 2):
        return lz4_into(src, address(src), out) if _lz4 is not None else None
    if comp in (3, 4):
        return zstd_into(src, address(src), out) if _zstd is not None else None
    return None
