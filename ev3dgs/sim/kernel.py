"""The change-detector kernel: threshold crossings with per-pixel timestamps, compiled with numba.

Between two consecutive frames each pixel's (filtered) log intensity is taken to move linearly, as in ESIM.
The detector watches d(s) = L(s) - ref(s) for s in [0, 1] across the interval, where ref drifts down by
`drift` over the interval when leak is on. d is linear in s, so every crossing time is exact for that model:

* d reaches +C_on  -> ON event at that instant; ref += C_on (whole thresholds: the residual carries on)
* d reaches -C_off -> OFF event; ref -= C_off
* a shot-noise event at its sampled instant resets the pixel: ref = L (d = 0)

Refractory semantics (chosen to follow the pixel circuit, as IEBCS does): after any event the pixel is held
in reset for `refractory_us`; while held, ref follows the input, so the change that happens during the
refractory period is lost, and at release ref = L(release). Events (signal or noise) cannot occur while held.
This differs from v2e (the blocked change is kept and fires later) and ESIM (drop the event, but the
reference still advances by a threshold).

Exact thresholds: a change that lands on a threshold to within TOL (1e-6 log units) fires, in the screen and
in the crossing count alike. Without it, floating-point error in d = L - ref lost the last event of a pixel
that rose and came back exactly (14-19% of such pixels) and a log step of exactly 5 thresholds gave 4 events.
1e-6 covers the rounding of float32 logs (ulp/2 <= 5e-7 for |log I| < 8); v2e rounds its logs to 1e-8 for
the same reason. An event found only thanks to TOL is stamped at the interval end (its time is clamped to 1).
"""
from __future__ import annotations

import numpy as np
from numba import njit

EMPTY_F8 = np.zeros(0, np.float64)
EMPTY_I8 = np.zeros(0, np.int64)
EMPTY_I1 = np.zeros(0, np.int8)
NEVER = -1e300  # blocked_until of a pixel that was never blocked
TOL = 1e-6      # a change within TOL of a threshold crosses it (log units)


@njit(cache=True, nogil=True)
def crossings(
    cand, width, L0, L1, ref, c_on, c_off, inv_c_min, drift, blocked_until, t0, dt, refractory_us,
    noise_pix, noise_s, noise_p, out_t, out_x, out_y, out_p, start, n, k,
):
    """Emit one interval's events for the candidate pixels cand[start:], appending at out[n].

    cand: ascending flat pixel indices (row-major) that may fire: past a threshold at the interval end,
    with noise events, or held by the refractory period. width: the sensor width (for x, y). Every other pixel emits nothing and its reference
    is already final. L0, L1: (P,) signal at the interval ends. ref: (P,) reference at the interval *end*
    (already lowered by `drift` when leak is on), updated in place. c_on, c_off: (P,) thresholds, inv_c_min
    1 / their minimum.
    drift: (P,) how far each reference fell over the interval, or empty. blocked_until: (P,) absolute us,
    or empty when the refractory period is off. noise_pix (ascending, all in cand), noise_s (fractions in
    [0, 1), ascending within a pixel), noise_p: shot-noise events, or empty; k is the cursor into them.
    out_t gets whole-microsecond offsets from t0 (rounded to nearest).

    Returns (n, stop, k): stop == len(cand) when done; otherwise the buffers might overflow at cand[stop]
    (not yet touched) and the caller grows them and calls again from there. (Growing inside the kernel
    rebinds the arrays in the loop, which made numba's emission loop several times slower.)
    """
    has_drift = drift.shape[0] > 0
    has_refr = refractory_us > 0.0
    n_noise = noise_pix.shape[0]
    inv_dt = 1.0 / dt
    dt_int = np.int64(np.floor(dt + 0.5))
    inv_width = 1.0 / width
    refr_s = refractory_us * inv_dt
    cap = out_t.shape[0]
    for ci in range(start, cand.shape[0]):
        i = cand[ci]
        a = L0[i]
        b = L1[i]
        cp = c_on[i]
        cn = c_off[i]
        lk = drift[i] if has_drift else 0.0
        g = (b - a) + lk            # slope of d = L - ref over the interval (ref falls by lk)
        d = a - (ref[i] + lk)       # d at the interval start
        k_end = k
        while k_end < n_noise and noise_pix[k_end] == i:
            k_end += 1
        # every signal event but the first needs a full threshold of travel since the last event/reset
        if n + (k_end - k) + 2 + abs(g) * inv_c_min > cap:
            return n, ci, k
        # y = i // width by a float multiply: exact here ((i + 0.5) / width stays >= 0.5 / 65535 away from
        # an integer, far above float64 rounding for i < 2**32); integer division cost more than the rest
        row = np.int64((i + 0.5) * inv_width)
        col = i - row * width
        s = 0.0
        if has_refr and blocked_until[i] > t0:
            rel = (blocked_until[i] - t0) * inv_dt
            if rel >= 1.0:          # held for the whole interval: ref follows the input
                ref[i] = b
                k = k_end
                continue
            s = rel
            d = 0.0
            while k < k_end and noise_s[k] < s:
                k += 1
        d_end = d + g * (1.0 - s)
        if k == k_end and not has_refr:      # only signal crossings: closed form, s_j = (j*C - d) / g
            up = d_end > 0.0                 # selects, not branches: ON/OFF is a coin flip per pixel
            step = cp if up else -cn
            pol = 1 if up else -1
            m = np.int64(np.floor((d_end + pol * TOL) / step))
            inv_g = 1.0 / g if g != 0.0 else 0.0
            n0 = n
            for j in range(1, m + 1):
                out_t[n] = np.int64(np.floor((j * step - d) * inv_g * dt + 0.5))
                out_x[n] = col
                out_y[n] = row
                out_p[n] = pol
                n += 1
            if m > 0:  # only the last event can lie past the end (by TOL / g) and the first before the
                # start (never, barring rounding); clamping there keeps the loop as fast as before
                out_t[n - 1] = min(out_t[n - 1], dt_int)
                out_t[n0] = max(out_t[n0], 0)
            ref[i] = b - (d_end - m * step)
            continue
        held = False
        while True:
            # time of the next threshold crossing of d from (s, d) with slope g
            # (an event within TOL of the threshold at the interval end fires there)
            sc = 2.0
            if g > 0.0:
                need = cp - d
                if need - TOL <= g * (1.0 - s):
                    sc = min(s + need / g, 1.0) if need > 0.0 else s
            elif g < 0.0:
                need = -cn - d
                if need + TOL >= g * (1.0 - s):
                    sc = min(s + need / g, 1.0) if need < 0.0 else s
            sn = noise_s[k] if k < k_end else 2.0
            if sc > 1.0 and sn > 1.0:
                break
            if sc <= sn:
                se = sc
                if g > 0.0:
                    out_p[n] = 1
                    d = d + g * (se - s) - cp
                else:
                    out_p[n] = -1
                    d = d + g * (se - s) + cn
            else:
                se = sn
                out_p[n] = noise_p[k]
                k += 1
                d = 0.0
            out_t[n] = np.int64(np.floor(se * dt + 0.5))
            out_x[n] = col
            out_y[n] = row
            n += 1
            s = se
            if has_refr:
                blocked_until[i] = t0 + se * dt + refractory_us
                if se + refr_s >= 1.0:
                    held = True
                    break
                s = se + refr_s
                d = 0.0
                while k < k_end and noise_s[k] < s:
                    k += 1
        k = k_end
        if held:
            ref[i] = b
        else:
            ref[i] = b - (d + g * (1.0 - s))  # the (drifted) reference at the interval end
    return n, cand.shape[0], k


@njit(cache=True, nogil=True)
def sort_interval(offs, x, y, p, n, t0, dt):
    """Order one interval's events by time, ties by pixel index (they were emitted in pixel order).

    A stable counting sort over the dt+1 possible microsecond offsets: O(n + dt), no comparison sort;
    a stable merge sort only when the interval is much longer than its event count."""
    t_out = np.empty(n, np.int64)
    x_out = np.empty(n, np.uint16)
    y_out = np.empty(n, np.uint16)
    p_out = np.empty(n, np.int8)
    nb = np.int64(dt) + 1
    if nb <= 4 * n + 4096:
        count = np.zeros(nb + 1, np.int64)
        for j in range(n):
            count[offs[j] + 1] += 1
        for b in range(nb):
            count[b + 1] += count[b]
        for j in range(n):
            o = offs[j]
            dst = count[o]
            count[o] += 1
            t_out[dst] = t0 + o
            x_out[dst] = x[j]
            y_out[dst] = y[j]
            p_out[dst] = p[j]
    else:
        order = np.argsort(offs[:n], kind="mergesort")
        for dst in range(n):
            j = order[dst]
            t_out[dst] = t0 + offs[j]
            x_out[dst] = x[j]
            y_out[dst] = y[j]
            p_out[dst] = p[j]
    return t_out, x_out, y_out, p_out


@njit(cache=True, nogil=True)
def screen(L1, ref, c_on, c_off, blocked_until, t0, noise_pix, cand):
    """Compact the pixels that may fire (past a threshold at the interval end, held by the refractory
    period, or with shot-noise events) into cand, ascending; returns their count. Branch-free on the
    threshold test: about a fifth of the pixels fire, at random, and a branch there mispredicted so often
    that the loop ran 4x slower."""
    nc = 0
    has_refr = blocked_until.shape[0] > 0
    n_noise = noise_pix.shape[0]
    kn = 0
    next_noisy = noise_pix[0] if n_noise > 0 else -1
    for i in range(L1.shape[0]):
        d = L1[i] - ref[i]
        hit = (d >= c_on[i] - TOL) | (d <= TOL - c_off[i])
        if has_refr:
            hit |= blocked_until[i] > t0
        if i == next_noisy:  # rare: noise events are sparse
            hit = True
            while kn < n_noise and noise_pix[kn] == i:
                kn += 1
            next_noisy = noise_pix[kn] if kn < n_noise else -1
        cand[nc] = i
        nc += hit
    return nc


@njit(cache=True, nogil=True)
def start_references(undecided, n_und, L0, L1, drift, ref, c_on, c_off, phase, noise_pix):
    """Random-phase start (DVSConfig.reference = "random"): for each still undecided pixel (undecided[:n_und],
    ascending; its ref equals L0) that moves in this interval, put its reference u * C_on below L0 if the
    move is up, (1 - u) * C_off above if down (u = phase). Pixels with a noise event keep ref = L0 (the
    noise resets them anyway). Compacts the pixels that stay undecided (no move, no noise) to the front of
    `undecided` and returns their count."""
    has_drift = drift.shape[0] > 0
    n_noise = noise_pix.shape[0]
    kn = 0
    keep = 0
    for j in range(n_und):
        i = undecided[j]
        while kn < n_noise and noise_pix[kn] < i:
            kn += 1
        g = L1[i] - L0[i] + (drift[i] if has_drift else 0.0)
        if kn < n_noise and noise_pix[kn] == i:
            continue
        if g > 0.0:
            ref[i] = L0[i] - phase[i] * c_on[i]
        elif g < 0.0:
            ref[i] = L0[i] + (1.0 - phase[i]) * c_off[i]
        else:
            undecided[keep] = i
            keep += 1
    return keep


def interval_events(L0, L1, ref, c_on, c_off, c_min, drift, blocked_until, t0, dt, refractory_us, noise,
                    width, buf, scratch):
    """One interval: screen the pixels, run `crossings` on the candidates, growing the output buffers
    (doubling) whenever it stops early. `ref` is updated in place; scratch is an int64 (P,) work buffer
    (reused across intervals: a fresh 0.7 MB array per interval cost more in page faults than the screen).
    Returns (n, buf): the first n entries of buf = (t offsets, x, y, p) hold the events, in pixel order."""
    if drift.shape[0]:
        ref -= drift
    cand = scratch[:screen(L1, ref, c_on, c_off, blocked_until, t0, noise[0], scratch)]
    n, start, k = 0, 0, 0
    while True:
        n, start, k = crossings(cand, width, L0, L1, ref, c_on, c_off, 1.0 / c_min, drift, blocked_until, t0, dt,
                                refractory_us, *noise, *buf, start, n, k)
        if start >= len(cand):
            return n, buf
        grown = []
        for b in buf:
            g = np.empty(2 * len(b) + 1024, b.dtype)
            g[:n] = b[:n]
            grown.append(g)
        buf = tuple(grown)
