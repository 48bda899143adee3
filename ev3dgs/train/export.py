"""Gaussian models to and from the graphdeco (INRIA 3DGS) PLY layout that common splat viewers open.

One ``vertex`` element, binary little endian, float32 properties in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_{3(K-1)-1} opacity scale_0..2 rot_0..3

``f_dc`` is ``sh0`` (N, 1, 3) flattened; ``f_rest`` is ``shN`` (N, K-1, 3) stored channel-major, as
graphdeco's ``features_rest.transpose(1, 2).flatten(start_dim=1)``: ``f_rest_{c*(K-1)+j} = shN[:, j, c]``.
``opacity`` is the logit, ``scale_*`` the log-scales, ``rot_*`` the raw (unnormalised) quaternion wxyz, and
the normals are zero.  Only the raw parameters are stored (no activations), exactly as graphdeco does.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..splat.model import GaussianModel

__all__ = ["save_ply", "load_ply", "ply_property_names"]


def ply_property_names(sh_degree: int) -> list[str]:
    """The vertex property names, in file order, for a model of ``sh_degree``."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _np32(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float32).numpy()


def save_ply(model: GaussianModel, path: str | os.PathLike) -> Path:
    """Write ``model`` as a graphdeco 3DGS PLY (atomically: temporary file beside ``path``, then rename)."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    p = model.params
    n = len(model)
    k1 = p["shN"].shape[1]
    cols = [
        _np32(p["means"]),
        np.zeros((n, 3), np.float32),
        _np32(p["sh0"]).reshape(n, 3),
        _np32(p["shN"]).transpose(0, 2, 1).reshape(n, 3 * k1),
        _np32(p["opacity_logits"]).reshape(n, 1),
        _np32(p["log_scales"]),
        _np32(p["quats"]),
    ]
    flat = np.concatenate(cols, axis=1)
    names = ply_property_names(model.sh_degree)
    assert flat.shape[1] == len(names)
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertex[name] = flat[:, i]
    ply = PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<")

    from ..outputs import OutputError, atomic_path, os_error_message, remove_stale_temps

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot write {os_error_message(e, path.parent)}", e.errno) from None
    remove_stale_temps(path.parent, path.name)
    with atomic_path(path) as tmp:  # removes the temporary and names the reason on failure
        with open(tmp, "wb") as f:
            ply.write(f)
    return path


def load_ply(path: str | os.PathLike, device=None) -> GaussianModel:
    """Read a graphdeco 3DGS PLY back into a float32 GaussianModel (inverse of :func:`save_ply`).

    ``sh_degree`` is inferred from the number of ``f_rest_*`` properties; ``active_sh_degree`` is set to
    it (a saved model is rendered at its full degree).  Unreadable files or missing properties raise
    InputError.  Extra properties are ignored.
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such PLY file")
    try:
        with open(path, "rb") as f:
            ply = PlyData.read(f, mmap=False)
    except Exception as e:  # plyfile raises several types (PlyParseError, ValueError, EOF...)
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"{path}: not a readable PLY file ({msg})") from None
    try:
        v = ply["vertex"]
    except KeyError:
        raise InputError(f"{path}: PLY file has no 'vertex' element") from None
    props = set(v.data.dtype.names or ())
    n_rest = sum(1 for name in props if name.startswith("f_rest_"))
    k = n_rest // 3 + 1
    deg = int(round(math.sqrt(k))) - 1
    if n_rest % 3 or (deg + 1) ** 2 != k:
        raise InputError(f"{path}: {n_rest} f_rest properties do not match any SH degree")
    names = ply_property_names(deg)
    missing = [name for name in names if name not in props and name not in ("nx", "ny", "nz")]
    if missing:
        shown = ", ".join(missing[:6]) + (", ..." if len(missing) > 6 else "")
        raise InputError(f"{path}: PLY vertex element lacks properties {shown}")

    data = v.data
    n = len(data)

    def cols(*names_: str) -> torch.Tensor:
        a = np.stack([np.asarray(data[name], dtype=np.float32) for name in names_], axis=1) if names_ \
            else np.zeros((n, 0), np.float32)
        return torch.from_numpy(np.ascontiguousarray(a))

    params = {
        "means": cols("x", "y", "z"),
        "log_scales": cols("scale_0", "scale_1", "scale_2"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacity_logits": cols("opacity")[:, 0].contiguous(),
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3),
        "shN": cols(*(f"f_rest_{i}" for i in range(n_rest))).reshape(n, 3, k - 1).transpose(1, 2).contiguous(),
    }
    params = {name: t.to(device) for name, t in params.items()}
    return GaussianModel(params, sh_degree=deg, active_sh_degree=deg)
