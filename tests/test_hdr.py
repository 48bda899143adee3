"""--hdr: renders above 1 decode to radiance above full scale, and the blurry frame is the sensor's clip of the
exposure integral. Checked against the closed forms of the decode and of the clipped loss."""
import math

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from ev3dgs.train.losses import (HDR_MAX_DISPLAY, HDR_MAX_LINEAR, HDR_RATE, average_loss, blur_average,
                                 srgb_to_linear_hdr_torch, srgb_to_linear_torch)

SLOPE = 2.4 / 1.055   # d/dx ((x + 0.055) / 1.055) ** 2.4 at x = 1


def test_below_full_scale_it_is_the_srgb_eotf_bit_for_bit():
    x = torch.linspace(0, 1, 1001, dtype=torch.float64)
    assert torch.equal(srgb_to_linear_hdr_torch(x), srgb_to_linear_torch(x))


def test_above_full_scale_the_closed_form_with_value_and_slope_continuous_at_1():
    x = torch.tensor([1.25, 1.5, 1.75, 2.0], dtype=torch.float64)
    want = 1 + SLOPE / HDR_RATE * np.expm1(HDR_RATE * (x.numpy() - 1))
    np.testing.assert_allclose(srgb_to_linear_hdr_torch(x).numpy(), want, rtol=1e-14)
    assert 100 < srgb_to_linear_hdr_torch(torch.tensor(1.75, dtype=torch.float64)) < 130   # a specular highlight
    # C1 at 1: the one-sided derivatives of each branch, in double (rounding ~1e-16 per op)
    for at in (1 - 1e-12, 1 + 1e-12):
        x = torch.tensor(at, dtype=torch.float64, requires_grad=True)
        srgb_to_linear_hdr_torch(x).backward()
        assert x.grad.item() == pytest.approx(SLOPE, rel=1e-9)
    # capped at HDR_MAX_LINEAR, where the gradient is zero
    x = torch.tensor([HDR_MAX_DISPLAY, HDR_MAX_DISPLAY + 1, 1e30, math.inf], dtype=torch.float64,
                     requires_grad=True)
    y = srgb_to_linear_hdr_torch(x)
    np.testing.assert_allclose(y.detach().numpy(), HDR_MAX_LINEAR, rtol=1e-12)
    y.sum().backward()
    assert torch.all(x.grad[1:] == 0)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False, width=32), min_size=2, max_size=40))
@example([1e6, -1e6])
@example([HDR_MAX_DISPLAY, 1.0])
def test_decode_is_monotone_finite_with_finite_gradients(values):
    x = torch.tensor(sorted(values), dtype=torch.float32, requires_grad=True)
    y = srgb_to_linear_hdr_torch(x)
    assert torch.isfinite(y).all() and torch.all(y[1:] >= y[:-1]) and y.max() <= HDR_MAX_LINEAR * (1 + 1e-6)
    y.sum().backward()
    assert torch.isfinite(x.grad).all() and torch.all(x.grad >= 0)


def _frame(lin_subframes):
    """The blurry sRGB frame a sensor makes of (K, ...) linear sub-frames: mean, clip at full scale, encode
    (full scale is exactly 1.0, as 255 / 255 of a stored frame; 1.055 - 0.055 rounds below it)."""
    mean = np.clip(np.mean(lin_subframes, axis=0), 0, 1)
    enc = np.where(mean <= 0.0031308, 12.92 * mean, 1.055 * mean ** (1 / 2.4) - 0.055)
    return np.where(mean >= 1, 1.0, enc)


def test_a_highlight_above_full_scale_is_fit_exactly_only_with_the_sensor_clip():
    """One sub-frame of five sees a highlight 60x full scale at the first pixel (the frame saturates) and 3x at
    the second (it does not): rendered with the HDR decode the true radiance gives zero loss; without the
    clip the saturated pixel's average overshoots 1 and the same renders cost a loss."""
    lin = np.full((5, 8, 8, 3), 0.2)
    lin[2, 0, 0] = 60.0
    lin[2, 0, 1] = 3.0
    target = torch.as_tensor(_frame(lin))
    assert target[0, 0].min() == 1.0 and target[0, 1].max() < 1.0
    # the display values that decode to the true radiance (the decode's inverse, per branch)
    disp = np.where(lin > 1, 1 + np.log1p((np.maximum(lin, 1) - 1) * HDR_RATE / SLOPE) / HDR_RATE,
                    1.055 * np.clip(lin, 0, 1) ** (1 / 2.4) - 0.055)
    renders = torch.as_tensor(disp, dtype=torch.float64).requires_grad_(True)
    lin_r = srgb_to_linear_hdr_torch(renders)
    np.testing.assert_allclose(lin_r.detach().numpy(), lin, rtol=1e-12)
    avg = blur_average(renders, "linear", linear=lin_r)
    clipped = average_loss(avg, target, lam=0.0, clip=True)
    assert clipped.item() < 1e-24     # exact to double rounding
    clipped.backward()
    assert renders.grad.abs().max() < 1e-10
    # without the clip the saturated pixel's average (2.17 in display terms) is 1.17 above its 1.0
    plain = average_loss(avg.detach(), target, lam=0.0, clip=False)
    over = (avg[0, 0].detach() - 1.0).numpy()
    assert plain.item() == pytest.approx(np.sum(over ** 2) / target.numel(), rel=1e-9)


def test_the_clip_only_forgives_overshoot_at_saturated_pixels():
    """Saturated target, average above 1: no loss, no gradient. Saturated target, average below 1: pulled up.
    Unsaturated target, average above it, even above 1: pulled down (the clip is not applied there)."""
    target = torch.tensor([[[1.0, 1.0, 0.5]]], dtype=torch.float64)
    avg = torch.tensor([[[1.4, 0.8, 1.3]]], dtype=torch.float64, requires_grad=True)
    loss = average_loss(avg, target, lam=0.0, clip=True)
    assert loss.item() == pytest.approx((0.2 ** 2 + 0.8 ** 2) / 3, rel=1e-12)
    loss.backward()
    np.testing.assert_allclose(avg.grad.numpy().ravel(), [0.0, 2 * -0.2 / 3, 2 * 0.8 / 3], rtol=1e-12)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.floats(0.5, 40.0))
def test_clipped_loss_with_ssim_has_finite_gradients(seed, scale):
    rng = np.random.default_rng(seed)
    renders = torch.tensor(rng.uniform(0, 1, (3, 12, 12, 3)) * scale, dtype=torch.float32, requires_grad=True)
    target = torch.tensor(np.minimum(rng.uniform(0, 1.5, (12, 12, 3)), 1.0), dtype=torch.float32)
    lin = srgb_to_linear_hdr_torch(renders)
    loss = average_loss(blur_average(renders, "linear", linear=lin), target, lam=0.2, clip=True)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(renders.grad).all()
