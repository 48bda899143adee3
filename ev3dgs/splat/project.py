"""EWA projection of 3D Gaussians to the image plane (gsplat / inria math, pure torch, autograd).

Conventions
-----------
* ``viewmat`` (4, 4) is world->camera with OpenCV axes (x right, y down, z forward).
* ``K`` (3, 3) uses OpenCV's *pixel* convention: the centre of the top-left pixel is (0, 0), so pixel
  (column x, row y) is evaluated at exactly the 2D point (x, y) and the image's pixel area is
  [-0.5, W-0.5] x [-0.5, H-0.5]. (gsplat puts pixel centres at +0.5; we do not.) Skew K[0, 1] is ignored.
* Gaussians: ``means`` (N, 3); ``quats`` (N, 4) wxyz, normalised here with ``norm.clamp_min(1e-12)``
  (a zero quaternion gives the identity rotation); ``scales`` (N, 3) already activated; ``opacities`` (N,)
  already activated in [0, 1].

Math (per Gaussian)
-------------------
R = R(q / |q|); Sigma = R S S R^T; camera point t = W x + tw, z = t_z.

* Depth cull: z <= near or z >= far. For culled rows z is replaced by 1 with ``torch.where`` *before* any
  division, so no inf/NaN enters the graph (values or gradients). Rows with any non-finite input
  (means, quats, scales, opacities) are also culled: their inputs are swapped for harmless finite values
  with ``torch.where`` (their gradient is exactly 0) instead of propagating NaN.
* FOV clamp (gsplat ``_persp_proj``, translated to our pixel convention, whose image edges are at -0.5 and
  W-0.5 instead of 0 and W)::

      tan_x = 0.5 * W / fx ;  tan_y = 0.5 * H / fy
      lim_x_pos = (W - 0.5 - cx) / fx + 0.3 * tan_x ;  lim_x_neg = (cx + 0.5) / fx + 0.3 * tan_x
      lim_y_pos = (H - 0.5 - cy) / fy + 0.3 * tan_y ;  lim_y_neg = (cy + 0.5) / fy + 0.3 * tan_y
      tx = z * clamp(x / z, -lim_x_neg, lim_x_pos) ;  ty = z * clamp(y / z, -lim_y_neg, lim_y_pos)

  For a centred principal point cx = (W-1)/2 this is exactly x/z in [-1.3 tan(fov_x/2), +1.3 tan(fov_x/2)].
  The clamped tx, ty enter only the Jacobian.
* J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]; cov2d = J W Sigma W^T J^T + eps2d I.
* det = (c11 c22 - c12^2).clamp_min(1e-12); conic = (a, b, c) = (c22, -c12, c11) / det.
* means2d = (fx x/z + cx, fy y/z + cy) with the *unclamped* x, y; depths = z (the raw camera z).

Radius (differs from gsplat on purpose)
---------------------------------------
The rasterizers skip a pixel when alpha = min(0.99, o exp(-d^2/2)) < 1/255 (d^2 = Mahalanobis distance
under the conic). A Gaussian can therefore only matter where d^2/2 <= ln(255 o), i.e. inside the ellipse of
"radius" extent = sqrt(2 ln(255 o)) standard deviations. With

    lambda_max = mid + sqrt(max(mid^2 - det, 0.1)),  mid = (c11 + c22) / 2   (an upper bound on the
                                                                              largest eigenvalue of cov2d)
    radius = ceil(extent * sqrt(lambda_max) * (1 + 1e-5))

every pixel outside the square [mx - r, mx + r] x [my - r, my + r] has d^2 > r^2 / lambda_max >= extent^2,
hence alpha < 1/255, so a tile/box based rasterizer that uses this square is EXACT w.r.t. the per-pixel
rule. (The 1e-5 relative margin only absorbs rounding of the conic in float32; it makes the square a
superset.) Radius is 0 (culled) when: o < 1/255 (compared in the opacities' dtype, exactly like the
rasterizer's skip test; a surviving Gaussian gets radius >= 1), the depth cull applies, an input row is
non-finite, or the square lies entirely outside the pixel area [-0.5, W-0.5] x [-0.5, H-0.5].
Radii are int32 and computed under ``no_grad`` (in float64).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

ALPHA_MIN = 1.0 / 255.0
RADIUS_MARGIN = 1e-5


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities. Tensors are in the dtype of ``means``."""

    means2d: torch.Tensor  # (N, 2) pixel coords (x, y), OpenCV pixel convention
    conics: torch.Tensor  # (N, 3) (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depths: torch.Tensor  # (N,) camera-space z
    radii: torch.Tensor  # (N,) int32, 0 = culled
    cov2d: Optional[torch.Tensor] = None  # (N, 3) (c11, c12, c22) of the 2D covariance (incl. eps2d)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz (any norm) -> (N, 3, 3). Zero quaternions give the identity; finite gradients everywhere."""
    sq = (quats * quats).sum(-1, keepdim=True)
    # == q / norm.clamp_min(1e-12), written so the gradient at q = 0 is finite (0 instead of 0/0)
    q = quats / sq.clamp_min(1e-24).sqrt()
    w, x, y, z = q.unbind(-1)  # q = 0 gives R = I
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S R^T, (N, 3, 3)."""
    M = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # R @ diag(s)
    return M @ M.transpose(-1, -2)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """Project N Gaussians with the EWA approximation. See the module docstring for the exact math."""
    dtype, device = means.dtype, means.device
    viewmat = torch.as_tensor(viewmat).to(dtype=dtype, device=device)
    K = torch.as_tensor(K).to(dtype=dtype, device=device)
    width, height = int(width), int(height)

    # ---- non-finite rows: cull and sanitise (torch.where => exactly zero gradient there)
    finite = (
        torch.isfinite(means).all(-1)
        & torch.isfinite(quats).all(-1)
        & torch.isfinite(scales).all(-1)
        & torch.isfinite(opacities)
    )
    fin = finite.unsqueeze(-1)
    means = torch.where(fin, means, torch.zeros_like(means))
    quats = torch.where(fin, quats, torch.ones_like(quats))
    scales = torch.where(fin, scales, torch.ones_like(scales))

    Wr = viewmat[:3, :3]
    tw = viewmat[:3, 3]
    t = means @ Wr.T + tw  # (N, 3)
    x, y, z_raw = t.unbind(-1)
    valid_z = (z_raw > near) & (z_raw < far) & finite
    z = torch.where(valid_z, z_raw, torch.ones_like(z_raw))

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_x_pos = (width - 0.5 - cx) / fx + 0.3 * tan_x
    lim_x_neg = (cx + 0.5) / fx + 0.3 * tan_x
    lim_y_pos = (height - 0.5 - cy) / fy + 0.3 * tan_y
    lim_y_neg = (cy + 0.5) / fy + 0.3 * tan_y
    xz = x / z
    yz = y / z
    tx = z * torch.minimum(torch.maximum(xz, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(yz, -lim_y_neg), lim_y_pos)

    zero = torch.zeros_like(z)
    rz = 1.0 / z
    rz2 = rz * rz
    J = torch.stack(
        [fx * rz, zero, -fx * tx * rz2, zero, fy * rz, -fy * ty * rz2], dim=-1
    ).reshape(-1, 2, 3)

    Sigma = covariance_3d(quats, scales)  # (N, 3, 3)
    JW = J @ Wr  # (N, 2, 3)
    cov = JW @ Sigma @ JW.transpose(-1, -2)  # (N, 2, 2)
    c11 = cov[:, 0, 0] + eps2d
    c12 = cov[:, 0, 1]
    c22 = cov[:, 1, 1] + eps2d
    det = (c11 * c22 - c12 * c12).clamp_min(1e-12)
    conics = torch.stack([c22 / det, -c12 / det, c11 / det], dim=-1)
    cov2d = torch.stack([c11, c12, c22], dim=-1)
    means2d = torch.stack([fx * xz + cx, fy * yz + cy], dim=-1)

    radii = compute_radii(means2d, cov2d, opacities, valid_z, width, height)
    return Projection(means2d=means2d, conics=conics, depths=z_raw, radii=radii, cov2d=cov2d)


@torch.no_grad()
def compute_radii(
    means2d: torch.Tensor,
    cov2d: torch.Tensor,
    opacities: torch.Tensor,
    valid: torch.Tensor,
    width: int,
    height: int,
) -> torch.Tensor:
    """Exact-support radius (see module docstring). Returns int32 (N,), 0 = culled."""
    o = opacities.detach()
    visible = valid & torch.isfinite(o) & ~(o < ALPHA_MIN)  # same comparison/dtype as the rasterizer
    o64 = torch.where(visible, o.double(), torch.ones_like(o, dtype=torch.float64))
    extent = (2.0 * torch.log(255.0 * o64).clamp_min(0.0)).sqrt()
    cv = cov2d.detach().double()
    c11, c12, c22 = cv.unbind(-1)
    mid = 0.5 * (c11 + c22)
    det = c11 * c22 - c12 * c12
    lam = mid + (mid * mid - det).clamp_min(0.1).sqrt()
    r = torch.ceil(extent * lam.clamp_min(0.0).sqrt() * (1.0 + RADIUS_MARGIN))
    ok = visible & torch.isfinite(r)
    r = torch.where(ok, r.clamp_min(1.0), torch.zeros_like(r))
    m = means2d.detach().double()
    mx, my = m[:, 0], m[:, 1]
    off = (mx + r < -0.5) | (mx - r > width - 0.5) | (my + r < -0.5) | (my - r > height - 0.5)
    off = off | ~torch.isfinite(mx) | ~torch.isfinite(my)
    r = torch.where(off, torch.zeros_like(r), r)
    # int32 range guard (a radius that large covers any image anyway)
    r = r.clamp_max(float(2**30))
    return r.to(torch.int32)


__all__ = ["Projection", "project_gaussians", "compute_radii", "quat_to_rotmat", "covariance_3d", "ALPHA_MIN"]
