"""Trainer building blocks: event binning/pairs, blur and event losses, sRGB transfer, SSIM/PSNR metrics."""
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.logmap import DEFAULT_LOG_KNEE, safe_log_torch
from ev3dgs.sensor import LUMINANCE_WEIGHTS, cfa_channels
from ev3dgs.train.events import bin_signed_events, pair_list, pair_targets, pose_counts, sub_pose_times
from ev3dgs.train.losses import (average_loss, blur_average, blur_loss, linear_to_srgb_torch, log_intensity,
                                 pose_event_loss, srgb_to_linear_torch, ssim)
from ev3dgs.train.metrics import lpips_unavailable_reason, psnr, ssim_metric

torch.set_default_dtype(torch.float32)


# ----------------------------------------------------------------------------------------------- events

def test_sub_pose_times_ends_and_spacing():
    exp = np.array([[1000, 2000], [0, 7], [5, 5], [10**12, 10**12 + 33333]], dtype=np.int64)
    for n in (2, 3, 5, 9):
        t = sub_pose_times(exp, n)
        assert t.dtype == np.int64 and t.shape == (4, n)
        assert np.array_equal(t[:, 0], exp[:, 0]) and np.array_equal(t[:, -1], exp[:, 1])
        assert np.all(np.diff(t, axis=1) >= 0)
        for v in range(4):
            expect = [exp[v, 0] + round(k * (exp[v, 1] - exp[v, 0]) / (n - 1)) for k in range(n)]
            assert np.array_equal(t[v], expect)
    even = sub_pose_times(np.array([[0, 1000]]), 5)
    assert np.array_equal(even[0], [0, 250, 500, 750, 1000])
    assert np.all(np.diff(even[0]) == 250)
    mid = sub_pose_times(np.array([[1000, 2000], [0, 10]]), 1)
    assert np.array_equal(mid[:, 0], [1500, 5])
    with pytest.raises(ValueError):
        sub_pose_times(exp, 0)


def _brute_bins(t, x, y, p, times, h, w):
    n, k = times.shape
    out = np.zeros((n, k - 1, h, w), np.float64)
    for v in range(n):
        for b in range(k - 1):
            lo, hi = times[v, b], times[v, b + 1]
            last = b == k - 2
            for ti, xi, yi, pi in zip(t.tolist(), x.tolist(), y.tolist(), p.tolist()):
                if lo <= ti and (ti <= hi if last else ti < hi):
                    out[v, b, yi, xi] += pi
    return out


@pytest.mark.parametrize("k", [2, 3, 4, 6])
def test_bin_signed_events_matches_brute_force_and_keeps_inputs(k):
    rng = np.random.default_rng(k)
    h, w = 5, 7
    exposure = np.array([[0, 1000], [1500, 2600], [400, 1200], [5000, 6000], [3000, 3000]], np.int64)
    times = sub_pose_times(exposure, k)
    # random events over [0, 4000) (none in view 3's window), plus events exactly on every boundary
    t = np.concatenate([rng.integers(0, 4000, 300), times[:3].ravel(), times[4].ravel()]).astype(np.int64)
    t.sort(kind="stable")
    e = len(t)
    x = rng.integers(0, w, e).astype(np.uint16)
    y = rng.integers(0, h, e).astype(np.uint16)
    p = np.where(rng.random(e) < 0.5, -1, 1).astype(np.int8)
    copies = [a.copy() for a in (t, x, y, p, times)]
    bins = bin_signed_events(t, x, y, p, times, h, w)
    assert bins.dtype == np.float32 and bins.shape == (5, k - 1, h, w)
    np.testing.assert_array_equal(bins, _brute_bins(t, x, y, p, times, h, w))
    assert not bins[3].any()  # window without events
    for a, c in zip((t, x, y, p, times), copies):
        assert np.array_equal(a, c) and a.dtype == c.dtype
    # an empty window (zero-length bins) and an empty stream
    empty = bin_signed_events(t[:0], x[:0], y[:0], p[:0], times, h, w)
    assert empty.shape == (5, k - 1, h, w) and not empty.any()


def test_bin_signed_events_end_event_counts_in_last_bin():
    times = np.array([[0, 10, 20]], np.int64)
    t = np.array([0, 10, 20, 21], np.int64)
    x = np.zeros(4, np.uint16)
    y = np.zeros(4, np.uint16)
    p = np.array([1, 1, -1, 1], np.int8)
    b = bin_signed_events(t, x, y, p, times, 1, 1)
    assert b[0, :, 0, 0].tolist() == [1.0, 0.0]  # +1 at 10 and -1 at 20 (inclusive end) share bin 1; 21 is out


def test_pair_list_all_and_random():
    assert pair_list(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    assert pair_list(1) == []
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    a, b = pair_list(5, 4, g1), pair_list(5, 4, g2)
    assert a == b and len(set(a)) == 4 and all(0 <= i < j < 5 for i, j in a)
    with pytest.raises(ValueError):
        pair_list(3, 4)


def test_pair_targets_brute_force_and_bins_untouched():
    rng = np.random.default_rng(0)
    bins = torch.from_numpy(rng.integers(-3, 4, (5, 4, 6)).astype(np.float32))
    before = bins.clone()
    pairs = pair_list(6)
    tg = pair_targets(bins, pairs)
    assert tg.shape == (len(pairs), 4, 6)
    for i, (k1, k2) in enumerate(pairs):
        brute = np.zeros((4, 6), np.float32)
        for kk in range(k1, k2):
            brute += before[kk].numpy()
        np.testing.assert_array_equal(tg[i].numpy(), brute)
    assert torch.equal(bins, before)
    tg += 100.0  # results must not alias the bins
    assert torch.equal(bins, before)


# ----------------------------------------------------------------------------------------------- sRGB

def test_srgb_round_trip_and_finite_gradients():
    x = torch.linspace(0, 1, 1001, dtype=torch.float64)
    np.testing.assert_allclose(linear_to_srgb_torch(srgb_to_linear_torch(x)).numpy(), x.numpy(), atol=1e-12)
    np.testing.assert_allclose(srgb_to_linear_torch(linear_to_srgb_torch(x)).numpy(), x.numpy(), atol=1e-12)
    assert float(srgb_to_linear_torch(torch.tensor(1.0))) == pytest.approx(1.0)
    for fn in (srgb_to_linear_torch, linear_to_srgb_torch):
        z = torch.tensor([-0.5, 0.0, 1e-9, 0.003, 0.04045, 0.5, 1.0, 1.2], requires_grad=True)
        fn(z).sum().backward()
        assert torch.isfinite(z.grad).all()


# ----------------------------------------------------------------------------------------------- event loss

def _renders(value, k=3, h=4, w=4):
    return torch.full((k, h, w, 3), float(value), requires_grad=True)


def event_loss(log_l, pair_counts, pairs, tp, tn):
    """The one-pair form the tests below state their expectations in: the loss of pair (0, 1) with
    ``pair_counts`` (1, 2, H, W) ON/OFF or (1, H, W) net (n > 0: n ON events, n < 0: |n| OFF) events
    between the two poses, through the trainer's pose_event_loss (cumulative counts: pose 0 has none)."""
    assert list(pairs) == [(0, 1)] and log_l.shape[0] == 2
    c = pair_counts.float()
    if c.ndim == 3:
        c = torch.stack([c.clamp(min=0), (-c).clamp(min=0)], dim=1)
    return pose_event_loss(log_l, torch.cat([torch.zeros_like(c), c]), pairs, tp, tn)


def _random_pose_counts(k, h, w, high, generator=None):
    """Cumulative ON/OFF counts (k, 2, h, w) from random per-interval counts in [0, high)."""
    return pose_counts(torch.randint(0, high, (k - 1, 2, h, w), generator=generator).float())


@pytest.mark.parametrize("value", [0.0, 1.0])
@pytest.mark.parametrize("cf", ["none", "RGGB"])
def test_event_loss_finite_at_black_and_white(value, cf):
    r = _renders(value)
    pairs = pair_list(3)
    counts = pose_counts(torch.ones(2, 2, 4, 4))
    loss = pose_event_loss(log_intensity(r, cf), counts, pairs, 0.2, 0.3)
    assert torch.isfinite(loss) and loss >= 0
    loss.backward()
    assert torch.isfinite(r.grad).all()


def test_event_loss_sign_and_hand_computed_prediction():
    tp, tn = 0.25, 0.4
    dark = torch.full((1, 2, 2, 3), 0.4)  # linear 0.133, above the log knee
    bright = torch.full((1, 2, 2, 3), 0.7)
    log_up = log_intensity(torch.cat([dark, bright]))  # later pose brighter
    d = float(log_up[1, 0, 0] - log_up[0, 0, 0])
    assert d > 0
    # log of the luminance of the linear values (all channels equal -> luminance = the channel value)
    lin = lambda s: (s / 1.055 + 0.055 / 1.055) ** 2.4  # noqa: E731
    assert d == pytest.approx(math.log(lin(0.7)) - math.log(lin(0.4)), rel=1e-5)
    n = 3.0
    pos = event_loss(log_up, torch.full((1, 2, 2), n), [(0, 1)], tp, tn)
    neg = event_loss(log_up, torch.full((1, 2, 2), -n), [(0, 1)], tp, tn)
    assert pos < neg
    # residual in log units over the mean threshold: zero target -> (d / theta_mean)^2 either way
    tm = 0.5 * (tp + tn)
    z = event_loss(log_up, torch.zeros(1, 2, 2), [(0, 1)], tp, tn)
    assert float(z) == pytest.approx((d / tm) ** 2, rel=1e-5)
    log_down = log_intensity(torch.cat([bright, dark]))
    zd = event_loss(log_down, torch.zeros(1, 2, 2), [(0, 1)], tp, tn)
    assert float(zd) == pytest.approx((d / tm) ** 2, rel=1e-5)
    # a net count n > 0 means n ON events (expected change n * theta_on), n < 0 |n| OFF (n * theta_off)
    ll = torch.tensor([[[0.0, 0.0]], [[0.5, -0.6]]])
    got = event_loss(ll, torch.tensor([[[1.0, -1.0]]]), [(0, 1)], tp, tn)
    want = ((0.5 - tp) ** 2 + (-0.6 + tn) ** 2) / 2 / tm ** 2
    assert float(got) == pytest.approx(want, rel=1e-6)
    # ON/OFF pair counts: expected theta_on * n_on - theta_off * n_off
    onoff = torch.tensor([[[[3.0, 1.0]], [[1.0, 2.0]]]])  # (P=1, 2, H=1, W=2): ON (3, 1), OFF (1, 2)
    got = event_loss(ll, onoff, [(0, 1)], tp, tn)
    want = ((0.5 - (3 * tp - tn)) ** 2 + (-0.6 - (tp - 2 * tn)) ** 2) / 2 / tm ** 2
    assert float(got) == pytest.approx(want, rel=1e-6)
    # symmetric thresholds: exactly the old mean((delta / theta - n)^2), so --event-weight keeps its meaning
    old = ((0.5 / 0.2 - 1.0) ** 2 + (-0.6 / 0.2 + 1.0) ** 2) / 2
    assert float(event_loss(ll, torch.tensor([[[1.0, -1.0]]]), [(0, 1)], 0.2, 0.2)) == pytest.approx(old, rel=1e-6)


def test_event_loss_learnable_thresholds_get_finite_gradients():
    torch.manual_seed(0)
    r = torch.rand(4, 5, 5, 3)
    r[0] = 0.0  # exact black pose
    r.requires_grad_(True)
    tp = torch.tensor(0.2, requires_grad=True)
    tn = torch.tensor(0.3, requires_grad=True)
    pairs = pair_list(4)
    loss = pose_event_loss(log_intensity(r), _random_pose_counts(4, 5, 5, 4), pairs, tp, tn)
    loss.backward()
    for g in (tp.grad, tn.grad, r.grad):
        assert g is not None and torch.isfinite(g).all()
    assert float(tp.grad) != 0.0 and float(tn.grad) != 0.0


def test_log_intensity_luminance_and_bayer_channel():
    torch.manual_seed(1)
    h, w = 4, 6
    base = torch.rand(1, h, w, 3) * 0.8 + 0.1
    lum = log_intensity(base, "none")
    lin = srgb_to_linear_torch(base)
    expect = safe_log_torch((lin * torch.as_tensor(LUMINANCE_WEIGHTS, dtype=lin.dtype)).sum(-1), DEFAULT_LOG_KNEE)
    torch.testing.assert_close(lum, expect)
    before = log_intensity(base, "RGGB")
    moved = base.clone()
    moved[..., 0] += 0.05  # only the R channel changes
    after = log_intensity(moved, "RGGB")
    is_r = torch.from_numpy(cfa_channels("RGGB", h, w) == 0)
    changed = (after != before)[0]
    assert torch.equal(changed, is_r)
    assert is_r[0, 0] and not is_r[0, 1] and not is_r[1, 0] and not is_r[1, 1]
    with pytest.raises(ValueError):
        log_intensity(base, "XYZW")


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), tp=st.floats(0.01, 2.0), tn=st.floats(0.01, 2.0),
       k=st.integers(2, 5), extreme=st.sampled_from(["none", "black", "white"]))
def test_event_loss_nonnegative_finite_property(seed, tp, tn, k, extreme):
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(k, 3, 4, 3, generator=g)
    if extreme == "black":
        r[0] = 0.0
    elif extreme == "white":
        r[-1] = 1.0
    r.requires_grad_(True)
    pairs = pair_list(k)
    loss = pose_event_loss(log_intensity(r), _random_pose_counts(k, 3, 4, 21, g), pairs, tp, tn)
    assert torch.isfinite(loss) and float(loss.detach()) >= 0.0
    loss.backward()
    assert torch.isfinite(r.grad).all()


# ----------------------------------------------------------------------------------------------- SSIM / blur

def _gauss11():
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5 ** 2))
    return g / g.sum()


def _ssim_numpy(a, b):
    """Independent SSIM: explicit separable zero-padded numpy convolution, per channel."""
    g = _gauss11()

    def blur(z):
        h, w, c = z.shape
        zp = np.zeros((h + 10, w + 10, c))
        zp[5:-5, 5:-5] = z
        rows = sum(g[i] * zp[i:i + h] for i in range(11))  # (h, w+10, c)
        return sum(g[j] * rows[:, j:j + w] for j in range(11))

    mu1, mu2 = blur(a), blur(b)
    s1 = blur(a * a) - mu1 ** 2
    s2 = blur(b * b) - mu2 ** 2
    s12 = blur(a * b) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s1 + s2 + c2))
    return m.mean()


def test_ssim_identity_symmetry_and_independent_numpy():
    rng = np.random.default_rng(5)
    a = rng.random((23, 31, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    # float64: the 11x11 window sums 121 O(1) terms (error <= 121 u ~ 1.3e-14, in any summation order the
    # conv kernel picks), and the variance terms are divided by C2 = 9e-4: <= ~1.5e-11 per pixel, the mean
    # does not amplify. TOL leaves a margin of ~70; a wrong window or constant differs by > 1e-3.
    TOL = 1e-9
    assert float(ssim(ta, ta)) == pytest.approx(1.0, abs=TOL)
    assert float(ssim(ta, tb)) == pytest.approx(float(ssim(tb, ta)), abs=TOL)
    assert float(ssim(ta, tb)) == pytest.approx(_ssim_numpy(a, b), abs=TOL)
    assert ssim_metric(a, b) == pytest.approx(_ssim_numpy(a, b), abs=TOL)
    # ssim_metric casts float32 input to float64 first (exactly), so against the float64 maths on the same
    # values the same bound holds (numpy on float32 would round a*a to float32: a different computation)
    a32 = a.astype(np.float32)
    assert ssim_metric(a32, b) == pytest.approx(_ssim_numpy(a32.astype(np.float64), b), abs=TOL)


def test_ssim_matches_scipy_gaussian_filter():
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(6)
    a, b = rng.random((20, 17, 3)), rng.random((20, 17, 3))

    def blur(z):  # truncate 5/1.5 -> radius int(5 + 0.5) = 5, an 11-tap window; zero padding as conv2d
        return ndimage.gaussian_filter(z, sigma=(1.5, 1.5, 0), truncate=5 / 1.5, mode="constant", cval=0.0)

    mu1, mu2 = blur(a), blur(b)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu1 * mu2 + c1) * (2 * (blur(a * b) - mu1 * mu2) + c2)) / (
        (mu1 ** 2 + mu2 ** 2 + c1) * (blur(a * a) - mu1 ** 2 + blur(b * b) - mu2 ** 2 + c2))
    # same bound as above: 121-term window sums, divided by C2 = 9e-4
    assert float(ssim(torch.from_numpy(a), torch.from_numpy(b))) == pytest.approx(m.mean(), abs=1e-9)


def _plain(render, target, lam):
    return (1 - lam) * torch.mean((render - target) ** 2) + lam * (1 - ssim(render, target))


def test_blur_loss_single_identical_and_linear_space():
    torch.manual_seed(2)
    r = torch.rand(1, 16, 16, 3, dtype=torch.float64)
    tgt = torch.rand(16, 16, 3, dtype=torch.float64)
    for lam in (0.0, 0.2, 1.0):
        assert float(blur_loss(r, tgt, lam)) == pytest.approx(float(_plain(r[0], tgt, lam)), abs=1e-12)
        assert float(blur_loss(r, tgt, lam, "linear")) == pytest.approx(float(_plain(r[0], tgt, lam)), abs=1e-10)
    same = r.expand(4, -1, -1, -1)
    for space in ("srgb", "linear"):
        assert float(blur_loss(same, tgt, 0.2, space)) == pytest.approx(float(_plain(r[0], tgt, 0.2)), abs=1e-10)
    diff = torch.rand(3, 16, 16, 3, dtype=torch.float64)
    assert abs(float(blur_loss(diff, tgt, 0.2, "srgb")) - float(blur_loss(diff, tgt, 0.2, "linear"))) > 1e-6
    with pytest.raises(ValueError):
        blur_loss(diff, tgt, 0.2, "log")
    diff.requires_grad_(True)
    blur_loss(diff, tgt, 0.2, "linear").backward()
    assert torch.isfinite(diff.grad).all()


# ----------------------------------------------------------------------------------------------- metrics

def test_psnr_identical_uint8_and_value():
    rng = np.random.default_rng(7)
    u = rng.integers(0, 256, (8, 9, 3), dtype=np.uint8)
    v = rng.integers(0, 256, (8, 9, 3), dtype=np.uint8)
    same = psnr(u, u)
    assert math.isfinite(same) and same >= 100
    assert psnr(u, v) == pytest.approx(psnr(u / 255.0, v / 255.0), abs=1e-12)
    assert psnr(torch.from_numpy(u / 255.0), v) == pytest.approx(psnr(u, v), abs=1e-12)
    assert psnr(np.zeros((2, 2)), np.full((2, 2), 0.1)) == pytest.approx(20.0)


def test_lpips_reason(tmp_path):
    assert "--lpips-weights" in lpips_unavailable_reason(None)
    assert "--lpips-weights" in lpips_unavailable_reason(tmp_path / "missing.pth")
    assert lpips_unavailable_reason(tmp_path) is not None  # a directory is not a weights file
    f = tmp_path / "w.pth"
    f.write_bytes(b"x")
    assert lpips_unavailable_reason(f) is None


def test_ssim_separable_equals_the_2d_window_float64():
    """The separable SSIM equals graphdeco's 2-D 11x11 window version (values and gradients) to rounding."""
    import math

    import torch.nn.functional as F

    from ev3dgs.train.losses import ssim

    def ssim_2d(a, b):
        g = torch.tensor([math.exp(-((i - 5) ** 2) / (2 * 1.5 ** 2)) for i in range(11)], dtype=torch.float64)
        g = g / g.sum()
        win = torch.outer(g, g).expand(3, 1, 11, 11).contiguous()
        x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
        conv = lambda z: F.conv2d(z, win, padding=5, groups=3)  # noqa: E731
        mu1, mu2 = conv(x), conv(y)
        s1, s2, s12 = conv(x * x) - mu1 ** 2, conv(y * y) - mu2 ** 2, conv(x * y) - mu1 * mu2
        m = ((2 * mu1 * mu2 + 1e-4) * (2 * s12 + 9e-4)) / ((mu1 ** 2 + mu2 ** 2 + 1e-4) * (s1 + s2 + 9e-4))
        return m.mean()

    gen = torch.Generator().manual_seed(0)
    for h, w in ((5, 7), (24, 31), (72, 96)):
        a = torch.rand(h, w, 3, generator=gen, dtype=torch.float64, requires_grad=True)
        b = torch.rand(h, w, 3, generator=gen, dtype=torch.float64)
        x, y = ssim(a, b), ssim_2d(a, b)
        ga, = torch.autograd.grad(x, a)
        gb, = torch.autograd.grad(y, a)
        assert abs(float((x - y).detach())) < 1e-12 and float((ga - gb).abs().max()) < 1e-12


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.sampled_from(["none", "RGGB"]))
def test_shared_linear_decode_equals_two_decodes(seed, cf):
    """The trainer decodes the renders to linear light once and hands that to blur_average and log_intensity
    (``linear=``). Values: the same operations on the same numbers, so bitwise equal to each decoding on its
    own. Gradients (float64): autograd now adds the two losses' gradients before the one decode's backward,
    f'(x) (g1 + g2) instead of f'(x) g1 + f'(x) g2; both are within a few ulps (a couple of roundings of
    each product and sum) of the exact value, so they agree to 1e-12 relative to the gradient's scale."""
    g = torch.Generator().manual_seed(seed)
    stack = (torch.rand(3, 6, 5, 3, generator=g, dtype=torch.float64) * 1.1 - 0.05).requires_grad_(True)
    target = torch.rand(6, 5, 3, generator=g, dtype=torch.float64)
    counts = torch.randint(0, 3, (3, 2, 6, 5), generator=g).to(torch.float64)
    pairs = [(0, 1), (0, 2), (1, 2)]

    def losses(shared):
        lin = srgb_to_linear_torch(stack) if shared else None
        avg = blur_average(stack, "linear", linear=lin)
        log_l = log_intensity(stack, cf, transfer="srgb", linear=lin)
        return avg, log_l, average_loss(avg, target) + pose_event_loss(log_l, counts, pairs, 0.2, 0.25)

    avg1, log1, l1 = losses(False)
    avg2, log2, l2 = losses(True)
    assert torch.equal(avg1, avg2) and torch.equal(log1, log2) and torch.equal(l1, l2)
    other = srgb_to_linear_torch(stack.detach()) * 0.5  # the argument is used, not recomputed
    assert not torch.equal(blur_average(stack, "linear", linear=other), avg1)
    assert not torch.equal(log_intensity(stack, cf, transfer="srgb", linear=other), log1)
    assert torch.equal(blur_loss(stack, target, 0.2, "linear"), average_loss(blur_average(stack, "linear"), target))
    (g1,) = torch.autograd.grad(l1, stack)
    (g2,) = torch.autograd.grad(l2, stack)
    assert torch.all(torch.isfinite(g1))
    assert float((g1 - g2).abs().max()) <= 1e-12 * max(1.0, float(g1.abs().max()))


def test_shared_linear_decode_rejects_a_wrong_shape():
    stack = torch.rand(2, 4, 4, 3)
    with pytest.raises(ValueError, match="linear must have"):
        blur_average(stack, "linear", linear=torch.rand(1, 4, 4, 3))
    with pytest.raises(ValueError, match="linear must have"):
        log_intensity(stack, linear=torch.rand(2, 4, 3, 3))
