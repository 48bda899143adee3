"""A tiny, bounds-checked reader for FlatBuffers tables (clean room, from the documented binary layout).

Layout (all little-endian): a buffer starts with a uoffset32 to the root table (size-prefixed buffers have
one more uint32 before it: the length of the rest). A table starts with an soffset32; table_pos - soffset is
its vtable: uint16 vtable size, uint16 table size, then one uint16 per field slot (0 = absent, use the
default) giving the field's offset from the table start. Reference fields (vectors, strings, tables) store a
uoffset32 relative to the field's own position; a vector starts with a uint32 element count.

Every position read from the buffer is checked against the buffer before it is used, so a corrupt buffer
raises FlatbufError (with the offset inside the buffer) and never an IndexError or a giant allocation.
"""
from __future__ import annotations

import struct

import numpy as np


class FlatbufError(ValueError):
    """A corrupt flatbuffer; `pos` is the offset inside the buffer where reading failed."""

    def __init__(self, pos: int, msg: str) -> None:
        super().__init__(f"offset {pos}: {msg}")
        self.pos = pos
        self.msg = msg


_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")


class Table:
    """One flatbuffer table inside `buf` (bytes, bytearray or memoryview) at `pos`."""

    __slots__ = ("buf", "pos", "vt", "vt_size", "size")

    def __init__(self, buf, pos: int) -> None:
        n = len(buf)
        if pos < 0 or pos + 4 > n:
            raise FlatbufError(pos, f"table position outside the buffer ({n} bytes)")
        vt = pos - _I32.unpack_from(buf, pos)[0]
        if vt < 0 or vt + 4 > n:
            raise FlatbufError(pos, f"vtable position {vt} outside the buffer ({n} bytes)")
        vt_size, size = _U16.unpack_from(buf, vt)[0], _U16.unpack_from(buf, vt + 2)[0]
        if vt_size < 4 or vt_size % 2 or vt + vt_size > n:
            raise FlatbufError(vt, f"bad vtable size {vt_size}")
        if size < 4 or pos + size > n:
            raise FlatbufError(vt, f"table size {size} runs past the buffer ({n} bytes)")
        self.buf, self.pos, self.vt, self.vt_size, self.size = buf, pos, vt, vt_size, size

    def offset(self, slot: int, width: int = 0) -> int:
        """Offset of the field in slot `slot` from the table start, 0 if absent; checks `width` bytes fit."""
        at = 4 + 2 * slot
        if at + 2 > self.vt_size:
            return 0
        off = _U16.unpack_from(self.buf, self.vt + at)[0]
        if off and (off < 4 or off + width > self.size):
            raise FlatbufError(self.vt + at, f"field {slot} offset {off} outside its table ({self.size} bytes)")
        return off

    def scalar(self, slot: int, fmt: str, default=0):
        s = struct.calcsize("<" + fmt)
        off = self.offset(slot, s)
        return struct.unpack_from("<" + fmt, self.buf, self.pos + off)[0] if off else default

    def struct_pos(self, slot: int, size: int) -> int:
        """Absolute position of an inline struct field of `size` bytes, or -1 if absent."""
        off = self.offset(slot, size)
        return self.pos + off if off else -1

    def _ref(self, slot: int) -> int:
        off = self.offset(slot, 4)
        if not off:
            return -1
        p = self.pos + off
        q = p + _U32.unpack_from(self.buf, p)[0]
        if q + 4 > len(self.buf):
            raise FlatbufError(p, f"reference to {q} outside the buffer ({len(self.buf)} bytes)")
        return q

    def vector(self, slot: int, elem_size: int) -> tuple[int, int]:
        """(position of the first element, element count) of a vector field; (0, 0) if absent."""
        q = self._ref(slot)
        if q < 0:
            return 0, 0
        count = _U32.unpack_from(self.buf, q)[0]
        if q + 4 + count * elem_size > len(self.buf):
            raise FlatbufError(q, f"vector of {count} x {elem_size} bytes runs past the buffer ({len(self.buf)} bytes)")
        return q + 4, count

    def string(self, slot: int, default: str = "") -> str:
        start, count = self.vector(slot, 1)
        if not count:
            return default
        return bytes(self.buf[start:start + count]).decode("utf-8", errors="replace")

    def table(self, slot: int) -> Table | None:
        q = self._ref(slot)
        return None if q < 0 else Table(self.buf, q)


def root(buf, size_prefixed: bool = True) -> tuple[Table, bytes, memoryview]:
    """Parse a (size-prefixed) flatbuffer: (root table, 4-byte file identifier, buffer without the prefix)."""
    mv = memoryview(buf).cast("B")
    if size_prefixed:
        if len(mv) < 4:
            raise FlatbufError(0, f"{len(mv)} bytes: too short for a size prefix")
        n = _U32.unpack_from(mv, 0)[0]
        if n + 4 > len(mv):
            raise FlatbufError(0, f"size prefix {n} runs past the buffer ({len(mv)} bytes)")
        mv = mv[4:4 + n]
    if len(mv) < 8:
        raise FlatbufError(0, f"{len(mv)} bytes: too short for a flatbuffer")
    return Table(mv, _U32.unpack_from(mv, 0)[0]), bytes(mv[4:8]), mv


def gather(u8: np.ndarray, pos: np.ndarray, dtype) -> np.ndarray:
    """Values of `dtype` read at byte positions `pos` (any alignment) of the uint8 array `u8`, vectorised.
    The caller guarantees pos + itemsize <= len(u8)."""
    dt = np.dtype(dtype)
    if len(pos) == 0:
        return np.zeros(0, dt)
    idx = pos[:, None] + np.arange(dt.itemsize, dtype=np.int64)
    return np.ascontiguousarray(u8[idx]).view(dt).reshape(len(pos))


def table_vector(buf, start: int, count: int, fields: dict[str, tuple[int, str]]) -> dict[str, np.ndarray]:
    """Decode a vector of tables (element i is a uoffset at start + 4 i) into one array per field, vectorised.
    `fields` maps name -> (slot, numpy dtype string[, byte offset inside an inline struct field]); absent
    fields read as 0."""
    u8 = np.frombuffer(buf, np.uint8)
    n = len(u8)
    elem = start + 4 * np.arange(count, dtype=np.int64)
    tpos = elem + gather(u8, elem, "<u4").astype(np.int64)
    bad = (tpos + 4 > n)
    if bad.any():
        i = int(np.argmax(bad))
        raise FlatbufError(int(elem[i]), f"element {i}: table position {int(tpos[i])} outside the buffer ({n} bytes)")
    vt = tpos - gather(u8, tpos, "<i4").astype(np.int64)
    bad = (vt < 0) | (vt + 4 > n)
    if bad.any():
        i = int(np.argmax(bad))
        raise FlatbufError(int(tpos[i]), f"element {i}: vtable position {int(vt[i])} outside the buffer")
    if count and (vt == vt[0]).all():
        return _shared_vtable(u8, tpos, int(vt[0]), count, fields)
    vt_size = gather(u8, vt, "<u2").astype(np.int64)
    t_size = gather(u8, vt + 2, "<u2").astype(np.int64)
    bad = (vt_size < 4) | (vt + vt_size > n) | (t_size < 4) | (tpos + t_size > n)
    if bad.any():
        i = int(np.argmax(bad))
        raise FlatbufError(int(vt[i]), f"element {i}: bad vtable ({int(vt_size[i])}) or table size ({int(t_size[i])})")
    out = {}
    for name, spec in fields.items():
        slot, dt, delta = spec[0], np.dtype(spec[1]), (spec[2] if len(spec) > 2 else 0)
        present = vt_size >= 6 + 2 * slot
        off = np.zeros(count, np.int64)
        if present.any():
            off[present] = gather(u8, vt[present] + 4 + 2 * slot, "<u2")
        bad = (off != 0) & ((off < 4) | (off + delta + dt.itemsize > t_size))
        if bad.any():
            i = int(np.argmax(bad))
            raise FlatbufError(int(tpos[i]), f"element {i}: field {slot} offset {int(off[i])} outside its table")
        vals = np.zeros(count, dt)
        has = off != 0
        if has.any():
            vals[has] = gather(u8, (tpos + off + delta)[has], dt)
        out[name] = vals
    return out


def _shared_vtable(u8: np.ndarray, tpos: np.ndarray, vt: int, count: int, fields) -> dict[str, np.ndarray]:
    """table_vector when every element uses the one vtable at `vt` (flatbuffers builders deduplicate vtables,
    so this is the usual case): the layout is read and checked once, then each field is one gather."""
    n = len(u8)
    vt_size, t_size = (int(v) for v in np.frombuffer(u8, "<u2", count=2, offset=vt))
    if vt_size < 4 or vt + vt_size > n or t_size < 4:
        raise FlatbufError(vt, f"bad vtable ({vt_size}) or table size ({t_size})")
    if int(tpos.max()) + t_size > n:
        i = int(np.argmax(tpos + t_size > n))
        raise FlatbufError(int(tpos[i]), f"element {i}: table of {t_size} bytes runs past the buffer ({n} bytes)")
    rows = u8[tpos[:, None] + np.arange(t_size, dtype=np.int64)]     # every table's bytes: one gather
    out = {}
    for name, spec in fields.items():
        slot, dt, delta = spec[0], np.dtype(spec[1]), (spec[2] if len(spec) > 2 else 0)
        off = _U16.unpack_from(u8, vt + 4 + 2 * slot)[0] if vt_size >= 6 + 2 * slot else 0
        if off and (off < 4 or off + delta + dt.itemsize > t_size):
            raise FlatbufError(int(tpos[0]), f"element 0: field {slot} offset {off} outside its table")
        at = off + delta
        out[name] = (np.ascontiguousarray(rows[:, at:at + dt.itemsize]).view(dt).reshape(count) if off
                     else np.zeros(count, dt))
    return out
