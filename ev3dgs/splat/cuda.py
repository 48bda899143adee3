"""The `cuda` backend: gsplat's CUDA kernels behind our conventions (an optional extra, `pip install ev3dgs[cuda]`,
tested against gsplat 1.5.3).

The same pipeline as gsplat's `rasterization()` (projection, SH, tile intersection, rasterization), called
step by step so that ``meta["means2d"]`` is the tensor the rasterizer reads: its ``.grad`` (after
``retain_grad()``) is the screen-space gradient densification needs. (Taking ``meta["means2d"][0]`` from
`rasterization()` gives a view that nothing downstream uses, whose ``.grad`` stays None.)

A stack of C cameras (viewmat (C, 4, 4): every sub-pose and event-pair pose of a training step) goes through
the same five calls once, with viewmats (C, 4, 4) and Ks (C, 3, 3): ``meta["means2d"]`` is (C, N, 2) and its
``.grad[c]`` camera c's screen-space gradient. Densification (ev3dgs.splat.strategy, as gsplat 1.5.3's
DefaultStrategy) takes, per camera and Gaussian visible in it, the norm of that camera's gradient scaled by
(W/2, H/2), sums these norms over cameras and counts the cameras that see the Gaussian; the mean is norm sum /
count. (gsplat's strategy also multiplies by n_cameras because its loss averages over the C images; ours takes
a ``grad_scale`` instead.) So the gradients must stay per camera: the norm of a sum over cameras is not the sum
of the norms.

Convention differences from the `reference` backend, each pinned by tests/test_gsplat_parity.py on the CPU
(gsplat's torch reference functions fed the exact arguments built here) and tests marked ``gpu``:

* pixel centres: gsplat evaluates pixel (x, y) at (x + 0.5, y + 0.5), we at (x, y): the principal point is
  shifted by +0.5 on the way in, and the projected means shifted back by -0.5 for ``meta["means2d"]``;
* radius: gsplat's per-axis box ``ceil(min(3.33, sqrt(2 ln(255 o))) * sqrt(cov_xx or cov_yy))`` is inside our
  square (exact opacity-aware bound over the largest eigenvalue); both contain every pixel with
  alpha >= 1/255, so the images agree; ``meta["radii"]`` is the larger axis, and a Gaussian whose box misses
  the image while our square touches it (it colours no pixel in either) is culled here and not in `reference`;
* alpha cap: gsplat's kernel caps alpha at 0.999, ours at 0.99 (and it stops when the transmittance would
  reach <= 1e-4, ours < 1e-4): pixels where a Gaussian's opacity exceeds 0.99 differ;
* culling: near/far keep near <= z <= far (ours near < z < far); a zero quaternion is NaN in gsplat (identity
  in ours); non-finite rows are not culled by gsplat;
* depth (render_mode "RGB+D"): the camera z appended as a colour channel with a zero background, i.e. the
  alpha-weighted depth (gsplat's "RGB+D"), not gsplat's "RGB+ED" (that divided by alpha);
* unpacked (``packed=False``), tile size 16, classic (no antialiasing compensation), float32 only; K gets no
  gradient (the view matrix does: camera gradients for --refine-poses).

Not bitwise reproducible: gsplat's backward sums each Gaussian's gradient over pixels with float atomicAdd,
whose order changes from run to run, so two CUDA runs with the same seed agree closely but not bit for bit
(the CPU backends, `reference` and `cpu`, are bitwise reproducible for any thread count)."""
from __future__ import annotations

import math

import torch

TILE_SIZE = 16


def rasterization_cuda(means, quats, scales, opacities, colors, viewmat, K, width, height, *, sh_degree,
                       near_plane, far_plane, eps2d, background, render_mode, ops=None):
    """One camera (viewmat (4, 4)) or a stack of C cameras (viewmat (C, 4, 4)), rendered by one sequence of
    gsplat calls either way: projection of all C cameras, SH, tile intersection over all C images, one
    rasterizer call. K: (3, 3) shared by every camera, or (C, 3, 3).

    Returns image (H, W, D) / alpha (H, W, 1) for one camera, (C, H, W, D) / (C, H, W, 1) for a stack, and meta
    with ``means2d`` ((N, 2) or (C, N, 2): the tensor the rasterizer reads, so after ``retain_grad()`` its
    ``.grad[c]`` is camera c's screen-space gradient), ``radii``, ``depths`` ((N,) or (C, N)), ``conics``,
    ``width``, ``height``, ``n_cameras``.

    Nothing here reads a GPU value back to the host (no ``.item()``, no branch on tensor values, no
    ``torch.linalg.inv``, whose singularity check synchronises: ``inv_ex``, no host-to-device copy; pinned
    by tests/test_train_sync.py through gsplat's torch implementations); gsplat's
    ``isect_tiles`` itself reads the intersection count back once per call to size its buffers (gsplat
    1.5.3, Intersect.cpp): once per stack, not once per camera.

    ``ops``: a namespace with gsplat's `fully_fused_projection`, `spherical_harmonics`, `isect_tiles`,
    `isect_offset_encode`, `rasterize_to_pixels` (default: gsplat itself; the parity tests pass torch
    implementations)."""
    if ops is None:
        import gsplat as ops

    batched = viewmat.ndim == 3
    viewmats = viewmat if batched else viewmat[None]
    C = viewmats.shape[0]
    Ks = K.detach() if K.ndim == 3 else K.detach()[None].expand(C, 3, 3)
    Kg = Ks.clone()   # gsplat's pixel centres: the principal point + 0.5 (in place: a constant made with
    Kg[:, :2, 2] += 0.5   # new_tensor would be a blocking host-to-device copy at every call)
    radii, means2d_g, depths, conics, _ = ops.fully_fused_projection(
        means, None, quats, scales, viewmats, Kg.contiguous(), width, height, eps2d=eps2d, near_plane=near_plane,
        far_plane=far_plane, packed=False, opacities=opacities)
    # our pixel convention; the rasterizer below reads exactly this tensor (shifted back), so its .grad is the
    # screen-space gradient: (C, N, 2) for a stack, (N, 2) for one camera (a [0] view of a (1, N, 2) tensor would
    # not be on the image's path and would get no .grad)
    means2d = means2d_g - 0.5 if batched else means2d_g[0] - 0.5
    if colors.ndim == 3:  # SH coefficients (N, K, 3), evaluated towards each camera's centre
        campos = torch.linalg.inv_ex(viewmats).inverse[:, :3, 3]  # inv would synchronise (its singularity check)
        dirs = means[None, :, :] - campos[:, None, :]  # (C, N, 3)
        coeffs = colors[None].expand(C, *colors.shape)  # (C, N, K, 3); gsplat makes it contiguous
        colors = ops.spherical_harmonics(sh_degree, dirs, coeffs, masks=(radii > 0).all(dim=-1))
        colors = torch.clamp_min(colors + 0.5, 0.0)  # (C, N, 3)
    else:
        colors = colors[None].expand(C, *colors.shape)  # (C, N, D)
    bg = background
    if render_mode == "RGB+D":  # the alpha-weighted camera z, zero background
        colors = torch.cat([colors, depths[..., None].to(colors.dtype)], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, bg.new_zeros(1)])
    tiles_x, tiles_y = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    m2d = means2d + 0.5 if batched else (means2d + 0.5)[None]
    _, isect_ids, flatten_ids = ops.isect_tiles(m2d, radii, depths, TILE_SIZE, tiles_x, tiles_y, packed=False,
                                                n_images=C)
    offsets = ops.isect_offset_encode(isect_ids, C, tiles_x, tiles_y).reshape(C, tiles_y, tiles_x)
    images, alphas = ops.rasterize_to_pixels(
        m2d, conics, colors.contiguous(), opacities[None].expand(C, -1).contiguous(), width, height, TILE_SIZE,
        offsets, flatten_ids, backgrounds=None if bg is None else bg[None].expand(C, -1).contiguous(),
        packed=False)
    meta = {"means2d": means2d, "radii": radii.max(dim=-1).values, "depths": depths, "conics": conics,
            "width": width, "height": height, "n_cameras": C}
    if not batched:
        meta.update(radii=meta["radii"][0], depths=depths[0], conics=conics[0])
        return images[0], alphas[0], meta
    return images, alphas, meta
