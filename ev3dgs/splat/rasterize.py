"""One rasterization function over backends, in the spirit of gsplat's `rasterization()`.

    image, alpha, meta = rasterization(means, quats, scales, opacities, colors, viewmat, K, width, height)

means (N,3), quats (N,4) wxyz, scales (N,3) and opacities (N,) already activated; colors (N,D) or SH
coefficients (N,K,3) with sh_degree; viewmat (4,4) world->camera (OpenCV axes); K (3,3) with the OpenCV
pixel convention (pixel (x, y) is evaluated at exactly (x, y)). Returns image (H,W,D) (D+1 channels with
render_mode="RGB+D": the last is the alpha-weighted depth, as gsplat's "D"), alpha (H,W,1), and meta with
the projected `means2d` (whose .grad feeds densification), `radii`, `depths`, `width`, `height`.

Batched: viewmat (C,4,4) renders C cameras at once: image (C,H,W,D), alpha (C,H,W,1), meta means2d (C,N,2),
radii/depths (C,N), n_cameras C. On "cpu" that is one numba projection + SH kernel for all cameras
(project_cpu.py, hand-written backward), one binning pass and one rasterizer kernel over (camera, tile); each
camera's image and gradients are bitwise those of its own single-camera call. On "cuda" one sequence of gsplat
calls renders the stack (cuda.py). "reference" loops over the cameras inside the call, rasterizing each from its
slice of one stacked (C,N,2) means2d; a backend without a batched call loops over single-camera calls and hooks
each camera's gradient into the stacked means2d. On every backend, after backward, meta["means2d"].grad holds
every camera's screen-space gradient (C,N,2).

Backends: "reference" (plain torch, the test oracle), "cpu" (numba kernels, exact), "cuda" (gsplat, when
CUDA and gsplat are available), "auto" (cuda for CUDA tensors when possible, else cpu). Every backend
differentiates the view matrix (camera gradients for pose refinement): reference by autograd, cpu by its
hand-written projection backward (project_cpu.py), cuda by gsplat. The cpu backend uses the torch projection
instead when K requires a gradient.
"""
from __future__ import annotations

import torch

from ..errors import InputError
from .project import project_gaussians
from .sh import eval_sh

BACKENDS = ("auto", "reference", "cpu", "cuda")


def cuda_available() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def _check(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree):
    n = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise InputError(f"means must be (N, 3), got {tuple(means.shape)}")
    if viewmat.ndim == 3 and (viewmat.shape[0] < 1 or tuple(viewmat.shape[1:]) != (4, 4)):
        raise InputError(f"viewmat must be (4, 4) or (C, 4, 4), got {tuple(viewmat.shape)}")
    for name, t, shape in (("quats", quats, (n, 4)), ("scales", scales, (n, 3)), ("opacities", opacities, (n,)),
                           ("viewmat", viewmat[0] if viewmat.ndim == 3 else viewmat, (4, 4)), ("K", K, (3, 3))):
        if tuple(t.shape) != shape:
            raise InputError(f"{name} must be {shape}, got {tuple(t.shape)}")
    if colors.shape[0] != n or colors.ndim not in (2, 3):
        raise InputError(f"colors must be (N, D) or SH (N, K, 3), got {tuple(colors.shape)}")
    if colors.ndim == 3 and (sh_degree is None or colors.shape[1] < (sh_degree + 1) ** 2):
        raise InputError("SH colours need sh_degree with (sh_degree + 1)**2 <= K")
    if not (0 < width <= 16384 and 0 < height <= 16384):
        raise InputError(f"impossible image size {width}x{height}")


def rasterization(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, *,
                  sh_degree: int | None = None, near_plane: float = 0.01, far_plane: float = 1e10,
                  eps2d: float = 0.3, background=None, render_mode: str = "RGB", backend: str = "auto",
                  threads: int | None = None):
    if backend not in BACKENDS:
        raise InputError(f"unknown backend {backend!r} (one of {', '.join(BACKENDS)})")
    if render_mode not in ("RGB", "RGB+D"):
        raise InputError(f"render_mode must be 'RGB' or 'RGB+D', got {render_mode!r}")
    _check(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree)
    if backend == "auto":
        backend = "cuda" if means.is_cuda and cuda_available() else "cpu"
    if backend == "cpu" and not (K.requires_grad or means.is_cuda):
        return _rasterization_cpu(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree,
                                  near_plane, far_plane, eps2d, background, render_mode, threads)
    if backend == "cuda":  # one camera or a stack (C, 4, 4): one sequence of gsplat calls either way
        from .cuda import rasterization_cuda

        return rasterization_cuda(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                  sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
                                  background=background, render_mode=render_mode)
    if viewmat.ndim == 3:  # one camera at a time inside this call (the oracle for the batched cpu path)
        kw = dict(sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
                  background=background, render_mode=render_mode)
        if backend == "reference":
            return _rasterization_reference_batched(means, quats, scales, opacities, colors, viewmat, K, width,
                                                    height, **kw)
        return _rasterization_loop(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                   backend=backend, threads=threads, **kw)
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height,
                             near=near_plane, far=far_plane, eps2d=eps2d)
    if colors.ndim == 3:
        campos = torch.linalg.inv(viewmat)[:3, 3]
        colors = eval_sh(sh_degree, colors, means - campos)
    if background is None:
        background = torch.zeros(colors.shape[1], dtype=colors.dtype, device=colors.device)
    if render_mode == "RGB+D":
        colors = torch.cat([colors, proj.depths[:, None].to(colors.dtype)], dim=1)
        background = torch.cat([background, background.new_zeros(1)])
    args = (proj.means2d, proj.conics, colors, opacities, proj.depths, proj.radii, width, height, background)
    if backend == "reference":
        from .reference import rasterize_reference

        image, alpha = rasterize_reference(*args)
    else:
        from .cpu import announce_compile, rasterize_cpu

        announce_compile()
        image, alpha = rasterize_cpu(*args, threads=threads)
    meta = {"means2d": proj.means2d, "radii": proj.radii, "depths": proj.depths, "conics": proj.conics,
            "width": width, "height": height, "n_cameras": 1}
    return image, alpha, meta


def _rasterization_reference_batched(means, quats, scales, opacities, colors, viewmats, K, width, height, *,
                                     sh_degree, near_plane, far_plane, eps2d, background, render_mode):
    """C cameras on the reference backend: each camera projected, the screen-space means stacked into one
    (C, N, 2) tensor and each camera rasterized from its slice of it, so that meta["means2d"] carries every
    camera's screen-space gradient after backward (retain_grad it), as the batched cpu and cuda backends'."""
    from .reference import rasterize_reference

    projs = [project_gaussians(means, quats, scales, opacities, v, K, width, height, near=near_plane,
                               far=far_plane, eps2d=eps2d) for v in viewmats]
    means2d = torch.stack([p.means2d for p in projs])
    images, alphas = [], []
    for c, (v, proj) in enumerate(zip(viewmats, projs)):
        cols = colors
        if colors.ndim == 3:
            campos = torch.linalg.inv(v)[:3, 3]
            cols = eval_sh(sh_degree, colors, means - campos)
        bg = background
        if bg is None:
            bg = torch.zeros(cols.shape[1], dtype=cols.dtype, device=cols.device)
        if render_mode == "RGB+D":
            cols = torch.cat([cols, proj.depths[:, None].to(cols.dtype)], dim=1)
            bg = torch.cat([bg, bg.new_zeros(1)])
        image, alpha = rasterize_reference(means2d[c], proj.conics, cols, opacities, proj.depths, proj.radii,
                                           width, height, bg)
        images.append(image)
        alphas.append(alpha)
    meta = {"means2d": means2d, "radii": torch.stack([p.radii for p in projs]),
            "depths": torch.stack([p.depths for p in projs]), "conics": torch.stack([p.conics for p in projs]),
            "width": width, "height": height, "n_cameras": len(projs)}
    return torch.stack(images), torch.stack(alphas), meta


def _rasterization_loop(means, quats, scales, opacities, colors, viewmats, K, width, height, *, backend,
                        threads, **kw):
    """C cameras through C single-camera calls (the cuda backend where it has no batched call). The stacked
    meta["means2d"] (C, N, 2) is not in the autograd graph, so each camera's means2d passes its gradient to
    it with a hook: after a backward pass meta["means2d"].grad holds every camera's screen-space gradient.
    ``meta["means2d_parts"]``: the per-camera tensors (autograd.grad of a single term's loss goes through
    them)."""
    outs = [rasterization(means, quats, scales, opacities, colors, v, K, width, height, backend=backend,
                          threads=threads, **kw) for v in viewmats]
    meta = {k: (torch.stack([o[2][k] for o in outs]) if torch.is_tensor(outs[0][2][k]) else outs[0][2][k])
            for k in outs[0][2]}
    parts = [o[2]["means2d"] for o in outs]
    stacked = meta["means2d"] = torch.stack([p.detach() for p in parts])
    if any(p.requires_grad for p in parts):
        def keep(c):
            def hook(grad):
                if stacked.grad is None:
                    stacked.grad = torch.zeros_like(stacked)
                stacked.grad[c] = grad
            return hook

        for c, p in enumerate(parts):
            if p.requires_grad:
                p.register_hook(keep(c))
        meta["means2d_parts"] = parts
    meta["n_cameras"] = len(outs)
    return torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs]), meta


def _rasterization_cpu(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, near_plane,
                       far_plane, eps2d, background, render_mode, threads):
    """numba projection + SH for all cameras in one call, then one batched rasterizer call."""
    from .cpu import announce_compile, rasterize_cpu, set_numba_threads
    from .project_cpu import project_sh_cpu

    announce_compile()
    if threads is not None:  # the projection kernel runs on the same numba thread count as the rasterizer
        set_numba_threads(threads)
    batched = viewmat.ndim == 3
    viewmats = viewmat if batched else viewmat[None]
    sh = colors if colors.ndim == 3 else None
    m2d, conics, depths, sh_colors, radii = project_sh_cpu(
        means, quats, scales, opacities, sh, viewmats, K, width, height,
        sh_degree=sh_degree if sh is not None else None, near=near_plane, far=far_plane, eps2d=eps2d)
    cols = sh_colors if sh is not None else colors  # (C,N,3) per camera, or (N,D) shared
    if background is None:
        background = torch.zeros(cols.shape[-1], dtype=cols.dtype, device=cols.device)
    if render_mode == "RGB+D":
        if cols.ndim == 2:
            cols = cols.expand(viewmats.shape[0], -1, -1)
        cols = torch.cat([cols, depths[..., None].to(cols.dtype)], dim=-1)
        background = torch.cat([background, background.new_zeros(1)])
    if not batched:  # views (squeeze's backward is a view; a select's fills a zero tensor and copies into it)
        m2d, conics, depths, radii = (t.squeeze(0) for t in (m2d, conics, depths, radii))
        cols = cols.squeeze(0) if cols.ndim == 3 else cols
    image, alpha = rasterize_cpu(m2d, conics, cols, opacities, depths, radii, width, height, background,
                                 threads=threads)
    meta = {"means2d": m2d, "radii": radii, "depths": depths, "conics": conics, "width": width, "height": height,
            "n_cameras": viewmats.shape[0] if batched else 1}
    return image, alpha, meta
