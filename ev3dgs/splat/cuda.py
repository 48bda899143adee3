"""The `cuda` backend: gsplat's CUDA rasterizer behind our conventions (an optional extra:
`pip install ev3dgs[cuda]`). gsplat puts pixel centres at +0.5, we put them at integer coordinates, so
the principal point is shifted by half a pixel on the way in. Its radius rule (3.33 sigma) differs from
ours (the exact, opacity-aware 1/255 bound), which changes nothing visible: every pixel it drops has
alpha < 1/255 in both. A parity test against `reference` runs whenever CUDA is available.

Not bitwise reproducible: gsplat's backward sums each Gaussian's gradient over pixels with float atomicAdd,
whose order changes from run to run, so two CUDA runs with the same seed agree closely but not bit for bit
(the CPU backends, `reference` and `cpu`, are bitwise reproducible for any thread count)."""
from __future__ import annotations

import torch


def rasterization_cuda(means, quats, scales, opacities, colors, viewmat, K, width, height, *, sh_degree,
                       near_plane, far_plane, eps2d, background, render_mode):
    from gsplat import rasterization as gs_rasterization

    Kg = K.clone()
    Kg[0, 2] += 0.5
    Kg[1, 2] += 0.5
    bg = None if background is None else background[None]
    image, alpha, meta = gs_rasterization(
        means, quats, scales, opacities, colors, viewmat[None], Kg[None], width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, packed=False,
        backgrounds=bg, render_mode="RGB+ED" if render_mode == "RGB+D" else "RGB")
    if render_mode == "RGB+D":  # gsplat's ED is normalised by alpha; ours is the accumulated depth
        image = torch.cat([image[..., :-1], image[..., -1:] * alpha], dim=-1)
    means2d = meta["means2d"][0]
    out_meta = {"means2d": means2d, "radii": meta["radii"][0].max(dim=-1).values if meta["radii"].ndim == 3
                else meta["radii"][0], "depths": meta["depths"][0], "conics": meta["conics"][0],
                "width": width, "height": height, "n_cameras": 1}
    return image[0], alpha[0], out_meta
