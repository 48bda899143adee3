"""The noise-model event norm (losses.noise_event_loss, count_variance, update_floor) against an independent
simulation of the count noise, and its numerical behaviour at the extremes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.train.losses import (FLOOR_MIN, chi2_floor, count_variance, huber, huber_mean, noise_event_loss,
                                 pose_event_loss, update_floor)


def _simulate_counts(rng, change, theta, rel):
    """Pixels with their own thresholds theta (1 + e), e ~ N(0, rel^2), a random reference phase and a
    monotone log change `change` (> 0, per pixel): their ON counts (a crossing every threshold)."""
    th = theta * np.clip(1 + rel * rng.standard_normal(len(change)), 0.05, None)
    phase = rng.uniform(0, 1, len(change)) * th      # distance already travelled towards the next crossing
    return np.floor((change + phase) / th).astype(np.int64)


@pytest.mark.parametrize("theta,rel", [(0.05, 0.0), (0.2, 0.1), (0.1, 0.2)])
def test_count_variance_matches_simulated_error(theta, rel):
    """The variance model against brute-force counts: the error of theta * n (nominal threshold) as an
    estimate of a random change, with random phases at both ends (quantisation: the difference of two
    uniform residuals, theta^2 / 6) and per-pixel thresholds (mismatch, rel^2 a^2 to first order in e).
    Tolerance: 5 standard errors of a variance from n samples (sqrt(2 / n), generous for these bounded
    errors) plus the second-order term of 1 / (1 + e) that the model leaves out, 9 rel^2 relative."""
    rng = np.random.default_rng(0)
    n = 200_000
    change = rng.uniform(0.5, 1.0, n)
    counts = _simulate_counts(rng, change, theta, rel)
    err = theta * counts - change
    c = torch.zeros((2, 2, 1, n), dtype=torch.float64)
    c[1, 0, 0] = torch.from_numpy(counts).double()
    v = count_variance(c, torch.tensor([[0, 1]]), torch.tensor(theta, dtype=torch.float64),
                       torch.tensor(theta, dtype=torch.float64), rel)
    model = float(v.mean())
    measured = float(np.mean(err ** 2))
    assert measured == pytest.approx(model, rel=5 * math.sqrt(2 / n) + 9 * rel ** 2)


def test_count_variance_terms_by_hand():
    c = torch.zeros((3, 2, 1, 2), dtype=torch.float64)
    c[1, 0, 0, 0], c[2, 0, 0, 0], c[2, 1, 0, 0] = 2, 3, 1     # pixel 0: 3 ON, 1 OFF by pose 2
    tp, tn = torch.tensor(0.2, dtype=torch.float64), torch.tensor(0.3, dtype=torch.float64)
    idx = torch.tensor([[0, 2], [1, 2]])
    v = count_variance(c, idx, tp, tn, 0.1, torch.tensor([0.5, 0.0]))
    theta2 = 0.5 * (0.04 + 0.09)
    # pair (0, 2): 3 ON, 1 OFF -> a = 0.6 + 0.3; pair (1, 2): 1 ON, 1 OFF -> a = 0.5
    assert float(v[0, 0, 0]) == pytest.approx(theta2 / 6 + (0.1 * 0.9) ** 2 + theta2 * 0.5, rel=1e-12)
    assert float(v[1, 0, 0]) == pytest.approx(theta2 / 6 + (0.1 * 0.5) ** 2, rel=1e-12)
    assert float(v[0, 0, 1]) == pytest.approx(theta2 / 6 + theta2 * 0.5, rel=1e-12)   # no events: quantisation


def test_chi_square_is_one_when_residuals_follow_the_model():
    """Residuals drawn with the model's variance and a zero floor-excess give a loss near 1 (chi-square per
    sample), whatever the threshold: the term's size does not depend on theta; the count norm's grows as
    1 / theta^2 for the same log-unit residuals."""
    rng = np.random.default_rng(1)
    H, W = 64, 64
    out, out_count = [], []
    for theta in (0.05, 0.2):
        c = torch.from_numpy(rng.integers(0, 4, (5, 2, H, W)).cumsum(0)).double()
        tp = tn = torch.tensor(theta, dtype=torch.float64)
        pairs = [(a, b) for a in range(5) for b in range(a + 1, 5)]
        idx = torch.tensor(pairs)
        v = count_variance(c, idx, tp, tn, 0.1)
        # log renders whose pair differences match the expected change up to noise of variance v + floor:
        # build per-pose values, then check the loss on pairs (0, k) only (independent residuals)
        floor = 0.01
        E = tp * c[:, 0] - tn * c[:, 1]
        noise = torch.zeros(5, H, W, dtype=torch.float64)
        for k in range(1, 5):
            noise[k] = torch.from_numpy(rng.standard_normal((H, W))) * (v[pairs.index((0, k))] + floor).sqrt()
        log_l = E + noise
        star = [(0, k) for k in range(1, 5)]
        loss, _ = noise_event_loss(log_l, c, star, tp, tn, rel_mismatch=0.1, floor=floor, knee=None)
        out.append(float(loss))
        out_count.append(float(pose_event_loss(log_l, c, star, tp, tn)))
    n = 4 * H * W
    for x in out:   # mean of n chi-square(1) variables: s.d. sqrt(2 / n)
        assert x == pytest.approx(1.0, abs=5 * math.sqrt(2 / n))
    assert out_count[0] > 4 * out_count[1]


def test_update_floor_tracks_the_estimate_and_is_bounded():
    assert update_floor(None, 0.04) == pytest.approx(0.04)
    assert update_floor(None, -0.01) == FLOOR_MIN           # residual below the count noise
    f = None
    for _ in range(200):
        f = update_floor(f, 0.02)
    assert f == pytest.approx(0.02, rel=1e-6)
    assert update_floor(0.5, -1.0) >= FLOOR_MIN
    assert update_floor(0.02, float("nan")) == 0.02        # a non-finite step leaves the floor as it was
    assert update_floor(None, float("inf")) == FLOOR_MIN


def test_floor_estimate_is_the_excess_over_the_count_noise_in_intensity_units():
    """Residuals of known size at a known rendered intensity: the step's floor estimate is (r^2 - v) I^2."""
    K, H, W = 2, 3, 4
    I = 0.25
    c = torch.zeros(K, 2, H, W, dtype=torch.float64)
    log_l = torch.full((K, H, W), math.log(I), dtype=torch.float64)
    log_l[1] += 0.1                                   # r = 0.1 everywhere (no events: E = 0)
    _, est = noise_event_loss(log_l, c, [(0, 1)], 0.2, 0.2, rel_mismatch=0.0, floor=1e-2)   # knee 1e-3 < I
    v = 0.04 / 6
    g = 0.5 * (I ** -2 + (I * math.exp(0.1)) ** -2)
    assert est == pytest.approx((0.01 - v) / g, rel=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), theta=st.floats(0.01, 1.0), rel=st.floats(0.0, 0.5),
       n_pairs=st.integers(1, 4), outlier=st.floats(0.0, 1e4), stat=st.sampled_from(["mean", "median"]),
       c=st.sampled_from([0.0, 0.5, 3.0]))
def test_floor_estimate_and_loss_computed_independently(seed, theta, rel, n_pairs, outlier, stat, c):
    """The step's floor estimate and loss against numpy on the same samples: the mean (or the lower median:
    the middle value of an odd count, the lower of the two middle ones of an even count) over pairs and
    pixels of (r^2 - v) / g, with v and g computed here from their definitions (asymmetric thresholds,
    mismatch, the default knee) and one pixel the model renders far off; the loss is the mean of
    x = r^2 / (v + g), Huber-penalised beyond c: x, or 2 c sqrt(x) - c^2. In double: a sample is a few
    operations on values up to max |x| (a few ulps of it), the mean adds n of them; the median is one of
    the samples."""
    rng = np.random.default_rng(seed)
    K, H, W = 5, 4, 5
    log_np = rng.normal(math.log(0.3), 0.5, (K, H, W))
    log_np[-1, 0, 0] += outlier ** 0.5
    counts = rng.integers(0, 4, (K, 2, H, W)).cumsum(0)
    pairs = [(a, b) for a in range(K) for b in range(a + 1, K)][:n_pairs]
    tp, tn = theta, 1.3 * theta
    loss, got = noise_event_loss(torch.from_numpy(log_np), torch.from_numpy(counts), pairs, tp, tn,
                                 rel_mismatch=rel, floor=1.0, floor_stat=stat, huber_c=c)
    x, chi = [], []
    for a, b in pairs:
        d = (log_np[b] - log_np[a]) - (tp * (counts[b, 0] - counts[a, 0]) - tn * (counts[b, 1] - counts[a, 1]))
        n_on, n_off = np.abs(counts[b, 0] - counts[a, 0]), np.abs(counts[b, 1] - counts[a, 1])
        v = 0.5 * (tp ** 2 + tn ** 2) / 6 + (rel * (tp * n_on + tn * n_off)) ** 2
        inv2 = np.exp(log_np).clip(min=1e-3) ** -2
        g = 0.5 * (inv2[a] + inv2[b])
        x.append(((d * d - v) / g).ravel())
        chi.append((d * d / (v + g)).ravel())
    x, chi = np.concatenate(x), np.concatenate(chi)
    want = float(np.mean(x)) if stat == "mean" else float(np.sort(x)[(x.size - 1) // 2])
    assert got == pytest.approx(want, rel=1e-12, abs=1e-12 * float(np.abs(x).max()))
    pen = chi if c == 0 else np.where(chi <= c * c, chi, 2 * c * np.sqrt(chi) - c * c)
    assert float(loss) == pytest.approx(float(np.mean(pen)), rel=1e-12, abs=1e-12 * float(pen.max()))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), theta=st.floats(1e-3, 2.0), rel=st.floats(0.0, 1.0),
       scale=st.sampled_from([0.0, 1e-6, 1.0, 1e3]), floor=st.one_of(st.none(), st.floats(FLOOR_MIN, 10.0)),
       stat=st.sampled_from(["mean", "median"]), c=st.sampled_from([0.0, 3.0]))
def test_noise_loss_finite_with_finite_bounded_gradients(seed, theta, rel, scale, floor, stat, c):
    """Any threshold, mismatch, residual size, floor statistic and penalty: finite, non-negative loss and
    finite gradients, and the gradient per residual is bounded by 2 r / floor (never 1 / theta^2), and with
    the Huber penalty also by 2 c / sqrt(floor), whatever r."""
    g = torch.Generator().manual_seed(seed)
    K, H, W = 4, 6, 5
    log_l = (torch.randn(K, H, W, generator=g, dtype=torch.float64) * scale).requires_grad_(True)
    counts = torch.randint(0, 50, (K, 2, H, W), generator=g).cumsum(0)
    tp = torch.tensor(theta, dtype=torch.float64, requires_grad=True)
    pairs = [(0, 1), (1, 3), (0, 3)]
    loss, est = noise_event_loss(log_l, counts, pairs, tp, tp * 1.3, rel_mismatch=rel, floor=floor, knee=None,
                                 floor_stat=stat, huber_c=c)
    loss.backward()
    assert math.isfinite(float(loss.detach())) and float(loss.detach()) >= 0
    assert torch.isfinite(log_l.grad).all() and torch.isfinite(tp.grad)
    f = floor if floor is not None else max(est, FLOOR_MIN)
    # d loss / d log_l[k] = sum over the pairs holding k of +-2 r / (v + f) / n, |r| <= max |r|
    n = len(pairs) * H * W
    with torch.no_grad():
        d = log_l - (tp * counts[:, 0] - tp * 1.3 * counts[:, 1])
        r = torch.stack([d[b] - d[a] for a, b in pairs])
    per = 2 * float(r.abs().max()) / f
    if c > 0:   # beyond c: d/dr (2 c |r| / s - c^2) = 2 c / s, s = sqrt(v + f) >= sqrt(f)
        per = min(per, 2 * c / math.sqrt(f))
    bound = 2 * per / n          # every pose is in at most two of the pairs
    assert float(log_l.grad.abs().max()) <= bound * (1 + 1e-9) + 1e-300


def test_huber_is_the_square_within_c_and_linear_in_the_residual_beyond():
    """x <= c^2: x; beyond, 2 c sqrt(x) - c^2, which meets x at c^2 with the same slope (1) and at x = 4 c^2
    is 3 c^2; c = 0 leaves x as it is."""
    c = 3.0
    x = torch.tensor([0.0, 4.0, 9.0, 36.0, 1e6], dtype=torch.float64)
    assert huber(x, c).tolist() == pytest.approx([0.0, 4.0, 9.0, 27.0, 6e3 - 9.0], rel=1e-15)
    t = torch.tensor([9.0 - 1e-6, 9.0 + 1e-6], dtype=torch.float64)
    slopes = (huber(t + 1e-7, c) - huber(t, c)) / 1e-7
    assert slopes.tolist() == pytest.approx([1.0, 1.0], abs=1e-6)
    assert torch.equal(huber(x, 0.0), x)


@pytest.mark.parametrize("c", [0.5, 1.0, 3.0, 10.0])
def test_huber_mean_is_the_gaussian_expectation(c):
    """huber_mean(c) against a numerical integral of huber(z^2, c) over the standard normal density."""
    from scipy.integrate import quad
    from scipy.stats import norm

    def rho(z):
        return z * z if abs(z) <= c else 2 * c * abs(z) - c * c

    want = 2 * (quad(lambda z: rho(z) * norm.pdf(z), 0, c)[0] + quad(lambda z: rho(z) * norm.pdf(z), c, np.inf)[0])
    assert huber_mean(c) == pytest.approx(want, rel=1e-9)
    assert huber_mean(0.0) == 1.0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 1e2), tail=st.floats(0.0, 0.2),
       c=st.sampled_from([0.0, 3.0]))
def test_chi2_floor_is_the_root_found_independently(seed, scale, tail, c):
    """chi2_floor against scipy's brentq on the same function, mean huber(r^2 / (v + f g), c) - huber_mean(c),
    for residuals of a model error of known size (scale) with a share of them (tail) 30 times larger (2000
    pixel-pairs: all of them are used); brentq to 1e-12. Residuals the counts' noise already explains give
    FLOOR_MIN. From no start, from the root's neighbourhood and from far off (safeguarded Newton in log f,
    stopped when a step is below 1e-3: f within 0.1 %)."""
    from scipy.optimize import brentq

    rng = np.random.default_rng(seed)
    n = 2000
    v = rng.uniform(1e-3, 1e-2, n)
    g = rng.uniform(0.5, 4.0, n)
    sd = np.sqrt(v + scale * g) * np.where(rng.random(n) < tail, 30.0, 1.0)
    r2 = (rng.normal(size=n) * sd) ** 2
    T = tuple(torch.from_numpy(x) for x in (r2, v, g))
    got = [chi2_floor(*T, c, start) for start in (None, scale, 1e-4 * scale, 1e4)]

    def h(logf):
        x = r2 / (v + math.exp(logf) * g)
        pen = x if c == 0 else np.where(x <= c * c, x, 2 * c * np.sqrt(x) - c * c)
        return float(np.mean(pen)) - huber_mean(c)

    if h(math.log(FLOOR_MIN)) <= 0:
        assert got == [FLOOR_MIN] * 4
    else:
        want = math.exp(brentq(h, math.log(FLOOR_MIN), math.log(float(np.max((r2 - v) / g))), xtol=1e-12))
        assert got == pytest.approx([want] * 4, rel=1e-3)
    quiet = chi2_floor(*(torch.from_numpy(x) for x in (0.5 * v, v, g)), c)   # every r^2 below v
    assert quiet == FLOOR_MIN


def test_chi2_floor_on_a_heavy_tail_is_the_population_root():
    """The model error 1e-3 everywhere, 2 % of the pixel-pairs 100 times further off (a tail the model cannot
    render), v = 1e-4, g = 1: the mean excess is pulled to ~ 1e-3 (1 + 0.02 * 1e4) = 0.2, the median stays
    near 1e-3 times the median of a chi-square with one degree of freedom (0.45). The penalised chi-square
    floor lies between them, where the population equation puts it: E huber(a z^2, c) with a = s^2 / (v + f)
    in closed form (b = c / sqrt(a): a (1 - 2 (b phi(b) + Q(b))) + 2 (2 c sqrt(a) phi(b) - c^2 Q(b))), mixed
    98 / 2 and solved by brentq. The root is taken from CHI2_SAMPLES (16 384) evenly strided pixel-pairs of
    the 50 000, about 330 of them in the tail, whose mean |z| sets f through its square: a relative sampling
    error of about 2 * 0.6 / sqrt(330) = 6.6 %, so 25 % is about four of it."""
    from scipy.optimize import brentq
    from scipy.stats import norm

    rng = np.random.default_rng(0)
    n, c, v0 = 50_000, 3.0, 1e-4
    s2 = np.where(rng.random(n) < 0.02, 1e4, 1.0) * 1e-3
    r2 = torch.from_numpy(rng.normal(size=n) ** 2 * (s2 + v0))
    v, g = torch.full((n,), v0, dtype=torch.float64), torch.ones(n, dtype=torch.float64)
    excess = (r2 - v) / g
    mean, median = float(excess.mean()), float(excess.median())
    f = chi2_floor(r2, v, g, c)

    def pop(a):
        b = c / math.sqrt(a)
        q = norm.sf(b)
        return a * (1 - 2 * (b * norm.pdf(b) + q)) + 2 * (2 * c * math.sqrt(a) * norm.pdf(b) - c * c * q)

    def h(logf):
        fv = math.exp(logf) + v0
        return 0.98 * pop((1e-3 + v0) / fv) + 0.02 * pop((10.0 + v0) / fv) - huber_mean(c)

    want = math.exp(brentq(h, math.log(1e-4), math.log(100.0)))
    assert median < 1e-3 < f < mean and mean > 0.1
    assert f == pytest.approx(want, rel=0.25)


def test_noise_loss_rejects_bad_arguments():
    log_l = torch.zeros(3, 2, 2)
    c = torch.zeros(3, 2, 2, 2)
    with pytest.raises(ValueError):
        noise_event_loss(log_l, c, [(0, 1)], 0.2, 0.2, rel_mismatch=-0.1)
    with pytest.raises(ValueError):
        noise_event_loss(log_l, c, [(0, 1)], 0.2, 0.2, floor=0.0)
    with pytest.raises(ValueError):
        noise_event_loss(log_l[0], c, [(0, 1)], 0.2, 0.2)
    with pytest.raises(ValueError):
        noise_event_loss(log_l, c, [(0, 1)], 0.2, 0.2, floor_stat="mode")
    with pytest.raises(ValueError):
        noise_event_loss(log_l, c, [(0, 1)], 0.2, 0.2, huber_c=float("nan"))
    loss, _ = noise_event_loss(log_l, c, [], 0.2, 0.2)
    assert float(loss) == 0.0
