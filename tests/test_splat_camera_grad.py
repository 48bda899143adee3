"""Camera (view-matrix) gradients of every CPU backend: the numba projection's hand-written backward
against torch autograd through the `reference` path, and against central finite differences.

Tolerances (float64, u = 1.1e-16): the two implementations evaluate the same sums in different orders, so
values differ by a few ulp times the condition of each step; the gradients pass through 1/z^2, 1/det and
the compositing's division by T (bounded by 1/T_min = 1e4), so 1e-10 relative to the largest entry leaves
several orders of magnitude of margin over the ~1e-13 seen, while a wrong term (the smallest of which is a
few percent of the total) would show at 1e-3."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.geometry import look_at, rotvec_to_matrix
from ev3dgs.splat.project import project_gaussians
from ev3dgs.splat.project_cpu import project_sh_cpu
from ev3dgs.splat.rasterize import rasterization
from ev3dgs.splat.sh import eval_sh

F64 = torch.float64


def gaussians(n, seed, deg=3):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * 1.6
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = 0.03 + 0.15 * torch.rand(n, 3, generator=g, dtype=F64)
    opac = 0.1 + 0.85 * torch.rand(n, generator=g, dtype=F64)
    sh = 0.4 * torch.randn(n, (deg + 1) ** 2, 3, generator=g, dtype=F64)
    return means, quats, scales, opac, sh


def cameras(c, seed):
    """c world->camera matrices on a circle around the origin, each slightly rotated off its look-at."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(c):
        az = 2 * np.pi * k / max(c, 1) + rng.uniform(0, 0.3)
        c2w = look_at(3.0 * np.array([np.cos(az), np.sin(az), 0.4]), [0, 0, 0])
        c2w[:3, :3] = rotvec_to_matrix(rng.normal(0, 0.05, 3)) @ c2w[:3, :3]
        out.append(np.linalg.inv(c2w))
    return torch.tensor(np.stack(out), dtype=F64)


def K_of(width, height):
    f = 1.2 * width
    return torch.tensor([[f, 0, (width - 1) / 2 + 0.3], [0, f, (height - 1) / 2 - 0.2], [0, 0, 1.0]], dtype=F64)


def torch_projection(means, quats, scales, opac, sh, vms, K, W, H, deg):
    """The reference path's projection + SH, one camera at a time (rasterize.py's torch branch)."""
    outs = []
    for vm in vms:
        p = project_gaussians(means, quats, scales, opac, vm, K, W, H)
        campos = torch.linalg.inv(vm)[:3, 3]
        outs.append((p.means2d, p.conics, p.depths, eval_sh(deg, sh, means - campos), p.radii))
    return [torch.stack([o[i] for o in outs]) for i in range(5)]


def upstream(shapes, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(s, generator=g, dtype=F64) for s in shapes]


@pytest.mark.parametrize("deg", [0, 1, 3])
@pytest.mark.parametrize("seed", range(3))
def test_projection_viewmat_gradient_matches_torch(deg, seed):
    W, H = 48, 36
    means, quats, scales, opac, sh = gaussians(200, seed, deg)
    vms, K = cameras(3, seed), K_of(W, H)
    res = {}
    for name in ("torch", "cpu"):
        vm = vms.clone().requires_grad_(True)
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, sh)]
        if name == "torch":
            m2d, con, dep, col, rad = torch_projection(leaves[0], leaves[1], leaves[2], opac, leaves[3], vm, K,
                                                       W, H, deg)
        else:
            m2d, con, dep, col, rad = project_sh_cpu(leaves[0], leaves[1], leaves[2], opac, leaves[3], vm, K,
                                                     W, H, sh_degree=deg)
        gs = upstream([m2d.shape, con.shape, dep.shape, col.shape], seed + 10)
        ((m2d * gs[0]).sum() + (con * gs[1]).sum() + (dep * gs[2]).sum() + (col * gs[3]).sum()).backward()
        res[name] = ([m2d, con, dep, col], [vm.grad] + [x.grad for x in leaves], rad)
    assert torch.equal(res["torch"][2], res["cpu"][2])
    for a, b in zip(res["torch"][0], res["cpu"][0]):
        a, b = a.detach(), b.detach()
        assert float((a - b).abs().max()) <= 1e-10 * max(1.0, float(a.abs().max()))
    for a, b in zip(res["torch"][1], res["cpu"][1]):
        assert float((a - b).abs().max()) <= 1e-10 * max(1.0, float(a.abs().max())), (a - b).abs().max()
    if deg > 0:  # the SH directions make the bottom row matter (inv()'s gradient); degree 0 has none
        assert float(res["cpu"][1][0][:, 3, :3].abs().max()) > 0


def test_projection_viewmat_gradient_finite_differences():
    """torch.autograd.gradcheck: central differences (eps 1e-6) of every output entry against the
    hand-written backward, all 16 entries of two view matrices (inv() makes the bottom row matter)."""
    W, H = 40, 30
    means, quats, scales, opac, sh = gaussians(25, 4, 2)
    K = K_of(W, H)

    def f(vm):
        m2d, con, dep, col, _ = project_sh_cpu(means, quats, scales, opac, sh, vm, K, W, H, sh_degree=2)
        return m2d, con, dep, col

    vm = cameras(2, 4).requires_grad_(True)
    # gradcheck compares with atol + rtol * |numerical|; central differences have error O(eps^2 f''') +
    # O(u f / eps) ~ 1e-10 relative for these smooth (no clamp is active at this scene) outputs
    assert torch.autograd.gradcheck(f, (vm,), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("batched", [False, True])
def test_render_camera_gradient_cpu_matches_reference(seed, batched):
    W, H = 40, 30
    means, quats, scales, opac, sh = gaussians(150, seed, 3)
    vms, K = cameras(3 if batched else 1, seed), K_of(W, H)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=F64)
    res = {}
    for backend in ("reference", "cpu"):
        vm = (vms if batched else vms[0]).clone().requires_grad_(True)
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, sh)]
        image, alpha, _ = rasterization(*leaves, vm, K, W, H, sh_degree=3, background=bg, backend=backend)
        w = torch.linspace(-1, 1, image.numel(), dtype=F64).reshape(image.shape)
        ((image * w).sum() + (alpha ** 2).sum()).backward()
        res[backend] = (image.detach(), [vm.grad] + [x.grad for x in leaves])
    assert float((res["reference"][0] - res["cpu"][0]).abs().max()) <= 1e-10
    for a, b in zip(res["reference"][1], res["cpu"][1]):
        assert torch.isfinite(b).all()
        assert float((a - b).abs().max()) <= 1e-10 * max(1.0, float(a.abs().max()))
    assert float(res["cpu"][1][0].abs().max()) > 0


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 4), st.integers(1, 60))
def test_batched_camera_gradient_is_the_sum_of_single_ones(seed, c, n):
    """A batch's viewmat gradient per camera equals that camera's own single-camera gradient (bitwise
    would need the same summation order; the block sums make it so up to the final per-block adds)."""
    W, H = 24, 20
    means, quats, scales, opac, sh = gaussians(n, seed, 1)
    vms, K = cameras(c, seed), K_of(W, H)
    gs = upstream([(c, n, 2), (c, n, 3), (c, n), (c, n, 3)], seed)

    def grad(vm_in, sl):
        vm = vm_in.clone().requires_grad_(True)
        out = project_sh_cpu(means, quats, scales, opac, sh, vm, K, W, H, sh_degree=1)[:4]
        sum((o * g[sl]).sum() for o, g in zip(out, gs)).backward()
        return vm.grad

    full = grad(vms, slice(None))
    for k in range(c):
        one = grad(vms[k:k + 1], slice(k, k + 1))
        assert torch.allclose(full[k:k + 1], one, rtol=0, atol=1e-12 * max(1.0, float(one.abs().max())))


def test_camera_gradient_independent_of_thread_count():
    import numba

    means, quats, scales, opac, sh = [t.float() for t in gaussians(3000, 2, 3)]
    vms, K = cameras(4, 2).float(), K_of(64, 48).float()
    grads = []
    for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
        vm = vms.clone().requires_grad_(True)
        image, alpha, _ = rasterization(means, quats, scales, opac, sh, vm, K, 64, 48, sh_degree=3,
                                        backend="cpu", threads=threads)
        image.sum().backward()
        grads.append(vm.grad)
    assert torch.equal(grads[0], grads[1])


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.floats(0.0, 10.0))
def test_inv4_is_the_inverse(seed, t_scale):
    """project_cpu.inv4 (torch's LAPACK, so numpy's OpenBLAS pool is never woken per render) against the
    definition: V^-1 V = I. For rigid view matrices with |t| <= 10*sqrt(3) the condition number is below
    ~400, and LU with partial pivoting has a residual of a few n u kappa ~ 1e-13: 1e-11 leaves 100x room;
    and equal to numpy's inverse (a second LAPACK) to the same bound."""
    from ev3dgs.splat.project_cpu import inv4

    rng = np.random.default_rng(seed)
    vm = np.zeros((3, 4, 4))
    for c in range(3):
        q, r = np.linalg.qr(rng.standard_normal((3, 3)))
        vm[c, :3, :3] = q * np.sign(np.diag(r))
        vm[c, :3, 3] = rng.uniform(-1, 1, 3) * t_scale
        vm[c, 3, 3] = 1.0
    inv = inv4(vm)
    assert inv.dtype == np.float64 and inv.shape == (3, 4, 4)
    assert np.abs(inv @ vm - np.eye(4)).max() < 1e-11
    assert np.abs(inv - np.linalg.inv(vm)).max() < 1e-11
