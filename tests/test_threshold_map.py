"""Learned per-pixel thresholds (train/threshold_map.py): the fixed pattern is recovered from counts made with
it, as precisely as the Laplace posterior the map reports, and the terms stay finite at the extremes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from ev3dgs.train.losses import FLOOR_MIN, count_variance, noise_event_loss
from ev3dgs.train.threshold_map import ThresholdMap

H, W = 32, 32


def _views(rng, n_views, k, theta, e_on, e_off, model_error=0.0):
    """Per view: (K, H, W) log intensities as the model renders them and the (K-1, 2, H, W) ON/OFF bins a
    random-phase sensor with per-pixel thresholds theta (1 + e) fires along the true ones. The true change is
    linear over the exposure, up or down at random, up to 1.5 log units; the reference starts a random
    fraction of a threshold from the signal. The rendering adds an independent N(0, model_error^2) error to
    each bin's change (a random walk in the log intensity)."""
    out = []
    th_on, th_off = theta * (1 + e_on), theta * (1 + e_off)
    for _ in range(n_views):
        start = rng.uniform(-1.0, 0.0, (H, W))
        change = rng.uniform(-1.5, 1.5, (H, W))
        lt = start[None] + change[None] * np.linspace(0, 1, k)[:, None, None]
        d = lt - start[None]
        phase = rng.uniform(0, 1, (H, W))
        on = np.where(d > 0, np.floor(np.clip(d, 0, None) / th_on + phase), 0)
        off = np.where(d < 0, np.floor(np.clip(-d, 0, None) / th_off + phase), 0)
        cum = np.stack([on, off], axis=1)                      # (K, 2, H, W) cumulative since pose 0
        walk = np.concatenate([np.zeros((1, H, W)), np.cumsum(rng.normal(0, model_error, (k - 1, H, W)), 0)])
        out.append((torch.tensor(lt + walk, dtype=torch.float64), torch.tensor(np.diff(cum, axis=0))))
    return out


def _fit(views, theta, s, passes=1, floor=FLOOR_MIN):
    """The map from every view's equations, the model's error variance per bin ``floor`` (log units)."""
    tmap = ThresholdMap(s, len(views), H, W, "cpu", dtype=torch.float64)
    tp = tn = torch.tensor(theta, dtype=torch.float64)
    for _ in range(passes):
        for v, (log_l, bins) in enumerate(views):
            tmap.update(v, bins, tp, tn, floor, log_l, None)
    return tmap


def _lowpass_gain(sigma_px: float) -> np.ndarray:
    """(H, W): the variance a white unit-variance pattern leaves in the map's local mean at each pixel, sum of
    the squared Gaussian weights inside the image (zero outside, as the map's normalised convolution)."""
    r = int(3 * sigma_px)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_px) ** 2)
    k /= k.sum()

    def along(n):
        return np.array([sum(k[j - i + r] ** 2 for j in range(n) if abs(j - i) <= r) for i in range(n)])

    return along(H)[:, None] * along(W)[None, :]


def _error_and_prediction(tmap, e, theta, s) -> tuple[float, float]:
    """The map's RMS error against 1 + e, and the RMS the analysis predicts (see the next test)."""
    from ev3dgs.train.threshold_map import SMOOTH_PX

    rms_err = float(np.sqrt(np.mean((tmap.multiplier.numpy() - (1 + e)) ** 2)))
    spread2 = tmap.spread.numpy() ** 2
    bias2 = ((theta ** 2 / 6) / (1.5 ** 2 / 3 / 16)) ** 2 * (1 + e) ** 2
    local2 = _lowpass_gain(SMOOTH_PX)[None] * (s ** 2 + spread2)
    return rms_err, float(np.sqrt(np.mean(spread2 + bias2 + local2)))


def test_the_fixed_pattern_is_recovered_to_its_posterior_spread():
    """Per-pixel thresholds theta (1 + e), e ~ N(0, 0.3^2) fixed across 12 views, a rendering whose bin changes
    are off by N(0, 0.05^2) (the model's error, which dominates the quantisation at theta = 0.05 as in
    training): the map matches 1 + e as well as the analysis says, far better than the nominal thresholds
    (error RMS = s). The expected squared error per pixel, from the analysis: the posterior variance the map
    reports; the attenuation the counts' quantisation (variance theta^2 / 6 per bin, on the regressor's side)
    brings, at most theta^2 / 6 / E[d^2] = 4.2e-4 / 0.047 of m (E[d^2] = 1.5^2 / 3 / 16 for these changes);
    and the local mean the map divides by, which sees the white pattern and its estimation noise through the
    squared weights of its kernel (_lowpass_gain). Tolerance: 4 standard errors of an RMS from 2048 samples
    (1 / sqrt(2 * 2048)) on top."""
    rng = np.random.default_rng(0)
    theta, s, sigma = 0.05, 0.3, 0.05
    e = np.clip(s * rng.standard_normal((2, H, W)), -0.6, None)
    views = _views(rng, 12, 5, theta, e[0], e[1], model_error=sigma)
    tmap = _fit(views, theta, s, floor=sigma ** 2)
    rms_err, predicted = _error_and_prediction(tmap, e, theta, s)
    assert float(np.sqrt(np.mean(tmap.spread.numpy() ** 2))) < 0.5 * s     # the counts pin the pattern
    assert rms_err <= predicted * (1 + 4 / math.sqrt(2 * e.size))
    assert rms_err < 0.5 * float(np.sqrt(np.mean(e ** 2)))


def test_a_rendering_worse_than_the_floor_says_is_shrunk_and_reported_honestly():
    """The rendering's bin changes are off by N(0, 0.15^2) but the map is told a floor 100 times smaller, with
    a 10 % pattern the model's error swamps: the calibration finds the noise (c near 100, against 2-3 at the
    true floor, where the quantisation and the local mean add their share) and shrinks the map towards 1, so
    it is still no worse than the nominal thresholds and its reported spread is as honest as the analysis of
    the first test says (same tolerance)."""
    rng = np.random.default_rng(0)
    theta, s, sigma = 0.05, 0.1, 0.15
    e = np.clip(s * rng.standard_normal((2, H, W)), -0.6, None)
    views = _views(rng, 12, 5, theta, e[0], e[1], model_error=sigma)
    told = _fit(views, theta, s, floor=sigma ** 2)
    fooled = _fit(views, theta, s, floor=sigma ** 2 / 100)
    assert (fooled.calibration > 10 * told.calibration).all()
    rms_err, predicted = _error_and_prediction(fooled, e, theta, s)
    assert rms_err <= predicted * (1 + 4 / math.sqrt(2 * e.size))
    assert rms_err < float(np.sqrt(np.mean(e ** 2)))


def test_one_pixel_is_the_weighted_least_squares_solution():
    """One pixel, two views, bins with ON and OFF events: its fit is the MAP of the linear model, computed
    here as an augmented least-squares problem (numpy lstsq on rows sqrt(w) [A_on, -A_off] -> sqrt(w) d and
    the prior's rows [1, 0] / s -> 1 / s, [0, 1] / s -> 1 / s), its spread the square roots of the diagonal
    of the inverse normal matrix."""
    theta_on, theta_off, s, floor = 0.2, 0.15, 0.25, 1e-3
    paths = [np.array([0.0, 0.5, 0.7, 1.3]), np.array([0.2, -0.4, -0.3, -0.9])]
    on = [np.array([2.0, 1.0, 3.0]), np.array([0.0, 1.0, 0.0])]
    off = [np.array([1.0, 0.0, 0.0]), np.array([4.0, 0.0, 4.0])]
    tmap = ThresholdMap(s, 2, 1, 1, "cpu", dtype=torch.float64)
    rows, rhs = [], []
    w = 1 / (0.5 * (theta_on ** 2 + theta_off ** 2) / 6 + floor)
    for v in range(2):
        bins = torch.tensor(np.stack([on[v], off[v]], axis=1)).reshape(3, 2, 1, 1)
        tmap.update(v, bins, torch.tensor(theta_on, dtype=torch.float64),
                    torch.tensor(theta_off, dtype=torch.float64), floor,
                    torch.tensor(paths[v]).reshape(4, 1, 1), None)
        for k in range(3):
            rows.append(np.sqrt(w) * np.array([theta_on * on[v][k], -theta_off * off[v][k]]))
            rhs.append(np.sqrt(w) * (paths[v][k + 1] - paths[v][k]))
    rows += [np.array([1 / s, 0.0]), np.array([0.0, 1 / s])]
    rhs += [1 / s, 1 / s]
    x = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    cov = np.linalg.inv(np.array(rows).T @ np.array(rows))
    assert tmap.fitted[:, 0, 0].numpy() == pytest.approx(x, rel=1e-10)
    assert tmap.spread[:, 0, 0].numpy() == pytest.approx(np.sqrt(np.diag(cov)), rel=1e-10)


def test_a_view_seen_again_replaces_its_equations_and_a_checkpoint_restores_the_map():
    rng = np.random.default_rng(2)
    views = _views(rng, 3, 5, 0.1, np.zeros((H, W)), np.zeros((H, W)))
    once, twice = _fit(views, 0.1, 0.2), _fit(views, 0.1, 0.2, passes=2)
    assert torch.equal(once.multiplier, twice.multiplier) and torch.equal(once.spread, twice.spread)
    again = ThresholdMap(0.2, 3, H, W, "cpu", dtype=torch.float64)
    again.load_state_dict(once.state_dict())
    assert torch.equal(again.multiplier, once.multiplier)


def test_without_events_the_prior_keeps_the_nominal_thresholds():
    """A static pixel fires nothing: the prior alone, the map stays at 1 with the prior's spread."""
    views = [(torch.zeros(5, H, W, dtype=torch.float64), torch.zeros(4, 2, H, W, dtype=torch.float64))
             for _ in range(3)]
    tmap = _fit(views, 0.2, 0.4)
    assert torch.equal(tmap.multiplier, torch.ones(2, H, W, dtype=torch.float64))
    assert torch.allclose(tmap.spread, torch.full((2, H, W), 0.4, dtype=torch.float64))
    with pytest.raises(ValueError, match="mismatch > 0"):
        ThresholdMap(0.0, 6, H, W, "cpu")


@settings(max_examples=40, deadline=None)
@given(theta=st.floats(0.01, 1.0), s=st.floats(0.01, 1.0), count=st.integers(0, 10_000),
       scale=st.floats(0.0, 30.0), floor=st.floats(1e-4, 1.0), seed=st.integers(0, 2 ** 16))
# large counts firing both ways in the same bins: the normal matrix's determinant is all rounding there
@example(theta=1.0, s=1.0, count=1926, scale=6.0, floor=1.0, seed=1)
def test_map_and_event_term_finite_with_finite_gradients(theta, s, count, scale, floor, seed):
    """Extreme counts, thresholds, spreads, rendered log intensities (down to the knee, up to e^30) and
    floors: the map stays finite and inside its bounds, its spread below the prior's, and the event term
    with it is finite with a finite gradient."""
    g = torch.Generator().manual_seed(seed)
    tmap = ThresholdMap(s, 2, 3, 4, "cpu")
    bins = torch.randint(0, count + 1, (2, 2, 3, 4), generator=g).float()
    counts = torch.cat([torch.zeros_like(bins[:1]), bins.cumsum(0)])
    log_l = (torch.rand(3, 3, 4, generator=g) * 2 - 1) * scale
    log_l.requires_grad_(True)
    tp = tn = torch.tensor(theta)
    tmap.update(0, bins, tp, tn, floor, log_l, 1e-3)
    mp, mn = tmap.thresholds(tp, tn)
    loss, est = noise_event_loss(log_l, counts, [(0, 1), (0, 2), (1, 2)], mp, mn, rel_mismatch=s, floor=floor,
                                 spread=tmap.spread)
    loss.backward()
    assert torch.isfinite(loss) and math.isfinite(est) and torch.isfinite(log_l.grad).all()
    assert torch.isfinite(tmap.multiplier).all() and torch.isfinite(tmap.spread).all()
    assert ((tmap.multiplier >= 0.2) & (tmap.multiplier <= 5.0)).all()
    assert (tmap.spread <= s * (1 + 1e-5)).all()


@settings(max_examples=50, deadline=None)
@given(tp=st.floats(0.01, 1.0), tn=st.floats(0.01, 1.0), s=st.floats(0.01, 1.0), seed=st.integers(0, 2 ** 16))
def test_mismatch_variance_joint_without_a_spread_independent_with_one(tp, tn, s, seed):
    """count_variance's two forms, written out in numpy for random cumulative counts: without ``spread`` the
    noise norm's theta^2 / 6 + (s (tp n_on + tn n_off))^2, the ON and OFF errors of a pixel taken as one; with a
    spread map of s everywhere theta^2 / 6 + (s tp n_on)^2 + (s tn n_off)^2, which is never larger (the
    cross term 2 s^2 tp tn n_on n_off >= 0) and smaller exactly where a pixel fired both ways in the pair."""
    rng = np.random.default_rng(seed)
    counts = np.cumsum(rng.integers(0, 4, (4, 2, 3, 5)), axis=0).astype(np.float64)
    idx = torch.tensor([[0, 1], [0, 3], [1, 2], [2, 3]])
    n = np.abs(counts[idx[:, 1]] - counts[idx[:, 0]])
    base = 0.5 * (tp * tp + tn * tn) / 6.0
    joint = base + (s * (tp * n[:, 0] + tn * n[:, 1])) ** 2
    indep = base + (s * tp * n[:, 0]) ** 2 + (s * tn * n[:, 1]) ** 2
    c = torch.tensor(counts)
    t_p, t_n = torch.tensor(tp, dtype=torch.float64), torch.tensor(tn, dtype=torch.float64)
    got_joint = count_variance(c, idx, t_p, t_n, s).numpy()
    got_indep = count_variance(c, idx, t_p, t_n, 0.7, spread=torch.full((2, 3, 5), s, dtype=torch.float64)).numpy()
    # float64 sums of a few products: rounding ~1e-15 relative
    assert got_joint == pytest.approx(joint, rel=1e-12) and got_indep == pytest.approx(indep, rel=1e-12)
    both = (n[:, 0] > 0) & (n[:, 1] > 0)
    # the cross term is at least 2 (0.01 * 0.01)^2 = 2e-8 where both fired, far above the rounding
    assert (got_indep <= got_joint * (1 + 1e-12)).all() and (got_indep[both] < got_joint[both]).all()
