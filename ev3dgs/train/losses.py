"""Training losses: blur (rendered sub-poses averaged against the blurry frame) and event (log-intensity
change between sub-poses against the observed signed event count).

Fixes relative to the published E2NeRF / Ev3DGS code (reference notes section 4):

* The event loss is a non-negative quantity the trainer ADDS to the blur loss (Ev3DGS subtracted it).
* The log is ``ev3dgs.logmap.safe_log_torch``, the same lin-log the simulator uses: finite value and finite,
  bounded gradient at exactly 0 (E2NeRF's ``torch.where(x <= 20, x * f, log(x))`` gives NaN gradients at
  black pixels even when they are masked out).
* The sRGB transfer functions clamp inside their pow branches so gradients are finite for all inputs.
* ON and OFF counts are compared separately with theta_on * n_on - theta_off * n_off (not a net count with
  the threshold picked by the sign of the predicted change), with the expectation the scene's count
  convention implies (random phase: unbiased counts; exact reference: truncated counts, centred).
"""
from __future__ import annotations

import functools
import math
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..logmap import DEFAULT_LOG_KNEE, safe_log_torch
from ..sensor import LUMINANCE_WEIGHTS, cfa_channels
from .config import FLOOR_STATS
from .readback import to_device

_BAYER = {"RGGB", "BGGR", "GRBG", "GBRG"}
_SRGB_KNEE = 0.04045
_LINEAR_KNEE = 0.0031308


def srgb_to_linear_torch(x: torch.Tensor) -> torch.Tensor:
    """sRGB EOTF (display [0,1] -> linear). Negative inputs are clamped to 0 (zero gradient there); the pow
    branch only ever sees values >= the knee, so gradients are finite everywhere, including at 0."""
    x = torch.clamp(x, min=0.0)
    low = x / 12.92
    high = ((torch.clamp(x, min=_SRGB_KNEE) + 0.055) / 1.055) ** 2.4
    return torch.where(x <= _SRGB_KNEE, low, high)


# Radiance above full scale (--hdr). A render above 1 continues the sRGB EOTF with an exponential of the same
# value and slope at 1: linear = 1 + (s / HDR_RATE) * (exp(HDR_RATE * (x - 1)) - 1), s = 2.4 / 1.055 the EOTF's
# slope at 1, so 1.5 decodes to 16x full scale and 1.75 to 115x (a specular highlight), where the plain EOTF
# would need a render of 7.7; renders past HDR_MAX_DISPLAY (1e4x full scale) are held there (zero gradient).
HDR_RATE = 8.0
HDR_MAX_LINEAR = 1.0e4
_SRGB_SLOPE_AT_1 = 2.4 / 1.055
HDR_MAX_DISPLAY = 1.0 + math.log1p((HDR_MAX_LINEAR - 1.0) * HDR_RATE / _SRGB_SLOPE_AT_1) / HDR_RATE


def srgb_to_linear_hdr_torch(x: torch.Tensor) -> torch.Tensor:
    """``srgb_to_linear_torch`` below 1; above it the exponential continuation of the HDR note above, C1 at 1
    and capped at HDR_MAX_LINEAR, so values and gradients stay finite for any input."""
    over = torch.clamp(x, min=1.0, max=HDR_MAX_DISPLAY) - 1.0
    high = 1.0 + (_SRGB_SLOPE_AT_1 / HDR_RATE) * torch.expm1(HDR_RATE * over)
    return torch.where(x > 1.0, high, srgb_to_linear_torch(torch.clamp(x, max=1.0)))


def linear_to_srgb_torch(x: torch.Tensor) -> torch.Tensor:
    """Inverse sRGB EOTF (linear -> display [0,1]). Clamped at 0 below; the x^(1/2.4) branch only sees values
    >= its knee, so the infinite slope of the power at 0 never reaches the gradient."""
    x = torch.clamp(x, min=0.0)
    low = x * 12.92
    high = 1.055 * torch.clamp(x, min=_LINEAR_KNEE) ** (1.0 / 2.4) - 0.055
    return torch.where(x <= _LINEAR_KNEE, low, high)


@functools.lru_cache(maxsize=16)
def _weights(values: tuple, dtype, device) -> torch.Tensor:
    """A constant vector on the device, made once (a host-to-device copy per step would wait for the device)."""
    return torch.as_tensor(values, dtype=dtype).to(device)


@functools.lru_cache(maxsize=16)
def _gaussian_taps(size: int, sigma: float, channels: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The 1-D Gaussian as horizontal (channels,1,1,size) and vertical (channels,1,size,1) depthwise kernels."""
    g = torch.tensor([math.exp(-((i - size // 2) ** 2) / float(2 * sigma ** 2)) for i in range(size)],
                     dtype=torch.float64)
    g = (g / g.sum()).to(dtype=dtype, device=device)
    return (g.view(1, 1, 1, size).expand(channels, 1, 1, size).contiguous(),
            g.view(1, 1, size, 1).expand(channels, 1, size, 1).contiguous())


def ssim(a: torch.Tensor, b: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images, as graphdeco 3DGS ``utils/loss_utils.py``: Gaussian window 11,
    sigma 1.5, per-channel filtering with zero 'same' padding, C1=0.01^2, C2=0.03^2. The 2-D Gaussian is
    separable, so it runs as a horizontal then a vertical 1-D pass (22 taps instead of 121 per pixel), over
    the five maps (a, b, a^2, b^2, ab) stacked in one depthwise call (equal to the 2-D window to rounding)."""
    if a.shape != b.shape:
        raise ValueError(f"ssim needs equal shapes, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.ndim != 3:
        raise ValueError(f"ssim expects (H, W, C) images, got {tuple(a.shape)}")
    c = a.shape[-1]
    img1 = a.permute(2, 0, 1).unsqueeze(0)
    img2 = b.permute(2, 0, 1).unsqueeze(0).to(img1.dtype)
    gh, gv = _gaussian_taps(window_size, float(sigma), 5 * c, img1.dtype, img1.device)
    pad = window_size // 2
    maps = torch.cat([img1, img2, img1 * img1, img2 * img2, img1 * img2], dim=1)
    blurred = F.conv2d(F.conv2d(maps, gh, padding=(0, pad), groups=5 * c), gv, padding=(pad, 0), groups=5 * c)
    mu1, mu2, e11, e22, e12 = blurred.split(c, dim=1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq = e11 - mu1_sq
    sigma2_sq = e22 - mu2_sq
    sigma12 = e12 - mu1_mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim_map = ((2 * mu1_mu2 + c1) * (2 * sigma12 + c2)) / ((mu1_sq + mu2_sq + c1) * (sigma1_sq + sigma2_sq + c2))
    return ssim_map.mean()


def _check_linear(renders: torch.Tensor, linear):
    """``linear``, an already decoded ``srgb_to_linear_torch(renders)`` a caller shares between losses (one
    decode and one decode backward per step instead of one per loss), must match the renders' shape."""
    if linear is not None and tuple(linear.shape) != tuple(renders.shape):
        raise ValueError(f"linear must have the renders' shape {tuple(renders.shape)}, got {tuple(linear.shape)}")
    return linear


def blur_average(renders: torch.Tensor, space: str = "srgb", linear: torch.Tensor | None = None) -> torch.Tensor:
    """(K, H, W, 3) sub-pose renders -> (H, W, 3) the blurry frame they make: the mean of the display values
    (``space="srgb"``) or the mean in linear light, re-encoded (``space="linear"``; ``linear``: the renders
    already through ``srgb_to_linear_torch`` or ``srgb_to_linear_hdr_torch``, used instead of decoding them
    again)."""
    if renders.ndim != 4:
        raise ValueError(f"renders must be (K, H, W, 3), got {tuple(renders.shape)}")
    if space == "srgb":
        return renders.mean(dim=0)
    if space == "linear":
        lin = _check_linear(renders, linear)
        return linear_to_srgb_torch((srgb_to_linear_torch(renders) if lin is None else lin).mean(dim=0))
    raise ValueError(f"space must be 'srgb' or 'linear', got {space!r}")


def blur_loss(renders: torch.Tensor, target: torch.Tensor, lam: float = 0.2, space: str = "srgb") -> torch.Tensor:
    """(K, H, W, 3) sub-pose renders and the (H, W, 3) blurry sRGB frame -> (1-lam)*MSE + lam*(1-SSIM) of
    their average. ``space="srgb"`` averages display values; ``space="linear"`` averages in linear light
    (each render through the sRGB EOTF, mean, back to sRGB), which is how a real exposure integrates."""
    return average_loss(blur_average(renders, space), target, lam)


def average_loss(avg: torch.Tensor, target: torch.Tensor, lam: float = 0.2, clip: bool = False) -> torch.Tensor:
    """blur_loss from the (H, W, 3) average (``blur_average``) the caller already has (the trainer keeps it
    for the step's PSNR): (1-lam)*MSE + lam*(1-SSIM) against the blurry sRGB frame. ``clip``: the sensor
    clips after the exposure integral, so where the frame is at full scale (1.0) the average is compared
    clipped at 1 (any brighter exposure made that value); elsewhere it is compared unclipped, so an average
    above an unsaturated value is pulled down."""
    target = target.to(avg.dtype)
    if clip:
        avg = torch.where(target >= 1.0, torch.clamp(avg, max=1.0), avg)
    mse = torch.mean((avg - target) ** 2)
    return (1.0 - lam) * mse + lam * (1.0 - ssim(avg, target))


# Rec. 601 luma of display values: the grey v2e (OpenCV's BGR2GRAY) and E2NeRF take before their log.
LUMA_601 = (0.299, 0.587, 0.114)
_TRANSFERS = ("srgb", "linear", "display")


def log_intensity(renders: torch.Tensor, color_filter: str = "none", knee: float = DEFAULT_LOG_KNEE,
                  transfer: str = "srgb", raw_matrix=None, linear: torch.Tensor | None = None) -> torch.Tensor:
    """(K, H, W, 3) renders -> (K, H, W) safe log of the intensity each event pixel sees, with the
    simulator's ``safe_log_torch`` and the scene's knee.

    ``transfer`` (the scene's /train transfer, or the trainer's --event-domain override) says what that is:
    "srgb": renders are sRGB-encoded, events see linear light: decode (sRGB EOTF) first; "linear": renders
    are linear light already; "display": events were simulated on display values (v2e on 8-bit frames, as
    E2NeRF's data): no decode, and the grey is Rec. 601 luma (``LUMA_601``) as v2e/E2NeRF compute it.

    Colour: the sRGB luminance (``LUMINANCE_WEIGHTS``) for ``color_filter="none"``; under a Bayer pattern
    ("RGGB", "BGGR", "GRBG", "GBRG") the pixel's own channel of camera raw = ``raw_matrix`` @ linear sRGB
    (``ev3dgs.sensor.camera_raw_matrix(ccm, wb)``, the scene's /events attr camera_raw_matrix; None =
    identity), as the simulator's ColorFilterArray. For "display" the pixel's own display channel is used
    (raw_matrix ignored). Computed as a per-pixel weighted sum (no gather/scatter): deterministic.
    ``linear``: with transfer "srgb", the renders already decoded (``srgb_to_linear_torch(renders)``, shared
    with blur_average), used instead of decoding again; ignored for the other transfers."""
    if renders.ndim != 4 or renders.shape[-1] != 3:
        raise ValueError(f"renders must be (K, H, W, 3), got {tuple(renders.shape)}")
    if transfer not in _TRANSFERS:
        raise ValueError(f"transfer must be one of {_TRANSFERS}, got {transfer!r}")
    if transfer == "srgb":
        lin = _check_linear(renders, linear)
        lin = srgb_to_linear_torch(renders) if lin is None else lin
    else:
        lin = renders
    cf = (color_filter or "none")
    if cf.lower() == "none":
        w = _weights(tuple(LUMA_601 if transfer == "display" else LUMINANCE_WEIGHTS), lin.dtype, lin.device)
        inten = (lin * w).sum(dim=-1)
    elif cf.upper() in _BAYER:
        _, h, wd, _ = lin.shape
        m = np.eye(3) if raw_matrix is None or transfer == "display" else np.asarray(raw_matrix, np.float64)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError(f"raw_matrix must be a finite 3x3 matrix, got {m.tolist()}")
        w_px = torch.as_tensor(m[cfa_channels(cf.upper(), h, wd)], dtype=lin.dtype, device=lin.device)  # (H,W,3)
        inten = (lin * w_px).sum(dim=-1)
    else:
        raise ValueError(f"color_filter must be 'none' or a Bayer pattern {sorted(_BAYER)}, got {color_filter!r}")
    return safe_log_torch(inten, knee)


COUNT_CONVENTIONS = ("random_phase", "exact_reference")


def _thetas(theta_pos, theta_neg, like: torch.Tensor):
    for th in (theta_pos, theta_neg):
        if not torch.is_tensor(th) and not float(th) > 0:
            raise ValueError(f"thresholds must be positive, got {th!r}")
    tp = torch.as_tensor(theta_pos, dtype=like.dtype, device=like.device)
    tn = torch.as_tensor(theta_neg, dtype=like.dtype, device=like.device)
    return tp, tn


def _scaled_mse(residual: torch.Tensor, tp: torch.Tensor, tn: torch.Tensor) -> torch.Tensor:
    # residual in log units over the mean threshold (detached: a constant of the step, so a learned threshold
    # cannot shrink the loss by growing the scale): the error in "events", as E2NeRF's (delta/theta - n)
    scale = (0.5 * (tp + tn)).detach()
    return torch.mean((residual / scale) ** 2)


def expected_log_change(counts: torch.Tensor, theta_pos, theta_neg,
                        convention: str = "random_phase") -> torch.Tensor:
    """(K, 2, H, W) cumulative ON/OFF counts since the exposure's first pose (``events.pose_counts``) ->
    (K, H, W) expected log-intensity change since that pose, E[L_k - L_0 | counts]:

    * "random_phase" (a running sensor; our simulator's default): theta_on * C_on - theta_off * C_off.
      The reference moves by +theta_on per ON and -theta_off per OFF event, so this is L_k - L_0 up to the
      change of the residual (signal - reference), whose expectation is the same at both poses when the
      pixel last moved the same way before each: unbiased for up-and-down paths inside a bin (where a net
      count with one threshold is not). A reversal between the poses shifts it by half the dead band,
      (theta_on + theta_off) / 2: the sensor's hysteresis, which counts alone cannot reveal.
    * "exact_reference" (the reference equals L_0 at the exposure start: v2e/ESIM restarted per view, E2NeRF's
      data): after the last event the signal lies between the reference and the next threshold, so the
      change is in [X, X + theta_on) after an upward move and (X - theta_off, X] after a downward one, X =
      theta_on * C_on - theta_off * C_off; the expectation (uniform inside) is X + theta_on / 2 where X > 0,
      X - theta_off / 2 where X < 0, and 0 where the pixel fired nothing or its events cancel (a static
      pixel: most of them). For one monotone change this is E2NeRF's count +- 0.5; unlike E2NeRF's per-pair
      +-0.5 it is applied to the change since the reference, so pairs (k1 > 0, k2) get the difference of two
      such centres.
    """
    if counts.ndim != 4 or counts.shape[1] != 2:
        raise ValueError(f"counts must be (K, 2, H, W), got {tuple(counts.shape)}")
    if convention not in COUNT_CONVENTIONS:
        raise ValueError(f"count convention must be one of {COUNT_CONVENTIONS}, got {convention!r}")
    c = counts.to(torch.float32 if not torch.is_floating_point(counts) else counts.dtype)
    tp, tn = _thetas(theta_pos, theta_neg, c)
    x = tp * c[:, 0] - tn * c[:, 1]
    if convention == "random_phase":
        return x
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    return x + torch.where(x > 0, 0.5 * tp, torch.where(x < 0, -0.5 * tn, zero))


def pose_event_loss(log_l: torch.Tensor, counts: torch.Tensor, pairs: Sequence[tuple[int, int]],
                    theta_pos, theta_neg, convention: str = "random_phase") -> torch.Tensor:
    """The trainer's event loss. (K, H, W) log intensities at the sub-poses and (K, 2, H, W) cumulative ON/OFF
    counts since pose 0 -> mean over pairs and pixels of

        ((log_l[k2] - log_l[k1]) - (E_k2 - E_k1)) ** 2 / theta_mean ** 2,   E = expected_log_change(counts)

    theta_mean = (theta_on + theta_off) / 2, detached. The residual is in log units (linear in the prediction,
    so one convex quadratic whatever the sign of the change: no threshold picked by the sign of a prediction),
    divided by the mean threshold so the loss counts events: with theta_on = theta_off = theta and random-phase
    data it is exactly the old mean((delta / theta - n) ** 2), and --event-weight keeps its meaning (weight
    per squared event). Thresholds may be 0-d tensors requiring grad (learnable). Non-negative: the trainer
    ADDS it to the blur loss (the published Ev3DGS subtracted it)."""
    _check_event_shapes(log_l, counts)
    tp, tn = _thetas(theta_pos, theta_neg, log_l)
    if len(pairs) == 0:
        return log_l.sum() * 0.0
    residual, _ = _pair_residuals(log_l, counts, pairs, tp, tn, convention)
    return _scaled_mse(residual, tp, tn)


def _check_event_shapes(log_l: torch.Tensor, counts: torch.Tensor) -> None:
    if log_l.ndim != 3 or counts.ndim != 4 or counts.shape[0] != log_l.shape[0]:
        raise ValueError(f"log_l must be (K, H, W) and counts (K, 2, H, W), got {tuple(log_l.shape)} and "
                         f"{tuple(counts.shape)}")


def _pair_residuals(log_l, counts, pairs, tp, tn, convention) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, H, W) residuals (log_l[k2] - log_l[k1]) - (E_k2 - E_k1) for the pairs, and the (P, 2) pair index."""
    d = log_l - expected_log_change(counts.to(log_l.dtype), tp, tn, convention)
    idx = to_device([tuple(pr) for pr in pairs], torch.long, log_l.device)   # (drawn on the host)
    # index_select, not d[idx]: the backward of advanced indexing with repeated indices (every pose is in
    # several pairs) is index_put_(accumulate=True), whose multi-threaded CPU kernel adds in a racy order;
    # index_select's backward (index_add_) adds slice by slice in index order: bitwise reproducible
    return d.index_select(0, idx[:, 1]) - d.index_select(0, idx[:, 0]), idx


# --------------------------------------------------------------------------- event term with a noise model
FLOOR_MIN = 1e-4      # intensity^2 (1 = white): the model floor never goes below a 1 % error of full scale
                      # (8-bit frames resolve 0.4 %; nothing a 3DGS at these sizes fits is finer)
FLOOR_MOMENTUM = 0.9  # exponential average of the model's excess squared residual over steps


def count_variance(counts: torch.Tensor, idx: torch.Tensor, tp: torch.Tensor, tn: torch.Tensor,
                   rel_mismatch: float, noise_events: torch.Tensor | None = None,
                   spread: torch.Tensor | None = None) -> torch.Tensor:
    """Expected squared error (log units) of the count-based change estimate for each pair and pixel:

    * quantisation: the signal sits somewhere inside the threshold band at each pose (uniform over one
      threshold): two ends, variance theta^2 / 12 each, theta^2 = (theta_on^2 + theta_off^2) / 2;
    * mismatch: every event moves the true reference by the pixel's own threshold, theta (1 + e), e ~ N(0,
      rel_mismatch^2) fixed per pixel: the error of theta_on n_on + theta_off n_off events at the nominal
      thresholds has variance rel_mismatch^2 (theta_on n_on + theta_off n_off)^2 (it grows with the change,
      not with the number of events: finer thresholds do not shrink it);
    * noise events: each moves the estimate by a threshold; ``noise_events`` (pairs,) = expected noise events
      per pixel in each pair's window (Poisson): variance theta^2 times that.

    ``spread`` (2, H, W), with a learned threshold map and --map-weights posterior (train/threshold_map.py):
    each pixel's remaining relative error of its ON and OFF thresholds, which are independent: the mismatch
    variance is then (s_on theta_on n_on)^2 + (s_off theta_off n_off)^2 and ``rel_mismatch`` is not used.
    tp, tn may be (H, W) maps.

    counts: (K, 2, H, W) cumulative; idx: (P, 2) pose indices -> (P, H, W)."""
    c = counts.to(tp.dtype)
    n = (c.index_select(0, idx[:, 1]) - c.index_select(0, idx[:, 0])).abs()
    theta2 = 0.5 * (tp * tp + tn * tn)
    if spread is None:
        v = theta2 / 6.0 + (rel_mismatch * (tp * n[:, 0] + tn * n[:, 1])) ** 2
    else:
        v = theta2 / 6.0 + (spread[0] * tp * n[:, 0]) ** 2 + (spread[1] * tn * n[:, 1]) ** 2
    if noise_events is not None:
        v = v + theta2 * noise_events.to(v.dtype)[:, None, None]
    return v


def noise_terms(log_l: torch.Tensor, counts: torch.Tensor, pairs: Sequence[tuple[int, int]], tp: torch.Tensor,
                tn: torch.Tensor, convention: str, rel_mismatch: float, noise_events: torch.Tensor | None,
                knee: float | None, spread: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pieces of :func:`noise_event_loss` for a non-empty ``pairs``, each (P, H, W): the residual r (with
    its gradient), the counts' variance v (count_variance) and g, which carries the linear-intensity floor
    into log units (detached; 1 with ``knee`` None). tp, tn: the thresholds as tensors (scalars or maps)."""
    residual, idx = _pair_residuals(log_l, counts, pairs, tp, tn, convention)
    v = count_variance(counts, idx, tp.detach(), tn.detach(), rel_mismatch, noise_events, spread)
    with torch.no_grad():
        if knee is None:
            g = torch.ones_like(v)
        else:
            inv2 = log_l.detach().exp().clamp(min=knee) ** -2
            g = 0.5 * (inv2.index_select(0, idx[:, 0]) + inv2.index_select(0, idx[:, 1]))
    return residual, v, g


def huber(x: torch.Tensor, c: float) -> torch.Tensor:
    """A normalised squared residual x = r^2 / s^2 (>= 0) penalised as x within c standard deviations and
    2 c |r| / s - c^2 beyond: continuous, with a continuous slope, so a residual past c s pulls as |r|, not
    as r^2. c <= 0: x unchanged."""
    if c <= 0:
        return x
    c2 = c * c
    return torch.where(x <= c2, x, 2 * c * torch.sqrt(x.clamp(min=c2)) - c2)


def huber_mean(c: float) -> float:
    """E[huber(z^2, c)] for z ~ N(0, 1): what the penalised chi-square of one sample averages where the
    residuals follow the noise model; 1 + 2 c phi(c) - 2 (1 + c^2) (1 - Phi(c)), 1 without the penalty."""
    if c <= 0:
        return 1.0
    phi = math.exp(-0.5 * c * c) / math.sqrt(2 * math.pi)
    tail = 0.5 * math.erfc(c / math.sqrt(2))
    return 1.0 + 2 * c * phi - 2 * (1 + c * c) * tail


CHI2_TOL = 1e-3        # the root in log f to this (f to 0.1 %; the trainer averages f over steps anyway)
CHI2_MAX_ITER = 60     # safeguarded Newton: a few steps from a warm start; bisection when Newton leaves the bracket
CHI2_SAMPLES = 16384   # the root from at most this many pixel-pairs, evenly strided: a scale statistic


def chi2_floor(r2: torch.Tensor, v: torch.Tensor, g: torch.Tensor, c: float, start: float | None = None) -> float:
    """The floor f >= FLOOR_MIN at which the pixel-pairs' penalised chi-square, mean huber(r^2 / (v + f g), c),
    averages what it would if the residuals followed the noise model (huber_mean): a robust scale estimate.
    The mean excess makes every pixel-pair as uncertain as the tail the model cannot render; the median
    ignores that tail altogether; this f grows only as far as the tail needs for the residuals, penalised,
    to be as large as the model says.

    The mean is decreasing in s = log f; at f = max (r^2 - v) / g every sample is at most 1, so the root lies
    in [FLOOR_MIN, that]. Found by Newton's method in s from ``start`` (the previous floor; else the mean
    excess), bisecting whenever a step leaves the bracket, to CHI2_TOL in s; on at most CHI2_SAMPLES
    pixel-pairs (every k-th of the flattened arrays), deterministic."""
    target = huber_mean(c)
    k = -(-r2.numel() // CHI2_SAMPLES)
    r2, v, g = (t.reshape(-1)[::k] for t in (r2, v, g))
    excess = (r2 - v) / g
    top = float(torch.max(excess))
    if not math.isfinite(top):   # a non-finite residual: no estimate (the trainer's NaN guard stops the step)
        return float("nan")
    c2 = c * c

    def h(s: float) -> tuple[float, float]:   # mean penalised chi-square - target, and its slope in s
        fg = math.exp(s) * g
        d = v + fg
        x = r2 / d
        slope = torch.where(x <= c2, x, c * torch.sqrt(x)) if c > 0 else x   # x huber'(x)
        return float(torch.mean(huber(x, c))) - target, -float(torch.mean(slope * fg / d))

    lo, hi = math.log(FLOOR_MIN), math.log(max(top, FLOOR_MIN))
    if h(lo)[0] <= 0:
        return FLOOR_MIN
    guess = start if start is not None and math.isfinite(start) and start > 0 else float(torch.mean(excess))
    s = min(max(math.log(max(guess, FLOOR_MIN)), lo), hi)
    for _ in range(CHI2_MAX_ITER):
        val, slope = h(s)
        if val > 0:
            lo = s
        else:
            hi = s
        step = -val / slope if slope < 0 else float("inf")
        nxt = s + step
        if not lo < nxt < hi:   # outside the bracket (or no slope): bisect
            nxt = 0.5 * (lo + hi)
        if abs(nxt - s) < CHI2_TOL or hi - lo < CHI2_TOL:
            return math.exp(nxt)
        s = nxt
    return math.exp(0.5 * (lo + hi))


def noise_event_loss(log_l: torch.Tensor, counts: torch.Tensor, pairs: Sequence[tuple[int, int]], theta_pos,
                     theta_neg, convention: str = "random_phase", rel_mismatch: float = 0.1,
                     noise_events: torch.Tensor | None = None, floor: float | None = None,
                     knee: float | None = DEFAULT_LOG_KNEE,
                     spread: torch.Tensor | None = None, floor_stat: str = "mean",
                     huber_c: float = 0.0, device_floor: bool = False) -> tuple[torch.Tensor, float]:
    """The event loss weighted by a noise model of the counts: mean over pairs and pixels of

        r^2 / (v + floor * g),   r = (log_l[k2] - log_l[k1]) - (E_k2 - E_k1)   (log units, as pose_event_loss)

    v = count_variance (quantisation, per-pixel mismatch, noise events): what the counts cannot say. floor * g
    = the model's own squared error, which no event count can beat: ``floor`` is a variance in linear
    intensity (the trainer estimates it as it goes: :func:`update_floor`; None = this step's own estimate, as
    on a run's first step) and g = (1 / I_k1^2 + 1 / I_k2^2) / 2 carries it into log units at the pixel's
    rendered intensities I (detached, at least the log knee; ``knee`` None: g = 1, one floor in log units for
    every pixel). A chi-square per sample: about 1 where the rendering fits the counts to their noise, so its
    size does not depend on the threshold; a pixel-pair weighs by how precisely its counts measure the
    change, and never above 1 / (floor g), so finer thresholds sharpen the target without letting the term
    outgrow the blur loss (the count norm, residual / theta, grows as 1 / theta^2).
    Returns (loss, this step's floor estimate: by default the mean of (r^2 - v) / g, else as ``floor_stat``
    says; a detached float, which update_floor bounds). ``theta_pos``/``theta_neg`` may be (H, W) per-pixel
    maps and ``spread`` their remaining relative error (count_variance).

    ``floor_stat`` "median": the estimate is the median of (r^2 - v) / g instead of the mean. The mean is set
    by the few pixel-pairs the model cannot render (a heavy tail) and caps every other pixel-pair's weight at
    theirs; the median is the error of a typical pixel-pair. "chi2": the floor at which the penalised
    chi-square averages what the noise model says it should (:func:`chi2_floor`). ``huber_c`` > 0: each
    r^2 / (v + floor g) through :func:`huber`, so the pixel-pairs beyond huber_c standard deviations, which a
    lower floor weighs more, pull as |r|.

    A ``floor`` given as a 0-dim float64 tensor (or ``device_floor`` with floor None), floor_stat "mean" or
    "median": the estimate is such a tensor too and nothing is read back to the host (the trainer's step on a
    GPU); the values are those of the float path (the float32 statistic widened exactly, the floor cast to
    float32 where it meets the float32 arrays, as a Python float is). "chi2" solves on the host (chi2_floor)."""
    _check_event_shapes(log_l, counts)
    if floor_stat not in FLOOR_STATS:
        raise ValueError(f"floor_stat must be one of {', '.join(FLOOR_STATS)}, got {floor_stat!r}")
    if not (huber_c >= 0 and math.isfinite(huber_c)):
        raise ValueError(f"huber_c must be finite and >= 0, got {huber_c!r}")
    if not (rel_mismatch >= 0 and math.isfinite(rel_mismatch)):
        raise ValueError(f"rel_mismatch must be finite and >= 0, got {rel_mismatch!r}")
    on_device = torch.is_tensor(floor) or (floor is None and device_floor)
    if floor is not None and not torch.is_tensor(floor) and not (floor > 0 and math.isfinite(floor)):
        raise ValueError(f"floor must be finite and > 0, got {floor!r}")
    if on_device and floor_stat == "chi2":
        raise ValueError("a floor on the device needs floor_stat mean or median (chi2 is solved on the host)")
    tp, tn = _thetas(theta_pos, theta_neg, log_l)
    if len(pairs) == 0:
        return log_l.sum() * 0.0, (torch.full((), FLOOR_MIN, dtype=torch.float64, device=log_l.device)
                                   if on_device else FLOOR_MIN)
    residual, v, g = noise_terms(log_l, counts, pairs, tp, tn, convention, rel_mismatch, noise_events, knee,
                                 spread)
    with torch.no_grad():
        r2 = residual * residual
        if floor_stat == "chi2":
            estimate = chi2_floor(r2, v, g, huber_c, floor)
        else:
            excess = (r2 - v) / g
            estimate = torch.median(excess) if floor_stat == "median" else torch.mean(excess)
            # a float32 value widened to float64 (exact): the number float() gives, left on the device
            estimate = estimate.to(torch.float64) if on_device else float(estimate)
    if floor is None and on_device:
        floor = torch.where(torch.isfinite(estimate), estimate.clamp_min(FLOOR_MIN), FLOOR_MIN)
    elif floor is None:
        floor = max(estimate, FLOOR_MIN) if math.isfinite(estimate) else FLOOR_MIN
    loss = torch.mean(huber(residual * residual / (v + floor * g), huber_c))
    return loss, estimate


def update_floor(floor: float | None, estimate: float) -> float:
    """The model's squared error beyond the counts' own noise (noise_event_loss's estimate of one step) as an
    exponential average over steps (None: the first step's value), never below FLOOR_MIN. Early in training
    the rendering is far from the counts, the floor is large and the event term weighs little; it tightens
    as the model fits. A non-finite estimate (a step the trainer's NaN guard stops) leaves the floor as it was.
    A tensor ``estimate`` (0-dim float64, noise_event_loss on the device): the same arithmetic in float64 tensor
    operations, one IEEE operation each as in Python, so the same bits, and nothing read back."""
    if torch.is_tensor(estimate):
        e = estimate.clamp_min(FLOOR_MIN)
        if floor is None:
            return torch.where(torch.isfinite(estimate), e, FLOOR_MIN)
        if not torch.is_tensor(floor):   # (a float floor from an older checkpoint: made once)
            floor = torch.as_tensor(floor, dtype=torch.float64, device=estimate.device)
        new = (FLOOR_MOMENTUM * floor + (1.0 - FLOOR_MOMENTUM) * e).clamp_min(FLOOR_MIN)
        return torch.where(torch.isfinite(estimate), new, floor)
    if not math.isfinite(estimate):
        return FLOOR_MIN if floor is None else floor
    estimate = max(estimate, FLOOR_MIN)
    if floor is None:
        return estimate
    return max(FLOOR_MOMENTUM * floor + (1.0 - FLOOR_MOMENTUM) * estimate, FLOOR_MIN)
