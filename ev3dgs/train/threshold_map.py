"""Per-pixel contrast thresholds (``--threshold-map``): the sensor's fixed-pattern mismatch, estimated.

A DVS pixel's ON and OFF thresholds differ from the nominal ones by a fixed per-pixel factor (mismatch,
sigma / theta of a few to tens of percent). The same pixel sees different scene content in every view, so
the pattern is identifiable: a pixel whose counts overshoot the rendered log change in every view has a
threshold below nominal. Here each pixel's multipliers m_on, m_off (thresholds theta_on m_on, theta_off m_off)
are the MAP estimate of a linear model, solved in closed form per pixel after every step:

    d_k = m_on A_on,k - m_off A_off,k + noise,   noise variance sigma_k^2 = theta^2 / 6 + floor g_k,
    prior m ~ N(1, s^2) for each polarity, independently,

over the consecutive sub-pose bins k of every view's latest visit: d the rendered log change of the bin,
A = nominal threshold x the polarity's count in it, sigma^2 the quantisation plus the model's own error
(the noise norm's floor, carried into log units by g = 1 / I^2 at the rendered intensities: see
losses.noise_event_loss), s the relative mismatch. A pixel that fired little keeps the nominal thresholds.
The posterior covariance (the 2 x 2 normal matrix's inverse) gives each pixel's remaining threshold error.
By default (``--map-weights prior``) the event term still weighs the counts by the prior's mismatch
variance, as without a map: the map changes the thresholds, not the weights. The posterior spread treats
the model's error as independent between bins and views, which it is not (one model renders them all), and
weighing by it (``--map-weights posterior``: (s_on theta_on n_on)^2 + (s_off theta_off n_off)^2 in place of
the prior's, losses.count_variance) lost on two of the three built-in scenes with a mismatch where the
prior's weights did not (docs/fidelity.md).

Why closed form and not a gradient step per view: a per-element optimiser (Adam) moves every pixel by
about its learning rate whatever the evidence, so pixels with little information drift with the noise of
single views; the normal equations weigh each view by what it says. Consecutive bins share their ends, so
their quantisation errors are correlated; for a monotone change the bins' sum of squared counts is below
the total's square, so the information is undercounted and the spread errs on the cautious side.
"""

from __future__ import annotations

import torch

MIN_MULTIPLIER, MAX_MULTIPLIER = 0.2, 5.0   # a fitted threshold stays within these factors of the nominal one
SMOOTH_PX = 4.0   # sigma (pixels) of the low-pass removed from the fitted pattern: it takes ~1 / (4 pi sigma^2)
                  # = 0.5 % of a white pattern's variance, and the slowly varying part of the model's error


class ThresholdMap:
    """Per-pixel ON/OFF multipliers m (2, H, W) of the nominal thresholds, fitted in closed form.

    Each visit of view v stores, per pixel, the normal equations of that view's bins: the rendered change
    d of each bin against m_on A_on - m_off A_off (A = nominal threshold x count) with variance
    sigma^2 = theta^2 / 6 + floor g. The map is the MAP estimate from every view's latest equations and the
    prior m ~ N(1, s^2); its posterior covariance gives the spread the event term's mismatch variance
    uses. Nothing here is a trained parameter: the map follows the model as the model fits, like the floor."""

    def __init__(self, rel_mismatch: float, n_views: int, height: int, width: int, device,
                 dtype=torch.float32):
        if not rel_mismatch > 0:
            raise ValueError(f"a threshold map needs a mismatch > 0 to set its prior, got {rel_mismatch!r}")
        self.s = float(rel_mismatch)
        # per view: sums over its bins of A_on^2, A_off^2, -A_on A_off, A_on d, -A_off d (each / sigma^2)
        self.stats = torch.zeros(int(n_views), 5, height, width, device=device, dtype=dtype)
        self.multiplier = torch.ones(2, height, width, device=device, dtype=dtype)   # what the event term uses
        self.fitted = self.multiplier.clone()    # each pixel's MAP before the local mean is divided out
        self.calibration = torch.ones(2, device=device, dtype=dtype)   # c of _calibrate, ON and OFF
        self.spread = torch.full((2, height, width), self.s, device=device, dtype=dtype)

    def thresholds(self, tp: torch.Tensor, tn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(H, W) ON and OFF threshold maps from the nominal ones (0-d, possibly learned themselves)."""
        return tp * self.multiplier[0], tn * self.multiplier[1]

    @torch.no_grad()
    def update(self, view: int, bins: torch.Tensor, tp: torch.Tensor, tn: torch.Tensor, floor: float,
               log_l: torch.Tensor, knee: float | None) -> None:
        """Replace view ``view``'s equations from its (K-1, 2, H, W) bins, the nominal thresholds (tp, tn),
        the model floor (linear intensity^2) and the (K, H, W) rendered log intensities; solve again."""
        tp, tn = tp.detach().to(self.stats.dtype), tn.detach().to(self.stats.dtype)
        log_l = log_l.detach().to(self.stats.dtype)
        if knee is None:
            g = torch.ones_like(log_l)
        else:
            g = log_l.exp().clamp(min=knee) ** -2
        w = 1.0 / (0.5 * (tp * tp + tn * tn) / 6.0 + floor * 0.5 * (g[:-1] + g[1:]))   # (K-1, H, W)
        b = bins.to(self.stats.dtype)
        a_on, a_off, d = tp * b[:, 0], tn * b[:, 1], log_l[1:] - log_l[:-1]
        self.stats[view] = torch.stack([(w * a_on * a_on).sum(0), (w * a_off * a_off).sum(0),
                                        -(w * a_on * a_off).sum(0), (w * a_on * d).sum(0),
                                        -(w * a_off * d).sum(0)])
        self._solve()

    def _solve(self) -> None:
        t = self.stats.sum(0).to(torch.float64)   # in double: the sums reach ~1e7 where counts are large
        p = 1.0 / (self.s * self.s)
        m00, m11, m01 = t[0] + p, t[1] + p, t[2]
        r0, r1 = t[3] + p, t[4] + p              # the prior pulls towards m = 1
        # det = (a + p)(b + p) - c^2 >= p (a + b) + p^2 since a b >= c^2 (Cauchy-Schwarz); where A_on and
        # A_off are proportional, a b - c^2 is all rounding and can come out negative: hold it to the bound
        det = torch.maximum(m00 * m11 - m01 * m01, p * (m00 + m11) - p * p)
        self.fitted = m = torch.stack([(m11 * r0 - m01 * r1) / det,
                                       (m00 * r1 - m01 * r0) / det]).clamp(MIN_MULTIPLIER, MAX_MULTIPLIER)
        self.spread = torch.stack([(m11 / det).sqrt(), (m00 / det).sqrt()])
        # the fixed pattern is white (independent per pixel); what the model renders wrong is not: a model
        # smoother than the scene renders smaller changes than the counts measure, in every view, near where
        # the scene's texture is. Divide the map by its local mean over the pixels the counts say more about
        # than the prior (unweighted: a pixel's information grows as its threshold falls, so weighting by it
        # would favour low thresholds); the mismatch has mean 1
        informed = self.spread ** -2 > 2 * p
        w = informed.to(m.dtype)
        low = (_blur(w * m) + (1 - _blur(w)).clamp(min=0)).clamp(min=MIN_MULTIPLIER)  # no information: 1
        self._calibrate(m / low, informed)

    def _calibrate(self, m: torch.Tensor, informed: torch.Tensor) -> None:
        """Empirical Bayes on the model's error. Per pixel the MAP is m - 1 = k (ML - 1), k = 1 - spread^2 /
        s^2, the ML estimate's noise variance sig^2 = spread^2 / k. If the noise model holds, the informed
        pixels' mean (m - 1)^2 is the mean of k^2 (s^2 + sig^2) = s^2 - spread^2. Where it is larger, the
        rendering errs more than the floor says (its error is not independent between bins and views); the
        noise variances are scaled by the c >= 1 (one per polarity) that makes the two agree, and each pixel
        shrunk again with it: k' = s^2 / (s^2 + c sig^2), m' - 1 = (k' / k)(m - 1), spread'^2 = k' c sig^2.
        A map the model's error dominates stays near 1 (and its events weigh as without it)."""
        s2 = self.s * self.s
        spread2 = self.spread ** 2
        k = (1 - spread2 / s2).clamp(min=1e-6)
        sig2 = spread2 / k
        c = torch.ones(2, 1, 1, dtype=m.dtype, device=m.device)
        for j in range(2):
            sel = informed[j]
            if bool(sel.any()):
                kk = k[j][sel] ** 2
                excess = ((m[j][sel] - 1) ** 2).mean() - (kk * s2).mean()
                c[j] = (excess / (kk * sig2[j][sel]).mean()).clamp(min=1.0)
        k2 = s2 / (s2 + c * sig2)
        dtype = self.stats.dtype
        self.calibration = c.flatten().to(dtype)
        self.multiplier = (1 + (k2 / k) * (m - 1)).clamp(MIN_MULTIPLIER, MAX_MULTIPLIER).to(dtype)
        self.spread = (k2 * c * sig2).sqrt().to(dtype)
        self.fitted = self.fitted.to(dtype)

    def state_dict(self) -> dict:
        return {"stats": self.stats.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.stats.copy_(state["stats"])
        self._solve()


def _blur(x: torch.Tensor) -> torch.Tensor:
    """(C, H, W) -> the same, Gaussian-blurred with sigma SMOOTH_PX (zero outside the image: a normalised
    convolution divides two of these)."""
    r = int(3 * SMOOTH_PX)
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (t / SMOOTH_PX) ** 2)
    k = k / k.sum()
    y = torch.nn.functional.conv2d(x[:, None], k.view(1, 1, 1, -1), padding=(0, r))
    y = torch.nn.functional.conv2d(y, k.view(1, 1, -1, 1), padding=(r, 0))
    return y[:, 0]
