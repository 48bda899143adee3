"""AEDAT 4.0 packet decompression straight into a caller's buffer with the C libraries' own decoders.

DV writes every packet as one LZ4 frame (linked 64 KiB blocks, no checksums, usually no content size) or one
zstd frame. cramjam's `decompress_into` decodes such a frame through a streaming reader that copies it once
more (and zeroes memory); here one `LZ4F_decompress` call (told that the output buffer is stable, so linked
blocks refer back into it as in dv-processing) or one `ZSTD_decompressDCtx` call decodes the whole frame
straight into the buffer. They are called through ctypes, which releases the GIL for the call: a packet costs
one GIL release, so a worker thread decompressing packets hands the GIL back and forth rarely.

The functions come from the C libraries that the declared dependencies already ship (the `lz4` package's
frame module and the `zstandard` package's cffi module export them), else from a system liblz4 / libzstd;
when neither is found `available()` is False for that codec and callers keep using cramjam.

Safety: both decoders are the libraries' bounds-checked ones, given the buffer's size (they never write past
it) and verifying what the frame carries (LZ4 header checksum, block and content checksums when present).
A frame that is corrupt, does not fit, is unfinished or is followed by further bytes gives None: the caller
then takes its general path, which reports the error exactly as before.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import importlib.util
import threading

import numpy as np

_LZ4F_VERSION = 100


class _LZ4FOptions(ctypes.Structure):
    # LZ4F_decompressOptions_t (lz4 >= 1.9.3): stableDst, skipChecksums, two reserved words
    _fields_ = [("stableDst", ctypes.c_uint), ("skipChecksums", ctypes.c_uint), ("reserved1", ctypes.c_uint),
                ("reserved0", ctypes.c_uint)]


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


_lz4 = _load([_module_file("lz4.frame._frame"), ctypes.util.find_library("lz4")], "LZ4F_resetDecompressionContext")
if _lz4 is not None:
    _lz4.LZ4F_createDecompressionContext.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_uint]
    _lz4.LZ4F_createDecompressionContext.restype = ctypes.c_size_t
    _lz4.LZ4F_freeDecompressionContext.argtypes = [ctypes.c_void_p]
    _lz4.LZ4F_freeDecompressionContext.restype = ctypes.c_size_t
    _lz4.LZ4F_resetDecompressionContext.argtypes = [ctypes.c_void_p]
    _lz4.LZ4F_resetDecompressionContext.restype = None
    _lz4_decompress = _lz4.LZ4F_decompress      # (dctx, dst, &dst size, src, &src size, &options): addresses
    _lz4_decompress.argtypes = [ctypes.c_void_p] * 6
    _lz4_decompress.restype = ctypes.c_size_t
    _lz4.LZ4F_isError.argtypes = [ctypes.c_size_t]
    _lz4.LZ4F_isError.restype = ctypes.c_uint

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


def new_lz4_context() -> int:
    """A fresh LZ4F decompression context (address); free it with free_lz4_context."""
    ptr = ctypes.c_void_p()
    if _lz4.LZ4F_isError(_lz4.LZ4F_createDecompressionContext(ctypes.byref(ptr), _LZ4F_VERSION)):
        raise MemoryError("LZ4F_createDecompressionContext failed")
    return ptr.value


def new_zstd_context() -> int:
    """A fresh zstd decompression context (address); free it with free_zstd_context."""
    ctx = _zstd.ZSTD_createDCtx()
    if not ctx:
        raise MemoryError("ZSTD_createDCtx failed")
    return ctx


def free_lz4_context(ctx: int) -> None:
    _lz4.LZ4F_freeDecompressionContext(ctx)


def free_zstd_context(ctx: int) -> None:
    _zstd.ZSTD_freeDCtx(ctx)


_char_at = ctypes.c_char.from_buffer


def address(buf) -> int:
    """Address of the first byte of a contiguous buffer (bytes, bytearray, memoryview, numpy array); ~1 us for
    a writable one (numpy's .ctypes.data costs ~4 us, which matters per packet)."""
    try:
        return ctypes.addressof(_char_at(buf))
    except (TypeError, ValueError):         # read-only (bytes) or empty
        a = buf if isinstance(buf, np.ndarray) else np.frombuffer(buf, np.uint8)
        return a.__array_interface__["data"][0]


class _Contexts(threading.local):
    """Per thread: one LZ4F and one zstd decompression context (created on first use, freed with the thread)."""

    def __init__(self) -> None:
        self.lz4 = self.zstd = None
        self._free_lz4 = _lz4.LZ4F_freeDecompressionContext if _lz4 is not None else None
        self._free_zstd = _zstd.ZSTD_freeDCtx if _zstd is not None else None    # kept: module globals may be
        self.lz4_opts = _LZ4FOptions(1, 0, 0, 0)                                  # gone when this is freed
        self.src_size, self.dst_size = ctypes.c_size_t(), ctypes.c_size_t()
        self.src_ptr, self.dst_ptr = ctypes.addressof(self.src_size), ctypes.addressof(self.dst_size)
        self.opts_ptr = ctypes.addressof(self.lz4_opts)

    def lz4_ctx(self):
        if self.lz4 is None:
            ptr = ctypes.c_void_p()
            if _lz4.LZ4F_isError(_lz4.LZ4F_createDecompressionContext(ctypes.byref(ptr), _LZ4F_VERSION)):
                raise MemoryError("LZ4F_createDecompressionContext failed")
            self.lz4 = ptr.value
        return self.lz4

    def zstd_ctx(self):
        if self.zstd is None:
            self.zstd = _zstd.ZSTD_createDCtx()
            if not self.zstd:
                raise MemoryError("ZSTD_createDCtx failed")
        return self.zstd

    def __del__(self) -> None:
        if self.lz4:
            self._free_lz4(self.lz4)
        if self.zstd:
            self._free_zstd(self.zstd)


_ctx = _Contexts()


def lz4_into(src, src_addr: int, out, out_addr: int | None = None) -> int | None:
    """Decode the one LZ4 frame that is all of `src` (a buffer whose first byte is at src_addr) into `out` (a
    contiguous uint8 buffer, first byte at out_addr) with one LZ4F_decompress call; the number of bytes written,
    or None when the frame is corrupt, does not fit, is unfinished or is followed by more bytes (the general
    path then says which)."""
    c = _ctx
    dctx = c.lz4 or c.lz4_ctx()
    n = len(src)
    c.src_size.value, c.dst_size.value = n, len(out)
    hint = _lz4_decompress(dctx, address(out) if out_addr is None else out_addr, c.dst_ptr, src_addr, c.src_ptr,
                           c.opts_ptr)
    if hint != 0 or c.src_size.value != n:     # error (LZ4F_isError), unfinished frame, or trailing bytes
        _lz4.LZ4F_resetDecompressionContext(dctx)
        return None
    return c.dst_size.value


def zstd_into(src, src_addr: int, out, out_addr: int | None = None) -> int | None:
    """Decode the zstd frame(s) in `src` into `out`; bytes written, or None (buffer too small, corrupt)."""
    got = _zstd.ZSTD_decompressDCtx(_ctx.zstd or _ctx.zstd_ctx(), address(out) if out_addr is None else out_addr,
                                    len(out), src_addr, len(src))
    return None if _zstd.ZSTD_isError(got) else got


def decompress_into(src, comp: int, out, src_addr: int | None = None, out_addr: int | None = None) -> int | None:
    """Bytes of `src` (compression comp) decoded into `out`, or None: take the general path."""
    if comp in (1, 2) and _lz4 is not None:
        return lz4_into(src, address(src) if src_addr is None else src_addr, out, out_addr)
    if comp in (3, 4) and _zstd is not None:
        return zstd_into(src, address(src) if src_addr is None else src_addr, out, out_addr)
    return None
