"""The `cuda` backend's glue (ev3dgs/splat/cuda.py) checked on the CPU against our `reference` backend.

gsplat's CUDA kernels cannot run here, but gsplat ships torch reference functions of them
(`gsplat.cuda._torch_impl`). `TorchOps` below puts those behind the five gsplat calls cuda.py makes, with the
two parts gsplat's torch code does not reproduce written out from the 1.5.3 CUDA source:

* radii: the CUDA projection kernel's opacity-aware per-axis box (ProjectionEWA3DGSFused.cu),
  ``ceil(min(3.33, sqrt(2 ln(255 o))) * sqrt(cov2d_xx or _yy))``, cull when o < 1/255, z < near or z > far,
  det <= 0, or the box misses [0, W] x [0, H] (gsplat's pixel area); culled rows of means2d / depths / conics
  are left unwritten by the kernel (here: NaN, so anything that reads them shows);
* rasterization: `composite_gsplat` follows RasterizeToPixels3DGSFwd.cu over the tile lists: pixel centres at
  (x + 0.5, y + 0.5), alpha = min(0.999, o exp(-sigma)), skip sigma < 0 or alpha < 1/255, stop (exclusive)
  when the next transmittance is <= 1e-4, C + T * background.

Every call also binds its arguments to the real gsplat function's signature, so a misspelt or missing argument
fails here, not on the first GPU. Convention differences (cuda.py's docstring) are each asserted below.

Tolerances (tests/conftest.py policy): everything runs in float64 unless said otherwise. The projections are
short closed forms written in different operation orders; the conic inverts the 2D covariance, whose
condition number is at most lambda_max / eps2d (<= 1e4 for these scenes: sigma <= 30 px), so
rtol = 100 u * 1e4 ~ 1e-10 (we use 1e-9). Images are sums of <= 200 fragments of O(1) terms: atol 1e-10. A
threshold decision (alpha vs 1/255, T vs 1e-4) could flip only if a value lies within ~1e-15 of the
threshold; with these seeded scenes none does (deterministic inputs, so this cannot flake).
"""
from __future__ import annotations

import inspect
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ev3dgs.splat.cuda import TILE_SIZE, rasterization_cuda
from ev3dgs.splat.project import project_gaussians
from ev3dgs.splat.rasterize import rasterization
from ev3dgs.splat.reference import rasterize_reference
from ev3dgs.splat.sh import eval_sh

gsplat = pytest.importorskip("gsplat", reason="gsplat is not installed (pip install ev3dgs[cuda])")
ti = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat without its torch reference functions")

F64 = torch.float64
ALPHA_MIN = 1.0 / 255.0
W, H = 48, 40
NEAR, FAR, EPS2D = 0.01, 1e10, 0.3


# --------------------------------------------------------------------------------------------- gsplat in torch
def composite_gsplat(px, py, m, con, col, op, bg, alpha_max=0.999):
    """One pixel block against its ordered Gaussians, by gsplat's CUDA rules (m in gsplat's +0.5 convention,
    px / py the pixel centres j + 0.5, i + 0.5). Returns (P, D) colour and (P,) transmittance. Autograd."""
    dx = m[None, :, 0] - px[:, None]
    dy = m[None, :, 1] - py[:, None]
    sigma = 0.5 * (con[None, :, 0] * dx * dx + con[None, :, 2] * dy * dy) + con[None, :, 1] * dx * dy
    neg = sigma < 0
    alpha = torch.clamp_max(op[None, :] * torch.exp(-torch.where(neg, torch.zeros_like(sigma), sigma)), alpha_max)
    alpha = torch.where(neg | (alpha < ALPHA_MIN), torch.zeros_like(alpha), alpha)
    T_after = torch.cumprod(1.0 - alpha, dim=-1)
    include = T_after > 1e-4  # "next_T <= 1e-4: done, exclusive"; T_after is non-increasing: a prefix
    T_all = torch.cat([torch.ones_like(T_after[:, :1]), T_after], dim=-1)
    wgt = torch.where(include, alpha * T_all[:, :-1], torch.zeros_like(alpha))
    T = T_all.gather(-1, include.sum(-1, keepdim=True))[:, 0]
    C = torch.stack([(wgt * col[None, :, d]).sum(-1) for d in range(col.shape[1])], dim=-1)
    if bg is not None:
        C = C + T[:, None] * bg[None, :]
    return C, T


def cuda_radii(means2d_g, covars2d, depths, opacities, width, height, near, far):
    """ProjectionEWA3DGSFused.cu's radii (C, N, 2) int32; means2d_g in gsplat's convention."""
    c11, c12, c22 = covars2d[..., 0, 0], covars2d[..., 0, 1], covars2d[..., 1, 1]
    det = c11 * c22 - c12 * covars2d[..., 1, 0]
    o = opacities.expand_as(depths)
    extend = torch.clamp_max(torch.sqrt(2.0 * torch.log(torch.clamp_min(o, ALPHA_MIN) / ALPHA_MIN)), 3.33)
    rx = torch.ceil(extend * torch.sqrt(c11.clamp_min(0)))
    ry = torch.ceil(extend * torch.sqrt(c22.clamp_min(0)))
    ok = (depths >= near) & (depths <= far) & (det > 0) & ~(o < ALPHA_MIN) & ((rx > 0) | (ry > 0))
    mx, my = means2d_g[..., 0], means2d_g[..., 1]
    ok &= ~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))
    return torch.where(ok[..., None], torch.stack([rx, ry], -1), torch.zeros_like(torch.stack([rx, ry], -1))).int()


class TorchOps:
    """gsplat's five calls as used by cuda.py, on the CPU. `calls` records (name, bound arguments)."""

    def __init__(self):
        self.calls = []

    def _bind(self, name, *args, **kwargs):
        bound = inspect.signature(getattr(gsplat, name)).bind(*args, **kwargs)
        bound.apply_defaults()
        self.calls.append((name, dict(bound.arguments)))
        return bound.arguments

    def fully_fused_projection(self, *args, **kwargs):
        a = self._bind("fully_fused_projection", *args, **kwargs)
        assert a["covars"] is None and not a["packed"] and not a["calc_compensations"] and a["radius_clip"] == 0
        assert a["camera_model"] == "pinhole" and a["opacities"] is not None
        means, viewmats, Ks = a["means"], a["viewmats"], a["Ks"]
        N, C = means.shape[0], viewmats.shape[0]
        assert a["quats"].shape == (N, 4) and a["scales"].shape == (N, 3) and viewmats.shape == (C, 4, 4)
        assert Ks.shape == (C, 3, 3) and a["opacities"].shape == (N,)
        covars, _ = ti._quat_scale_to_covar_preci(a["quats"], a["scales"], True, False, triu=False)
        _, means2d, depths, conics, _ = ti._fully_fused_projection(
            means, covars, viewmats, Ks, a["width"], a["height"], eps2d=a["eps2d"], near_plane=a["near_plane"],
            far_plane=a["far_plane"])
        means_c, covars_c = ti._world_to_cam(means, covars, viewmats)
        _, cov2d = ti._persp_proj(means_c, covars_c, Ks, a["width"], a["height"])
        cov2d = cov2d + a["eps2d"] * torch.eye(2, dtype=cov2d.dtype)
        radii = cuda_radii(means2d.detach(), cov2d.detach(), depths.detach(), a["opacities"].detach()[None],
                           a["width"], a["height"], a["near_plane"], a["far_plane"])
        vis = (radii > 0).all(-1)
        nan = float("nan")
        unwritten = lambda t: torch.where(vis[..., None] if t.ndim == 3 else vis, t, torch.full_like(t, nan))  # noqa
        return radii, unwritten(means2d), unwritten(depths), unwritten(conics), None

    def spherical_harmonics(self, *args, **kwargs):
        a = self._bind("spherical_harmonics", *args, **kwargs)
        out = ti._spherical_harmonics(a["degrees_to_use"], a["dirs"], a["coeffs"])
        return out if a["masks"] is None else torch.where(a["masks"][..., None], out, torch.zeros_like(out))

    def isect_tiles(self, *args, **kwargs):
        a = self._bind("isect_tiles", *args, **kwargs)
        assert not a["packed"] and not a["segmented"] and a["sort"]
        assert a["means2d"].shape[:-1] == a["radii"].shape[:-1] == a["depths"].shape
        return ti._isect_tiles(a["means2d"].detach(), a["radii"], a["depths"].detach(), a["tile_size"],
                               a["tile_width"], a["tile_height"])

    def isect_offset_encode(self, *args, **kwargs):
        a = self._bind("isect_offset_encode", *args, **kwargs)
        return ti._isect_offset_encode(a["isect_ids"], a["n_images"], a["tile_width"], a["tile_height"])

    def rasterize_to_pixels(self, *args, **kwargs):
        a = self._bind("rasterize_to_pixels", *args, **kwargs)
        assert not a["packed"] and not a["absgrad"] and a["masks"] is None
        m, con, col, op = a["means2d"], a["conics"], a["colors"], a["opacities"]
        I, N = m.shape[0], m.shape[1]
        Wd, Hd, ts = a["image_width"], a["image_height"], a["tile_size"]
        offsets, flat = a["isect_offsets"], a["flatten_ids"]
        assert con.shape == (I, N, 3) and col.shape[:2] == (I, N) and op.shape == (I, N)
        bgs = a["backgrounds"]
        assert bgs is None or bgs.shape == (I, col.shape[-1])
        th, tw = offsets.shape[-2:]
        ends = torch.cat([offsets.flatten()[1:], torch.tensor([flat.numel()])])
        images, alphas = [], []
        for i in range(I):
            rows = []
            for ty in range(th):
                row = []
                for tx in range(tw):
                    k = (i * th + ty) * tw + tx
                    ids = flat[int(offsets.flatten()[k]):int(ends[k])].long() - i * N
                    y0, x0 = ty * ts, tx * ts
                    ys, xs = torch.meshgrid(torch.arange(y0, min(y0 + ts, Hd), dtype=m.dtype),
                                            torch.arange(x0, min(x0 + ts, Wd), dtype=m.dtype), indexing="ij")
                    C, T = composite_gsplat(xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5, m[i, ids], con[i, ids],
                                            col[i, ids], op[i, ids], None if bgs is None else bgs[i])
                    row.append(torch.cat([C, 1.0 - T[:, None]], -1).reshape(*xs.shape, -1))
                rows.append(torch.cat(row, dim=1))
            out = torch.cat(rows, dim=0)
            images.append(out[..., :-1])
            alphas.append(out[..., -1:])
        return torch.stack(images), torch.stack(alphas)


# --------------------------------------------------------------------------------------------------- scenes
def rot(q):
    q = q / q.norm()
    w, x, y, z = q.tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=F64)


def make_scene(seed, n=150, max_opacity=0.99, sh_degree=3, max_scale=0.25):
    """Gaussians in the frustum, plus: behind the camera, between 0 and the near plane, just beyond the near
    plane, far outside the field of view (the Jacobian clamp), and with opacity < 1/255 (culled)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    f = 40.0
    K = torch.tensor([[f, 0, (W - 1) / 2 + 0.3], [0, f * 1.1, (H - 1) / 2 - 0.2], [0, 0, 1]], dtype=F64)
    z = 1.0 + 4.0 * u(n)
    x = (u(n) - 0.5) * 1.4 * W / f * z
    y = (u(n) - 0.5) * 1.4 * H / f * z
    k = n // 15
    z[:k] = -0.5 - u(k)  # behind the camera
    z[k:2 * k] = NEAR * u(k)  # between the camera and the near plane
    z[2 * k:3 * k] = NEAR + 0.2 * u(k)  # just beyond the near plane: huge, partly clamped
    x[3 * k:4 * k] = (3.0 + u(k)) * W / f * z[3 * k:4 * k]  # far right of the image (FOV clamp)
    cam = torch.stack([x, y, z], -1)
    Rv = rot(torch.randn(4, generator=g, dtype=F64))
    tv = torch.randn(3, generator=g, dtype=F64)
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3], viewmat[:3, 3] = Rv, tv
    means = (cam - tv) @ Rv  # world = R^T (cam - t)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.exp(math.log(0.01) + (math.log(max_scale) - math.log(0.01)) * u(n, 3))
    opac = 0.02 + (max_opacity - 0.02) * u(n)
    opac[4 * k:4 * k + 3] = 0.5 / 255  # culled by opacity
    sh = 0.4 * torch.randn(n, 16, 3, generator=g, dtype=F64)
    return SimpleNamespace(means=means, quats=quats, scales=scales, opacities=opac, sh=sh, viewmat=viewmat, K=K,
                           sh_degree=sh_degree, rgb=u(n, 3))


def kg(K):
    Kg = K.clone()
    Kg[0, 2] += 0.5
    Kg[1, 2] += 0.5
    return Kg


def close(a, b, rtol, atol, what):
    err = (a.detach() - b.detach()).abs() - rtol * b.detach().abs()
    assert float(err.max()) <= atol, f"{what}: max excess {float(err.max()):.3g}"


# ------------------------------------------------------------------------------------------- projection / SH
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projection_matches_reference_with_the_half_pixel_shift(seed):
    s = make_scene(seed)
    vm = s.viewmat.clone().requires_grad_(True)
    means = s.means.clone().requires_grad_(True)
    ours = project_gaussians(means, s.quats, s.scales, s.opacities, vm, s.K, W, H, NEAR, FAR, EPS2D)
    vm2 = s.viewmat.clone().requires_grad_(True)
    means2 = s.means.clone().requires_grad_(True)
    covars, _ = ti._quat_scale_to_covar_preci(s.quats, s.scales, True, False, triu=False)
    _, m2d, depths, conics, _ = ti._fully_fused_projection(means2, covars, vm2[None], kg(s.K)[None], W, H,
                                                           eps2d=EPS2D, near_plane=NEAR, far_plane=FAR)
    valid = (ours.depths > NEAR) & (ours.depths < FAR)
    assert int(valid.sum()) >= 100 and int((~valid).sum()) >= 20  # both kinds present
    close(m2d[0][valid] - 0.5, ours.means2d[valid], 1e-12, 1e-10, "means2d (gsplat - 0.5 vs ours)")
    close(conics[0][valid], ours.conics[valid], 1e-9, 1e-12, "conics")
    assert torch.equal(depths[0], ours.depths)  # the same z = (R x + t)_z
    # camera and mean gradients of the same smooth function of the valid rows
    g = torch.Generator().manual_seed(seed + 100)
    wm, wc = torch.randn(int(valid.sum()), 2, generator=g, dtype=F64), torch.randn(int(valid.sum()), 3,
                                                                                  generator=g, dtype=F64)
    loss1 = (wm * ours.means2d[valid]).sum() + (wc * ours.conics[valid]).sum() + ours.depths[valid].sum()
    loss2 = (wm * m2d[0][valid]).sum() + (wc * conics[0][valid]).sum() + depths[0][valid].sum()
    gv1, gm1 = torch.autograd.grad(loss1, (vm, means))
    gv2, gm2 = torch.autograd.grad(loss2, (vm2, means2))
    close(gv2, gv1, 1e-9, 1e-9 * float(gv1.abs().max()), "d/d viewmat")
    close(gm2, gm1, 1e-9, 1e-9 * float(gm1.abs().max()), "d/d means")


def test_without_the_half_pixel_shift_the_means_are_half_a_pixel_off():
    s = make_scene(0)
    ours = project_gaussians(s.means, s.quats, s.scales, s.opacities, s.viewmat, s.K, W, H, NEAR, FAR, EPS2D)
    covars, _ = ti._quat_scale_to_covar_preci(s.quats, s.scales, True, False, triu=False)
    _, m2d, _, _, _ = ti._fully_fused_projection(s.means, covars, s.viewmat[None], s.K[None], W, H)
    valid = (ours.depths > NEAR) & (ours.depths < FAR)
    close(m2d[0][valid], ours.means2d[valid], 1e-12, 1e-10, "means2d, unshifted K")  # same point, other label
    # ...but gsplat samples pixel x at x + 0.5: a Gaussian at our (x, y) must be at gsplat's (x + .5, y + .5)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_match(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(200, 3, generator=g, dtype=F64) * 3
    sh = torch.randn(200, 16, 3, generator=g, dtype=F64)
    theirs = torch.clamp_min(ti._spherical_harmonics(degree, dirs, sh) + 0.5, 0.0)  # cuda.py adds the 0.5
    close(theirs, eval_sh(degree, sh, dirs), 1e-12, 1e-12, f"SH degree {degree}")


# ----------------------------------------------------------------------------------------- radii, tile lists
def _contributors(s, proj):
    """(N,) bool: alpha >= 1/255 at some pixel centre (reference rule, opacity capped as in both), and the
    (tiles_y, tiles_x, N) bool of which 16x16 tile it reaches."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    ok = (proj.depths > NEAR) & (proj.depths < FAR) & ~(s.opacities < ALPHA_MIN)
    d = torch.stack([xs.reshape(-1, 1) - proj.means2d[None, :, 0], ys.reshape(-1, 1) - proj.means2d[None, :, 1]])
    a, b, c = proj.conics.unbind(-1)
    sigma = 0.5 * (a * d[0] ** 2 + c * d[1] ** 2) + b * d[0] * d[1]
    hit = ok[None] & (sigma >= 0) & (s.opacities[None] * torch.exp(-sigma.clamp_min(0)) >= ALPHA_MIN)
    hit = hit.reshape(H, W, -1)
    tiles = torch.zeros(math.ceil(H / TILE_SIZE), math.ceil(W / TILE_SIZE), hit.shape[-1], dtype=torch.bool)
    for ty in range(tiles.shape[0]):
        for tx in range(tiles.shape[1]):
            tiles[ty, tx] = hit[ty * TILE_SIZE:(ty + 1) * TILE_SIZE, tx * TILE_SIZE:(tx + 1) * TILE_SIZE].any(0).any(0)
    return hit.any(0).any(0), tiles


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_radii_rule_and_tile_lists(seed):
    s = make_scene(seed)
    ops = TorchOps()
    proj = project_gaussians(s.means, s.quats, s.scales, s.opacities, s.viewmat, s.K, W, H, NEAR, FAR, EPS2D)
    radii, m2d, depths, _, _ = ops.fully_fused_projection(s.means, None, s.quats, s.scales, s.viewmat[None],
                                                          kg(s.K)[None], W, H, eps2d=EPS2D, near_plane=NEAR,
                                                          far_plane=FAR, packed=False, opacities=s.opacities)
    rg = radii[0].max(-1).values
    vis_g, vis_r = rg > 0, proj.radii > 0
    contrib, tiles = _contributors(s, proj)
    assert int(contrib.sum()) >= 50
    # every Gaussian that colours a pixel is visible in both; gsplat's visible set is inside ours
    assert bool((contrib <= vis_g).all()) and bool((vis_g <= vis_r).all())
    # gsplat's per-axis box is inside our square: r_g <= r; and r - 1 <= 2.04 r_g (module docstring of the
    # radii: lambda_ours <= lambda_max + 0.32 <= 2.07 lambda_max for lambda_max >= eps2d, max axis variance
    # >= lambda_max / 2)
    assert bool((rg[vis_g] <= proj.radii[vis_g]).all())
    assert bool((proj.radii[vis_g] - 1 <= 2.04 * rg[vis_g]).all())
    # tile lists: each tile lists, in ascending depth, every Gaussian that reaches one of its pixels
    tw, th = math.ceil(W / TILE_SIZE), math.ceil(H / TILE_SIZE)
    _, isect_ids, flat = ops.isect_tiles(m2d, radii, depths, TILE_SIZE, tw, th, packed=False, n_images=1)
    offsets = ops.isect_offset_encode(isect_ids, 1, tw, th).reshape(th, tw)
    ends = torch.cat([offsets.flatten()[1:], torch.tensor([flat.numel()])]).reshape(th, tw)
    r = proj.radii
    for ty in range(th):
        for tx in range(tw):
            ids = flat[int(offsets[ty, tx]):int(ends[ty, tx])].long()
            listed = torch.zeros(len(s.means), dtype=torch.bool)
            listed[ids] = True
            assert bool((tiles[ty, tx] <= listed).all()), (ty, tx)
            assert bool((torch.diff(proj.depths[ids]) > 0).all())  # the reference's (stable) depth order
            # a listed Gaussian's box meets the tile's area (pixel edges: [x0 - 0.5, x1 + 0.5] in our
            # convention), not necessarily a pixel centre: gsplat may list a Gaussian that colours none of the
            # tile's pixels (harmless, alpha < 1/255 there); our square contains its box
            x0, y0 = tx * TILE_SIZE, ty * TILE_SIZE
            x1, y1 = min(x0 + TILE_SIZE, W) - 1, min(y0 + TILE_SIZE, H) - 1
            mx, my = proj.means2d[ids, 0], proj.means2d[ids, 1]
            assert bool(((mx + r[ids] >= x0 - 0.5) & (mx - r[ids] <= x1 + 0.5) & (my + r[ids] >= y0 - 0.5)
                         & (my - r[ids] <= y1 + 0.5)).all())


# ------------------------------------------------------------------------------------ the glue, end to end
CASES = [dict(sh_degree=3, background=None, render_mode="RGB"),
         dict(sh_degree=0, background=(0.2, 0.5, 0.9), render_mode="RGB"),
         dict(sh_degree=1, background=(1.0, 1.0, 1.0), render_mode="RGB+D"),
         dict(sh_degree=None, background=(0.3, 0.3, 0.3), render_mode="RGB+D")]


def _render(s, backend, case, ops=None, requires_grad=True):
    leaves = {k: getattr(s, k).clone().requires_grad_(requires_grad)
              for k in ("means", "quats", "scales", "opacities", "viewmat")}
    colors = s.sh if case["sh_degree"] is not None else s.rgb
    leaves["colors"] = colors.clone().requires_grad_(requires_grad)
    bg = None if case["background"] is None else torch.tensor(case["background"], dtype=F64)
    kw = dict(sh_degree=case["sh_degree"], near_plane=NEAR, far_plane=FAR, eps2d=EPS2D, background=bg,
              render_mode=case["render_mode"])
    args = [leaves[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmat")] + [s.K, W, H]
    if backend == "glue":
        img, alpha, meta = rasterization_cuda(*args, ops=ops, **kw)
    else:
        img, alpha, meta = rasterization(*args, backend="reference", **kw)
    return img, alpha, meta, leaves


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"sh{c['sh_degree']}-{c['render_mode']}-bg{c['background']}")
def test_glue_reproduces_reference_images_meta_and_gradients(case):
    s = make_scene(3)
    ops = TorchOps()
    img_g, a_g, meta_g, lv_g = _render(s, "glue", case, ops)
    img_r, a_r, meta_r, lv_r = _render(s, "reference", case)
    assert [c[0] for c in ops.calls] == ["fully_fused_projection"] + (["spherical_harmonics"] if case["sh_degree"]
                                        is not None else []) + ["isect_tiles", "isect_offset_encode",
                                                                "rasterize_to_pixels"]
    assert img_g.shape == img_r.shape == (H, W, 3 + (case["render_mode"] == "RGB+D"))
    assert a_g.shape == a_r.shape == (H, W, 1)
    assert float(a_r.detach().max()) > 0.9 and float((a_r < 0.5).float().mean()) > 0.05  # a scene, not a blank
    close(img_g, img_r, 0, 1e-10, "image")
    close(a_g, a_r, 0, 1e-10, "alpha")
    vis = meta_g["radii"] > 0
    assert meta_g["means2d"].shape == meta_r["means2d"].shape and meta_g["radii"].shape == meta_r["radii"].shape
    close(meta_g["means2d"][vis], meta_r["means2d"][vis], 1e-12, 1e-10, "meta means2d")
    close(meta_g["conics"][vis], meta_r["conics"][vis], 1e-9, 1e-12, "meta conics")
    assert torch.equal(meta_g["depths"][vis], meta_r["depths"][vis])
    # gradients, including the camera's and the screen-space one densification reads
    for meta in (meta_g, meta_r):
        meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(7)
    wimg = torch.rand(img_r.shape, generator=g, dtype=F64)
    ((wimg * img_g).sum() + a_g.sum()).backward()
    ((wimg * img_r).sum() + a_r.sum()).backward()
    assert meta_g["means2d"].grad is not None, "meta['means2d'] is not on the rasterizer's path"
    ref = meta_r["means2d"].grad
    close(meta_g["means2d"].grad[vis], ref[vis], 1e-9, 1e-9 * float(ref.abs().max()), "means2d.grad")
    for k in lv_r:
        gr, gg = lv_r[k].grad, lv_g[k].grad
        close(gg, gr, 1e-8, 1e-8 * float(gr.abs().max()), f"d/d {k}")
    assert float(lv_r["viewmat"].grad.abs().max()) > 0


def test_glue_sends_nothing_unwritten_into_the_image():
    """Culled rows of gsplat's projection outputs are garbage (NaN in TorchOps): with the depth channel, SH
    and backgrounds all in use, image and gradients stay finite."""
    s = make_scene(4)
    case = dict(sh_degree=3, background=(0.1, 0.2, 0.3), render_mode="RGB+D")
    img, alpha, meta, lv = _render(s, "glue", case, TorchOps())
    assert bool(torch.isfinite(img).all()) and bool(torch.isfinite(alpha).all())
    assert int((meta["radii"] == 0).sum()) >= 20
    (img.sum() + alpha.sum()).backward()
    for k, v in lv.items():
        assert bool(torch.isfinite(v.grad).all()), k


def test_glue_means2d_view_of_gsplat_rasterization_would_have_no_grad():
    """Why cuda.py does not call gsplat.rasterization(): its meta['means2d'] is (C, N, 2); a [0] view of it is
    not on the image's path, so retain_grad() on the view leaves .grad None (densification would see no
    gradient on the cuda backend)."""
    x = torch.ones(5, 2, requires_grad=True)
    full = (x * 2)[None]  # what the rasterizer reads
    view = full[0]
    view.retain_grad()
    (full ** 2).sum().backward()
    assert view.grad is None


# ------------------------------------------------------------------------ the glue, C cameras in one call
def small_rotation(axis_angle):
    """exp of the skew matrix of a 3-vector (Rodrigues), float64."""
    theta = float(axis_angle.norm())
    if theta == 0.0:
        return torch.eye(3, dtype=F64)
    k = axis_angle / theta
    Kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=F64)
    return torch.eye(3, dtype=F64) + math.sin(theta) * Kx + (1 - math.cos(theta)) * Kx @ Kx


def moved(viewmat, rot_deg, shift, g):
    """viewmat with the camera turned by up to rot_deg about a random axis and moved by up to `shift`."""
    out = viewmat.clone()
    R = small_rotation(torch.randn(3, generator=g, dtype=F64) * math.radians(rot_deg) / math.sqrt(3))
    out[:3, :3] = R @ viewmat[:3, :3]
    out[:3, 3] = R @ viewmat[:3, 3] + shift * (2 * torch.rand(3, generator=g, dtype=F64) - 1)
    return out


def camera_stack(s, C, seed):
    """C cameras jittered around the scene's (camera 0 is the scene's own): the stack of one step's poses."""
    g = torch.Generator().manual_seed(1000 + seed)
    return torch.stack([s.viewmat] + [moved(s.viewmat, 6.0, 0.15, g) for _ in range(C - 1)])


def mixed_stack(s, seed, subposes=(5, 9, 1), pairs=1):
    """A step over mixed exposures: exposures at different poses with different sub-pose counts (a trajectory
    of small turns each), then event pairs (two poses close together). Returns (viewmats (C,4,4), groups: a list
    of (kind, camera indices))."""
    g = torch.Generator().manual_seed(2000 + seed)
    poses, groups = [], []
    for n in subposes:
        base = moved(s.viewmat, 8.0, 0.2, g)
        step = torch.randn(3, generator=g, dtype=F64) * math.radians(0.4)
        groups.append(("exposure", list(range(len(poses), len(poses) + n))))
        for j in range(n):
            v = base.clone()
            v[:3, :3] = small_rotation(step * j) @ base[:3, :3]
            poses.append(v)
    for _ in range(pairs):
        base = moved(s.viewmat, 8.0, 0.2, g)
        groups.append(("pair", [len(poses), len(poses) + 1]))
        poses += [base, moved(base, 0.5, 0.01, g)]
    return torch.stack(poses), groups


def _leaves(s, case, viewmats):
    lv = {k: getattr(s, k).clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities")}
    lv["colors"] = (s.sh if case["sh_degree"] is not None else s.rgb).clone().requires_grad_(True)
    lv["viewmat"] = viewmats.clone().requires_grad_(True)
    return lv


def _kw(case):
    bg = None if case["background"] is None else torch.tensor(case["background"], dtype=F64)
    return dict(sh_degree=case["sh_degree"], near_plane=NEAR, far_plane=FAR, eps2d=EPS2D, background=bg,
                render_mode=case["render_mode"])


def _args(lv, K, vm):
    return [lv[k] for k in ("means", "quats", "scales", "opacities", "colors")] + [vm, K, W, H]


def step_loss(images, alphas, groups, g):
    """A training step's loss over a stack: per exposure the mean of its sub-pose images (a blur term; one
    sub-pose: a sharp term) against a random target, per event pair a log-difference term, alpha everywhere.
    Every camera enters with its own weight, so a camera whose gradient is lost or misrouted changes the
    result."""
    loss = alphas.sum() * 0.1
    for kind, idx in groups:
        if kind == "exposure":
            blur = images[idx].mean(0)
            loss = loss + ((blur - torch.rand(blur.shape, generator=g, dtype=F64)) ** 2).sum()
        else:
            lum = images[idx, ..., :3].mean(-1)
            d = torch.log(lum[1] + 0.1) - torch.log(lum[0] + 0.1)
            loss = loss + (torch.randn(d.shape, generator=g, dtype=F64) * d).sum()
    return loss


def render_batched_and_per_camera(s, case, viewmats, groups):
    """The batched glue (one call over the stack) and the reference backend one camera at a time (the same
    leaves), the same step loss backpropagated through each. Returns (glue, reference): dicts with images,
    alphas, per-camera metas (means2d with .grad) and the leaves' gradients."""
    C = viewmats.shape[0]
    kw = _kw(case)
    ops = TorchOps()
    lv_g = _leaves(s, case, viewmats)
    img_g, a_g, meta_g = rasterization_cuda(*_args(lv_g, s.K, lv_g["viewmat"]), ops=ops, **kw)
    meta_g["means2d"].retain_grad()
    step_loss(img_g, a_g, groups, torch.Generator().manual_seed(11)).backward()
    lv_r = _leaves(s, case, viewmats)
    outs = [rasterization(*_args(lv_r, s.K, lv_r["viewmat"][c]), backend="reference", **kw) for c in range(C)]
    for o in outs:
        o[2]["means2d"].retain_grad()
    img_r, a_r = torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs])
    step_loss(img_r, a_r, groups, torch.Generator().manual_seed(11)).backward()
    return (dict(images=img_g, alphas=a_g, meta=meta_g, grads={k: v.grad for k, v in lv_g.items()}, ops=ops),
            dict(images=img_r, alphas=a_r, metas=[o[2] for o in outs], grads={k: v.grad for k, v in lv_r.items()}))


def check_batched_parity(s, case, viewmats, groups):
    C = viewmats.shape[0]
    glue, ref = render_batched_and_per_camera(s, case, viewmats, groups)
    names = [c[0] for c in glue["ops"].calls]
    assert names == ["fully_fused_projection"] + (["spherical_harmonics"] if case["sh_degree"] is not None
                                                   else []) + ["isect_tiles", "isect_offset_encode",
                                                               "rasterize_to_pixels"], names  # one call each
    a = dict(glue["ops"].calls[0][1])
    assert a["viewmats"].shape == (C, 4, 4) and a["Ks"].shape == (C, 3, 3)
    assert dict(glue["ops"].calls[-3][1])["n_images"] == C
    D = 3 + (case["render_mode"] == "RGB+D")
    assert glue["images"].shape == ref["images"].shape == (C, H, W, D)
    assert glue["alphas"].shape == (C, H, W, 1)
    meta = glue["meta"]
    N = len(s.means)
    assert meta["means2d"].shape == (C, N, 2) and meta["radii"].shape == meta["depths"].shape == (C, N)
    assert meta["conics"].shape == (C, N, 3) and meta["n_cameras"] == C and (meta["width"], meta["height"]) == (W, H)
    # every camera renders a scene, not a blank (so each one's images and gradients are tested)
    per_cam_alpha = ref["alphas"].detach().amax(dim=(1, 2, 3))
    assert bool((per_cam_alpha > 0.5).all()), per_cam_alpha
    close(glue["images"], ref["images"], 0, 1e-10, "images")
    close(glue["alphas"], ref["alphas"], 0, 1e-10, "alphas")
    for c in range(C):
        mr = ref["metas"][c]
        vis = meta["radii"][c] > 0
        assert bool((vis <= (mr["radii"] > 0)).all())  # gsplat's visible set inside ours (test_radii_rule...)
        close(meta["means2d"][c][vis], mr["means2d"][vis], 1e-12, 1e-10, f"camera {c} means2d")
        close(meta["conics"][c][vis], mr["conics"][vis], 1e-9, 1e-12, f"camera {c} conics")
        # z = (R x + t)_z: three products and three sums, in another order for a batched einsum: |error| <=
        # 4 u (|R||x| + |t|) ~ 1e-14 for these scenes (|x|, |t| < 10)
        close(meta["depths"][c][vis], mr["depths"][vis], 0, 1e-12, f"camera {c} depths")
        gr = mr["means2d"].grad
        scale = float(gr.abs().max())
        assert scale > 0, f"camera {c} has no screen-space gradient in the reference"
        close(meta["means2d"].grad[c][vis], gr[vis], 1e-9, 1e-9 * scale, f"camera {c} means2d.grad")
        # a Gaussian only the reference keeps colours no pixel: its screen-space gradient is zero there
        close(gr[~vis & (mr["radii"] > 0)], torch.zeros_like(gr[~vis & (mr["radii"] > 0)]), 0, 1e-9 * scale,
              f"camera {c} means2d.grad of a Gaussian culled by gsplat")
    for k, gr in ref["grads"].items():
        gg = glue["grads"][k]
        assert gg is not None and gg.shape == gr.shape, k
        close(gg, gr, 1e-8, 1e-8 * float(gr.abs().max()), f"d/d {k}")
    vm_g = ref["grads"]["viewmat"]
    assert bool((vm_g.flatten(1).abs().amax(1) > 0).all())  # every camera's pose gets a gradient
    return glue, ref


def _plain_groups(C):
    return [("exposure", [c]) for c in range(C)]


@pytest.mark.parametrize("C", [1, 5, pytest.param(17, marks=pytest.mark.slow)])  # 17: ~8 s in the emulation
def test_batched_glue_matches_reference_per_camera(C):
    """C cameras in one call through the glue == the reference backend camera by camera: images, alphas, meta,
    each camera's means2d.grad and every leaf's gradient, the view matrices' included (float64: the
    tolerances of test_glue_reproduces_reference_images_meta_and_gradients, the module docstring's analysis;
    the loss sums C cameras' terms, each of the per-camera error, so the relative bound holds per camera)."""
    s = make_scene(3)
    case = dict(sh_degree=3, background=(0.2, 0.5, 0.9), render_mode="RGB")
    check_batched_parity(s, case, camera_stack(s, C, C), _plain_groups(C))


@pytest.mark.parametrize("case", [CASES[2]] + [pytest.param(c, marks=pytest.mark.slow) for c in (CASES[1], CASES[3])],
                         ids=lambda c: f"sh{c['sh_degree']}-{c['render_mode']}-bg{c['background']}")
def test_batched_glue_matches_reference_for_mixed_exposures(case):
    """One step's stack: exposures of 5, 9 and 1 sub-poses at different poses plus an event pair (17
    cameras), a loss that averages each exposure's sub-poses and differences the pair: every case of colour,
    background and depth channel."""
    s = make_scene(4)
    viewmats, groups = mixed_stack(s, 0)
    assert viewmats.shape[0] == 17
    check_batched_parity(s, case, viewmats, groups)


def test_single_camera_call_keeps_its_shapes_and_a_gradient_on_means2d():
    """A (4, 4) viewmat still gives (H, W, D), (H, W, 1) and a (N, 2) means2d on the rasterizer's path."""
    s = make_scene(3)
    case = CASES[0]
    img, alpha, meta, lv = _render(s, "glue", case, TorchOps())
    assert img.shape == (H, W, 3) and alpha.shape == (H, W, 1) and meta["means2d"].shape == (len(s.means), 2)
    assert meta["radii"].shape == meta["depths"].shape == (len(s.means),) and meta["n_cameras"] == 1
    meta["means2d"].retain_grad()
    img.sum().backward()
    assert meta["means2d"].grad is not None and float(meta["means2d"].grad.abs().max()) > 0


def test_densification_statistic_of_a_batched_render_is_the_sum_over_its_cameras():
    """The screen-space statistic densification accumulates (ev3dgs.splat.strategy.DefaultStrategy.accumulate,
    as gsplat 1.5.3's DefaultStrategy._update_state): per camera and visible Gaussian, the norm of that camera's
    means2d gradient scaled by (W/2, H/2), summed over cameras, and the count of cameras that see it. From one
    batched render it must equal the sum over the same cameras rendered one at a time by the glue, with the
    same loss: a camera whose gradient the batched call dropped or mixed with another's fails this (the per
    camera norms of a sum are not the sum of per camera norms)."""
    from ev3dgs.splat.strategy import DefaultStrategy

    s = make_scene(5)
    case = dict(sh_degree=1, background=None, render_mode="RGB")
    viewmats, groups = mixed_stack(s, 1, subposes=(3, 4), pairs=1)
    C, N = viewmats.shape[0], len(s.means)
    kw = _kw(case)
    strat = DefaultStrategy()
    # batched
    lv = _leaves(s, case, viewmats)
    img, alpha, meta = rasterization_cuda(*_args(lv, s.K, lv["viewmat"]), ops=TorchOps(), **kw)
    strat.step_pre_backward(meta)
    step_loss(img, alpha, groups, torch.Generator().manual_seed(3)).backward()
    st_b = strat.initialize_state(N)
    strat.accumulate(st_b, meta)
    # one camera at a time, the same loss over the stacked images
    lv1 = _leaves(s, case, viewmats)
    outs = [rasterization_cuda(*_args(lv1, s.K, lv1["viewmat"][c]), ops=TorchOps(), **kw) for c in range(C)]
    for o in outs:
        strat.step_pre_backward(o[2])
    step_loss(torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs]), groups,
              torch.Generator().manual_seed(3)).backward()
    st_1 = strat.initialize_state(N)
    for o in outs:
        strat.accumulate(st_1, o[2])
    # and written out: the sum over cameras of the scaled per-camera norms
    scale = torch.tensor([W / 2.0, H / 2.0], dtype=F64)
    expect = torch.zeros(N, dtype=F64)
    count = torch.zeros(N, dtype=F64)
    for c, o in enumerate(outs):
        sel = o[2]["radii"] > 0
        expect += torch.where(sel, (o[2]["means2d"].grad * scale).norm(dim=-1), 0.0)
        count += sel
    seen = count >= 2
    assert int(seen.sum()) >= 50 and float(expect.max()) > 0  # Gaussians seen by several cameras
    assert torch.equal(st_b["count"], count.to(st_b["count"])) and torch.equal(st_1["count"], st_b["count"])
    # the strategy's state is float32: the gradient rounded to float32 (u), scaled (u), its norm (2u: two
    # squares, a sum, a square root), C positive terms added (C u): relative (C + 5) u with u = 2**-24, plus the
    # float64 glue-vs-glue difference (far below)
    rel = (C + 5) * 2.0 ** -24
    close(st_b["grad2d"].double(), expect, rel, 1e-30, "batched grad2d vs per-camera sum")
    close(st_1["grad2d"].double(), expect, rel, 1e-30, "per-camera grad2d vs per-camera sum")
    # and each camera's share is there: dropping any one camera's term changes the statistic beyond the bound
    for c, o in enumerate(outs):
        sel = o[2]["radii"] > 0
        share = torch.where(sel, (o[2]["means2d"].grad * scale).norm(dim=-1), 0.0)
        assert float((share - 2 * rel * expect).max()) > 0, f"camera {c} contributes nothing testable"


def test_glue_reads_nothing_back_from_the_device(monkeypatch):
    """No host synchronisation inside the call: the glue's own lines never turn a tensor into a Python value
    (.item(), .tolist(), bool(), int(), float(), .cpu(), .numpy()) and never call torch.linalg.inv, which on CUDA
    synchronises to check for a singular matrix (inv_ex does not). (gsplat's isect_tiles reads its
    intersection count back itself, once per call; the torch emulation's own reads are not the glue's.)"""
    import sys

    import ev3dgs.splat.cuda as cuda_mod

    hits = []

    def guard(name, orig):
        def wrapper(*a, **k):
            f = sys._getframe(1)
            if f.f_code.co_filename == cuda_mod.__file__:
                hits.append((name, f.f_lineno))
            return orig(*a, **k)
        return wrapper

    for name in ("item", "tolist", "__bool__", "__int__", "__float__", "__index__", "cpu", "numpy"):
        monkeypatch.setattr(torch.Tensor, name, guard(name, getattr(torch.Tensor, name)))
    monkeypatch.setattr(torch.linalg, "inv", guard("torch.linalg.inv", torch.linalg.inv))
    s = make_scene(4)
    viewmats, groups = mixed_stack(s, 0, subposes=(3, 2), pairs=1)
    for case in (CASES[0], CASES[2]):  # SH with RGB, SH with RGB+D and a background
        lv = _leaves(s, case, viewmats)
        img, alpha, meta = rasterization_cuda(*_args(lv, s.K, lv["viewmat"]), ops=TorchOps(), **_kw(case))
        step_loss(img, alpha, groups, torch.Generator().manual_seed(0)).backward()
    assert hits == []


def test_rasterization_sends_a_stack_on_cuda_to_the_batched_glue_in_one_call(monkeypatch):
    """rasterize.rasterization(backend="cuda") with viewmat (C, 4, 4) calls cuda.rasterization_cuda once with
    the whole stack (not once per camera)."""
    import ev3dgs.splat.cuda as cuda_mod

    calls = []

    def spy(*args, **kwargs):
        calls.append(tuple(args[5].shape))
        return rasterization_cuda(*args, ops=TorchOps(), **kwargs)

    monkeypatch.setattr(cuda_mod, "rasterization_cuda", spy)
    s = make_scene(3)
    vm = camera_stack(s, 4, 0)
    img, alpha, meta = rasterization(s.means, s.quats, s.scales, s.opacities, s.rgb, vm, s.K, W, H,
                                     background=torch.ones(3, dtype=F64), backend="cuda")
    assert calls == [(4, 4, 4)] and img.shape == (4, H, W, 3) and meta["means2d"].shape == (4, len(s.means), 2)


# ----------------------------------------------------------------------------- the compositor: CUDA rules
def _composite_dense(proj, colors, opac, bg, alpha_max=0.999):
    """The whole image by gsplat's rules, one block, all visible Gaussians in depth order."""
    vis = torch.nonzero(proj.radii > 0).squeeze(-1)
    idx = vis[torch.argsort(proj.depths[vis], stable=True)]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    C, T = composite_gsplat(xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5, proj.means2d[idx] + 0.5, proj.conics[idx],
                            colors[idx], opac[idx], bg, alpha_max)
    return C.reshape(H, W, -1), (1 - T).reshape(H, W, 1)


@pytest.mark.parametrize("seed", [5, 6])
def test_cuda_rules_compositor_matches_reference_rasterizer(seed):
    """Opacities <= 0.99: the 0.999 vs 0.99 cap never binds, so gsplat's rules give our image."""
    s = make_scene(seed, n=400, max_scale=0.8)  # dense: many pixels reach the transmittance stop
    s.opacities[5 * (400 // 15)::2] = 0.99  # the highest opacity at which the caps agree
    proj = project_gaussians(s.means, s.quats, s.scales, s.opacities, s.viewmat, s.K, W, H, NEAR, FAR, EPS2D)
    bg = torch.tensor([0.2, 0.7, 0.4], dtype=F64)
    img_c, a_c = _composite_dense(proj, s.rgb, s.opacities, bg)
    img_r, a_r = rasterize_reference(proj.means2d, proj.conics, s.rgb, s.opacities, proj.depths, proj.radii, W, H,
                                     bg)
    assert float((a_r > 1 - 1e-3).float().mean()) > 0.1  # pixels near or at the transmittance stop
    close(img_c, img_r, 0, 1e-10, "image")
    close(a_c, a_r, 0, 1e-10, "alpha")


def test_alpha_cap_differs_0999_vs_099():
    """A fully opaque Gaussian at a pixel centre: gsplat 0.999, reference 0.99 (a documented difference)."""
    m = torch.tensor([[3.0, 2.0]], dtype=F64)
    con = torch.tensor([[1.0, 0.0, 1.0]], dtype=F64)
    col = torch.ones(1, 3, dtype=F64)
    C, T = composite_gsplat(torch.tensor([3.5]), torch.tensor([2.5]), m + 0.5, con, col, torch.ones(1, dtype=F64),
                            None)
    img, alpha = rasterize_reference(m, con, col, torch.ones(1, dtype=F64), torch.ones(1, dtype=F64),
                                     torch.tensor([4], dtype=torch.int32), 8, 6)
    assert float(C[0, 0]) == pytest.approx(0.999, abs=1e-12) and float(img[2, 3, 0]) == pytest.approx(0.99, abs=1e-12)
    # and the stop: behind a 0.95-alpha layer (T = 0.05), a 0.999 one would leave 5e-5 <= 1e-4: gsplat drops it
    # entirely (exclusive stop), the reference (cap 0.99: T 5e-4) composites it. With the 0.999 cap, an opaque
    # Gaussian is dropped whenever T < 0.1 before it (0.01 with 0.99)
    m2 = torch.tensor([[3.0, 2.0], [3.0, 2.0]], dtype=F64)
    con2 = con.repeat(2, 1)
    op2 = torch.tensor([0.95, 1.0], dtype=F64)
    col2 = torch.tensor([[0.0, 0, 0], [1.0, 1, 1]], dtype=F64)
    C, T = composite_gsplat(torch.tensor([3.5]), torch.tensor([2.5]), m2 + 0.5, con2, col2, op2, None)
    img, alpha = rasterize_reference(m2, con2, col2, op2, torch.tensor([1.0, 2.0], dtype=F64),
                                     torch.tensor([4, 4], dtype=torch.int32), 8, 6)
    assert float(T[0]) == pytest.approx(0.05, rel=1e-12) and float(C[0, 0]) == 0.0
    assert float(img[2, 3, 0]) == pytest.approx(0.05 * 0.99, rel=1e-12)


def test_cuda_rules_with_opacity_up_to_one_differ_only_where_the_cap_binds():
    s = make_scene(8, max_opacity=1.0)
    s.opacities[torch.rand(len(s.opacities), generator=torch.Generator().manual_seed(1), dtype=F64) < 0.3] = 1.0
    proj = project_gaussians(s.means, s.quats, s.scales, s.opacities, s.viewmat, s.K, W, H, NEAR, FAR, EPS2D)
    img_c, _ = _composite_dense(proj, s.rgb, s.opacities, None)
    img_099, _ = _composite_dense(proj, s.rgb, s.opacities, None, alpha_max=0.99)
    img_r, _ = rasterize_reference(proj.means2d, proj.conics, s.rgb, s.opacities, proj.depths, proj.radii, W, H)
    close(img_099, img_r, 0, 1e-10, "image, gsplat rules with our cap")  # the cap is the only difference...
    assert float((img_c - img_r).abs().max()) > 1e-3  # ...and it shows


# ------------------------------------------------------------------------------------------ on a real GPU
def _gpu_or_skip():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")


def _gpu_scene(seed, max_opacity=0.99):
    s = make_scene(seed, max_opacity=max_opacity)
    for k in ("means", "quats", "scales", "opacities", "sh", "viewmat", "K", "rgb"):
        setattr(s, k, getattr(s, k).float().cuda())
    return s


@pytest.mark.gpu
@pytest.mark.parametrize("case", CASES[:3], ids=lambda c: f"sh{c['sh_degree']}-{c['render_mode']}")
def test_gpu_cuda_backend_matches_reference(case):
    """The real kernels (float32, __expf) against the reference on the same CUDA tensors. A threshold decision
    (alpha vs 1/255, T vs 1e-4) that float32 rounding flips changes a pixel by at most 1/255 resp. 1e-2, so
    the bound is on the fraction of pixels that differ by more than 1e-4 (<= 1%) and on the maximum (0.02)."""
    _gpu_or_skip()
    s = _gpu_scene(3)
    bg = None if case["background"] is None else torch.tensor(case["background"], device="cuda")
    colors = s.sh if case["sh_degree"] is not None else s.rgb
    out = {}
    for backend in ("cuda", "reference"):
        leaves = [t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, colors, s.viewmat)]
        img, alpha, meta = rasterization(*leaves, s.K, W, H, sh_degree=case["sh_degree"], background=bg,
                                         render_mode=case["render_mode"], backend=backend)
        meta["means2d"].retain_grad()
        (img.sum() + alpha.sum()).backward()
        out[backend] = (img.detach(), alpha.detach(), meta, [t.grad for t in leaves])
    ic, ir = out["cuda"][0], out["reference"][0]
    diff = (ic - ir).abs()
    assert float(diff.max()) <= 0.02 and float((diff > 1e-4).float().mean()) <= 0.01
    assert out["cuda"][2]["means2d"].grad is not None
    for gc, gr in zip(out["cuda"][3], out["reference"][3]):
        assert float((gc - gr).norm()) <= 0.05 * float(gr.norm()) + 1e-6


@pytest.mark.gpu
def test_gpu_kernels_follow_the_torch_emulation():
    """The real CUDA pipeline against TorchOps (same float32 inputs, opacities up to 1: the 0.999 cap in both)."""
    _gpu_or_skip()
    s = _gpu_scene(9, max_opacity=1.0)
    case = dict(sh_degree=3, near_plane=NEAR, far_plane=FAR, eps2d=EPS2D, background=None, render_mode="RGB")
    args = (s.means, s.quats, s.scales, s.opacities, s.sh, s.viewmat, s.K, W, H)
    img_c, a_c, meta_c = rasterization_cuda(*args, **case)
    cpu = [t.cpu() for t in args[:7]]
    img_t, a_t, meta_t = rasterization_cuda(*cpu, W, H, ops=TorchOps(), **case)
    diff = (img_c.cpu() - img_t).abs()
    assert float(diff.max()) <= 0.02 and float((diff > 1e-4).float().mean()) <= 0.01
    vis = meta_c["radii"].cpu() > 0
    assert torch.equal(vis, meta_t["radii"] > 0) or float((vis != (meta_t["radii"] > 0)).float().mean()) < 0.02
    np.testing.assert_allclose(meta_c["means2d"].cpu()[vis].numpy(), meta_t["means2d"][vis].numpy(), atol=1e-3)


@pytest.mark.gpu
def test_gpu_batched_call_matches_one_call_per_camera():
    """The real kernels: a stack of 17 mixed-exposure cameras in one call against 17 single-camera calls (float32).
    Each (camera, Gaussian) and each pixel is computed by one thread from the same inputs in the same depth
    order, so the images agree unless float32 reordering moves a projected mean by a few ulps (<= 4 * 64 px *
    2**-24 ~ 2e-5 px, changing a pixel by ~2e-5 with gradients <= ~1 per px: below 1e-4) or flips a threshold
    (one Gaussian's alpha ~ 1/255 at a pixel): at most 1 in 1000 pixels beyond 1e-4, none beyond 0.02. The
    backward sums each Gaussian's gradient over pixels with float atomicAdd in a run-dependent order: over up to
    W*H = 1920 terms that is <= 1920 u32 ~ 1.2e-4 of the sum of magnitudes; with a cancellation factor of 10,
    1e-3 of the gradient's norm, per camera for means2d.grad."""
    _gpu_or_skip()
    s = make_scene(4)
    viewmats, groups = mixed_stack(s, 0)
    s = _gpu_scene(4)
    viewmats = viewmats.float().cuda()
    case = dict(sh_degree=3, near_plane=NEAR, far_plane=FAR, eps2d=EPS2D, background=None, render_mode="RGB")
    out = {}
    for mode in ("batched", "single"):
        lv = [t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, s.sh, viewmats)]
        if mode == "batched":
            img, alpha, meta = rasterization_cuda(*lv[:5], lv[5], s.K, W, H, **case)
            meta["means2d"].retain_grad()
            m2d = lambda: meta["means2d"].grad  # noqa: E731
        else:
            outs = [rasterization_cuda(*lv[:5], lv[5][c], s.K, W, H, **case) for c in range(len(viewmats))]
            for o in outs:
                o[2]["means2d"].retain_grad()
            img, alpha = torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs])
            m2d = lambda: torch.stack([o[2]["means2d"].grad for o in outs])  # noqa: E731
        w = torch.rand(img.shape, generator=torch.Generator().manual_seed(0)).to(img.device)
        ((w * img).sum() + alpha.sum()).backward()
        out[mode] = (img.detach(), alpha.detach(), m2d(), [t.grad for t in lv])
    b, o = out["batched"], out["single"]
    for x, y in ((b[0], o[0]), (b[1], o[1])):
        d = (x - y).abs()
        assert float(d.max()) <= 0.02 and float((d > 1e-4).float().mean()) <= 1e-3
    for c in range(len(viewmats)):
        assert float((b[2][c] - o[2][c]).norm()) <= 1e-3 * float(o[2][c].norm()) + 1e-12, c
    for gb, gs in zip(b[3], o[3]):
        assert float((gb - gs).norm()) <= 1e-3 * float(gs.norm()) + 1e-12
