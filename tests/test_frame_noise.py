"""--frame-noise: Immerkaer's estimate of the frames' noise, and the blur weight it sets against the events.

The estimator is checked against its closed form (white Gaussian noise of known sigma, on images the mask
cancels: constants and linear ramps) and against a second implementation (SciPy's 2-D correlation)."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import correlate2d

from ev3dgs.train.frame_noise import MSE_MOMENTUM, W_MIN, blur_weight, estimate_noise, update_mse

MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], float)


def _ramp(n, h, w, c, rng):
    """Linear ramps a*y + b*x + d per frame and channel: the mask's response to them is exactly 0."""
    y, x = np.mgrid[0:h, 0:w].astype(float)
    a, b = rng.uniform(-0.002, 0.002, (2, n, 1, 1, c))
    d = rng.uniform(0.3, 0.7, (n, 1, 1, c))
    return a * y[None, :, :, None] + b * x[None, :, :, None] + d


def test_white_noise_on_a_ramp_gives_its_variance():
    """For white Gaussian noise the response is N(0, 36 sigma^2), so median |response| / (6 * 0.6745) is sigma.
    The sample median of |N(0, 1)| over n samples spreads by 1 / (2 f(m) sqrt(n)) = 0.787 / sqrt(n) (f the
    density of |N(0, 1)| at its median m = 0.6745), 1.17 / sqrt(n) relative; neighbouring responses share
    noise (9 taps), so n > M / 9: 0.4 % for M = 4 x 254 x 254 x 3, 0.8 % on the variance, and 3 % is almost
    four standard deviations. A ramp alone gives exactly 0."""
    rng = np.random.default_rng(5)
    clean = _ramp(4, 256, 256, 3, rng)
    for sigma in (0.01, 0.05):
        noisy = clean + rng.normal(0, sigma, clean.shape)
        assert estimate_noise(noisy) == pytest.approx(sigma ** 2, rel=0.03)
    assert estimate_noise(clean) == pytest.approx(0.0, abs=1e-20)


@settings(max_examples=80, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(0, 1), st.integers(8, 40), st.integers(8, 40))
def test_a_rounded_ramp_is_never_noise(a, b, c, h, w):
    """8-bit rounding of a linear ramp: each axis' second difference of the rounded values is -1, 0 or 1, so
    the mask's response is an integer of at most 4 levels and the median form reads at most 0.99 levels,
    under the one level below which the estimate is 0."""
    y, x = np.mgrid[0:h, 0:w]
    ramp = a * y + b * x + c + 128 - (a * h + b * w) / 2          # centred: within 0..255 for these slopes
    frames = np.rint(ramp).astype(np.uint8)[None, :, :, None]
    assert np.abs(correlate2d(frames[0, :, :, 0].astype(float), MASK, mode="valid")).max() <= 4
    assert estimate_noise(frames) == 0.0


def test_noise_above_one_level_is_kept_through_8_bit_rounding():
    """Gaussian noise of 5 levels on a ramp, rounded to 8 bits: the rounding adds 1/12 level^2 (0.3 %); the
    response is then an integer, so its median (about 6 * 5 * 0.6745 = 20.2 levels) is off by up to half a
    level, 2.5 % on sigma and 5 % on the variance, beside the median's 3 % spread (as above): 8 %."""
    rng = np.random.default_rng(11)
    ramp = _ramp(4, 256, 256, 3, rng) * 200 + 25    # 85-165 levels plus at most 0.4 per pixel: no clipping
    noisy = np.clip(np.rint(ramp + rng.normal(0, 5.0, ramp.shape)), 0, 255).astype(np.uint8)
    assert estimate_noise(noisy) == pytest.approx((5.0 / 255) ** 2, rel=0.08)


def test_edges_move_the_mean_form_but_not_the_median():
    """A sharp diagonal step across a noise-free frame gives large responses along it, a few pixels per row of
    254 (a step along a row or column cancels: the mask is [1, -2, 1] x [1, -2, 1]): Immerkaer's mean form
    reports noise there, the median form none."""
    y, x = np.mgrid[0:64, 0:256]
    frames = np.where(x > y + 96, 0.8, 0.0)[None, :, :, None]
    resp = correlate2d(frames[0, :, :, 0], MASK, mode="valid")
    assert math.sqrt(math.pi / 2) / 6 * np.abs(resp).mean() > 0.005
    assert estimate_noise(frames) == 0.0


def test_a_second_implementation_and_uint8_frames():
    rng = np.random.default_rng(2)
    frames = rng.integers(0, 256, (3, 17, 23, 3), dtype=np.uint8)
    x = frames / 255.0

    def want(imgs):
        return np.mean([(np.median(np.abs(correlate2d(im, MASK, mode="valid"))) / (6 * 0.6744897501960817)) ** 2
                        for im in imgs])

    assert estimate_noise(frames) == pytest.approx(want([x[n, :, :, c] for n in range(3) for c in range(3)]),
                                                   rel=1e-12)
    assert estimate_noise(x) == pytest.approx(estimate_noise(frames), rel=1e-12)
    assert estimate_noise(x[..., 0]) == pytest.approx(want([x[n, :, :, 0] for n in range(3)]), rel=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.floats(0.1, 10.0))
def test_scales_as_a_variance_and_ignores_ramps(seed, k):
    rng = np.random.default_rng(seed)
    noise = rng.normal(0, 0.02, (2, 9, 11, 3))
    base = estimate_noise(noise)
    assert estimate_noise(k * noise) == pytest.approx(k * k * base, rel=1e-9)
    assert estimate_noise(noise + _ramp(2, 9, 11, 3, rng)) == pytest.approx(base, rel=1e-6)


def test_tiny_or_malformed_frames():
    assert estimate_noise(np.zeros((2, 2, 5, 3))) == 0.0
    with pytest.raises(ValueError, match="frames must be"):
        estimate_noise(np.zeros((4, 4)))


@given(st.floats(0, 1), st.one_of(st.none(), st.floats(-1, 1), st.just(math.inf), st.just(math.nan)))
def test_blur_weight_is_in_its_bounds_and_one_without_noise_or_error(noise_var, mse):
    w = blur_weight(noise_var, mse)
    assert W_MIN <= w <= 1.0
    if noise_var == 0 or mse is None or not (mse > 0 and math.isfinite(mse)):
        assert w == 1.0


def test_blur_weight_is_the_share_of_the_error_above_the_noise():
    assert blur_weight(1e-3, 4e-3) == pytest.approx(0.75)
    assert blur_weight(1e-3, 1e-3 * 1.0001) == W_MIN      # nearly all of it is noise: the bound
    assert blur_weight(2e-3, 1e-3) == W_MIN               # the model fits the noise: the bound


def test_update_mse_is_an_exponential_average_that_skips_non_finite_steps():
    assert update_mse(None, 0.5) == 0.5
    assert update_mse(0.5, 1.0) == pytest.approx(MSE_MOMENTUM * 0.5 + (1 - MSE_MOMENTUM) * 1.0)
    assert update_mse(0.5, math.nan) == 0.5 and update_mse(None, math.inf) is None
