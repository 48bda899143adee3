"""The event stream container shared by the simulator, the readers and the schema."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Events:
    """Events sorted by time: t int64 microseconds, x/y uint16 pixel (row 0 at the top), p int8 +1/-1."""

    t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    x: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))
    y: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))
    p: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.int64)
        self.x = np.asarray(self.x, dtype=np.uint16)
        self.y = np.asarray(self.y, dtype=np.uint16)
        self.p = np.asarray(self.p, dtype=np.int8)
        n = len(self.t)
        if not (len(self.x) == len(self.y) == len(self.p) == n):
            raise ValueError("t, x, y and p must have the same length")

    def __len__(self) -> int:
        return len(self.t)

    @staticmethod
    def concatenate(parts: list[Events]) -> Events:
        if not parts:
            return Events()
        return Events(
            np.concatenate([e.t for e in parts]),
            np.concatenate([e.x for e in parts]),
            np.concatenate([e.y for e in parts]),
            np.concatenate([e.p for e in parts]),
        )

    def window(self, start_us: int, end_us: int) -> Events:
        """Events with start <= t < end (binary search on the sorted timestamps)."""
        i, j = np.searchsorted(self.t, [start_us, end_us], side="left")
        return Events(self.t[i:j], self.x[i:j], self.y[i:j], self.p[i:j])

    @property
    def on_count(self) -> int:
        return int(np.count_nonzero(self.p > 0))

    @property
    def off_count(self) -> int:
        return int(np.count_nonzero(self.p < 0))
