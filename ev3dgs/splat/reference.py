"""Reference rasterizer: plain torch, dense, slow, obviously correct, autograd. The oracle for other backends.

Semantics (gsplat / inria front-to-back compositing, identical constants). Pixel (column x, row y) is
evaluated at the 2D point (x, y) (OpenCV pixel convention, no +0.5). Gaussians with radius > 0 are
sorted by depth ascending (stable: ties keep index order). Per pixel, with T = 1, C = 0, in that order:

    d = p - mean2d;  sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy
    if sigma < 0: skip
    alpha = min(0.99, o * exp(-sigma));  if alpha < 1/255: skip
    next_T = T * (1 - alpha);  if next_T < 1e-4: STOP (this Gaussian is NOT included)
    C += color * alpha * T;  T = next_T

    image = C + T * background;  alpha_out = 1 - T

Vectorised per block of pixels (block x block) as dense [P, n] tensors over the Gaussians whose radius box
reaches the block (the radius is exact: outside it alpha < 1/255, which the rules skip anyway), with
activation checkpointing so memory stays bounded: skipped entries get alpha 0 (``torch.where``),
T_after = cumprod(1 - alpha) along the sorted Gaussians. Because every factor is in [0.01, 1], T_after is
non-increasing (also in floating point), so ``include = T_after >= 1e-4`` is exactly a prefix and
reproduces "stop at the first next_T < 1e-4, nothing later counts". weights = alpha * T_before * include;
T_final = T_after of the last included Gaussian (1 if none). All masks are piecewise constant, so autograd
gives the exact gradient of this piecewise-smooth function. Works in the input dtype (float64 supported).

Determinism: no BLAS product and no scatter with repeated indices, so forward and backward are bitwise
reproducible for any torch thread count (tests/test_reliability_training.py).
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def rasterize_reference(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    background: Optional[torch.Tensor] = None,
    block: int = 32,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Composite Gaussians into an image. Returns (image (H, W, D), alpha (H, W, 1))."""
    width, height = int(width), int(height)
    dtype, device = means2d.dtype, means2d.device
    D = colors.shape[-1]
    if background is None:
        background = torch.zeros(D, dtype=dtype, device=device)
    background = background.to(dtype=dtype, device=device)

    # visible Gaussians, depth order (stable)
    vis = torch.nonzero(radii.reshape(-1) > 0).squeeze(-1)
    order = torch.argsort(depths.detach().reshape(-1)[vis], stable=True)
    idx = vis[order]
    m = means2d[idx]  # (n, 2)
    con = conics[idx]  # (n, 3)
    col = colors[idx].to(dtype)  # (n, D)
    op = opacities.reshape(-1)[idx].to(dtype)  # (n,)
    n = idx.numel()

    if n == 0:
        image = background.expand(height, width, D).clone() + 0 * colors.sum()
        return image, torch.zeros(height, width, 1, dtype=dtype, device=device)
    r = radii.reshape(-1)[idx].to(dtype)
    rows = []
    for y0 in range(0, height, block):
        row = []
        for x0 in range(0, width, block):
            x1, y1 = min(x0 + block, width), min(y0 + block, height)
            # Gaussians whose (exact) radius box reaches this block; outside it alpha < 1/255 anyway
            near = ((m[:, 0] + r >= x0) & (m[:, 0] - r <= x1 - 1) & (m[:, 1] + r >= y0)
                    & (m[:, 1] - r <= y1 - 1)).nonzero().squeeze(-1)
            args = (m[near], con[near], col[near], op[near], background)
            if torch.is_grad_enabled():  # recompute in the backward: bounded memory
                out = torch.utils.checkpoint.checkpoint(_composite, x0, x1, y0, y1, *args, use_reentrant=False)
            else:
                out = _composite(x0, x1, y0, y1, *args)
            row.append(out)
        rows.append(torch.cat(row, dim=1))
    out = torch.cat(rows, dim=0)
    return out[..., :D], out[..., D:]


def _composite(x0, x1, y0, y1, m, con, col, op, background):
    """One block of pixels against its (depth-sorted) Gaussians: returns (h, w, D+1) = image, alpha."""
    dtype, device = m.dtype, m.device
    ys, xs = torch.meshgrid(torch.arange(y0, y1, dtype=dtype, device=device),
                            torch.arange(x0, x1, dtype=dtype, device=device), indexing="ij")
    h, w = ys.shape
    n = m.shape[0]
    cx, cy = xs.reshape(-1, 1), ys.reshape(-1, 1)
    P = cx.shape[0]
    dx = cx - m[None, :, 0]  # (P, n)
    dy = cy - m[None, :, 1]
    a, b, c = con[None, :, 0], con[None, :, 1], con[None, :, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    neg = sigma < 0
    # never exponentiate a negative sigma (overflow -> inf * 0 = NaN in the backward)
    sigma_safe = torch.where(neg, torch.zeros_like(sigma), sigma)
    alpha = torch.clamp_max(op[None, :] * torch.exp(-sigma_safe), ALPHA_MAX)
    keep = ~neg & ~(alpha < ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1.0 - alpha, dim=-1)  # (P, n)
    include = T_after >= T_MIN  # a prefix along dim -1
    ones = torch.ones(P, 1, dtype=dtype, device=device)
    T_all = torch.cat([ones, T_after], dim=-1)  # T_all[:, k] = T before Gaussian k
    T_before = T_all[:, :n]
    wgt = torch.where(include, alpha * T_before, torch.zeros_like(alpha))
    n_inc = include.sum(-1, keepdim=True)
    T_final = T_all.gather(-1, n_inc)  # (P, 1)
    # not `wgt @ col`: its backward (col's gradient, a sum over the P pixels) goes through BLAS, whose
    # split of that sum depends on the torch thread count; one channel at a time, element-wise products
    # and a plain sum give bitwise the same result for any thread count
    C = torch.stack([(wgt * col[None, :, d]).sum(-1) for d in range(col.shape[1])], dim=-1)  # (P, D)
    return torch.cat([C + T_final * background[None, :], 1.0 - T_final], dim=-1).reshape(h, w, -1)


__all__ = ["rasterize_reference"]
