"""Contrast thresholds, their pixel-to-pixel spread and the APS dark level, from frame pairs and event counts.

Model. Between two exposure midpoints a pixel's log intensity changes by dL = log(I1 - dark) - log(I0 - dark);
the change detector emits N_on ON and N_off OFF events with

    dL = C_on N_on - C_off N_off + (d0 - d1)

where d is the pixel's distance from its reference (|d| < one threshold). With a random reference phase the
residual d0 - d1 has zero mean as long as the pixel keeps its direction, so summed over pixels and pairs

    sum_up dL   = C_on sum_up N_on - C_off sum_up N_off        (pairs with dL > tau)
    sum_down -dL = C_off sum_down N_off - C_on sum_down N_on   (pairs with dL < -tau)

a 2x2 linear system for (C_on, C_off): a ratio of sums (zero-count pairs included, so that the estimate is
unbiased whatever the distribution of changes), which the OFF events of an up pair (a reversal inside the
frame interval) and the ON events of a down pair enter with the other threshold. A pair next to a pair that
went the other way (before or after) is left out: after a reversal the pixel must first travel its dead band
(up to C_on + C_off) and the residual no longer has zero mean; a turning point inside pair k shows as pair
k-1 or k+1 going the other way, and the events say it directly: the pixel's last event before the pair and
its last event inside it must have the pair's polarity (a turning point on a flat top that no frame pair
resolves still shows there). The first pair of each run of pairs going one way is left out too: a turning
point or an unresolved flat stretch just before it leaves the pixel inside its dead band (measured on
synthetic recordings: +3 % / +7 % on C_on / C_off with it). Sub-frame wiggles that no frame sees are not
caught: faster motion than the frame rate resolves biases the thresholds up.

Refractory period R: while a pixel is held after an event its reference follows the input, so the change
in that time is lost. Each event counts as dt / (dt - R) thresholds, dt its interval to the pixel's next
event of the same polarity (aps.held_weights: at a slope steady between the two, the hold loses C R / (dt - R));
calibrate passes the refractory estimate in (refractory_us). The pair's mean slope (dL (1 - N R / dt)) misses
most of the loss because events crowd where the slope is steep.

Robust: pixels whose summed residual lies more than 5 robust standard deviations out (hot pixels, flicker,
pixels whose APS and DVS disagree) are dropped and the system solved again.

Frame noise: it enters dL with zero mean (so not the sums), but it decides which pairs pass |dL| > tau; tau is
4 standard deviations of dL predicted from the frame noise (measured on the quietest pixels of each intensity
band) so that noise alone selects almost no pair, and at least 0.02. It still biases: pairs that noise
pushed over the cut are kept, those it pushed under are not (+0-5 % on synthetic recordings).
Under-exposed pixels (less than aps.UNDER_DN above the dark level) and saturated pixels are masked in every
pair they touch.

Dark level and log knee: the fitted thresholds must not depend on intensity. A wrong APS dark level bends
log(I - dark) at the dark end only, and so does the DVS photoreceptor's own dark current (the simulator's
lin-log knee, ev3dgs.logmap): so (dark, knee) is the point on a one-parameter grid (knees from 0.5 to 0.005 at
dark 0, then dark levels at the default knee) that makes the thresholds fitted in three intensity bands
(terciles) agree best, provided it beats the default curve (dark 0, the simulator's knee) in at least 95 % of
bootstrap resamples over pixels; otherwise the default stays (_significant_curve). The two cannot be told apart
from frames and counts alone: a knee above the default means the event pixels lose contrast at the dark end
faster than the APS does.

Mismatch: from the products of the residuals e = dL - C_on N_on + C_off N_off of every two selected frame
pairs of a pixel at least two pairs apart, against the products of their counts (see _mismatch for the
derivation): every pixel with two such pairs counts, whatever its number of events. The count weights (pixels
with a low threshold fire more), the ratio of sums (a harmonic mean: C (1 - sigma^2 / C^2) to second order)
and the pair trim (a pixel far below the mean fires many events per pair, and its pairs fall outside) bias
both the spread and the thresholds; trimmed_moments models all three for the simulator's normal draws clipped
at its floor, and invert_trimmed solves for the nominal threshold and sigma. Modelling the trim instead of
widening it matters where many thresholds sit near the floor (sensor C: OFF 0.2, sigma 0.12): those pixels'
counts stop following 1 / C_i (refractory-limited, shot noise scaled up), and both the data and the model
leave them out alike. Outlier pixels (summed residual beyond 5 robust s.d., widened by sigma N) are dropped.

Uncertainties: bootstrap over pixels (the dark level refitted in every resample).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .aps import UNDER_DN, Recording, last_polarity

TAU_SIGMAS = 4.0
TAU_MIN = 0.02


@dataclass
class Value:
    """An estimate and its bootstrap standard error; value None = not estimated (note says why)."""

    value: float | None
    se: float | None = None
    note: str = ""


@dataclass
class ThresholdFit:
    c_on: Value
    c_off: Value
    sigma: Value
    sigma_on: Value
    sigma_off: Value
    dark: Value
    knee: Value
    frame_noise_dn: float
    pixels: int
    samples_up: int
    samples_down: int
    events_used: int
    notes: list[str] = field(default_factory=list)

    @property
    def curve(self) -> tuple[float, float]:
        """(dark DN, log knee) of the fit: the APS -> simulator intensity map and the simulator's log curve."""
        from ..logmap import DEFAULT_LOG_KNEE

        return float(self.dark.value), float(self.knee.value if self.knee.value is not None else DEFAULT_LOG_KNEE)


def frame_noise(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """Temporal noise of the APS frames (DN) by intensity: (band centres DN, noise DN), the lower of two
    estimates, each an upper bound of the noise (motion only adds spread):

    * quiet pixels (few events over the whole recording): per pixel the standard deviation over frames of
      the linearly detrended DN, per intensity band (6 quantile bands) the median. Precise where the scene
      has static pixels; with a moving camera no pixel is static and this reads the motion (tens of DN).
    * quiet pairs (quiet_pair_noise): frame pairs in which neither the pixel nor its 8 neighbours has an
      event, by the lower quartile of |frame difference|. Motion that fires no event still changes a pixel
      by up to a threshold, but it only widens the difference's distribution (Anderson's inequality), and
      the lower quartile is what it moves least; on a moving camera these pairs are the flat regions that
      stay flat under motion.

    Read and photon noise do not fall as the signal rises, so each band's bound also bounds every darker band
    (a running minimum from the bright end): a flat bright region then bounds the noise of a textured darker
    one, whose own event-free pairs still carry sub-threshold motion. Between and beyond the band centres the
    noise is interpolated, and held constant past the outer ones."""
    from .aps import pixel_index

    F = rec.frames.reshape(len(rec.frames), -1)
    ok = ~(rec.saturated().reshape(len(F), -1).any(0))
    if len(F) < 3:
        return np.array([0.0, 255.0]), np.array([1.0, 1.0])   # 2 frames: no temporal spread to measure
    counts = np.bincount(pixel_index(rec.events, rec.width), minlength=F.shape[1])
    q = float(np.percentile(counts, 25))
    quiet = ok & (counts <= q + 2 * np.sqrt(q + 1))
    if quiet.sum() < 20:
        quiet = ok
    X = F[:, quiet]
    t = np.linspace(-1, 1, len(F))[:, None]
    X = X - (t * X).sum(0) / (t * t).sum() * t
    sd = X.std(0, ddof=1)
    med = np.median(F[:, quiet], 0)
    edges = np.unique(np.percentile(med, np.linspace(0, 100, 7))) if len(med) else np.array([])
    centres, noise = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (med >= a) & (med <= b)
        if m.sum() >= 10:
            centres.append(float(np.median(med[m])))
            noise.append(max(float(np.median(sd[m])), 0.5))   # 8-bit quantisation: >= 0.5 DN
    pair = quiet_pair_noise(rec)
    if not centres and pair is None:
        return np.array([0.0, 255.0]), np.array([1.0, 1.0])
    if pair is None:
        at, sd = np.asarray(centres), np.asarray(noise)
    elif not centres:
        at, sd = pair
    else:
        at = np.union1d(centres, pair[0])
        sd = np.minimum(np.interp(at, centres, noise), np.interp(at, *pair))
    # read and photon noise never fall as the signal rises: a band's upper bound also bounds every darker band
    return at, np.minimum.accumulate(sd[::-1])[::-1]


QUIET_PAIR_QUANTILE = 0.25
QUIET_PAIR_Z = 0.318639363964375   # the standard normal's (1 + 0.25) / 2 quantile: |N(0, 1)|'s lower quartile


def _integer_quantile(a: np.ndarray, q: float) -> float:
    """The q quantile of integer-valued |a| with each value k spread uniformly over [k - 1/2, k + 1/2) ([0, 1/2)
    for 0): 8-bit frames make |frame difference| an integer, whose plain quantile would jump by whole DN."""
    k = np.abs(np.rint(a)).astype(np.int64)
    c = np.cumsum(np.bincount(k)) / len(k)
    j = int(np.searchsorted(c, q))
    lo, hi = (0.0, 0.5) if j == 0 else (j - 0.5, j + 0.5)
    below = 0.0 if j == 0 else float(c[j - 1])
    return lo + (hi - lo) * (q - below) / max(float(c[j]) - below, 1e-12)


def quiet_pair_noise(rec: Recording, min_pairs: int = 50) -> tuple[np.ndarray, np.ndarray] | None:
    """Frame noise (band centres DN, noise DN) from frame pairs where the pixel and its 8 neighbours have no
    event (both frames neither saturated nor under 3 DN): per intensity band (6 quantile bands of the pairs'
    mean DN, each with at least min_pairs pairs) the lower quartile of |F1 - F0| over sqrt(2) times |N(0, 1)|'s
    lower quartile, at least 0.5 DN. For Gaussian noise it is the noise; an unseen change only adds to it.
    None when fewer than min_pairs such pairs exist."""
    from .aps import pair_counts

    if len(rec.frames) < 2:
        return None
    on, off = pair_counts(rec)
    H, W = rec.height, rec.width
    n = np.pad((on + off).reshape(-1, H, W), ((0, 0), (1, 1), (1, 1)))
    hood = sum(n[:, dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)).reshape(len(on), -1)
    F = rec.frames.reshape(len(rec.frames), -1)
    ok = ~rec.saturated().reshape(len(F), -1) & (F >= UNDER_DN)
    use = (hood == 0) & ok[1:] & ok[:-1]
    if use.sum() < min_pairs:
        return None
    d = (F[1:] - F[:-1])[use]
    m = (0.5 * (F[1:] + F[:-1]))[use]
    edges = np.unique(np.percentile(m, np.linspace(0, 100, 7)))
    if len(edges) < 2:
        edges = np.array([m.min(), m.max()])
    centres, noise = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        s = (m >= a) & (m <= b)
        if s.sum() >= min_pairs:
            centres.append(float(np.median(m[s])))
            sd = _integer_quantile(d[s], QUIET_PAIR_QUANTILE) / QUIET_PAIR_Z / np.sqrt(2.0)
            noise.append(max(sd, 0.5))
    if not centres:
        return None
    return np.asarray(centres), np.asarray(noise)


class _Samples:
    """Selected frame pairs for one dark level: per-pixel sums of (dL, N_on, N_off) over up and down pairs,
    split by intensity band and by time half."""

    def __init__(self, rec: Recording, on: np.ndarray, off: np.ndarray, curve: tuple[float, float], noise,
                 band_edges, exclude: np.ndarray, held: tuple[np.ndarray, np.ndarray] | None = None,
                 run_starts: bool = False):
        dark, knee = curve
        F = rec.frames.reshape(len(rec.frames), -1)
        valid = rec.valid(dark).reshape(len(F), -1)
        valid[:, exclude] = False
        L = log_intensity(F, dark, knee, rec.full_scale)
        sdn = np.interp(F, *noise)
        rel = sdn / np.maximum(F - dark, knee * (rec.full_scale - dark))   # dL/dDN of the lin-log curve
        dL = L[1:] - L[:-1]
        v = valid[1:] & valid[:-1]
        tau = np.maximum(TAU_SIGMAS * np.sqrt(rel[1:] ** 2 + rel[:-1] ** 2), TAU_MIN)
        up = v & (dL > tau)
        dn = v & (dL < -tau)
        # a reversal inside pair k shows as pair k-1 or k+1 going the other way: drop pairs next to one
        rev = np.zeros_like(up)
        rev[1:] = (up[1:] & dn[:-1]) | (dn[1:] & up[:-1])
        rev[:-1] |= (up[:-1] & dn[1:]) | (dn[:-1] & up[1:])
        # the events say it directly: the last event before the pair and the last one inside it must go the
        # pair's way (none yet = unknown, kept)
        lp = last_polarity(rec)
        rev |= (up & ((lp[:-1] < 0) | (lp[1:] < 0))) | (dn & ((lp[:-1] > 0) | (lp[1:] > 0)))
        up, dn = up & ~rev, dn & ~rev
        # the first pair of a run starts where the pixel's reference is not in its steady state (a turning
        # point, or a flat stretch the frames did not resolve, lies just before it: the dead band of up to
        # C_on + C_off is still being crossed); keep a pair only when the pair before it went the same way
        # (run_starts=True keeps them: the fallback for recordings too short to have runs of two pairs)
        if run_starts:
            self.up0, self.dn0 = up, dn
        else:
            self.up0 = up & np.concatenate([np.zeros_like(up[:1]), up[:-1]])
            self.dn0 = dn & np.concatenate([np.zeros_like(dn[:1]), dn[:-1]])
        self.up, self.dn = self.up0, self.dn0
        self.dL = dL
        self.sd = np.sqrt(rel[1:] ** 2 + rel[:-1] ** 2)
        mean_dn = 0.5 * (F[1:] + F[:-1])
        self.band = np.digitize(mean_dn, band_edges)          # 0..len(edges)
        self.nb = len(band_edges) + 1
        half = np.zeros(len(dL), np.int64)
        half[len(dL) // 2:] = 1
        self.half = half[:, None]
        # held = the pairs' ON and OFF counts weighted by aps.held_weights (the change lost while a pixel is
        # held after each event: refractory period); the plain counts without one
        self.n_on, self.n_off = on.astype(float), off.astype(float)
        self.held = held
        self.on, self.off = self.n_on, self.n_off

    def weigh(self, c_on: float, c_off: float) -> None:
        """The held-weighted counts, each pair's capped: what the holds add (W - N) C cannot exceed the pair's
        whole change |dL| plus one threshold (the residual), which a step edge (the steady-slope assumption of
        held_weights at its worst) would otherwise break."""
        if self.held is None:
            return
        a = np.abs(self.dL)
        self.on = np.minimum(self.held[0], self.n_on + a / c_on + 1.0)
        self.off = np.minimum(self.held[1], self.n_off + a / c_off + 1.0)

    def trim(self, c_on: float, c_off: float) -> None:
        """Drop the pairs the model cannot explain: |dL - C_on N_on + C_off N_off| can reach C_on + C_off
        (the reference residual at both ends) plus frame noise, not more. Events lost to the refractory
        period at fast edges, flicker and hot pixels land outside."""
        r = np.abs(self.dL - c_on * self.on + c_off * self.off)
        # a pixel far from the mean threshold lands outside too: trimmed_moments models that (the mismatch)
        ok = r <= c_on + c_off + TAU_SIGMAS * self.sd
        self.up, self.dn = self.up0 & ok, self.dn0 & ok

    def fit(self, iterations: int = 4) -> tuple[float, float]:
        """Solve, trim (and cap the held weights), solve again."""
        if self.held is not None:   # a start for the cap: the plain counts' solution
            self.on, self.off = self.n_on, self.n_off
            c = solve(self.totals())
            if np.isfinite(c).all():
                self.weigh(*c)
        c = solve(self.totals())
        for _ in range(iterations):
            if not np.isfinite(c).all():
                break
            self.weigh(*c)
            self.trim(*c)
            c = solve(self.totals())
        return c

    def totals(self) -> np.ndarray:
        out = []
        for m, sgn in ((self.up, 1.0), (self.dn, -1.0)):
            out += [sgn * self.dL[m].sum(), self.on[m].sum(), self.off[m].sum()]
        return np.asarray(out, float)

    def sums(self, key: np.ndarray, nkeys: int) -> np.ndarray:
        """(P, nkeys, 6) per-pixel sums [dL_up, Non_up, Noff_up, -dL_dn, Non_dn, Noff_dn] by key (pairs, P)."""
        P = self.dL.shape[1]
        out = np.zeros((P, nkeys, 6))
        pix = np.broadcast_to(np.arange(P), self.dL.shape)
        for j, (m, sgn) in enumerate(((self.up, 1.0), (self.dn, -1.0))):
            idx = pix[m] * nkeys + np.broadcast_to(key, self.dL.shape)[m]
            for c, val in enumerate((sgn * self.dL[m], self.on[m], self.off[m])):
                out[..., 3 * j + c] = np.bincount(idx, weights=val, minlength=P * nkeys).reshape(P, nkeys)
        return out


def solve(s: np.ndarray) -> tuple[float, float]:
    """(C_on, C_off) from summed [dL_up, Non_up, Noff_up, dL_dn, Non_dn, Noff_dn]; nan if not solvable."""
    a = np.array([[s[1], -s[2]], [-s[4], s[5]]])
    b = np.array([s[0], s[3]])
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    if not det > 0 or s[1] <= 0 or s[5] <= 0:
        return float("nan"), float("nan")
    c = np.linalg.solve(a, b)
    return (float(c[0]), float(c[1])) if (c > 0).all() else (float("nan"), float("nan"))


CURVE_RESAMPLES = 60
CURVE_LEVEL = 0.05


def _significant_curve(grid, bands, gi: int, rng, resamples: int = CURVE_RESAMPLES,
                       level: float = CURVE_LEVEL) -> int:
    """The grid point gi that makes the intensity bands' thresholds agree best, or the simulator's default
    curve (dark 0, DEFAULT_LOG_KNEE) when the bands do not tell them apart: gi is kept only when its band
    spread lies below the default's in at least 1 - level of the bootstrap resamples over pixels (a one-sided
    test at `level`). The band spread is a noisy criterion: with few selected pairs per band (a shaking
    camera) its minimum wanders over the grid, and a dark level away from the truth bends every log change
    (on the lego `record` recording of sensor A, the minimum at a dark level of 12 DN, bootstrap s.e. 7 DN,
    read the thresholds +19 / +20 % against +6 / +5 % at the true curve)."""
    from ..logmap import DEFAULT_LOG_KNEE

    g0 = next((i for i, g in enumerate(grid) if g == (0.0, DEFAULT_LOG_KNEE)), None)
    if g0 is None or g0 == gi or len(grid) < 2:
        return gi
    used = np.flatnonzero((np.abs(bands[gi]) + np.abs(bands[g0])).sum((1, 2)) > 0)
    if len(used) < 2:
        return g0
    pair = np.stack([bands[gi][used], bands[g0][used]])           # (2, K, bands, 6)
    wins = 0
    for _ in range(resamples):
        w = np.bincount(rng.integers(0, len(used), len(used)), minlength=len(used)).astype(float)
        sb = np.einsum("k,gkbc->gbc", w, pair)
        wins += _band_spread(sb[0]) < _band_spread(sb[1])
    return gi if wins >= (1 - level) * resamples else g0


def _band_spread(s_bands: np.ndarray) -> float:
    """How much the thresholds fitted per intensity band disagree: sum of squared log deviations."""
    logs = []
    for b in range(s_bands.shape[0]):
        c = solve(s_bands[b])
        if np.isfinite(c).all():
            logs.append(np.log(c))
    if len(logs) < 2:
        return float("inf")
    logs = np.asarray(logs)
    return float(((logs - logs.mean(0)) ** 2).sum() / (len(logs) - 1))


KNEES = (0.5, 0.3, 0.2, 0.15, 0.1, 0.075, 0.05, 0.03, 0.02, 0.01, 0.005)


def log_intensity(F: np.ndarray, dark: float, knee: float, full: float) -> np.ndarray:
    """The simulator's lin-log curve (ev3dgs.logmap.safe_log) of the frames' linear intensity."""
    from ..logmap import safe_log

    return safe_log(np.clip((F - dark) / (full - dark), 0.0, None), knee)


def curve_grid(rec: Recording) -> list[tuple[float, float]]:
    """Candidate (dark DN, log knee) pairs along one line: at dark 0, knees from 0.5 down to 0.005 (the DVS
    photoreceptor's own dark current: its log bends over at the dark end of the frames); then, at the
    simulator's default knee, dark levels from 0 up to just below the darkest well-exposed level."""
    from ..logmap import DEFAULT_LOG_KNEE

    top = min(float(np.percentile(rec.frames, 0.5)), 40.0)
    step = max(1.0, float(np.ceil(top / 12)))
    darks = np.arange(0.0, np.floor(top) + 1e-9, step)
    return [(0.0, k) for k in KNEES] + [(float(d), DEFAULT_LOG_KNEE) for d in darks]


def fit_thresholds(rec: Recording, on: np.ndarray, off: np.ndarray, exclude: np.ndarray | None = None,
                   boot: int = 200, seed: int = 0, curve: tuple[float, float] | None = None,
                   refractory_us: float = 0.0) -> ThresholdFit:
    """Fit C_on, C_off, mismatch sigma and the dark level (or use `dark`); exclude = pixels to leave out
    (hot pixels). Raises InputError when no pair has a usable change in both directions."""
    P = rec.width * rec.height
    exclude = np.zeros(P, bool) if exclude is None else exclude
    noise = frame_noise(rec)
    F = rec.frames.reshape(len(rec.frames), -1)
    mean_dn = 0.5 * (F[1:] + F[:-1])
    ok = ~rec.saturated().reshape(len(F), -1)
    good = (ok[1:] & ok[:-1] & (mean_dn > 3))
    band_edges = np.percentile(mean_dn[good], [100 / 3, 200 / 3]) if good.any() else np.array([85.0, 170.0])
    from ..logmap import DEFAULT_LOG_KNEE

    grid = [curve] if curve is not None else curve_grid(rec)
    notes = []
    from .aps import held_weights, pair_counts

    held = pair_counts(rec, held_weights(rec, refractory_us)) if refractory_us > 0 else None
    for run_starts in (False, True):
        totals, bands, samples = [], [], []
        for g in grid:
            smp = _Samples(rec, on, off, g, noise, band_edges, exclude, held, run_starts)
            smp.fit()
            sb = smp.sums(smp.band, smp.nb)                     # (P, bands, 6)
            samples.append(smp)
            bands.append(sb)
            totals.append(sb.sum(1))
        spread = np.array([_band_spread(b.sum(0)) for b in bands])
        gi = int(np.argmin(spread)) if np.isfinite(spread).any() else 0
        gi = _significant_curve(grid, bands, gi, np.random.default_rng(seed + 2))
        smp, tot = samples[gi], totals[gi]
        used = (tot[:, [1, 2, 4, 5]].sum(1) > 0) | (np.abs(tot[:, [0, 3]]).sum(1) > 0)
        keep = used
        outlier = np.zeros(P, bool)
        c_on, c_off = solve(tot[keep].sum(0))
        if np.isfinite([c_on, c_off]).all():
            # robust: drop pixels whose summed residual is an outlier (flicker, pixels whose APS and DVS
            # disagree), allowing for the mismatch (a pixel's own threshold off the mean by sigma misses by sigma
            # N), so that the spread being measured is not trimmed: the trimmed model's spread, 5 robust s.d.
            mom0 = mismatch_moments(smp.dL, smp.on, smp.off, smp.up, smp.dn, c_on, c_off)[keep]
            s_on0, s_off0 = _mismatch(mom0, c_on, c_off, None, 0, _trim_samples(smp, keep, c_on, c_off, seed),
                                      spread_only=True)
            r = np.stack([tot[:, 0] - c_on * tot[:, 1] + c_off * tot[:, 2],
                          tot[:, 3] - c_off * tot[:, 5] + c_on * tot[:, 4]])
            scale = 1.4826 * np.median(np.abs(r[:, used])) + 1e-12
            spread = np.sqrt(scale ** 2 + np.stack([(s_on0 * tot[:, 1]) ** 2 + (s_off0 * tot[:, 2]) ** 2,
                                                    (s_off0 * tot[:, 5]) ** 2 + (s_on0 * tot[:, 4]) ** 2]))
            outlier[used] = (np.abs(r / spread)[:, used] > 5).any(0)
            keep = used & ~outlier
            c_on, c_off = solve(tot[keep].sum(0))
        if np.isfinite([c_on, c_off]).all():
            break
        if not run_starts:
            notes.append("no run of two frame pairs going the same way in both directions: the first pair of "
                         "each run is used too, which biases the thresholds up (the pixels are still crossing "
                         "their dead band there)")
    if not np.isfinite([c_on, c_off]).all():
        raise InputError(f"{rec.path}: no frame pair shows a log-intensity change with events in both directions "
                         "on well-exposed pixels: the contrast thresholds cannot be fitted")
    notes.append(f"{int((smp.up0 & ~smp.up).sum() + (smp.dn0 & ~smp.dn).sum())} of "
                 f"{int(smp.up0.sum() + smp.dn0.sum())} frame pairs trimmed (residual beyond both thresholds "
                 "plus 4 sigma of frame noise)")
    notes.append(f"{int(outlier.sum())} pixels dropped as outliers of the threshold fit")
    # bootstrap over pixels, the dark level refitted each time
    rng = np.random.default_rng(seed)
    kidx = np.flatnonzero(keep)
    bt = np.stack([b[kidx] for b in bands])               # (G, K, bands, 6)
    boots = []
    for _ in range(boot):
        w = np.bincount(rng.integers(0, len(kidx), len(kidx)), minlength=len(kidx)).astype(float)
        sb = np.einsum("k,gkbc->gbc", w, bt)
        sp = [_band_spread(x) for x in sb]
        j = int(np.argmin(sp)) if np.isfinite(sp).any() else gi
        boots.append((*solve(sb[j].sum(0)), j))
    boots = np.asarray(boots).reshape(-1, 3)
    fin = np.isfinite(boots).all(1)
    se = boots[fin].std(0, ddof=1) if fin.sum() > 2 else np.full(3, np.nan)
    # mismatch from products of the fit's frame pairs, and the thresholds corrected with it: both statistics
    # (the ratio of sums and the pair products) are modelled with the trim that selected their pairs
    mom = mismatch_moments(smp.dL, smp.on, smp.off, smp.up, smp.dn, c_on, c_off)[keep]
    s_on, s_off, c_on_v, c_off_v, dcdh = _mismatch(mom, c_on, c_off, rng, boot,
                                                   _trim_samples(smp, keep, c_on, c_off, seed))
    c_on, c_off = c_on_v.value, c_off_v.value
    # the thresholds' s.e.: the ratio of sums' (curve choice included) through dc/dh, and the spread's part
    for i, v in enumerate((c_on_v, c_off_v)):
        se[i] = float(np.hypot(dcdh[i] * se[i], v.se or 0.0)) if np.isfinite(se[i]) else np.nan
    sig_vals = [v.value for v in (s_on, s_off) if v.value is not None]
    if sig_vals:
        sigma = float(np.sqrt(np.mean(np.square(sig_vals))))
        # d sigma = sum(s_i ds_i) / (n sigma): independent errors
        parts = [(v.value * v.se) ** 2 for v in (s_on, s_off) if v.value is not None and v.se is not None]
        se_sig = float(np.sqrt(sum(parts)) / (len(sig_vals) * sigma)) if sigma > 0 and parts else None
        sigma_v = Value(sigma, se_sig, "rms of the ON and OFF spreads (the simulator draws both with one sigma)")
    else:
        sigma_v = Value(None, None, s_on.note if s_on.value is None else s_off.note)
    gd = np.array([g[0] for g in grid])
    gk = np.log10([g[1] for g in grid])
    js = boots[fin, 2].astype(int) if fin.any() else np.array([gi])
    se_d = float(gd[js].std(ddof=1)) if len(js) > 2 else None
    se_k = float(gk[js].std(ddof=1)) if len(js) > 2 else None
    edge = len(grid) > 1 and gi in (0, len(grid) - 1)
    why = (f"at the end of the searched range: not pinned down" if edge else
           "the grid value that makes the thresholds of three intensity bands agree best")
    if curve is not None:
        dark_v, knee_v = Value(curve[0], None, "given"), Value(curve[1], None, "given")
    else:
        dark_v = Value(float(grid[gi][0]), se_d, why)
        knee_v = Value(float(grid[gi][1]), se_k, why + "; +- in decades") if grid[gi][1] != DEFAULT_LOG_KNEE \
            else Value(None, se_k, f"the frames prefer the simulator's default {DEFAULT_LOG_KNEE:g} (a dark "
                                   f"offset of {grid[gi][0]:g} DN instead)")
    used_ev = int(tot[keep][:, [1, 2, 4, 5]].sum())
    return ThresholdFit(Value(c_on, float(se[0])), Value(c_off, float(se[1])), sigma_v, s_on, s_off, dark_v, knee_v,
                        float(np.median(noise[1])), int(keep.sum()), int(smp.up[:, keep].sum()),
                        int(smp.dn[:, keep].sum()), used_ev, notes)


def _pair_products(E: np.ndarray, N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, sum over every two of its selected frame pairs k != l at least two apart of E_k E_l and
    N_k N_l: (sum E)^2 - sum E^2 - 2 sum E_k E_k+1 (zeros where a pair is not selected)."""
    def cross(X):
        s1 = X.sum(0)
        return s1 * s1 - (X * X).sum(0) - 2 * (X[1:] * X[:-1]).sum(0)

    return cross(E), cross(N)


def mismatch_moments(dL, on, off, up, dn, c_on: float, c_off: float) -> np.ndarray:
    """(P, 4) per pixel [A_on, B_on, A_off, B_off]: for every two selected pairs of a pixel at least two pairs
    apart, A = sum e_k e_l with e = dL - C_on N_on + C_off N_off (up pairs; the sign flipped for down pairs)
    and B = sum N_k N_l (N = the pair's ON, resp. OFF count)."""
    e = dL - c_on * on + c_off * off
    out = []
    for m, sgn, n in ((up, 1.0, on), (dn, -1.0, off)):
        a, b = _pair_products(np.where(m, sgn * e, 0.0), np.where(m, n, 0).astype(float))
        out += [a, b]
    return np.stack(out, 1)


def _clipped_normal_nodes(c: float, sigma: float, floor: float, n: int = 2001):
    """Nodes and weights of N(c, sigma) clipped below at `floor`: the clipped mass as a point at the floor,
    the rest by Simpson's rule on [floor, c + 8 sigma] (the simulator's draw, effects.mismatch)."""
    from scipy.stats import norm

    if sigma <= 1e-9 * abs(c):
        return np.array([max(c, floor)]), np.array([1.0])
    lo = max(floor, c - 8 * sigma)
    x = np.linspace(lo, c + 8 * sigma, n)
    wx = np.full(n, 2.0)
    wx[1::2] = 4.0
    wx[0] = wx[-1] = 1.0
    wx *= (x[1] - x[0]) / 3 * norm.pdf(x, c, sigma)
    return np.concatenate([[floor], x]), np.concatenate([[norm.cdf(floor, c, sigma)], wx])


def model_moments(c: float, sigma: float, floor: float = 0.01) -> tuple[float, float]:
    """What the fit reads for per-pixel thresholds C_i ~ N(c, sigma) clipped at `floor` (the simulator's
    ThresholdMismatch): the ratio of sums (a harmonic mean, H = 1 / E[1/C_i]) and the pair-product statistic,
    whose pixel weights are their squared counts, proportional to 1/C_i^2: V = E[(C_i - H)^2 / C_i^2] /
    E[1 / C_i^2]."""
    ci, w = _clipped_normal_nodes(c, sigma, floor)
    w = w / w.sum()
    h = 1.0 / float(w @ (1.0 / ci))
    v = float(w @ ((ci - h) ** 2 / ci ** 2)) / float(w @ (1.0 / ci ** 2))
    return h, v


def invert_moments(h_obs: float, v_obs: float, floor: float = 0.01) -> tuple[float, float]:
    """(nominal threshold c, sigma) whose model_moments are (h_obs, v_obs): the bias correction of both the
    count-weighted threshold (a harmonic mean: low) and the count-weighted mismatch (high: pixels with a low
    threshold fire more and weigh more). sigma = 0 when v_obs <= 0."""
    from scipy.optimize import least_squares

    if not (np.isfinite(h_obs) and np.isfinite(v_obs)) or v_obs <= 1e-12 * h_obs ** 2 or h_obs <= floor:
        return h_obs, 0.0

    def res(p):
        h, v = model_moments(p[0], p[1], floor)
        return [(h - h_obs) / h_obs, (v - v_obs) / v_obs]

    x0 = [h_obs, float(np.sqrt(v_obs))]
    r = least_squares(res, x0, bounds=([floor * 1.01, 0.0], [np.inf, np.inf]), xtol=1e-12, ftol=1e-12,
                      gtol=1e-12, x_scale=[h_obs, max(x0[1], 1e-6)])
    return float(r.x[0]), float(r.x[1])


TRIM_SAMPLE = 300   # frame pairs (D, T) the trimmed model averages over (a random subset of the fit's)


def _trim_samples(smp: _Samples, keep: np.ndarray, c_on: float, c_off: float, seed: int):
    """Per polarity (D, T) of up to TRIM_SAMPLE of the fit's frame pairs (before the trim, kept pixels): the
    pair's change in its own direction and the trim's bound, for trimmed_moments."""
    trim = c_on + c_off + TAU_SIGMAS * smp.sd
    srng = np.random.default_rng(seed + 3)
    out = []
    for m0, sgn in ((smp.up0, 1.0), (smp.dn0, -1.0)):
        m0 = m0 & keep[None, :]
        D, T = sgn * smp.dL[m0], trim[m0]
        pick = srng.choice(len(D), min(TRIM_SAMPLE, len(D)), replace=False) if len(D) else np.zeros(0, int)
        out.append((D[pick], T[pick]))
    return out


def _mismatch(mom: np.ndarray, c_on: float, c_off: float, rng, boot: int, samples=None, spread_only=False):
    """ON and OFF mismatch from the pair products (see mismatch_moments) and the thresholds corrected with it:
    (sigma_on, sigma_off, c_on, c_off as Values, (dc_on/dh_on, dc_off/dh_off)). samples: per polarity the
    (change D, trim T) of the fit's frame pairs for trimmed_moments; None: no trim (T infinite).

    Derivation. For one pixel with threshold C_i, an up pair's e_k = (C_i - C) N_k + r_k, where the residual
    r_k = d_k - d_k+1 (the pixel's distance from its reference at the two exposure midpoints) has zero mean and
    depends only on the pair's two ends; two pairs at least two apart share no end, so E[r_k r_l] = 0 and
    E[e_k e_l] = (C_i - C)^2 N_k N_l. Frame noise enters e through the two frames of a pair only, so it drops
    out too. Summed over every such pair of pairs of every pixel, sum A / sum B estimates a count-weighted
    (C_i - C)^2: every event and every frame pair of a pixel with two or more non-adjacent selected pairs
    counts, whatever its number of events. The weights (N_k N_l, proportional to 1 / C_i^2), the harmonic
    mean C of the ratio of sums and the trim that selected the pairs bias it; trimmed_moments models all three
    for the simulator's clipped normal draws, and invert_trimmed solves for (c, sigma). The trim matters where
    many pixels sit near the floor: their counts follow 1 / C_i only until the refractory period limits them
    and shot noise (scaled by the nominal over the pixel's threshold) adds to them, and the untrimmed model,
    whose weights 1 / C_i^2 make them dominate, then reads both moments wrong (C's OFF threshold 0.2 with
    sigma 0.12: -45 % thresholds); trimmed, both the data and the model leave them out alike.

    Uncertainty: bootstrap over pixels of the pair products, mapped to (c, sigma) by the inversion's Jacobian
    (the delta method; one inversion per resample would cost seconds each)."""
    if samples is None:
        samples = [(np.ones(1), np.full(1, np.inf))] * 2
    if spread_only:   # (sigma_on, sigma_off) of the full sample, 0 where none: no bootstrap, no Values
        out = []
        for j, h, (D, T) in zip((0, 2), (c_on, c_off), samples):
            A, B = mom[:, j].sum(), mom[:, j + 1].sum()
            sig = invert_trimmed(h, A / B, D, T)[1] if B > 0 else 0.0
            out.append(float(sig) if np.isfinite(sig) else 0.0)
        return tuple(out)
    n = len(mom)
    idx = [rng.integers(0, n, n) for _ in range(boot)]
    used = [int(((mom[:, j + 1] > 0)).sum()) for j in (0, 2)]
    vals, cs, dcdh = [], [], []
    for i, (pol, j, h, (D, T)) in enumerate(zip(("ON", "OFF"), (0, 2), (c_on, c_off), samples)):
        A, B = mom[:, j].sum(), mom[:, j + 1].sum()
        v = A / B if B > 0 else np.nan
        vb = np.array([mom[k, j].sum() / max(mom[k, j + 1].sum(), 1e-300) for k in idx])
        c, sig = invert_trimmed(h, v, D, T)
        if sig > 0:
            dh, dv = 1e-3 * h, 1e-3 * v
            ch, sh = invert_trimmed(h + dh, v, D, T)
            cv, sv = invert_trimmed(h, v + dv, D, T)
            jac = np.array([[(ch - c) / dh, (cv - c) / dv], [(sh - sig) / dh, (sv - sig) / dv]])
            cb, sb = c + jac[0, 1] * (vb - v), sig + jac[1, 1] * (vb - v)
        else:
            jac = np.array([[1.0, 0.0], [0.0, 0.0]])
            cb, sb = np.full(len(vb), c), np.sqrt(np.clip(vb, 0, None))
        c_se = float(cb.std(ddof=1)) if len(vb) > 2 else None
        s_se = float(sb.std(ddof=1)) if len(vb) > 2 and np.isfinite(sb).all() else None
        cs.append(Value(float(c), c_se))
        dcdh.append(float(jac[0, 0]))
        if not np.isfinite(sig) or used[i] == 0:
            vals.append(Value(None, None, f"no pixel has two {pol} frame pairs at least two pairs apart"))
        elif sig <= 0 or (s_se is not None and s_se > sig):
            se_text = "" if s_se is None else f" +- {s_se:.2g}"
            why = "no spread beyond the counting noise" if sig <= 0 else "the standard error exceeds the value"
            vals.append(Value(None, s_se, f"{sig:.3g}{se_text} from {used[i]} pixels: {why}"))
        else:
            vals.append(Value(float(sig), s_se, f"{used[i]} pixels, products of frame pairs two or more apart"))
    return vals[0], vals[1], cs[0], cs[1], tuple(dcdh)

def _triangle_nodes(n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint nodes and weights of the triangular density on (-1, 1): the count residual N - D / C of a pair
    (the reference phases at its two ends, each uniform over a threshold)."""
    e = (np.arange(n) + 0.5) / n * 2 - 1
    w = 1 - np.abs(e)
    return e, w / w.sum()


def trimmed_moments(c: float, sigma: float, h: float, D: np.ndarray, T: np.ndarray, floor: float = 0.01,
                    nodes: int = 201) -> tuple[float, float]:
    """What the trimmed fit reads for per-pixel thresholds C_i ~ N(c, sigma) clipped at `floor`: the ratio of
    sums (h) and the pair-product statistic (v), with the trim that selects the pairs in the model.

    A selected pair of change D (> 0, the pair's own direction) on a pixel of threshold x holds N = D / x + eps
    events, eps the count residual of the reference phases at its two ends (triangular on (-1, 1)); the fit
    keeps it when its residual e = D - h N = D (1 - h / x) - h eps lies within T (the trim, centred on the
    fitted threshold h). Then, averaged over the recording's pairs (D, T) and eps:
      h = E_x[sum D K] / E_x[sum (D / x K + E[eps 1_kept])]              (K = P(kept | D, x)),
      v = E_x[M1(x)^2] / E_x[M0(x)^2],  M1 = mean E[e 1_kept], M0 = mean E[N 1_kept]
    (two pairs of one pixel at least two apart have independent residuals: E[e_k e_l] = M1^2 per pixel). A
    pixel far below the mean fires many events per pair and its pairs fall outside the trim: the model drops
    them as the fit does, so the low tail at the floor (refractory-limited, noise-dominated pixels the counts'
    1 / x law does not describe) no longer decides the estimate."""
    x, w = _clipped_normal_nodes(c, sigma, floor, nodes)
    w = w / w.sum()
    e, we = _triangle_nodes()
    a = D[None, :, None] * (1 - h / x[:, None, None])                     # (X, D, 1)
    res = a - h * e[None, None, :]                                         # (X, D, E)
    kept = (np.abs(res) <= T[None, :, None]) * we[None, None, :]
    K = kept.sum(2)                                                       # (X, D)
    n_kept = D[None, :] / x[:, None] * K + (kept * e[None, None, :]).sum(2)
    m1 = (kept * res).sum(2).mean(1)
    m0 = n_kept.mean(1)
    hh = float(w @ (D[None, :] * K).mean(1)) / max(float(w @ m0), 1e-300)
    v = float(w @ (m1 * m1)) / max(float(w @ (m0 * m0)), 1e-300)
    return hh, v


def invert_trimmed(h_obs: float, v_obs: float, D: np.ndarray, T: np.ndarray,
                   floor: float = 0.01) -> tuple[float, float]:
    """(c, sigma) whose trimmed_moments are (h_obs, v_obs), with the trim centred on h_obs (the fit's own)."""
    from scipy.optimize import least_squares

    if not (np.isfinite(h_obs) and np.isfinite(v_obs)) or v_obs <= 1e-12 * h_obs ** 2 or h_obs <= floor or not len(D):
        return h_obs, 0.0

    def res(p):
        hm, vm = trimmed_moments(p[0], p[1], h_obs, D, T, floor)
        return [(hm - h_obs) / h_obs, (vm - v_obs) / v_obs]

    x0 = [h_obs, float(np.sqrt(v_obs))]
    r = least_squares(res, x0, bounds=([floor * 1.01, 0.0], [np.inf, np.inf]), xtol=1e-10, ftol=1e-10,
                      gtol=1e-10, x_scale=[h_obs, max(x0[1], 1e-6)], diff_step=1e-3)
    return float(r.x[0]), float(r.x[1])


def invert_trimmed_mean(h_obs: float, sigma: float, D: np.ndarray, T: np.ndarray, floor: float = 0.01) -> float:
    """The nominal threshold c whose trimmed_moments h is h_obs at a given sigma."""
    from scipy.optimize import brentq

    if sigma <= 0 or not len(D) or not np.isfinite(h_obs):
        return h_obs
    f = lambda c: trimmed_moments(c, sigma, h_obs, D, T, floor)[0] - h_obs   # noqa: E731
    lo, hi = max(floor * 1.01, 0.3 * h_obs), 3 * h_obs
    if f(lo) * f(hi) > 0:
        return h_obs
    return float(brentq(f, lo, hi, xtol=1e-6 * h_obs))
