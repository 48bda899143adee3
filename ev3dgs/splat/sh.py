"""Real spherical harmonics (degree <= 3) with the inria / gsplat constants and signs.

Basis ordering is the usual ``k = l*l + l + m`` with ``m = -l..l``.  The sign convention
is the one of graphdeco-inria ``utils/sh_utils.py`` and gsplat ``_eval_sh_bases_fast``:
degree 1 is ``(-C1*y, C1*z, -C1*x)`` etc.  Relative to the textbook real SH built from
complex SH *with* the Condon-Shortley phase,
``Y_lm = sqrt(2) * (-1)^m * Im(Y_l^|m|)`` (m<0), ``Y_l0``, ``sqrt(2) * (-1)^m * Re(Y_l^m)`` (m>0),
the 3DGS basis differs by the factor ``(-1)^m`` on every ``m != 0`` basis, i.e. 3DGS uses
``sqrt(2) * Im/Re(Y_l^|m|)`` of the Condon-Shortley complex SH (see tests/test_splat_model.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["C0", "C1", "C2", "C3", "num_sh_bases", "sh_basis", "eval_sh", "rgb_to_sh", "sh_to_rgb"]

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients up to and including ``degree`` ((degree+1)^2)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    return (degree + 1) ** 2


def _safe_normalise(dirs: Tensor) -> Tensor:
    # sqrt of a clamped squared norm: finite values *and* finite gradients at dirs == 0.
    sq = (dirs * dirs).sum(dim=-1, keepdim=True).clamp_min(1e-24)
    return dirs / torch.sqrt(sq)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the (degree+1)^2 real SH basis functions at ``dirs`` (..., 3) -> (..., K).

    ``dirs`` need not be normalised; zero vectors give the degree-0 term only.
    """
    num_sh_bases(degree)  # validates degree
    d = _safe_normalise(dirs)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Colours from SH coefficients.

    sh: (N, K, 3) with K >= (degree+1)^2 (only the first (degree+1)^2 are used);
    dirs: (N, 3) view directions (camera -> Gaussian), normalised internally.
    Returns (N, 3) = max(sum_k basis_k * sh_k + 0.5, 0).
    """
    k = num_sh_bases(degree)
    if sh.shape[-2] < k:
        raise ValueError(f"need at least {k} SH coefficients for degree {degree}, got {sh.shape[-2]}")
    basis = sh_basis(degree, dirs).to(sh.dtype)  # (N, k)
    result = (basis.unsqueeze(-1) * sh[..., :k, :]).sum(dim=-2)
    return torch.clamp_min(result + 0.5, 0.0)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """Degree-0 coefficient whose colour (without view dependence) is ``rgb``."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh0: Tensor) -> Tensor:
    return sh0 * C0 + 0.5
