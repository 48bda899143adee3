"""The cpu backend's batched path (C cameras in one call) and its numba projection + SH backward, against
the torch oracle (reference backend, one camera at a time) in float64: values and every gradient to 1e-10."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.splat.project import project_gaussians
from ev3dgs.splat.project_cpu import project_sh_cpu
from ev3dgs.splat.rasterize import rasterization
from ev3dgs.splat.sh import eval_sh

from test_splat_backends import scene

F64 = torch.float64


def cameras(c, seed=0, dtype=F64):
    """c world->camera matrices: identity plus small rotations and shifts (a shaky exposure)."""
    g = torch.Generator().manual_seed(seed)
    out = [torch.eye(4, dtype=dtype)]
    for _ in range(c - 1):
        a = 0.05 * torch.randn(3, generator=g, dtype=F64)
        A = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=F64)
        vm = torch.eye(4, dtype=F64)
        vm[:3, :3] = torch.linalg.matrix_exp(A)
        vm[:3, 3] = 0.1 * torch.randn(3, generator=g, dtype=F64)
        out.append(vm.to(dtype))
    return torch.stack(out)


def render_batch(backend, params, sh, vms, K, W, H, deg, render_mode="RGB"):
    leaves = [p.clone().requires_grad_(True) for p in params[:4]] + [sh.clone().requires_grad_(True)]
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=params[0].dtype)
    image, alpha, meta = rasterization(*leaves, vms, K, W, H, sh_degree=deg, backend=backend, background=bg,
                                       render_mode=render_mode)
    meta["means2d"].retain_grad()
    # per camera the same weights: a camera's gradients do not depend on the batch it is rendered in
    w = torch.linspace(-1, 1, image[0].numel() if image.ndim == 4 else image.numel(), dtype=image.dtype)
    w = w.reshape(image.shape[-3:])
    loss = (image * w).sum() + (alpha ** 2).sum() + 1e-3 * image.sum()
    loss.backward()
    return image.detach(), alpha.detach(), [leaf.grad for leaf in leaves], meta


def assert_close(x, y, atol=1e-10, what=""):
    x = torch.zeros_like(y) if x is None else x
    y = torch.zeros_like(x) if y is None else y
    assert torch.isfinite(x).all() and torch.isfinite(y).all(), what
    assert x.shape == y.shape, (what, x.shape, y.shape)
    if x.numel() == 0:                 # e.g. no Gaussian in front of any camera: nothing to compare
        return
    scale = max(float(x.abs().max()) if x.numel() else 0.0, 1.0)
    assert float((x - y).abs().max()) <= atol * scale, (what, float((x - y).abs().max()))


@pytest.mark.parametrize("deg", [0, 1, 3])
@pytest.mark.parametrize("hard", [False, True])
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+D"])
def test_batched_cpu_matches_reference_per_camera(deg, hard, render_mode):
    params, _, K = scene(80, 40, seed=deg, hard=hard)
    sh = 0.3 * torch.randn(80, 16, 3, generator=torch.Generator().manual_seed(deg), dtype=F64)
    vms = cameras(4, seed=deg)
    ref = render_batch("reference", params, sh, vms, K, 40, 30, deg, render_mode)
    cpu = render_batch("cpu", params, sh, vms, K, 40, 30, deg, render_mode)
    assert ref[0].shape == cpu[0].shape == (4, 30, 40, 4 if render_mode == "RGB+D" else 3)
    assert_close(ref[0], cpu[0], what="image")
    assert_close(ref[1], cpu[1], what="alpha")
    for name, a, b in zip(("means", "quats", "scales", "opacities", "sh"), ref[2], cpu[2]):
        assert_close(a, b, what=name)
    assert torch.equal(ref[3]["radii"], cpu[3]["radii"])
    # the per-camera screen-space gradients the densification statistics read: each camera's own
    for c in range(4):
        one = render_batch("reference", params, sh, vms[c], K, 40, 30, deg, render_mode)
        solo = render_batch("cpu", params, sh, vms[c], K, 40, 30, deg, render_mode)
        assert_close(one[3]["means2d"].grad, solo[3]["means2d"].grad, what="means2d")


def test_batched_equals_single_calls_bitwise():
    """A batch of C cameras gives each camera exactly (bitwise) its own single-camera image and means2d
    gradient, so training with the batched path keeps the per-camera densification statistics."""
    params, _, K = scene(500, 64, seed=3, dtype=torch.float32)
    sh = 0.3 * torch.randn(500, 16, 3, generator=torch.Generator().manual_seed(1))
    vms = cameras(5, seed=2, dtype=torch.float32)
    full = render_batch("cpu", params, sh, vms, K, 64, 48, 2)
    for c in range(5):
        one = render_batch("cpu", params, sh, vms[c], K, 64, 48, 2)
        assert torch.equal(one[0], full[0][c]) and torch.equal(one[1], full[1][c])
        assert torch.equal(one[3]["means2d"].grad, full[3]["means2d"].grad[c])
        assert torch.equal(one[3]["radii"], full[3]["radii"][c])


def test_batched_thread_count_does_not_change_the_result():
    params, _, K = scene(1500, 96, seed=5, dtype=torch.float32)
    sh = 0.3 * torch.randn(1500, 16, 3, generator=torch.Generator().manual_seed(2))
    vms = cameras(3, seed=1, dtype=torch.float32)
    a = render_batch("cpu", params, sh, vms, K, 96, 72, 3)
    import numba

    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    b = render_batch("cpu", params, sh, vms, K, 96, 72, 3)
    numba.set_num_threads(1)
    c = render_batch("cpu", params, sh, vms, K, 96, 72, 3)
    for x, y in ((a, b), (a, c)):
        assert torch.equal(x[0], y[0]) and all(torch.equal(p, q) for p, q in zip(x[2], y[2]))


def _oracle_projection(means, quats, scales, opac, sh, vms, K, W, H, deg):
    outs = []
    for vm in vms:
        p = project_gaussians(means, quats, scales, opac, vm, K, W, H)
        col = eval_sh(deg, sh, means - torch.linalg.inv(vm)[:3, 3])
        outs.append((p.means2d, p.conics, p.depths, col, p.radii))
    return [torch.stack(t) for t in zip(*outs)]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 40), deg=st.integers(0, 3), c=st.integers(1, 4),
       log_scale=st.floats(-6, 1), zc=st.floats(0.5, 20), quat_scale=st.sampled_from([1e-13, 1e-3, 1.0, 1e3]))
def test_property_projection_and_sh_backward_match_autograd(seed, n, deg, c, log_scale, zc, quat_scale):
    rng = np.random.default_rng(seed)
    W, H = 48, 36
    f = 1.1 * W
    t = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    means = t(np.c_[rng.uniform(-1, 1, (n, 2)) * zc * 0.5, zc + rng.uniform(-0.4, 0.4, n) * zc])
    quats = t(rng.normal(size=(n, 4)) * quat_scale)
    scales = t(np.exp(log_scale + rng.uniform(-1, 1, (n, 3))))
    opac = t(rng.uniform(0.001, 1.0, n))
    sh = t(rng.normal(size=(n, 16, 3)) * 0.4)
    K = t([[f, 0, (W - 1) / 2 + 0.2], [0, f, (H - 1) / 2 - 0.3], [0, 0, 1]])
    vms = cameras(c, seed=seed)
    weights = [t(rng.normal(size=s)) for s in ((c, n, 2), (c, n, 3), (c, n), (c, n, 3))]

    def run(fn):
        leaves = [x.clone().requires_grad_(True) for x in (means, quats, scales, sh)]
        m2d, con, dep, col, radii = fn(leaves)
        ok = radii > 0  # the rasterizer never reads culled rows
        loss = sum((torch.where(ok[..., None] if o.ndim == 3 else ok, o, 0) * w).sum()
                   for o, w in zip((m2d, con, dep, col), weights))
        loss.backward()
        return (m2d, con, dep, col, radii), [x.grad for x in leaves]

    ref, gref = run(lambda L: _oracle_projection(L[0], L[1], L[2], opac, L[3], vms, K, W, H, deg))
    new, gnew = run(lambda L: project_sh_cpu(L[0], L[1], L[2], opac, L[3], vms, K, W, H, sh_degree=deg))
    assert torch.equal(ref[4], new[4])
    ok = ref[4] > 0
    for a, b in zip(ref[:4], new[:4]):
        assert_close(a[ok].detach(), b[ok].detach())
    for a, b in zip(gref, gnew):
        assert_close(a, b)


def test_projection_gradients_only_where_the_oracle_has_them():
    """Non-finite rows are culled with zero gradient; viewmat gradients fall back to the torch path."""
    params, vm, K = scene(30, 32, seed=0)
    means = params[0].clone()
    means[3, 1] = float("nan")
    params = [means] + params[1:]
    sh = 0.3 * torch.randn(30, 4, 3, dtype=F64)
    _, _, grads, meta = render_batch("cpu", params, sh, vm[None].repeat(2, 1, 1), K, 32, 24, 1)
    assert (meta["radii"][:, 3] == 0).all()
    assert all(torch.isfinite(g).all() and (g[3] == 0).all() for g in grads)
    clean, _, _ = scene(30, 32, seed=0)
    vm_leaf = vm.clone().requires_grad_(True)
    image, _, _ = rasterization(*clean[:4], sh, vm_leaf, K, 32, 24, sh_degree=1, backend="cpu")
    image.sum().backward()
    assert vm_leaf.grad is not None and torch.isfinite(vm_leaf.grad).all()
