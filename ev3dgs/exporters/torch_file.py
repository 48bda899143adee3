"""Write a large tensor as a torch.save file without holding it in memory.

torch.save needs the whole tensor in memory (E2NeRF's 100-view events.pt is 2 GB of float64). Instead:
torch itself writes the file's skeleton with `torch.serialization.skip_data()` (the pickle that describes the
tensor: dtype, shape, strides, storage key; no bytes), from an uninitialised `torch.empty` whose pages are
never touched; we copy every member of that skeleton into a new zip archive and stream the storage record
(STORED, uncompressed, 64-byte aligned like torch's own writer, CRC computed by zipfile as it goes) from an
iterator of row blocks. The result is an ordinary torch zip file: `torch.load` (weights_only, mmap or not)
reads it like one torch.save wrote.
"""
from __future__ import annotations

import io
import struct
import zipfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

_ALIGN = 64                 # torch's data record alignment (its .storage_alignment member)
_PAD_ID = 0x4246            # extra-field id of the padding ("FB", as torch's writer uses)
_ZIP64_LOCAL_EXTRA = 20     # zipfile adds this zip64 extra field to a local header with force_zip64


def _skeleton(shape: tuple[int, ...], dtype) -> zipfile.ZipFile:
    import torch

    tdtype = {np.dtype(np.float64): torch.float64, np.dtype(np.float32): torch.float32,
              np.dtype(np.int8): torch.int8, np.dtype(np.int16): torch.int16}[np.dtype(dtype)]
    buf = io.BytesIO()
    with torch.serialization.skip_data():
        torch.save(torch.empty(shape, dtype=tdtype), buf)
    buf.seek(0)
    return zipfile.ZipFile(buf)


def save_streamed(path: str | Path, shape: tuple[int, ...], dtype, blocks: Iterable[np.ndarray]) -> int:
    """Write a tensor of `shape` and `dtype` to `path` (torch.save format) from C-order row blocks along the
    first axis (each (k, *shape[1:]), together exactly shape[0] rows). Returns the bytes of tensor data."""
    shape = tuple(int(s) for s in shape)
    dtype = np.dtype(dtype)
    row = shape[1:]
    skel = _skeleton(shape, dtype)
    data_members = [i for i in skel.infolist() if "/data/" in i.filename and "/.data/" not in i.filename]
    if len(data_members) != 1:
        raise RuntimeError(f"unexpected torch.save layout: {[i.filename for i in skel.infolist()]}")
    rows = 0
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for info in skel.infolist():
            if info is not data_members[0]:
                z.writestr(info, skel.read(info.filename))
                continue
            zi = zipfile.ZipInfo(info.filename, date_time=info.date_time)
            zi.compress_type = zipfile.ZIP_STORED
            name_len = len(zi.filename.encode("utf-8"))
            start = z.fp.tell() + 30 + name_len + _ZIP64_LOCAL_EXTRA + 4
            pad = (-start) % _ALIGN
            zi.extra = struct.pack("<HH", _PAD_ID, pad) + bytes(pad)
            with z.open(zi, "w", force_zip64=True) as fh:
                for block in blocks:
                    b = np.ascontiguousarray(block, dtype=dtype.newbyteorder("<"))
                    if b.shape[1:] != row:
                        raise ValueError(f"block shape {b.shape} does not match rows of {shape}")
                    rows += len(b)
                    if rows > shape[0]:
                        raise ValueError(f"more than {shape[0]} rows")
                    fh.write(memoryview(b).cast("B"))
            if rows != shape[0]:
                raise ValueError(f"{rows} rows written, {shape[0]} expected")
    return int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
