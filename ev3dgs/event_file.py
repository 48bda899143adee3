"""The events of a scene file read straight from `/events/*`, never loaded whole: consecutive blocks (the
exporters), a time window found by binary search in /events/t (the viewer), and searchsorted over the whole
stream. The file is opened once; use as a context manager."""
from __future__ import annotations

import bisect
import os
from collections.abc import Iterator

import h5py
import numpy as np

from .events import Events
from .schema import SchemaError

CHUNK = 1 << 20          # events per block (13 MiB as t, x, y, p)
CACHE = 64 << 20         # HDF5 chunk cache: a binary search decompresses each chunk once


class EventFile:
    def __init__(self, path: str | os.PathLike, chunk: int = CHUNK) -> None:
        self.path = str(path)
        self.chunk = int(chunk)
        try:
            self._f = h5py.File(self.path, "r", rdcc_nbytes=CACHE)
        except OSError as e:
            from .schema import not_a_scene

            raise SchemaError(not_a_scene(self.path, e)) from None
        self._ds = {n: self._f[f"/events/{n}"] for n in ("t", "x", "y", "p")}
        self.n = int(self._ds["t"].shape[0])

    def __enter__(self) -> EventFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    def __len__(self) -> int:
        return self.n

    def read(self, i: int, j: int) -> Events:
        return Events(*(self._ds[n][i:j] for n in ("t", "x", "y", "p")))

    def blocks(self, i: int = 0, j: int | None = None) -> Iterator[Events]:
        """Events i..j-1 (default all) as consecutive Events of at most `chunk` rows."""
        j = self.n if j is None else j
        for a in range(i, j, self.chunk):
            yield self.read(a, min(a + self.chunk, j))

    def searchsorted(self, values, side: str = "left") -> np.ndarray:
        """np.searchsorted(t, values, side) over the whole stream in one pass over t: on sorted t the global
        index is the sum over blocks of the per-block counts."""
        v = np.asarray(values, dtype=np.int64)
        out = np.zeros(v.shape, dtype=np.int64)
        ds = self._ds["t"]
        for a in range(0, self.n, self.chunk):
            out += np.searchsorted(ds[a:a + self.chunk], v, side=side)
        return out

    def _index(self, t: int) -> int:
        ds = self._ds["t"]

        class _T:  # bisect over the dataset without reading it whole
            def __len__(_):
                return self.n

            def __getitem__(_, i):
                return int(ds[i])

        return bisect.bisect_left(_T(), int(t))

    def window(self, start_us: int, end_us: int):
        """Events with start <= t < end, as (t, x, y, p) numpy arrays (binary search: O(log n) reads)."""
        e = self.read(self._index(start_us), self._index(end_us))
        return e.t, e.x, e.y, e.p
