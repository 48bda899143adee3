"""Event supervision inputs: sub-pose times inside an exposure, event bins between them (ON and OFF counted
separately: ``bin_polarity_events``; net signed: ``bin_signed_events``), cumulative counts at each pose, pose
pairs and their observed counts.

Why ON and OFF are kept apart: with thresholds theta_on != theta_off a pixel that goes up by u and back down
by v inside one bin fires ~u/theta_on ON and ~v/theta_off OFF events; its net count (ON - OFF) times either
threshold is not the net log change u - v, whereas theta_on * n_on - theta_off * n_off is (up to the residual
within one threshold). On the demo scene a third of the events cancel inside a bin.

Nothing here modifies its inputs. The published Ev3DGS took ``event_data[start].view(H, W)`` and then
``+=``-ed later bins into it, so every call silently corrupted the stored event tensor; here every result is
a freshly allocated array/tensor (bins from ``np.bincount``, pair targets as differences of a cumulative
sum), and the tests check that inputs are unchanged.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

# Events handled per bincount call inside one view's window; bounds the temporary index/weight arrays.
_CHUNK = 1 << 22


def sub_pose_times(exposure: np.ndarray, n_poses: int) -> np.ndarray:
    """(N, 2) int64 [start, end] exposures -> (N, n_poses) int64 times spread evenly over [start, end],
    both ends included: start + round(k * (end - start) / (n_poses - 1)). One pose -> the midpoint."""
    n_poses = int(n_poses)
    if n_poses < 1:
        raise ValueError(f"n_poses must be >= 1, got {n_poses}")
    exp = np.asarray(exposure, dtype=np.int64)
    if exp.ndim != 2 or exp.shape[1] != 2:
        raise ValueError(f"exposure must have shape (N, 2), got {exp.shape}")
    start, end = exp[:, :1], exp[:, 1:]
    span = end - start
    if n_poses == 1:
        # start + round(span / 2), in integer arithmetic (half rounds to even like np.rint).
        return (start + np.rint(span / 2.0).astype(np.int64)).astype(np.int64)
    k = np.arange(n_poses, dtype=np.int64)[None, :]
    offs = np.rint(k * span / float(n_poses - 1)).astype(np.int64)
    out = start + offs
    out[:, -1:] = end  # exact end even for huge spans where the float division could be off by one
    return out.astype(np.int64)


def _checked(t, x, y, p, times):
    """The binning functions' inputs as arrays, validated (never copied when already arrays, never written)."""
    times = np.asarray(times, dtype=np.int64)
    if times.ndim != 2 or times.shape[1] < 2:
        raise ValueError(f"times must have shape (N, K) with K >= 2, got {times.shape}")
    if np.any(np.diff(times, axis=1) < 0):
        raise ValueError("times must be non-decreasing along each view")
    t, x, y, p = (np.asarray(a) for a in (t, x, y, p))
    if not (len(t) == len(x) == len(y) == len(p)):
        raise ValueError("t, x, y and p must have the same length")
    return t, x, y, p, times


def _view_chunks(t, x, y, p, times, height: int, width: int):
    """Yield (v, b, pix, p) per chunk of each view's events: b the sub-pose bin of each event (last bin
    closed), pix = y * width + x, p its polarities. Per view a binary search finds the window; chunks of
    _CHUNK events keep memory bounded."""
    if len(t) == 0:
        return
    n_bins = times.shape[1] - 1
    lo = np.searchsorted(t, times[:, 0], side="left")
    hi = np.searchsorted(t, times[:, -1], side="right")
    for v, row in enumerate(times):
        for i in range(int(lo[v]), int(hi[v]), _CHUNK):
            j = min(i + _CHUNK, int(hi[v]))
            xs = x[i:j].astype(np.int64)
            ys = y[i:j].astype(np.int64)
            if xs.size and (xs.max() >= width or ys.max() >= height or xs.min() < 0 or ys.min() < 0):
                raise ValueError(f"event coordinates outside a {width}x{height} sensor")
            b = np.searchsorted(row, t[i:j], side="right") - 1
            np.clip(b, 0, n_bins - 1, out=b)  # t == times[v, K-1] -> last bin
            yield v, b, ys * width + xs, p[i:j]


def bin_signed_events(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, times: np.ndarray,
                      height: int, width: int) -> np.ndarray:
    """Signed event counts between consecutive sub-pose times.

    t must be sorted (int64 us); times is (N, K) int64, non-decreasing along each row, K >= 2. Returns a new
    (N, K-1, H, W) float32 array whose [v, k] entry sums p over events with times[v,k] <= t < times[v,k+1];
    the last bin of each view is closed (t <= times[v, K-1]) so an event exactly at the exposure end counts.
    Vectorised per view (binary search for the window, bincount on flattened (bin, y, x) indices), in chunks,
    so memory stays bounded for very long streams. Inputs are never written to.
    """
    t, x, y, p, times = _checked(t, x, y, p, times)
    height, width = int(height), int(width)
    n_views, n_bins, plane = len(times), times.shape[1] - 1, height * width
    # counts are integers far below 2^24: float32 accumulation is exact
    out = np.zeros((n_views, n_bins * plane), dtype=np.float32)
    for v, b, pix, ps in _view_chunks(t, x, y, p, times, height, width):
        out[v] += np.bincount(b * plane + pix, weights=ps.astype(np.float64), minlength=n_bins * plane)
    return out.reshape(n_views, n_bins, height, width)


def bin_polarity_events(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, times: np.ndarray,
                        height: int, width: int) -> np.ndarray:
    """ON and OFF event counts between consecutive sub-pose times: a new (N, K-1, 2, H, W) float32 array,
    [v, k, 0] = number of ON events (p > 0) and [v, k, 1] = number of OFF events (p < 0, a positive number)
    with times[v,k] <= t < times[v,k+1] (last bin closed), so ``out[:, :, 0] - out[:, :, 1]`` is
    ``bin_signed_events``. Same windows, validation and chunked bincount as ``bin_signed_events``; the inputs
    are never written to."""
    t, x, y, p, times = _checked(t, x, y, p, times)
    height, width = int(height), int(width)
    n_views, n_bins, plane = len(times), times.shape[1] - 1, height * width
    out = np.zeros((n_views, n_bins * 2 * plane), dtype=np.float32)  # integer counts < 2^24: exact
    for v, b, pix, ps in _view_chunks(t, x, y, p, times, height, width):
        off = (ps < 0).astype(np.int64)  # polarity plane: 0 = ON, 1 = OFF
        out[v] += np.bincount((b * 2 + off) * plane + pix, minlength=n_bins * 2 * plane)
    return out.reshape(n_views, n_bins, 2, height, width)


def pose_counts(bins: torch.Tensor) -> torch.Tensor:
    """(K-1, 2, H, W) ON/OFF bins of one view -> new (K, 2, H, W) cumulative counts since the first pose:
    [k] = events between pose 0 and pose k (so [0] is zero). ``bins`` is not modified."""
    bins = torch.as_tensor(bins)
    if bins.ndim != 4 or bins.shape[1] != 2:
        raise ValueError(f"bins must have shape (K-1, 2, H, W), got {tuple(bins.shape)}")
    return torch.cat([bins.new_zeros((1,) + tuple(bins.shape[1:])), torch.cumsum(bins, dim=0)], dim=0)


def pair_list(n_poses: int, mode: str | int = "all",
              generator: torch.Generator | None = None) -> list[tuple[int, int]]:
    """All pairs (k1 < k2) of range(n_poses) in lexicographic order ("all"), or ``mode`` (an int) distinct
    pairs drawn at random with ``generator`` (deterministic given its state)."""
    n_poses = int(n_poses)
    if n_poses < 1:
        raise ValueError(f"n_poses must be >= 1, got {n_poses}")
    every = [(a, b) for a in range(n_poses) for b in range(a + 1, n_poses)]
    if isinstance(mode, str):
        if mode != "all":
            raise ValueError(f"pair mode must be 'all' or an int, got {mode!r}")
        return every
    if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)):
        raise ValueError(f"pair mode must be 'all' or an int, got {mode!r}")
    count = int(mode)
    if count < 0 or count > len(every):
        raise ValueError(f"cannot draw {count} distinct pairs from {len(every)} for {n_poses} poses")
    order = torch.randperm(len(every), generator=generator)[:count].tolist()
    return [every[i] for i in order]


def pair_targets(bins: torch.Tensor, pairs: Sequence[tuple[int, int]]) -> torch.Tensor:
    """(K-1, H, W) signed bins (or (K-1, 2, H, W) ON/OFF bins) -> (P, H, W) (or (P, 2, H, W)) new tensor: for
    pair (k1, k2) the count between poses k1 and k2, bins[k1:k2].sum(0), via prefix sums (prefix[k2] -
    prefix[k1]). ``bins`` is not modified."""
    bins = torch.as_tensor(bins)
    if bins.ndim not in (3, 4):
        raise ValueError(f"bins must have shape (K-1, H, W) or (K-1, 2, H, W), got {tuple(bins.shape)}")
    n_poses = bins.shape[0] + 1
    if len(pairs) == 0:
        return bins.new_zeros((0,) + tuple(bins.shape[1:]))
    idx = torch.as_tensor([tuple(pr) for pr in pairs], dtype=torch.long)
    k1, k2 = idx[:, 0], idx[:, 1]
    if bool((k1 < 0).any() or (k2 >= n_poses).any() or (k1 >= k2).any()):
        raise ValueError(f"pairs must satisfy 0 <= k1 < k2 < {n_poses}")
    prefix = torch.cat([bins.new_zeros((1,) + tuple(bins.shape[1:])), torch.cumsum(bins, dim=0)], dim=0)
    return prefix[k2] - prefix[k1]
