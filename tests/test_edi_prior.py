"""The EDI prior (ev3dgs/train/edi_prior.py): its targets against intensities the frame and counts were made
from, its variance against Monte Carlo draws of the count errors it models, its mask and its finiteness."""
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.sim.isp import linear_to_srgb
from ev3dgs.train.edi_prior import (anneal_factor, edi_log_targets, edi_prior_loss, edi_variance, valid_mask)
from ev3dgs.train.losses import log_intensity

KNEE = 1e-3


@settings(max_examples=100, deadline=None)
@given(k=st.integers(2, 9), seed=st.integers(0, 2**31 - 1), span=st.floats(0.01, 6.0))
def test_targets_are_the_sub_pose_intensities_the_frame_and_changes_were_made_from(k, seed, span):
    """Y_B = mean_k Y_k and E_k = log Y_k - log Y_0 exactly: the targets are log Y_k (float64 rounding only)."""
    rng = np.random.default_rng(seed)
    log_y = torch.as_tensor(rng.uniform(-span, span, (k, 4, 5)) + rng.uniform(-3, 0, (1, 4, 5)))
    log_b = torch.log(log_y.exp().mean(dim=0))
    got = edi_log_targets(log_b, log_y - log_y[:1])
    # each step adds/subtracts terms of size <= |log| + log K; double rounding, a few ulps of 10
    assert torch.allclose(got, log_y, rtol=0, atol=64 * 2.2e-16 * (2 * span + 3 + math.log(k)))


def _exact_case(theta=0.2, k=5, seed=0):
    """Linear sub-frames whose luminance moves by whole thresholds between poses, the blurry sRGB frame they
    make, the exact ON/OFF counts, and the sub-poses' log luminance."""
    rng = np.random.default_rng(seed)
    steps = rng.integers(-2, 3, (k - 1, 6, 7))                     # thresholds crossed per bin
    level = np.concatenate([np.zeros((1, 6, 7)), np.cumsum(steps, 0)]) * theta
    base = rng.uniform(0.05, 0.2, (6, 7, 3))                        # colour fixed, brightness scaled
    lin = base[None] * np.exp(level)[..., None]                     # (K, H, W, 3) linear, all < 1
    frame = torch.as_tensor(linear_to_srgb(lin.mean(0)))
    on = np.concatenate([np.zeros((1, 6, 7)), np.cumsum(np.clip(steps, 0, None), 0)])
    off = np.concatenate([np.zeros((1, 6, 7)), np.cumsum(np.clip(-steps, 0, None), 0)])
    counts = torch.as_tensor(np.stack([on, off], axis=1))
    log_l = log_intensity(torch.as_tensor(linear_to_srgb(lin)), knee=KNEE)
    return frame, counts, log_l


def test_the_true_sub_frames_cost_nothing_and_get_no_gradient():
    """Through the trainer's own decode and intensity: the frame's log intensity and exact counts give back
    the true sub-poses, so the loss there is zero with zero gradient, and any other render costs more."""
    frame, counts, log_l = _exact_case()
    log_b = log_intensity(frame[None], knee=KNEE)[0]
    mask = valid_mask(frame[None], log_b[None], KNEE)[0]
    assert mask.all()
    x = log_l.clone().requires_grad_(True)
    loss = edi_prior_loss(x, counts, log_b, mask, 0.2, 0.2, floor=1e-4, rel_mismatch=0.1, knee=KNEE)
    loss.backward()
    # float64 sRGB encode/decode round trip: ~1e-15 relative in intensity, squared in the loss
    assert loss.item() < 1e-20 and x.grad.abs().max().item() < 1e-9
    moved = log_l.clone()
    moved[2] += 0.05
    assert edi_prior_loss(moved, counts, log_b, mask, 0.2, 0.2, floor=1e-4, knee=KNEE).item() > 1e-6


def test_saturated_pixels_are_left_out():
    frame, counts, log_l = _exact_case()
    frame = frame.clone()
    frame[3, 4, 1] = 1.0                                           # one channel at full scale
    log_b = log_intensity(frame[None], knee=KNEE)[0]
    mask = valid_mask(frame[None], log_b[None], KNEE)[0]
    assert not mask[3, 4] and mask.sum() == mask.numel() - 1
    x = (log_l + 0.3).requires_grad_(True)
    edi_prior_loss(x, counts, log_b, mask, 0.2, 0.2, floor=1e-4, knee=KNEE).backward()
    assert torch.all(x.grad[:, 3, 4] == 0) and torch.all(x.grad[:, 3, 3] != 0)


@pytest.mark.parametrize("rel,rate", [(0.0, 0.0), (0.2, 0.0), (0.0, 30.0), (0.1, 10.0)])
def test_variance_matches_monte_carlo_draws_of_the_count_errors(rel, rate):
    """Draw the errors the noise model describes (quantisation uniform in a threshold band at every pose; one
    mismatch factor per pixel moving each event by theta (1 + e), as count_variance; Poisson noise events
    between poses, each +-theta) and push them through the exact, non-linear targets. Their variance matches
    edi_variance, to first order, where the ON and OFF deviations share a sign, and stays under it elsewhere
    (the mismatch term is a bound there). Tolerance: 5 standard errors of a variance from n draws
    (sqrt(2/n)) plus the second-order term, O(theta (1 + count)) relative at these sizes."""
    theta, k, n = 0.05, 5, 4000
    rng = np.random.default_rng(7)
    times = np.linspace(0.0, 0.1, k)
    steps = rng.integers(-6, 7, (k - 1, 3, 4))
    on = np.concatenate([np.zeros((1, 3, 4)), np.cumsum(np.clip(steps, 0, None), 0)])
    off = np.concatenate([np.zeros((1, 3, 4)), np.cumsum(np.clip(-steps, 0, None), 0)])
    counts = torch.as_tensor(np.stack([on, off], axis=1))
    change = theta * (counts[:, 0] - counts[:, 1])
    log_b = torch.zeros(3, 4, dtype=torch.float64)
    clean = edi_log_targets(log_b, change)
    q = rng.uniform(-theta / 2, theta / 2, (n, k, 3, 4))
    eps = rng.normal(0, rel, (n, 1, 3, 4))
    noise = np.zeros((n, k, 3, 4))
    for i in range(1, k):
        lam = rate * (times[i] - times[i - 1]) / 2          # ON and OFF noise events, each its own sign
        bumps = rng.poisson(lam, (n, 3, 4)) - rng.poisson(lam, (n, 3, 4))
        noise[:, i:] += theta * bumps[:, None]
    err = q + eps * theta * (counts[:, 0] + counts[:, 1]).numpy()[None] + noise
    drawn = torch.stack([edi_log_targets(log_b, change + torch.as_tensor(e)) - clean for e in err])
    mc = drawn.var(dim=0)
    th = torch.tensor(theta, dtype=torch.float64)
    pred = edi_variance(change, counts, th, th, rel, rate, times)
    w = torch.softmax(change, dim=0)
    dev = counts - (w[:, None] * counts).sum(dim=0)
    same_sign = dev[:, 0] * dev[:, 1] >= 0
    tol = 5 * math.sqrt(2 / n) + 2 * theta * (1 + 12 * rel)
    assert torch.all((mc - pred).abs()[same_sign] <= tol * pred[same_sign]), (mc / pred).min().item()
    assert torch.all(mc <= (1 + tol) * pred)
    if rel == 0:
        assert same_sign.all() or torch.allclose(mc, pred, rtol=tol)


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([1e-3, 1.0, 30.0, 1e3]),
       floor=st.sampled_from([1e-4, 1e-2, 10.0]))
def test_loss_and_gradient_stay_finite(seed, scale, floor):
    """Wild renders, large counts, dark and bright frames: values and gradients finite, loss >= 0."""
    rng = np.random.default_rng(seed)
    log_l = torch.as_tensor(rng.normal(0, scale, (5, 4, 6)), dtype=torch.float32).requires_grad_(True)
    counts = torch.as_tensor(np.cumsum(rng.integers(0, int(1 + scale), (5, 2, 4, 6)), 0), dtype=torch.float32)
    counts[0] = 0
    frame = torch.as_tensor(rng.uniform(0, 1, (4, 6, 3)), dtype=torch.float32)
    log_b = log_intensity(frame[None], knee=KNEE)[0]
    mask = valid_mask(frame[None], log_b[None], KNEE)[0]
    loss = edi_prior_loss(log_l, counts, log_b, mask, 0.1, 0.15, floor=floor, rel_mismatch=0.4, noise_rate=5.0,
                          times_s=np.linspace(0, 0.05, 5), knee=KNEE)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() >= 0 and torch.isfinite(log_l.grad).all()


def test_anneal_and_bad_floor():
    assert anneal_factor(0, 1000, 0.5) == 1.0
    assert anneal_factor(250, 1000, 0.5) == 0.5
    assert anneal_factor(500, 1000, 0.5) == 0.0 and anneal_factor(900, 1000, 0.5) == 0.0
    assert anneal_factor(999, 1000, 1.0) == pytest.approx(0.001)
    frame, counts, log_l = _exact_case()
    log_b = log_intensity(frame[None], knee=KNEE)[0]
    for bad in (0.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="floor"):
            edi_prior_loss(log_l, counts, log_b, torch.ones_like(log_b, dtype=torch.bool), 0.2, 0.2, floor=bad)
