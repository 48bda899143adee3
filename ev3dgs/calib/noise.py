"""Background activity (leak and shot noise), hot pixels and the refractory period.

Static pixels: well exposed in every frame, their APS log intensity spans less than half the smaller threshold
(plus 6 standard deviations of frame noise) over the whole recording, and so do their 8 neighbours (an edge next door leaks events through blur and
photoreceptor spread). Their events are noise: no signal crossing can happen there.

The simulator's noise model (ev3dgs.sim.config): shot noise emits ON and OFF alike at
rate_hz * (1 - (1 - white_fraction) I) per pixel (ON+OFF, I = linear intensity, 1 = full scale), leak emits ON
events only at rate_hz. So the OFF rate of static pixels gives the shot noise and its intensity dependence
(a straight line over intensity bands, weighted by Poisson variance), and ON minus OFF gives the leak (after
undoing the resets by shot noise: see invert_leak).
What the intensities of the static pixels do not span is not estimated.

Hot pixels: by their own signature, a steady rate that does not follow the APS signal (see hot_pixels). They
are listed and left out of every fit.

Refractory period: the onset of the inter-event-interval (IEI) histogram of every pixel pooled (see
refractory). With the simulator's refractory semantics a burst at log slope g has intervals of R + C/g, so the
onset is R plus the fastest edges' C/g: tight when the fastest edges hit the refractory limit.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .aps import Recording, pixel_index
from .thresholds import Value, log_intensity

IEI_QUANTILE = 0.002
IEI_WINDOW = 0.005          # the onset is fitted in the shortest 0.5 % of the intervals ...
MIN_WINDOW = 200            # ... at least this many
ONSET_JUMP = 5.0            # an onset: the density of intervals jumps by this factor over the floor below
MIN_IEI = 2000
HOT_FACTOR = 5.0
NB_FACTOR = 3.0          # ... and this many times its neighbours' count in the same pairs
MIN_PAIRS_HOT = 6        # hot pixels are looked for in recordings with at least this many frame pairs
MIN_QUIET = 2            # a pixel needs this many quiet frame pairs to be judged hot or not
STILL_SHARE = 0.75        # a quiet pair changes by at most this share of the smaller threshold (+ 2 noise s.d.)
MIN_SHOT_EVENTS = 5


@dataclass
class NoiseFit:
    leak_hz: Value
    shot_hz: Value
    white_fraction: Value
    on_rate_hz: Value
    off_rate_hz: Value
    refractory_us: Value
    static_pixels: int
    static_intensity: tuple[float, float]
    hot: list[tuple[int, int, float]]     # (x, y, rate Hz)
    seconds: float
    notes: list[str] = field(default_factory=list)


def window_counts(rec: Recording) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-pixel ON and OFF counts between the first and the last exposure midpoint, and its length (s)."""
    ev = rec.events
    m = (ev.t >= rec.t_mid[0]) & (ev.t < rec.t_mid[-1])
    pix = pixel_index(ev, rec.width)[m]
    p = ev.p[m]
    P = rec.width * rec.height
    return (np.bincount(pix[p > 0], minlength=P), np.bincount(pix[p < 0], minlength=P),
            (rec.t_mid[-1] - rec.t_mid[0]) * 1e-6)


def static_mask(rec: Recording, curve: tuple[float, float], c_min: float) -> np.ndarray:
    dark, knee = curve
    F = rec.frames
    valid = rec.valid(dark).all(0)
    L = log_intensity(F, dark, knee, rec.full_scale)
    # frame noise moves the log of a dark pixel too: allow 6 of its standard deviations (the range of ~50
    # Gaussian draws is about 4.5)
    from .thresholds import frame_noise

    med = np.median(F, 0)
    sd_l = np.interp(med, *frame_noise(rec)) / np.maximum(med - dark, knee * (rec.full_scale - dark))
    still = valid & ((L.max(0) - L.min(0)) <= 0.5 * c_min + 6 * sd_l)
    # erode by one pixel: all 8 neighbours still too
    pad = np.pad(still, 1, constant_values=False)
    H, W = still.shape
    out = still.copy()
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            out &= pad[dy:dy + H, dx:dx + W]
    return out.ravel()


def hot_pixels(rec: Recording, on, off, T: float, curve: tuple[float, float], c_on: float, c_off: float,
               static: np.ndarray):
    """(mask of hot pixels, list of (x, y, rate Hz)): pixels whose events do not follow the APS signal.

    A hot pixel fires at its own steady rate whatever the scene does, so it is judged on its quiet frame pairs
    only: pairs in which neither it nor any of its 8 neighbours changes by more than STILL_SHARE (3/4) of the
    smaller threshold (plus 2 frame-noise standard deviations), and neither do the pairs before and after (a
    turning point of the motion inside a pair shows there): at most about one signal event per pair, which
    the signal term below counts (a quarter of a threshold, with the frame noise measured right, left a
    texture shaking at the frame rate 2 quiet pairs in 24 per pixel). In those pairs a pixel is hot when
      * its count exceeds what the background (the static pixels' quiet-pair rate) and the APS-predicted
        signal (sum (|dL| - 2 s.d.) / C over its quiet pairs) explain, beyond the 1e-3 / P Poisson tail and
        by HOT_FACTOR;
      * it exceeds NB_FACTOR times the median of its 8 neighbours' counts in the same pairs, and their
        Poisson tail (textured pixels whose sub-frame motion the frames do not resolve fire together with
        their neighbours);
      * its rate is steady: the counts over its quiet pairs are Poisson (index of dispersion within 4
        standard errors of 1), not bursts, and both halves of its quiet pairs hold events.
    A pixel with fewer than MIN_QUIET quiet pairs (the scene never rests there) is hot when its count over
    every pair exceeds twice HOT_FACTOR times its neighbours' median and their Poisson tail, in both halves.
    The counts per pair come from the recording; `on` + `off` order the list, `static` gives the background.
    A recording with fewer than MIN_PAIRS_HOT frame pairs is not searched (none reported)."""
    from scipy.stats import poisson

    from .aps import pair_counts
    from .thresholds import frame_noise

    dark, knee = curve
    H, W = rec.height, rec.width
    P = H * W
    F = rec.frames.reshape(len(rec.frames), -1)
    valid = rec.valid(dark).reshape(len(F), -1)
    L = log_intensity(F, dark, knee, rec.full_scale)
    dL = np.diff(L, axis=0)
    rel = np.interp(F, *frame_noise(rec)) / np.maximum(F - dark, knee * (rec.full_scale - dark))
    sd = np.sqrt(rel[1:] ** 2 + rel[:-1] ** 2)
    c_min = min(c_on, c_off)
    v = valid[1:] & valid[:-1]
    still = v & (np.abs(dL) <= STILL_SHARE * c_min + 2 * sd)
    K = len(dL)
    s3 = still.reshape(K, H, W)
    pad = np.pad(s3, ((0, 0), (1, 1), (1, 1)), constant_values=True)
    quiet3 = np.ones_like(s3)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            quiet3 &= pad[:, dy:dy + H, dx:dx + W]
    quiet = quiet3.reshape(K, P)
    quiet[1:] &= still[:-1]
    quiet[:-1] &= still[1:]
    if K < MIN_PAIRS_HOT:   # a few frame pairs say nothing about a rate being steady
        return np.zeros(P, bool), []
    p_on, p_off = pair_counts(rec)
    n = (p_on + p_off).astype(float)                      # (K, P)
    dt = np.diff(rec.t_mid.astype(np.float64))[:, None] * 1e-6
    kq = quiet.sum(0)
    nq = (n * quiet).sum(0)
    tq = (dt * quiet).sum(0)
    judged = kq >= MIN_QUIET
    if not judged.any():
        return np.zeros(P, bool), []
    rate_q = np.where(judged, nq / np.maximum(tq, 1e-12), 0.0)
    # the background: the quiet-pair rate of the static pixels (the rest fire with sub-frame motion too, which
    # the neighbour test below handles), else the lower quartile of every pixel's
    ref = judged & np.asarray(static, bool)
    base = float(np.median(rate_q[ref])) if ref.sum() >= 50 else float(np.percentile(rate_q[judged], 25))
    # the change the frames see beyond their noise, in thresholds (a quiet pair's |dL| is mostly frame noise)
    signal = (np.clip(np.abs(dL) - 2 * sd, 0.0, None) * quiet / np.where(dL > 0, c_on, c_off)).sum(0)
    expected = base * tq + signal
    limit = poisson.isf(1e-3 / P, np.maximum(expected, 1e-9))
    # the neighbours' counts in this pixel's quiet pairs
    n3 = np.pad(n.reshape(K, H, W), ((0, 0), (1, 1), (1, 1)), mode="edge")
    nb = []
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            nb.append((n3[:, dy:dy + H, dx:dx + W].reshape(K, P) * quiet).sum(0))
    nb_med = np.median(np.stack(nb), 0)
    # steadiness: Poisson counts over the quiet pairs, events in both halves of them
    m = nq / np.maximum(kq, 1)
    var = (((n - m) ** 2) * quiet).sum(0) / np.maximum(kq - 1, 1)
    disp = var / np.maximum(m, 1e-12)
    steady = disp <= 1 + 4 * np.sqrt(2.0 / np.maximum(kq - 1, 1))
    order = np.cumsum(quiet, 0)
    first = quiet & (order <= (kq[None, :] + 1) // 2)
    n1 = (n * first).sum(0)
    both = (n1 > 0) & (nq - n1 > 0)
    hot = (judged & (nq > limit) & (nq > HOT_FACTOR * np.maximum(expected, 1.0))
           & (nq > NB_FACTOR * np.maximum(nb_med, 1.0)) & (nq > poisson.isf(1e-3 / P, np.maximum(nb_med, 1.0)))
           & steady & both)
    # a pixel the scene never leaves quiet for MIN_QUIET pairs: against its neighbours over every pair (they
    # see the same motion and texture), by twice the factor, and in both halves of the recording
    nt = n.sum(0)
    nb_all = np.median(np.stack([n3[:, dy:dy + H, dx:dx + W].reshape(K, P).sum(0)
                                 for dy in (0, 1, 2) for dx in (0, 1, 2) if (dy, dx) != (1, 1)]), 0)
    half = n[: K // 2].sum(0)
    lim_all = poisson.isf(1e-3 / P, np.maximum(nb_all, 1.0))
    busy = (~judged & valid.all(0) & (nt > lim_all) & (nt > 2 * HOT_FACTOR * np.maximum(nb_all, 1.0))
            & (half > 0) & (nt - half > 0))
    hot |= busy
    idx = np.flatnonzero(hot)
    tot = np.asarray(on) + np.asarray(off)
    t_all = float(dt.sum())
    # the rate in its quiet pairs; a pixel judged over every pair (no quiet pair): its rate over all of them
    lst = [(int(i % W), int(i // W), float(nq[i] / tq[i] if judged[i] else nt[i] / t_all))
           for i in idx[np.argsort(-tot[idx])]]
    return hot, lst


def _wls_line(x, y, var):
    w = 1.0 / np.maximum(var, 1e-12)
    X = np.stack([np.ones_like(x), x], 1)
    A = X.T @ (w[:, None] * X)
    if abs(np.linalg.det(A)) < 1e-12:
        return None
    return np.linalg.solve(A, X.T @ (w * y))


def _shot_fit(I, off, T, bands=5):
    """OFF rate = a + b I over intensity bands -> (shot rate_hz = 2a, white_fraction = (a + b) / a)."""
    edges = np.unique(np.percentile(I, np.linspace(0, 100, bands + 1)))
    xs, ys, vs = [], [], []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (I >= a) & (I <= b)
        if m.sum() < 10:
            continue
        xs.append(I[m].mean())
        ys.append(off[m].sum() / (m.sum() * T))
        vs.append(max(off[m].sum(), 1.0) / (m.sum() * T) ** 2)
    if len(xs) < 2:
        return None
    return _wls_line(np.array(xs), np.array(ys), np.array(vs))


def invert_leak(measured: float, reset_hz: float) -> float:
    """The simulator's leak rate from the measured ON-minus-OFF rate: each shot-noise event resets the
    reference, so a leak period of 1/r completes only when no reset (rate lambda) comes first, and leak events
    come at lambda / (exp(lambda / r) - 1); inverted: r = lambda / ln(1 + lambda / measured)."""
    if measured <= 0:
        return measured
    if reset_hz <= 1e-9:
        return measured
    return float(reset_hz / np.log1p(reset_hz / measured))


def invert_leak_pixels(measured: float, reset_hz: np.ndarray) -> float:
    """invert_leak for pixels with different reset rates lambda_i (shot noise depends on intensity): the
    leak rate r with mean_i lambda_i / (exp(lambda_i / r) - 1) = measured. Inverting with the mean lambda
    instead overestimates r (the function is convex in lambda), and so does ignoring the spread of the
    per-pixel leak rates."""
    lam = np.asarray(reset_hz, float)
    if measured <= 0 or not len(lam):
        return measured
    # the simulator's per-pixel leak rates are log-normal (rate_spread_decades, which calibrate leaves at
    # its default) with mean r; the event rate is very convex in the rate: average over it (Gauss-Hermite)
    from ..sim.config import Leak

    sig = Leak().rate_spread_decades * np.log(10.0)
    z, w = np.polynomial.hermite_e.hermegauss(15)
    scale = np.exp(sig * z - sig ** 2 / 2)
    w = w / w.sum()
    lam2 = lam[:, None]

    def f(r):
        rr = r * scale[None, :]
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            v = np.where(lam2 > 1e-9, lam2 / np.expm1(lam2 / rr), rr)
        return float((np.nan_to_num(v, nan=0.0, posinf=0.0) @ w).mean()) - measured

    lo, hi = measured, 2 * measured + float(lam.max()) + 1.0
    for _ in range(60):
        if f(hi) > 0:
            break
        hi *= 2
    else:
        return float("nan")
    from scipy.optimize import brentq

    return float(brentq(f, lo, hi, xtol=1e-6 * measured))


def bootstrap_se(samples: np.ndarray) -> np.ndarray:
    """Per column of `samples` (bootstrap replicates x quantities), the sample standard deviation of its finite
    values; NaN where fewer than two are finite (a quantity the fit could not estimate: numpy's nanstd would
    warn "Degrees of freedom <= 0 for slice" there)."""
    samples = np.asarray(samples, np.float64)
    samples = samples[:, None] if samples.ndim == 1 else samples
    out = np.full(samples.shape[1], np.nan)
    for j in range(samples.shape[1]):
        v = samples[np.isfinite(samples[:, j]), j]
        if len(v) > 1:
            out[j] = v.std(ddof=1)
    return out


def fit_noise(rec: Recording, curve: tuple[float, float], c_on: float, c_off: float, boot: int = 200,
              seed: int = 0) -> NoiseFit:
    dark = curve[0]
    on, off, T = window_counts(rec)
    static = static_mask(rec, curve, min(c_on, c_off))
    hot, hot_list = hot_pixels(rec, on, off, T, curve, c_on, c_off, static)
    static &= ~hot
    notes = []
    I_all = ((np.median(rec.frames, 0) - dark) / (rec.full_scale - dark)).ravel()
    idx = np.flatnonzero(static)
    ns = len(idx)
    refr = refractory(rec, hot, rng=np.random.default_rng(seed + 1), boot=boot)
    if ns < 50:
        none = Value(None, None, f"{ns} static pixels (need 50)")
        return NoiseFit(none, none, none, none, none, refr, ns, (0.0, 0.0), hot_list, T,
                        ["background activity not estimated: too few static pixels"])
    I = I_all[idx]
    on_s, off_s = on[idx].astype(float), off[idx].astype(float)
    lo, hi = (float(v) for v in np.percentile(I, [10, 90]))
    span_ok = hi - lo >= 0.25

    def estimate(sel):
        Is, ons, offs = I[sel], on_s[sel], off_s[sel]
        on_r, off_r = ons.sum() / (len(sel) * T), offs.sum() / (len(sel) * T)
        leak = invert_leak(on_r - off_r, 2 * off_r)
        if span_ok:
            ab = _shot_fit(Is, offs, T)
            if ab is None or ab[0] <= 0:
                return on_r, off_r, leak, np.nan, np.nan
            # each pixel's own reset rate: 2 x its OFF rate at its intensity (the correction is convex in it)
            leak = invert_leak_pixels(on_r - off_r, np.clip(2 * (ab[0] + ab[1] * Is), 0.0, None))
            return on_r, off_r, leak, 2 * ab[0], (ab[0] + ab[1]) / ab[0]
        # white_fraction not estimated: the default's shape, scaled to the mean OFF rate
        shape = np.mean(1.0 - 0.75 * np.clip(Is, 0, 1))
        return on_r, off_r, leak, 2 * off_r / shape, np.nan

    full = estimate(np.arange(ns))
    rng = np.random.default_rng(seed)
    bs = np.array([estimate(rng.integers(0, ns, ns)) for _ in range(boot)]).reshape(-1, 5)
    se = bootstrap_se(bs)
    on_v = Value(full[0], se[0], f"{ns} static pixels over {T:.2f} s")
    off_v = Value(full[1], se[1], f"{ns} static pixels over {T:.2f} s")
    if full[2] > 2 * se[2]:
        leak = Value(full[2], se[2], f"from the ON minus OFF rate of static pixels, {full[0] - full[1]:.3g} Hz, "
                                     "corrected for the shot-noise resets that cut leak periods short")
    else:
        leak = Value(None, se[2], f"ON minus OFF rate {full[2]:.3g} +- {se[2]:.2g} Hz: not above zero by 2 standard "
                                  "errors, so no leak is written")
    # shot noise is written only when the static OFF events are significantly above zero: at least
    # MIN_SHOT_EVENTS of them (a Poisson count n is 2 standard errors above zero from n = 5 on), the OFF rate
    # above 2 bootstrap s.e., and the fitted rate above 2 of its own s.e.
    n_off = int(off_s.sum())
    se_shot = float(max(se[3], 2 * np.sqrt(max(n_off, 1)) / (ns * T))) if np.isfinite(se[3]) else se[3]
    significant = (n_off >= MIN_SHOT_EVENTS and full[1] > 2 * se[1] and np.isfinite(full[3])
                   and full[3] > 2 * se_shot)
    if significant:
        shot = Value(full[3], se_shot, "2 x the OFF rate at zero intensity" if span_ok else
                     "2 x the OFF rate, scaled with the default intensity dependence (white_fraction not estimated)")
    else:
        from scipy.stats import chi2

        # 2 x the OFF rate's one-sided 95 % Poisson bound, or the fit's estimate + 2 s.e. if larger
        bound = 2 * float(chi2.ppf(0.95, 2 * n_off + 2)) / 2 / (ns * T)
        fitted = ""
        if np.isfinite(full[3]) and np.isfinite(se_shot):
            bound = max(bound, float(full[3] + 2 * se_shot))
            fitted = f", fitted shot rate {full[3]:.3g} +- {se_shot:.2g} Hz"
        shot = Value(None, None, f"{n_off} OFF events on {ns} static pixels over {T:.2f} s (OFF rate "
                                 f"{full[1]:.3g} +- {se[1]:.2g} Hz{fitted}): not significantly above zero; "
                                 f"shot noise below {bound:.2g} Hz (95 % upper bound)")
    if not significant:
        wf = Value(None, None, "no shot noise resolved")
    elif span_ok and np.isfinite(full[4]) and 0 <= full[4] <= 1:
        wf = Value(float(full[4]), float(se[4]), f"static pixels span I = {lo:.2f}-{hi:.2f}")
    elif span_ok and np.isfinite(full[4]):
        wf = Value(None, float(se[4]), f"fitted {full[4]:.2f} +- {se[4]:.2f}, outside the model's [0, 1]: "
                                       "the simulator's default applies")
    else:
        wf = Value(None, None, f"static pixels span only I = {lo:.2f}-{hi:.2f} (need 0.25): the simulator's "
                               "default applies")
    return NoiseFit(leak, shot, wf, on_v, off_v, refr, ns, (lo, hi), hot_list, T, notes)


def iei_by_pixel(rec: Recording, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Same-pixel inter-event intervals (us) and their pixel, every polarity."""
    ev = rec.events
    pix = pixel_index(ev, rec.width)
    if exclude is not None and exclude.any():
        keep = ~exclude[pix]
        pix, t = pix[keep], ev.t[keep]
    else:
        t = ev.t
    o = np.lexsort((t, pix))
    pix, t = pix[o], t[o]
    same = pix[1:] == pix[:-1]
    return np.diff(t)[same], pix[1:][same]


def onset(t: np.ndarray) -> float:
    """The first point where the density of the sorted intervals t jumps: the local density over the next m
    intervals (m = max(10, 2 % of them)) exceeds ONSET_JUMP times the mean density of all intervals below
    the point (the floor of early outliers), and stays so for the next m. nan if there is no such point."""
    x = np.sort(np.asarray(t, float))
    n = len(x)
    m = max(10, int(0.02 * n))
    if n < 3 * m:
        return float("nan")
    j = np.arange(n - 2 * m)
    local = m / (x[j + m] - x[j] + 1.0)
    local2 = m / (x[j + 2 * m] - x[j + m] + 1.0)
    floor = (j + 1) / (x[j] + 1.0)
    ok = (local > ONSET_JUMP * floor) & (local2 > ONSET_JUMP * floor)
    ok[0] = False   # the first interval has no floor below it
    return float(x[np.argmax(ok)]) if ok.any() else float("nan")


def refractory(rec: Recording, exclude, rng, boot: int = 200) -> Value:
    """The refractory period from the onset of the same-pixel interval histogram.

    With the simulator's (and a DVS pixel's) refractory semantics an interval is R + C/g (g: the log slope),
    so the histogram has no interval below R + C/g_max and rises from there; a few noise events and timing
    jitter put some intervals below. In the short end of the histogram (up to the IEI_WINDOW quantile, at
    least MIN_WINDOW intervals) the onset is the first point where the density jumps over the floor of those
    outliers (see onset). It is R plus the fastest edges' C/g: tight when an edge is fast enough to hit the
    refractory limit. Where the density never jumps (intervals from 0 up, no refractory edge) the
    IEI_QUANTILE quantile is reported as an upper bound.
    Standard error: bootstrap over pixels."""
    iei, pix = iei_by_pixel(rec, exclude)
    if len(iei) < MIN_IEI:
        return Value(None, None, f"{len(iei)} inter-event intervals (need {MIN_IEI})")
    k = max(MIN_WINDOW, int(IEI_WINDOW * len(iei)))
    U = float(np.partition(iei, min(k, len(iei) - 1))[min(k, len(iei) - 1)]) + 1.0

    def est(x):
        return onset(x[x < U])

    r = est(iei)
    order = np.argsort(pix, kind="stable")
    pix_s, iei_s = pix[order], iei[order]
    upix, cnt = np.unique(pix_s, return_counts=True)
    bs = []
    for _ in range(min(boot, 50)):   # 50 resamples give the standard error to about 10 %
        w = np.bincount(rng.integers(0, len(upix), len(upix)), minlength=len(upix))
        sel = np.repeat(iei_s, np.repeat(w, cnt))
        bs.append(est(sel))
    bs = np.asarray(bs, float)
    se = float(np.nanstd(bs, ddof=1)) if np.isfinite(bs).sum() > 2 else None
    below = int((iei < r).sum()) if np.isfinite(r) else 0
    if np.isfinite(r) and r > 2:
        return Value(r, se, f"onset of the interval histogram ({below} of {len(iei)} intervals below it, "
                            f"found in the shortest {int((iei < U).sum())}); R plus the fastest edges' C/g")
    q = float(np.quantile(iei, IEI_QUANTILE))
    if q <= 2:
        return Value(None, None, f"the {100 * IEI_QUANTILE:g} % quantile of the intervals is {q:g} us, at the "
                                 "timestamp resolution: no refractory period resolved")
    return Value(q, None, f"no onset in the interval histogram: its {100 * IEI_QUANTILE:g} % quantile, an upper "
                          "bound (R + C/g of the fastest edges)")
