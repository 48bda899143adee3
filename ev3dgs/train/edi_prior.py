"""The event double integral (EDI) prior: a sharp target for each sub-pose render, from the blurry frame and the
events of its exposure, weighted by its expected error and faded out over the first part of the run.

In the trainer's own discretisation the blurry frame is the mean of the K sub-pose intensities (linear light,
``blur_average``) and the events give each sub-pose's log change since pose 0, E_k (``expected_log_change``).
Per pixel the two fix every sub-pose's intensity (Pan et al.'s EDI with K samples of the exposure):

    Y_k = Y_B * exp(E_k) / mean_j exp(E_j),   log Y_k = log Y_B + E_k - log mean_j exp(E_j)

with Y the intensity an event pixel sees (``log_intensity``: luminance, or the pixel's raw channel under a
Bayer filter), which is linear in the light, so the blurry frame's Y_B is the mean of the Y_k. The
trainer's blur and event losses reach the same answer at their joint optimum; the prior hands it to every
sub-pose from the first step, where the blur loss alone says little about which sub-pose carries the light.

The target is wrong where the frame clips (a saturated pixel only bounds Y_B from below: masked) and where
the counts are: the error of log Y_k is -sum_j w_j (e_j - e_k) with w = softmax(E) and e the count errors,
its variance follows from the noise norm's error model of the counts (quantisation, mismatch, noise events:
``edi_variance``).
As in the noise norm, the model's own error (floor * g) bounds each pixel's weight. The weight falls
linearly to zero at ``anneal`` of the run: early on it gives the sub-poses their sharp targets; later the
blur and event losses, which also cover saturated pixels and colour, take over.
"""
from __future__ import annotations

import math

import torch

from .losses import expected_log_change

# blur model / event intensity combinations in which the event pixel's intensity is linear in what the blur
# model averages (so the blurry frame's intensity is the mean of the sub-pose intensities)
COMPATIBLE = {("linear", "srgb"), ("srgb", "display"), ("srgb", "linear")}
SATURATED = 254.5 / 255.0   # an 8-bit frame value at or above this is full scale


def anneal_factor(step: int, iterations: int, anneal: float) -> float:
    """The prior's weight multiplier at ``step`` (0-based): 1 at the start, falling linearly to 0 at
    ``anneal * iterations`` and 0 after."""
    end = anneal * iterations
    return max(0.0, 1.0 - step / end) if end > 0 else 0.0


def valid_mask(images: torch.Tensor, log_b: torch.Tensor, knee: float) -> torch.Tensor:
    """(N, H, W) bool: pixels where the EDI target is defined: no channel at full scale and an intensity well
    above the log knee (below it the log is linearised and exp(E) no longer scales the intensity)."""
    return (images < SATURATED).all(dim=-1) & (log_b > math.log(4.0 * knee))


def edi_log_targets(log_b: torch.Tensor, change: torch.Tensor) -> torch.Tensor:
    """(H, W) log intensity of the blurry frame and (K, H, W) expected log change since pose 0 -> (K, H, W) log
    intensity at each sub-pose: log_b + E_k - log mean_j exp(E_j)."""
    k = change.shape[0]
    return log_b + change - (torch.logsumexp(change, dim=0) - math.log(k))


def edi_variance(change: torch.Tensor, counts: torch.Tensor, tp: torch.Tensor, tn: torch.Tensor,
                 rel_mismatch: float, noise_rate: float = 0.0, times_s=None,
                 spread: torch.Tensor | None = None) -> torch.Tensor:
    """(K, H, W) expected squared error of each sub-pose's EDI log target, to first order in the count errors.

    The target's error is d_k = e_k - sum_j w_j e_j, w = softmax_j(E_j), e_j the error of E_j, with the noise
    norm's error sources (``losses.count_variance``) taken per pose:

    * quantisation: the signal's place in the threshold band, independent at every pose, variance theta^2/12:
      theta^2/12 ((1 - w_k)^2 + sum_{j != k} w_j^2) = theta^2/12 (1 - 2 w_k + sum_j w_j^2);
    * mismatch: every event moves the reference by the pixel's own threshold, theta (1 + e), e ~ N(0, s^2):
      (s (theta_on |n_on,k - nbar_on| + theta_off |n_off,k - nbar_off|))^2, nbar = sum_j w_j n_j the
      weighted mean of the cumulative counts: exact where the two deviations share a sign, an upper bound
      otherwise, whether one factor moves both polarities (count_variance's model) or each its own (with
      ``spread``, a threshold map's per-pixel remaining error, ON and OFF independently, as count_variance);
    * noise events: Poisson increments between consecutive sub-poses (rate ``noise_rate`` per pixel and
      second, ``times_s`` the K sub-pose times), each moving the estimate by a threshold: theta^2 rate
      sum_i dt_i (1[k >= i] - sum_{j >= i} w_j)^2.

    (K, H, W) change (expected_log_change), (K, 2, H, W) cumulative counts; tp, tn scalars or (H, W) maps."""
    c = counts.to(change.dtype)
    w = torch.softmax(change, dim=0)
    theta2 = 0.5 * (tp * tp + tn * tn)
    var = theta2 / 12.0 * (1.0 - 2.0 * w + (w * w).sum(dim=0))
    dev = (c - (w[:, None] * c).sum(dim=0)).abs()                 # (K, 2, H, W)
    if spread is None:
        var = var + (rel_mismatch * (tp * dev[:, 0] + tn * dev[:, 1])) ** 2
    else:
        var = var + (spread[0] * tp * dev[:, 0]) ** 2 + (spread[1] * tn * dev[:, 1]) ** 2
    if noise_rate > 0 and times_s is not None:
        k = change.shape[0]
        dt = [abs(float(times_s[i]) - float(times_s[i - 1])) for i in range(1, k)]
        tail = torch.flip(torch.cumsum(torch.flip(w, [0]), dim=0), [0])   # tail[i] = sum_{j >= i} w_j
        for i in range(1, k):
            for kk in range(k):
                coef = (1.0 if kk >= i else 0.0) - tail[i]
                var[kk] = var[kk] + theta2 * noise_rate * dt[i - 1] * coef * coef
    return var


def edi_prior_loss(log_l: torch.Tensor, counts: torch.Tensor, log_b: torch.Tensor, mask: torch.Tensor,
                   theta_pos, theta_neg, floor: float, convention: str = "random_phase",
                   rel_mismatch: float = 0.1, noise_rate: float = 0.0, times_s=None, knee: float = 1e-3,
                   spread: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over sub-poses and pixels of mask * (log_l[k] - T_k)^2 / (V_k + floor * g_k): T = edi_log_targets
    from the detached counts and blurry frame, V = edi_variance, g_k = 1 / I_k^2 at the rendered intensity
    (detached, clamped to [knee, 1]), as noise_event_loss. (K, H, W) log_l, (K, 2, H, W) cumulative counts, (H, W)
    log_b and mask. Finite for any finite input: every denominator is at least floor > 0."""
    if not torch.is_tensor(floor) and not (floor > 0 and math.isfinite(floor)):   # (a device floor: the
        raise ValueError(f"floor must be finite and > 0, got {floor!r}")        # trainer's, >= FLOOR_MIN)
    with torch.no_grad():
        c = counts.to(log_l.dtype)
        tp = torch.as_tensor(theta_pos, dtype=log_l.dtype, device=log_l.device)
        tn = torch.as_tensor(theta_neg, dtype=log_l.dtype, device=log_l.device)
        change = expected_log_change(c, tp, tn, convention)
        target = edi_log_targets(log_b.to(log_l.dtype), change)
        var = edi_variance(change, c, tp, tn, rel_mismatch, noise_rate, times_s, spread)
        # g at most 1, the weight of an error at full scale: a render above it weighs no more than one at
        # it, and every denominator stays at least floor > 0 (var can be 0: a pose that carries all the
        # exposure's light is the blurry frame itself)
        g = log_l.detach().exp().clamp(min=knee, max=1.0) ** -2
        weight = mask.to(log_l.dtype) / (var + floor * g)
    r = log_l - target
    return torch.mean(weight * r * r)
