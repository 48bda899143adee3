"""Plausibility of a recording's APS exposure times, checked when calibrate and compare load it.

A frame's exposure window [exposure_start, exposure_end] decides which events fall between two frames, so a
damaged window silently skews every fitted rate (a frame "exposed" for an hour in a 0.6 s recording turns the
leak rate into microhertz). Impossible windows are refused with one line (InputError, exit 2):
  * an exposure that ends before it starts (or has zero length),
  * an exposure longer than the whole recording (the span of all exposure midpoints and events),
  * two frames whose exposures overlap (one sensor exposes and reads out one frame at a time).
Merely suspicious ones give one warning each: an exposure longer than the median interval between frames, or
more than SUSPICIOUS_FACTOR times the median exposure.
"""
from __future__ import annotations

import warnings

import numpy as np

from ..errors import InputError

SUSPICIOUS_FACTOR = 10.0


def check_exposures(path, start: np.ndarray, end: np.ndarray, events_t: np.ndarray) -> None:
    """start, end: (F,) exposure window of each frame (us, file order); events_t: every event time (us)."""
    start, end = np.asarray(start, np.int64), np.asarray(end, np.int64)
    if not len(start):
        return
    bad = np.flatnonzero(end <= start)
    if bad.size:
        i = int(bad[0])
        raise InputError(f"{path}: frame {i} has no exposure window (start {start[i]}, end {end[i]}: it ends "
                         "before it starts): events cannot be assigned to frame pairs")
    expo = end - start
    mid = (start + end) // 2
    lo, hi = int(mid.min()), int(mid.max())
    if len(events_t):
        lo, hi = min(lo, int(np.min(events_t))), max(hi, int(np.max(events_t)))
    span = hi - lo
    i = int(np.argmax(expo))
    if expo[i] > span:
        raise InputError(f"{path}: frame {i} is exposed for {expo[i] * 1e-6:.6g} s, longer than the whole "
                         f"recording ({span * 1e-6:.6g} s of frames and events): its exposure times are damaged")
    order = np.argsort(start, kind="stable")
    s, e = start[order], end[order]
    over = np.flatnonzero(e[:-1] > s[1:])
    if over.size:
        a, b = int(order[over[0]]), int(order[over[0] + 1])
        raise InputError(f"{path}: the exposures of frames {a} ({s[over[0]]}..{e[over[0]]} us) and {b} "
                         f"({s[over[0] + 1]}..{e[over[0] + 1]} us) overlap: one sensor exposes one frame at a time")
    if len(start) > 1:
        interval = float(np.median(np.diff(np.sort(mid))))
        typical = float(np.median(expo))
        long_ = np.flatnonzero((expo > interval) | (expo > SUSPICIOUS_FACTOR * typical))
        if long_.size:
            j = int(long_[np.argmax(expo[long_])])
            warnings.warn(f"{path}: {long_.size} frame(s) exposed longer than the median frame interval "
                          f"({interval * 1e-3:.3g} ms) or {SUSPICIOUS_FACTOR:g}x the median exposure "
                          f"({typical * 1e-3:.3g} ms), e.g. frame {j} ({expo[j] * 1e-3:.3g} ms): check its times")
