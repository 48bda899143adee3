"""Event double integral (EDI, Pan et al. CVPR 2019): sharp latent frames from one blurry frame + its events.

Model (continuous form). Per pixel, let E(t) be the sum of signed threshold steps of the events between the
start of the exposure s and t (an event at t_i contributes +pos_threshold for ON, -neg_threshold for OFF, and
counts for every t >= t_i). Events change log intensity by one threshold, so the sharp latent frame is

    L(t) = L(s) * exp(E(t)),

and the blurry frame is the mean of L over the exposure [s, e]:

    B = L(s) * mean_{t in [s, e]} exp(E(t))   =>   L(t) = B * exp(E(t)) / mean_t exp(E(t)).

E is piecewise constant between a pixel's events, so the mean is computed exactly as a duration-weighted sum
over the pixel's segments (no time discretisation; E2NeRF's `EDI.py` uses the discrete b+1-sample version
I0 = (b+1) B / (1 + sum_k exp(E_k))). Everything is vectorised: the events are sorted by (pixel, time) once
and per-pixel cumulative sums give E after every event.

Input intensities are LINEAR (not sRGB-encoded, not log); decode an 8-bit sRGB frame first (e.g. with
`srgb_to_linear`). Events outside [s, e] are ignored. The log-intensity model is the pure log, so in the
simulator's lin-log region (below ev3dgs.logmap.DEFAULT_LOG_KNEE) it is only approximate.

Numerics: per pixel the exponentials are taken relative to the largest E held for a positive duration
(log-sum-exp), the mean is clamped away from 0 and the final exponent is capped, so the output is finite
for zero-intensity pixels, huge event counts and events that share a timestamp.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError

_MIN_MEAN = 1e-12        # floor of the relative mean exp(E - M) (it is >= 1 us / exposure for integer stamps)
_MAX_EXPONENT = 60.0     # cap of E(t) - M - log(mean): a latent pixel is at most e^60 times the blurry one


def srgb_to_linear(img: np.ndarray) -> np.ndarray:
    """uint8 (or [0, 1] float) sRGB -> linear float64 in [0, 1]."""
    x = np.asarray(img)
    x = x.astype(np.float64) / 255.0 if x.dtype == np.uint8 else np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] float64."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _check(blurry, t, x, y, p, exposure, times):
    b = np.asarray(blurry)
    if b.ndim != 2 or b.size == 0:
        raise InputError(f"blurry must be a non-empty (H, W) linear intensity image, got shape {b.shape}")
    if not np.issubdtype(b.dtype, np.floating):
        raise InputError(f"blurry must be float linear intensity (decode uint8 sRGB first), got {b.dtype}")
    b = b.astype(np.float64)
    if not np.all(np.isfinite(b)) or b.min() < 0:
        raise InputError("blurry must be finite and non-negative")
    t, x, y, p = (np.asarray(a).ravel() for a in (t, x, y, p))
    if not (len(t) == len(x) == len(y) == len(p)):
        raise InputError("events t, x, y and p must have the same length")
    s, e = (float(v) for v in exposure)
    if not e > s:
        raise InputError(f"exposure end must be after its start, got ({s}, {e})")
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if times.ndim != 1 or len(times) == 0:
        raise InputError("times must be a non-empty 1-D array of microseconds")
    if np.any(~np.isfinite(times)) or times.min() < s or times.max() > e:
        raise InputError(f"times must lie inside the exposure [{s}, {e}] us")
    h, w = b.shape
    if len(t):
        if x.min() < 0 or y.min() < 0 or x.max() >= w or y.max() >= h:
            raise InputError(f"event coordinates outside the {w}x{h} frame")
    return b, t.astype(np.float64), x.astype(np.int64), y.astype(np.int64), p, s, e, times


def edi_latent_frames(blurry, t, x, y, p, exposure, times, pos_threshold: float = 0.2,
                      neg_threshold: float = 0.2) -> np.ndarray:
    """Sharp latent frames at `times` (K,) us from a blurry (H, W) LINEAR float frame exposed over
    `exposure` = (start_us, end_us) and its events (t us, x column, y row, p +1/-1 or 1/0 for ON/OFF).
    Returns (K, H, W) float64 linear intensities. With no events every latent frame equals `blurry`."""
    if not (pos_threshold > 0 and neg_threshold > 0):
        raise InputError("pos_threshold and neg_threshold must be > 0")
    b, t, x, y, p, s, e, times = _check(blurry, t, x, y, p, exposure, times)
    h, w = b.shape
    n = h * w
    T = e - s

    keep = (t >= s) & (t <= e)
    t, x, y, p = t[keep], x[keep], y[keep], p[keep]
    step = np.where(p > 0, float(pos_threshold), -float(neg_threshold))
    pix = y * w + x
    order = np.lexsort((t, pix))                     # by pixel, then time
    pix_s, t_s, step_s = pix[order], t[order], step[order]
    m = len(pix_s)

    # per-pixel running sum: E after each event (the segment starting at that event)
    first_dur = np.full(n, T)                        # segment [s, first event) (whole exposure if none)
    max_e = np.zeros(n)                              # M: the largest E held for a positive duration
    if m:
        c = np.cumsum(step_s)
        start = np.r_[True, pix_s[1:] != pix_s[:-1]]
        start_idx = np.flatnonzero(start)
        group = np.cumsum(start) - 1
        e_after = c - (c - step_s)[start_idx][group]
        last = np.r_[pix_s[1:] != pix_s[:-1], True]
        t_next = np.where(last, e, np.r_[t_s[1:], e])
        dur = t_next - t_s
        first_dur[pix_s[start_idx]] = t_s[start_idx] - s
        held = np.where(dur > 0, e_after, -np.inf)
        seg_max = np.maximum.reduceat(held, start_idx)
        gp = pix_s[start_idx]
        max_e[gp] = np.where(first_dur[gp] > 0, np.maximum(seg_max, 0.0), seg_max)
        acc = np.bincount(pix_s, weights=dur * np.exp(np.minimum(e_after - max_e[pix_s], 0.0)), minlength=n)
    else:
        acc = np.zeros(n)
    acc += first_dur * np.exp(np.minimum(-max_e, 0.0))
    log_mean = np.log(np.maximum(acc / T, _MIN_MEAN))   # log mean exp(E - M)

    out = np.empty((len(times), h, w), dtype=np.float64)
    bf = b.ravel()
    for k, tk in enumerate(times):
        sel = t <= tk
        e_k = np.bincount(pix[sel], weights=step[sel], minlength=n) if m else np.zeros(n)
        expo = np.minimum(e_k - max_e - log_mean, _MAX_EXPONENT)
        out[k] = (bf * np.exp(expo)).reshape(h, w)
    return out


def edi_from_events(blurry, events, exposure, times, pos_threshold: float = 0.2,
                    neg_threshold: float = 0.2) -> np.ndarray:
    """`edi_latent_frames` taking an `ev3dgs.events.Events` container."""
    return edi_latent_frames(blurry, events.t, events.x, events.y, events.p, exposure, times,
                             pos_threshold, neg_threshold)


def edi_to_uint8(latent, gamma: bool = True, percentile: float = 99.5) -> np.ndarray:
    """Linear latent frame(s) (H, W) or (K, H, W) -> uint8 for SIFT/COLMAP. One robust white point for all
    frames (the `percentile` of the finite values, so brightness stays consistent across a sequence), clip
    to [0, 1], then sRGB-encode when `gamma` (else linear)."""
    a = np.asarray(latent, dtype=np.float64)
    finite = np.isfinite(a)
    a = np.where(finite, a, 0.0)
    white = float(np.percentile(a[finite], percentile)) if finite.any() else 0.0
    x = np.clip(a / white, 0.0, 1.0) if white > 0 else np.zeros_like(a)
    if gamma:
        x = linear_to_srgb(x)
    return np.round(x * 255.0).astype(np.uint8)
