"""Write a large tensor as a torch.save file without holding it in memory.

torch.save needs the whole tensor in memory (E2NeRF's 100-view events.pt is 2 GB of float64), and even its
`skip_data()` mode writes a placeholder of the full size. A torch.save file is a zip archive (STORED, no
compression) with, under one folder:
  data.pkl                 a protocol-2 pickle of torch._utils._rebuild_tensor_v2(storage, offset, size,
                           stride, requires_grad, backward_hooks), the storage given as the persistent id
                           ("storage", <dtype>Storage, key, location, numel)
  data/<key>               the storage's raw little-endian bytes, 64-byte aligned in the archive
  byteorder, version, .format_version, .storage_alignment, .data/serialization_id   small metadata
We take the metadata members from torch.save of a one-element tensor (so they are whatever this torch writes),
pickle data.pkl ourselves for the real shape (a test checks it equals torch's own bytes), and stream data/0
from row blocks through zipfile (CRC computed as it goes). `torch.load` (weights_only, mmap or not) reads the
result like a file torch.save wrote.
"""
from __future__ import annotations

import collections
import io
import pickle
import struct
import zipfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

_ALIGN = 64                 # torch's data record alignment (its .storage_alignment member)
_PAD_ID = 0x4246            # extra-field id of the alignment padding (the id torch's writer uses)
_ZIP64_LOCAL_EXTRA = 20     # zipfile adds this zip64 extra field to a local header with force_zip64


# numpy dtype -> (torch dtype name, the legacy storage class torch pickles for it)
_STORAGES = {np.float64: ("float64", "DoubleStorage"), np.float32: ("float32", "FloatStorage"),
             np.int8: ("int8", "CharStorage"), np.int16: ("int16", "ShortStorage"), np.int32: ("int32", "IntStorage"),
             np.int64: ("int64", "LongStorage"), np.uint8: ("uint8", "ByteStorage")}


def _storage(dtype) -> tuple[str, str]:
    try:
        return _STORAGES[np.dtype(dtype).type]
    except KeyError:
        raise ValueError(f"unsupported dtype {np.dtype(dtype)}") from None


def _torch_dtype(dtype):
    import torch

    return getattr(torch, _storage(dtype)[0])


class _Storage:
    """Stands for the tensor's storage in the pickle (written as a persistent id)."""


class _Tensor:
    def __init__(self, storage: _Storage, shape: tuple[int, ...]) -> None:
        self.storage, self.shape = storage, shape

    def __reduce__(self):
        from torch._utils import _rebuild_tensor_v2

        stride = tuple(int(np.prod(self.shape[i + 1:], dtype=np.int64)) for i in range(len(self.shape)))
        return _rebuild_tensor_v2, (self.storage, 0, self.shape, stride, False, collections.OrderedDict())


def tensor_pickle(shape: tuple[int, ...], dtype) -> bytes:
    """data.pkl of a contiguous CPU tensor of `shape`/`dtype` whose storage is record "0"."""
    import torch

    storage_type = getattr(torch, _storage(dtype)[1])
    numel = int(np.prod(shape, dtype=np.int64))
    st = _Storage()

    class _Pickler(pickle.Pickler):
        def persistent_id(self, obj):
            return ("storage", storage_type, "0", "cpu", numel) if obj is st else None

    buf = io.BytesIO()
    _Pickler(buf, protocol=2).dump(_Tensor(st, tuple(int(s) for s in shape)))
    return buf.getvalue()


def _metadata(dtype) -> tuple[str, list[tuple[zipfile.ZipInfo, bytes]]]:
    """(archive folder, small members) from torch.save of a one-element tensor of `dtype`."""
    import torch

    buf = io.BytesIO()
    torch.save(torch.zeros(1, dtype=_torch_dtype(dtype)), buf)
    z = zipfile.ZipFile(io.BytesIO(buf.getvalue()))
    pkl = [i.filename for i in z.infolist() if i.filename.endswith("/data.pkl")]
    if len(pkl) != 1:
        raise RuntimeError(f"unexpected torch.save layout: {z.namelist()}")
    root = pkl[0][:-len("data.pkl")]
    keep = [(i, z.read(i.filename)) for i in z.infolist()
            if i.filename != pkl[0] and not i.filename.startswith(root + "data/")]
    return root, keep


def save_streamed(path: str | Path, shape: tuple[int, ...], dtype, blocks: Iterable[np.ndarray]) -> int:
    """Write a tensor of `shape` and `dtype` to `path` (torch.save format) from C-order row blocks along the
    first axis (each (k, *shape[1:]), together exactly shape[0] rows). Returns the bytes of tensor data."""
    shape = tuple(int(s) for s in shape)
    dtype = np.dtype(dtype)
    root, meta = _metadata(dtype)
    rows = 0
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        z.writestr(zipfile.ZipInfo(root + "data.pkl", date_time=(1980, 1, 1, 0, 0, 0)), tensor_pickle(shape, dtype))
        for info, data in meta:
            if info.filename.endswith("/byteorder") or info.filename.endswith("/.format_version"):
                z.writestr(info, data)
        zi = zipfile.ZipInfo(root + "data/0", date_time=(1980, 1, 1, 0, 0, 0))
        zi.compress_type = zipfile.ZIP_STORED
        start = z.fp.tell() + 30 + len(zi.filename.encode("utf-8")) + _ZIP64_LOCAL_EXTRA + 4
        pad = (-start) % _ALIGN
        zi.extra = struct.pack("<HH", _PAD_ID, pad) + bytes(pad)
        with z.open(zi, "w", force_zip64=True) as fh:
            for block in blocks:
                b = np.ascontiguousarray(block, dtype=dtype.newbyteorder("<"))
                if b.shape[1:] != shape[1:]:
                    raise ValueError(f"block shape {b.shape} does not match rows of {shape}")
                rows += len(b)
                if rows > shape[0]:
                    raise ValueError(f"more than {shape[0]} rows")
                fh.write(memoryview(b).cast("B"))
        if rows != shape[0]:
            raise ValueError(f"{rows} rows written, {shape[0]} expected")
        for info, data in meta:
            if not (info.filename.endswith("/byteorder") or info.filename.endswith("/.format_version")):
                z.writestr(info, data)
    return int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
