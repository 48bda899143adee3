"""Where the random initial Gaussians go when a scene has neither /points nor bounds: a cube centred on the
point the cameras look at, as wide as the cameras' view there.

Centre: the least-squares point closest to every camera's optical axis (the line through its centre C_i along
its viewing direction d_i): minimise sum_i |(I - d_i d_i^T)(x - C_i)|^2, i.e. solve
sum_i (I - d_i d_i^T) x = sum_i (I - d_i d_i^T) C_i. For an orbit of cameras aimed at one point this is that
point exactly. Size: at the centre's median depth z in front of the cameras, the cube's half-width is
z * tan(half field of view) along the narrower image axis, so it covers what the cameras see there.

When the axes are (nearly) parallel (a forward-facing rig) or the point lies behind most cameras, the
cameras do not say where they look: if they face one general way (mean viewing direction of length >= 0.5)
the centre is put along it at the world origin's depth when the origin is in front of them (scenes are
usually built around it), else at unit depth; if they look all around (an inside-out rig) the centre is the
cameras' mean position. The cube is sized in the same way.
"""
from __future__ import annotations

import numpy as np

# Smallest eigenvalue of the mean of (I - d d^T) below which the axes are taken as parallel: for two axes at
# angle a it is about sin(a)^2 / 2 (half a degree of spread -> 4e-5).
PARALLEL_EIG = 1e-4


def look_centre(centres: np.ndarray, forwards: np.ndarray) -> tuple[np.ndarray, bool]:
    """(centre (3,), True) for the least-squares point closest to the optical axes, or (fallback centre, False)
    when the axes are nearly parallel or the point is behind most cameras (see the module doc)."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    d = np.asarray(forwards, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]          # (N, 3, 3) projections off each axis
    A = proj.mean(axis=0)
    b = np.einsum("nij,nj->i", proj, c) / len(c)
    if np.linalg.eigvalsh(A)[0] > PARALLEL_EIG:
        x = np.linalg.solve(A, b)
        if np.median(np.einsum("ni,ni->n", x[None] - c, d)) > 0:
            return x, True
    mean_dir = d.mean(axis=0)
    if np.linalg.norm(mean_dir) < 0.5:  # the cameras look all around (inside-out): the scene surrounds them
        return c.mean(axis=0), False
    mean_dir /= np.linalg.norm(mean_dir)
    origin_depth = float(np.median((0.0 - c) @ mean_dir))
    depth = origin_depth if origin_depth > 0 else 1.0
    return c.mean(axis=0) + depth * mean_dir, False


def init_bounds(centres: np.ndarray, forwards: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(2, 3) [min, max] of the initial cube: centred at :func:`look_centre`, half-width = median depth of
    the centre x tan(half the narrower field of view) (from K: (W/2) / fx and (H/2) / fy)."""
    x, _ = look_centre(centres, forwards)
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    d = np.asarray(forwards, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    depth = float(np.median(np.abs(np.einsum("ni,ni->n", x[None] - c, d))))
    K = np.asarray(K, np.float64)
    tan_half = min(0.5 * width / K[0, 0], 0.5 * height / K[1, 1])
    half = max(depth, 1e-6) * tan_half
    return np.stack([x - half, x + half])
