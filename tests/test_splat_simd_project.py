"""The `cpu` backend's projection + SH kernels in C (_raster.c's ev3dgs_project_forward / _backward, through
cpu_simd), used for float32 inputs: the numba kernels' float64 operations in the same order, 4 Gaussians per
vector (each lane the scalar operations, branches as selects), so every output and gradient is bitwise
theirs (rounded to float32 at the same place), for any thread count and in both builds; the numba kernels
stay for float64, EV3DGS_CPU_KERNEL=numba and a build without the extension.

Against the torch path (project_gaussians + eval_sh in float64 on the same float32 values, autograd): both
compute in float64 and only the C result is rounded to float32, so they differ by at most half an ulp of
float32 (2^-24 relative) plus the two float64 evaluation orders' difference. The latter is a few hundred
float64 roundings (u = 2^-53) of terms no larger than the largest of each output (the scenes here keep the
2D covariances well conditioned: eps2d = 0.3 on footprints of a few pixels), far below 2^-40 of that
largest value. So |C - torch| <= 2^-24 |torch| + 2^-40 max |torch| per output array, with a factor 2 of
margin: tol = 2^-23 |torch| + 2^-39 max |torch|. A gradient off by one part in 10^5 fails it (planted below).
"""
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import ev3dgs.splat.cpu as cpu
import ev3dgs.splat.cpu_simd as cpu_simd
from ev3dgs.splat.project import project_gaussians
from ev3dgs.splat.project_cpu import project_sh_cpu
from ev3dgs.splat.sh import eval_sh

from test_splat_batched import cameras


@pytest.fixture(autouse=True)
def c_projection(monkeypatch):
    """The product leaves the C projection off (project_cpu.C_PROJECTION: see there); these tests are its
    kernels' own, so they switch it on."""
    import ev3dgs.splat.project_cpu as project_cpu

    monkeypatch.setattr(project_cpu, "C_PROJECTION", True)

needs_c = pytest.mark.skipif(not cpu_simd.available(), reason="the C rasterizer extension is not built")
W, H = 64, 48


def scene(seed, n, C, hard=False):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.2 + 1e-3
    opac = torch.rand(n, generator=g)
    sh = torch.randn(n, 16, 3, generator=g) * 0.3
    if hard and n >= 6:  # behind the camera, beyond the image, non-finite rows, a zero quaternion, tiny opacity
        means[0, 2] = -1.0
        means[1, 0] = 40.0
        means[2, 1] = float("nan")
        scales[3, 0] = float("inf")
        quats[4] = 0.0
        opac[5] = 1e-3
    vms = cameras(C, seed=seed).float()
    K = torch.tensor([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
    return means, quats, scales, opac, sh, vms, K


def run(kind, tensors, deg, threads=1, dtype=torch.float32):
    """Outputs (means2d, conics, depths, colours, radii) and the gradients of a fixed random weighting of them
    (means, quats, scales, sh, viewmats)."""
    means, quats, scales, opac, sh, vms, K = (t.to(dtype) for t in tensors)
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, sh, vms)]
    old = cpu_simd.KERNEL
    cpu_simd.KERNEL = kind
    try:
        cpu.set_numba_threads(threads)
        m2d, con, dep, col, rad = project_sh_cpu(leaves[0], leaves[1], leaves[2], opac.to(dtype),
                                                 leaves[3] if deg is not None else None, leaves[4], K, W, H,
                                                 sh_degree=deg)
        g = torch.Generator().manual_seed(99)
        outs = [m2d, con, dep] + ([col] if col is not None else [])
        loss = sum((o * torch.randn(o.shape, generator=g, dtype=torch.float64).to(dtype)).sum() for o in outs)
        loss.backward()
    finally:
        cpu_simd.KERNEL = old
        cpu.set_numba_threads(1)
    grads = [torch.zeros_like(t) if t.grad is None else t.grad for t in leaves]
    return [o.detach() for o in outs] + [rad], grads


def bitwise(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)


@needs_c
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31), n=st.integers(1, 700), C=st.integers(1, 4),
       deg=st.sampled_from([None, 0, 1, 2, 3]), hard=st.booleans())
def test_c_projection_is_the_numba_projection_bitwise(seed, n, C, deg, hard):
    x = scene(seed, n, C, hard)
    got, got_g = run("simd", x, deg)
    want, want_g = run("numba", x, deg)
    assert all(bitwise(a, b) for a, b in zip(got, want))
    assert all(bitwise(a, b) for a, b in zip(got_g, want_g))
    assert all(torch.isfinite(g).all() for g in got_g)


@needs_c
@pytest.mark.parametrize("deg", [None, 3])
def test_c_projection_bitwise_the_same_for_1_2_3_threads(deg):
    x = scene(5, 1300, 3, hard=True)  # several blocks of VM_BLOCK Gaussians
    runs = [run("simd", x, deg, threads=t) for t in (1, 2, 3)]
    for outs, grads in runs[1:]:
        assert all(bitwise(a, b) for a, b in zip(runs[0][0], outs))
        assert all(bitwise(a, b) for a, b in zip(runs[0][1], grads))


def torch_path(tensors, deg):
    """The torch projection and SH colours per camera in float64 on the same float32 values (autograd), and
    the gradients of the same weighting as ``run``."""
    means, quats, scales, opac, sh, vms, K = (t.double() for t in tensors)
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, sh, vms)]
    outs = [[], [], [], []]
    for v in leaves[4]:
        p = project_gaussians(leaves[0], leaves[1], leaves[2], opac, v, K, W, H)
        outs[0].append(p.means2d)
        outs[1].append(p.conics)
        outs[2].append(p.depths)
        if deg is not None:
            outs[3].append(eval_sh(deg, leaves[3], leaves[0] - torch.linalg.inv(v)[:3, 3]))
    outs = [torch.stack(o) for o in outs if o]
    g = torch.Generator().manual_seed(99)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=torch.float64).float().double()).sum() for o in outs)
    loss.backward()
    return [o.detach() for o in outs], [torch.zeros_like(t) if t.grad is None else t.grad for t in leaves]


def close(got, want):
    tol = 2.0 ** -23 * want.abs() + 2.0 ** -39 * float(want.abs().max())
    return bool(((got.double() - want).abs() <= tol).all())


@needs_c
@pytest.mark.parametrize("deg", [None, 0, 3])
@pytest.mark.parametrize("C", [1, 3])
def test_c_projection_against_the_torch_path(deg, C):
    x = scene(11 + C, 400, C)
    got, got_g = run("simd", x, deg)
    want, want_g = torch_path(x, deg)
    for a, b in zip(got[:len(want)], want):
        assert close(a, b)
    for a, b in zip(got_g[:3], want_g[:3]):  # means, quats, scales
        assert close(a, b)
    if deg is not None:
        assert close(got_g[3][:, :(deg + 1) ** 2], want_g[3][:, :(deg + 1) ** 2])
        assert (got_g[3][:, (deg + 1) ** 2:] == 0).all()
    # planted errors: one gradient element off by 1e-5 of itself, one output off by 1e-6 of itself
    i = int(got_g[0].abs().argmax())
    bad = got_g[0].clone().reshape(-1)
    bad[i] *= 1 + 1e-5
    assert not close(bad.reshape(got_g[0].shape), want_g[0])
    bad = got[0].clone().reshape(-1)
    bad[7] *= 1 + 1e-6
    assert not close(bad.reshape(got[0].shape), want[0])
    assert math.isfinite(float(got_g[1].abs().sum()))


@needs_c
def test_float64_and_the_numba_choice_stay_on_numba(monkeypatch):
    called = []
    for name in ("project_forward", "project_backward"):
        real = getattr(cpu_simd, name)
        monkeypatch.setattr(cpu_simd, name, lambda *a, real=real, name=name: called.append(name) or real(*a))
    x = scene(3, 50, 2)
    run("simd", x, 3, dtype=torch.float64)
    run("numba", x, 3)
    assert called == []
    run("simd", x, 3)
    assert called == ["project_forward", "project_backward"]


def test_fallback_to_numba_without_the_extension(monkeypatch):
    """No C compiler at install: the numba projection runs, bitwise its forced results."""
    x = scene(8, 200, 2, hard=True)
    forced = run("numba", x, 3)
    monkeypatch.setattr(cpu_simd, "_ext", None)
    monkeypatch.setattr(cpu_simd, "_lib", None)
    assert not cpu_simd.project_active(np.zeros(1, np.float32))
    absent = run("simd", x, 3)
    assert all(bitwise(a, b) for a, b in zip(forced[0] + forced[1], absent[0] + absent[1]))


@needs_c
@pytest.mark.skipif(not cpu_simd.available() or cpu_simd.isa() != "avx2", reason="needs a CPU with AVX2")
@pytest.mark.parametrize("deg", [None, 3])
def test_portable_and_avx2_projection_bitwise_the_same(deg, monkeypatch):
    """The 4-lane kernels in both builds (and the scalar code on the tails: 1003 Gaussians, 3 left over)."""
    x = scene(9, 1003, 2, hard=True)
    avx2 = run("simd", x, deg)
    monkeypatch.setattr(cpu_simd, "ISA", 0)
    portable = run("simd", x, deg)
    assert all(bitwise(a, b) for a, b in zip(avx2[0] + avx2[1], portable[0] + portable[1]))
