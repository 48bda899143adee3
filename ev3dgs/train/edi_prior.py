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
variance about sum_j w_j^2 v_jk (v: ``count_variance`` of the pair, quantisation, mismatch and noise events).
As in the noise norm, the model's own error (floor * g) bounds each pixel's weight. The weight falls
linearly to zero at ``anneal`` of the run: early on it gives the sub-poses their sharp targets; later the
blur and event losses, which also cover saturated pixels and colour, take over.
"""
from __future__ import annotations

import math

import torch

from .losses import count_variance, expected_log_change

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
    """(K, H, W) expected squared error of each sub-pose's EDI log target from the counts: sum_j w_j^2 v_jk,
    w = softmax_j(E_j), v_jk = count_variance of the pair (j, k) (0 for j = k). ``times_s``: the K sub-pose
    times in seconds, for the noise events (rate ``noise_rate`` per pixel and second)."""
    k = change.shape[0]
    pairs = [(a, b) for a in range(k) for b in range(a + 1, k)]
    idx = torch.as_tensor(pairs, dtype=torch.long, device=change.device)
    noise = None
    if noise_rate > 0 and times_s is not None:
        noise = torch.as_tensor([noise_rate * abs(float(times_s[b]) - float(times_s[a])) for a, b in pairs],
                                dtype=change.dtype, device=change.device)
    v = count_variance(counts, idx, tp, tn, rel_mismatch, noise, spread)      # (P, H, W)
    w2 = torch.softmax(change, dim=0) ** 2                                    # (K, H, W)
    out = torch.zeros_like(change)
    for p, (a, b) in enumerate(pairs):   # v_ab enters pose a's target with w_b^2 and pose b's with w_a^2
        out[a] = out[a] + w2[b] * v[p]
        out[b] = out[b] + w2[a] * v[p]
    return out


def edi_prior_loss(log_l: torch.Tensor, counts: torch.Tensor, log_b: torch.Tensor, mask: torch.Tensor,
                   theta_pos, theta_neg, floor: float, convention: str = "random_phase",
                   rel_mismatch: float = 0.1, noise_rate: float = 0.0, times_s=None, knee: float = 1e-3,
                   spread: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over sub-poses and pixels of mask * (log_l[k] - T_k)^2 / (V_k + floor * g_k): T = edi_log_targets
    from the detached counts and blurry frame, V = edi_variance, g_k = 1 / I_k^2 at the rendered intensity
    (detached, at least the knee), as noise_event_loss. (K, H, W) log_l, (K, 2, H, W) cumulative counts, (H, W)
    log_b and mask. Finite for any finite input: every denominator is at least floor * g > 0."""
    if not (floor > 0 and math.isfinite(floor)):
        raise ValueError(f"floor must be finite and > 0, got {floor!r}")
    with torch.no_grad():
        c = counts.to(log_l.dtype)
        tp = torch.as_tensor(theta_pos, dtype=log_l.dtype, device=log_l.device)
        tn = torch.as_tensor(theta_neg, dtype=log_l.dtype, device=log_l.device)
        change = expected_log_change(c, tp, tn, convention)
        target = edi_log_targets(log_b.to(log_l.dtype), change)
        var = edi_variance(change, c, tp, tn, rel_mismatch, noise_rate, times_s, spread)
        g = log_l.detach().exp().clamp(min=knee) ** -2
        weight = mask.to(log_l.dtype) / (var + floor * g)
    r = log_l - target
    return torch.mean(weight * r * r)
