"""The `cpu` backend's SIMD C kernels (ev3dgs/splat/_raster.c via cpu_simd) against `reference` and against
the numba kernels, their exp(-sigma) against float64 exp, determinism across thread counts and builds, and
the numba fallback when the extension is absent.

Tolerances (u = 2^-24, float32's unit roundoff), first-order error propagation:

* alpha. The C kernel's sigma, alpha, T and compositing are the numba kernel's float32 operations in the same
  order (the backward's (colour behind) . G aside: below); exp(-sigma) differs: ours within
  EXP_REL_ERROR = 4u (cpu_simd's derivation, checked below), libm's expf within 1 ulp <= 2u, so the two
  alphas differ by delta <= 6u relative. Against `reference` (float64 on the same float32 inputs) the
  kernel's sigma also carries rounding: dx, dy, 3 products and 2 sums, <= 8u relative to
  0.5 (|a| dx^2 + |c| dy^2) + |b dx dy| <= kappa sigma, kappa = (1 + rho) / (1 - rho), rho = |b| / sqrt(ac);
  so |d sigma| <= 8u kappa smax and delta <= (8 kappa smax + 4 + 1 + 1) u.
* transmittance. A pixel's T = prod (1 - alpha_i); a relative change delta of every alpha moves it by
  sum_i alpha_i / (1 - alpha_i) delta. With alpha <= amax: alpha / (1 - alpha) <= g(amax) (-ln(1 - alpha)),
  g(a) = a / ((1 - a)(-ln(1 - a))) increasing, and sum_i -ln(1 - alpha_i) = -ln T >= ... <= ln(1e4) (T stays
  above T_MIN), so GROWTH = g(amax) ln(1e4) bounds it (198 at amax = 0.99). Every compositing weight
  alpha_i T_i then moves by <= (GROWTH + 1) delta relative, and the weights sum to <= 1: the image by
  <= (GROWTH + 1) delta max(|colour|, |background|), plus the kernel's own roundings against float64
  (2 per fragment in T and C: 3 L u, L fragments per pixel <= the Gaussians).
* gradients. Each fragment's term (abs_terms: evaluated on absolute values, from the reference rules in
  float64, so that a cancelling sum inside it does not hide its operands' errors) is a
  product of alphas, transmittances, colours behind and upstream gradients; the backward's division by 1 -
  alpha (<= 1 / (1 - amax)) multiplies the transmittance error, so a term moves by <= (GROWTH + 1)(1 + 1 /
  (1 - amax)) delta relative. A Gaussian's n fragments are summed in float32 (per tile and then over its tiles,
  in lanes or in sequence), within 2 n u of the sum of their absolute values for each of the two kernels:
  tol = ((GROWTH + 1)(1 + 1 / (1 - amax)) delta + 4 n u) sum |term|; plus 2 L u / (1 - amax) relative for the
  C backward's running sum of (colour behind) . G over the L fragments behind a pixel.
A fragment whose alpha lies within delta of 1/255 (or T within delta of 1e-4) may be composited by one and
not the other; the scenes here have none (a flip would exceed the image bound).
"""
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import ev3dgs.splat.cpu as cpu
import ev3dgs.splat.cpu_simd as cpu_simd
from ev3dgs.splat.cpu import rasterize_cpu
from ev3dgs.splat.project import project_gaussians
from ev3dgs.splat.reference import rasterize_reference

from test_splat_backends import scene
from test_splat_batched import cameras

U = 2.0 ** -24
SMAX = math.log(255 * 0.99) + 1e-6  # the largest cut-off sigma of an opacity <= 0.99 (alpha clamp)
needs_c = pytest.mark.skipif(not cpu_simd.available(), reason="the C rasterizer extension is not built")


def growth(amax):
    return amax / ((1 - amax) * -math.log1p(-amax)) * math.log(1e4)


def project(params, vms, K, W, H):
    """(means2d, conics, depths, radii), each (C, N, ...), one projection per camera."""
    with torch.no_grad():
        prs = [project_gaussians(params[0], params[1], params[2], params[3], vm, K, W, H) for vm in vms]
    return [torch.stack([getattr(p, k) for p in prs]) for k in ("means2d", "conics", "depths", "radii")]


def inputs(n, W, H, C=1, seed=0, opacity_max=0.95):
    """Projected float32 rasterizer inputs for C cameras (C, N, ...) and the same values in float64."""
    params, _, K = scene(n, max(W, H), seed=seed)
    params[3] = params[3].clamp(max=opacity_max)
    m, q, d, r = project(params, cameras(C, seed=seed + 1), K, W, H)
    g = torch.Generator().manual_seed(seed + 2)
    cols = torch.rand(C, n, 3, generator=g, dtype=torch.float64)
    return [m.float(), q.float(), cols.float(), params[3].float(), d.float(), r]


def loss_weights(shape, seed=5):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=torch.float64) * 2 - 1


def rasterize(kind, x, W, H, bg, threads=1):
    """(image, alpha, grads of means2d, conics, colours, opacities, background) of one call, float64 out."""
    m, q, col, o, d, r = x
    dtype = torch.float64 if kind == "reference" else torch.float32
    leaves = [t.to(dtype).clone().requires_grad_(True) for t in (m, q, col, o, bg)]
    if kind == "reference":
        outs = [rasterize_reference(leaves[0][c], leaves[1][c], leaves[2][c], leaves[3], d[c].double(), r[c], W, H,
                                    leaves[4]) for c in range(m.shape[0])]
        image, alpha = torch.stack([a for a, _ in outs]), torch.stack([b for _, b in outs])
    else:
        old = cpu_simd.KERNEL
        cpu_simd.KERNEL = kind
        try:
            image, alpha = rasterize_cpu(*leaves[:4], d, r, W, H, leaves[4], threads=threads)
        finally:
            cpu_simd.KERNEL = old
    wi, wa = loss_weights(image.shape), loss_weights(alpha.shape, 6)
    ((image * wi.to(dtype)).sum() + (alpha * wa.to(dtype)).sum()).backward()
    # (the reference leaves a gradient None when no Gaussian is visible: zero)
    return [image.detach().double(), alpha.detach().double()] + [
        torch.zeros_like(t, dtype=torch.float64) if t.grad is None else t.grad.double() for t in leaves]


def kappa(conics):
    a, b, c = conics[..., 0].double(), conics[..., 1].double(), conics[..., 2].double()
    rho = b.abs() / (a * c).clamp_min(1e-300).sqrt()
    return float(((1 + rho) / (1 - rho).clamp_min(1e-12)).max())


def abs_terms(x, W, H, bg):
    """Per camera and Gaussian, the sum over its fragments of each gradient's term evaluated on absolute
    values (float64, the reference rules, dense over pixels x Gaussians; the loss weights of `rasterize`):
    the scale of the rounding error of a float32 sum of those terms and of their perturbation. Also the
    fragment counts."""
    m, q, col, o, d, r = (t.double() for t in x)
    C, N = r.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    px, py = xs.reshape(-1, 1), ys.reshape(-1, 1)
    G = loss_weights((C, H, W, col.shape[-1])).reshape(C, H * W, -1)
    GA = loss_weights((C, H, W, 1), 6).reshape(C, H * W)
    out = {k: torch.zeros(C, N, n, dtype=torch.float64) for k, n in (("means2d", 2), ("conics", 3),
                                                                   ("colors", col.shape[-1]))}
    out["opacities"], count = torch.zeros(C, N, dtype=torch.float64), torch.zeros(C, N, dtype=torch.float64)
    for c in range(C):
        idx = torch.nonzero(r[c] > 0).squeeze(-1)
        idx = idx[torch.argsort(d[c][idx], stable=True)]
        dx, dy = px - m[c, idx, 0], py - m[c, idx, 1]
        a, b, cc = q[c, idx, 0], q[c, idx, 1], q[c, idx, 2]
        sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
        e = torch.exp(-sigma.clamp_min(0))
        raw = o[idx] * e
        alpha = raw.clamp_max(0.99)
        keep = (sigma >= 0) & (alpha >= 1 / 255)
        alpha = torch.where(keep, alpha, 0.0)
        t_after = torch.cumprod(1 - alpha, -1)
        frag = keep & (t_after >= 1e-4)
        alpha = torch.where(frag, alpha, 0.0)
        t_after = torch.cumprod(1 - alpha, -1)
        t_before = torch.cat([torch.ones(H * W, 1, dtype=torch.float64), t_after[:, :-1]], -1)
        tf = t_after[:, -1:]
        w = alpha * t_before
        cw = w[..., None] * col[c, idx][None]  # (P, n, D)
        behind = cw.flip(1).cumsum(1).flip(1) - cw + tf[..., None] * bg.double()  # colour behind each
        # every sum evaluated on absolute values (so a relative change of each operand, and each rounding,
        # is bounded relative to it even where the sum cancels)
        cg = (col[c, idx][None] * G[c][:, None]).abs().sum(-1)
        sg = (behind * G[c][:, None]).abs().sum(-1)
        d_alpha = t_before * cg + (sg + GA[c][:, None].abs() * tf) / (1 - alpha)
        ok = frag & (raw <= 0.99)
        ds = torch.where(ok, d_alpha * alpha, 0.0)
        adx, ady = dx.abs(), dy.abs()
        out["means2d"][c, idx] = torch.stack([(ds * (a.abs() * adx + b.abs() * ady)).sum(0),
                                              (ds * (cc.abs() * ady + b.abs() * adx)).sum(0)], -1)
        out["conics"][c, idx] = torch.stack([(ds * 0.5 * adx * adx).sum(0), (ds * adx * ady).sum(0),
                                             (ds * 0.5 * ady * ady).sum(0)], -1)
        out["colors"][c, idx] = (w[..., None] * G[c][:, None]).abs().sum(0)
        out["opacities"][c, idx] = torch.where(ok, d_alpha * e, 0.0).sum(0)
        f = frag.double()
        count[c, idx] = f.sum(0)
    return out, count


def check(got, want, x, W, H, bg, delta, compositing):
    """Every output of `got` within the bounds of the module docstring of `want`."""
    amax = float(x[3].max())
    gr = growth(amax)
    cm = max(float(x[2].abs().max()), float(bg.abs().max()))
    L = x[0].shape[1]
    own = 3 * L * U if compositing else 0.0  # the kernel's own roundings against float64
    img_tol = ((gr + 1) * delta + own) * cm
    assert (got[0] - want[0]).abs().max() <= img_tol
    assert (got[1] - want[1]).abs().max() <= (gr + 1) * delta + own
    terms, count = abs_terms(x, W, H, bg)
    # + 16 u against float64: a term's own float32 roundings (at most ~12 operations from the stored alpha,
    # T and S to the product, each relative to the absolute evaluation)
    # + 2 L u / (1 - amax): the C backward keeps (colour behind) . G as one running sum over the <= L fragments
    # behind (the numba kernel per channel), each addition within u of the absolute evaluation, times 1/(1-a)
    rel = (gr + 1) * (1 + 1 / (1 - amax)) * delta + own + (16 * U if compositing else 0.0) + 2 * L * U / (1 - amax)
    for i, name in enumerate(["means2d", "conics", "colors", "opacities"]):
        # each term within rel of the other's; a float32 sum of n terms within 2 n u of their absolute sum
        # (both orders); + 1e-30 for Gaussians without fragments (both 0)
        tol = (rel + 4 * count.reshape(count.shape + (1,) * (terms[name].ndim - 2)) * U) * terms[name] + 1e-30
        err = (got[2 + i] - want[2 + i]).abs()
        if name == "opacities":  # one opacity per Gaussian, the cameras' terms summed
            tol = tol.sum(0)
        assert (err <= tol).all(), (name, float((err / tol).max()))
    # background: d image / d bg = T, the same T bound (per pixel, summed over the pixels with weights <= 1)
    assert (got[6] - want[6]).abs().max() <= img_tol / cm * got[0].shape[0] * W * H
    return True


@needs_c
@pytest.mark.parametrize("C", [1, 5])
def test_c_kernel_matches_reference(C):
    W, H = 56, 40
    x = inputs(300, W, H, C=C, seed=C)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float32)
    got, want = rasterize("simd", x, W, H, bg), rasterize("reference", x, W, H, bg)
    k = kappa(x[1])
    delta = (8 * k * SMAX + 6) * U
    assert check(got, want, x, W, H, bg, delta, compositing=True)
    assert float(want[1].max()) > 0.5  # not an empty scene


@needs_c
@pytest.mark.parametrize("C", [1, 5])
@pytest.mark.parametrize("hard", [False, True])
def test_c_kernel_matches_numba_kernel(C, hard):
    W, H = 64, 48
    params, _, K = scene(600, 64, seed=2, hard=hard)
    params[3] = params[3].clamp(max=0.99)
    m, q, d, r = project(params, cameras(C, seed=3), K, W, H)
    cols = torch.rand(C, 600, 3, generator=torch.Generator().manual_seed(4))
    x = [m.float(), q.float(), cols, params[3].float(), d.float(), r]
    bg = torch.tensor([0.2, 0.4, 0.6])
    got, want = rasterize("simd", x, W, H, bg), rasterize("numba", x, W, H, bg)
    assert check(got, want, x, W, H, bg, cpu_simd.EXP_REL_ERROR + 2 * U, compositing=False)
    assert not torch.equal(got[2], want[2])  # a different kernel ran (its exp and sums differ)


@needs_c
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 120), W=st.integers(1, 40), H=st.integers(1, 40),
       C=st.integers(1, 3))
def test_property_c_kernel_against_reference_and_numba(seed, n, W, H, C):
    x = inputs(n, W, H, C=C, seed=seed)
    bg = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float32)
    got = rasterize("simd", x, W, H, bg)
    assert check(got, rasterize("numba", x, W, H, bg), x, W, H, bg, cpu_simd.EXP_REL_ERROR + 2 * U, False)
    delta = (8 * kappa(x[1]) * SMAX + 6) * U
    assert check(got, rasterize("reference", x, W, H, bg), x, W, H, bg, delta, True)


@needs_c
@pytest.mark.parametrize("C", [1, 4])
def test_c_kernel_bitwise_the_same_for_1_2_3_threads(C):
    W, H = 96, 72
    x = inputs(1500, W, H, C=C, seed=7)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float32)
    runs = [rasterize("simd", x, W, H, bg, threads=t) for t in (1, 2, 3)]
    for other in runs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(runs[0], other))


@needs_c
def test_c_kernel_replay_equals_recompute_bitwise(monkeypatch):
    W, H = 64, 48
    x = inputs(600, W, H, C=2, seed=11)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float32)
    replay = rasterize("simd", x, W, H, bg)
    monkeypatch.setattr(cpu, "FRAGMENT_BUDGET", 0)
    recompute = rasterize("simd", x, W, H, bg)
    assert all(torch.equal(a, b) for a, b in zip(replay, recompute))


@needs_c
@pytest.mark.skipif(not cpu_simd.available() or cpu_simd.isa() != "avx2", reason="needs a CPU with AVX2")
def test_portable_and_avx2_builds_bitwise_the_same(monkeypatch):
    W, H = 64, 48
    x = inputs(600, W, H, C=2, seed=13)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float32)
    avx2 = rasterize("simd", x, W, H, bg)
    monkeypatch.setattr(cpu_simd, "ISA", 0)
    assert cpu_simd.isa() == "portable"
    portable = rasterize("simd", x, W, H, bg)
    assert all(torch.equal(a, b) for a, b in zip(avx2, portable))
    s = np.linspace(0, 87, 100_003, dtype=np.float32)
    a = cpu_simd.exp_neg(s)
    monkeypatch.setattr(cpu_simd, "ISA", 1)
    assert np.array_equal(a, cpu_simd.exp_neg(s))


def test_fallback_to_numba_without_the_extension(monkeypatch):
    """No C compiler at install: _raster is absent, the numba kernels run (bitwise their forced results)."""
    W, H = 48, 40
    x = inputs(300, W, H, C=2, seed=17)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float32)
    forced = rasterize("numba", x, W, H, bg)
    monkeypatch.setattr(cpu_simd, "_ext", None)
    monkeypatch.setattr(cpu_simd, "_lib", None)
    assert not cpu_simd.available() and not cpu_simd.active(np.float32, 3)
    called = []
    monkeypatch.setattr(cpu_simd, "forward", lambda *a, **kw: called.append(a))
    absent = rasterize("simd", x, W, H, bg)
    assert not called and all(torch.equal(a, b) for a, b in zip(forced, absent))


@needs_c
def test_float64_and_many_channels_stay_on_numba(monkeypatch):
    called = []
    real = cpu_simd.forward
    monkeypatch.setattr(cpu_simd, "forward", lambda *a, **kw: called.append(1) or real(*a, **kw))
    m = torch.tensor([[[4.0, 4.0]]])
    q = torch.tensor([[[0.5, 0.0, 0.5]]])
    o, d, r = torch.tensor([0.8]), torch.tensor([[1.0]]), torch.tensor([[4]])
    rasterize_cpu(m.double(), q.double(), torch.ones(1, 1, 3, dtype=torch.float64), o.double(), d, r, 8, 8)
    rasterize_cpu(m, q, torch.ones(1, 1, cpu_simd.DMAX + 1), o, d, r, 8, 8)
    assert called == []
    img, _ = rasterize_cpu(m, q, torch.ones(1, 1, 3), o, d, r, 8, 8)
    assert called == [1] and float(img[0, 4, 4, 0]) == pytest.approx(0.8, rel=1e-6)


# --- exp(-sigma) ---------------------------------------------------------------------------------------------

def _exp_error(s):
    got = cpu_simd.exp_neg(s).astype(np.float64)
    want = np.exp(-s.astype(np.float64))
    return np.abs(got / want - 1).max()


def test_polynomial_part_of_the_exp_bound():
    """The derivation's approximation term: Cephes' P in exact (float64) arithmetic on |f| <= ln2/2 (+ a
    rounding): max |1 + f + f^2 P(f) - e^f| / e^f < 0.22 u."""
    p = [1.9875691500e-4, 1.3981999507e-3, 8.3334519073e-3, 4.1665795894e-2, 1.6666665459e-1, 5.0000001201e-1]
    p = [float(np.float32(c)) for c in p]
    f = np.linspace(-0.3466, 0.3466, 2_000_001)
    y = np.zeros_like(f)
    for c in p:
        y = y * f + c
    assert np.abs((1 + f + f * f * y) / np.exp(f) - 1).max() < 0.22 * U


@needs_c
def test_exp_within_its_bound_on_a_strided_sweep_of_every_cut_off_sigma():
    """Every 61st float32 in [0, SMAX] (the sigmas the kernels exponentiate): ~18M values."""
    top = np.float32(SMAX).view(np.uint32)
    s = np.arange(0, int(top) + 1, 61, dtype=np.uint32).view(np.float32)
    err = _exp_error(s)
    assert err <= cpu_simd.EXP_REL_ERROR
    assert err > 0.1 * U  # it is an approximation, and the comparison sees it


@needs_c
@pytest.mark.slow
def test_exp_within_its_bound_on_every_cut_off_sigma():
    top = int(np.float32(SMAX).view(np.uint32))
    worst = 0.0
    for lo in range(0, top + 1, 1 << 24):
        s = np.arange(lo, min(lo + (1 << 24), top + 1), dtype=np.uint32).view(np.float32)
        worst = max(worst, _exp_error(s))
    assert worst <= cpu_simd.EXP_REL_ERROR


@needs_c
@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0, 87, width=32), min_size=1, max_size=40))
def test_property_exp_bound_up_to_87(values):
    assert _exp_error(np.array(values, np.float32)) <= cpu_simd.EXP_REL_ERROR


# --- schedule model and benchmark ----------------------------------------------------------------------------

def _schedule():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
    import schedule

    return schedule


def test_schedule_models_against_hand_computed_loads():
    s = _schedule()
    cost = np.array([5.0, 4.0, 3.0, 3.0, 1.0])
    # round robin over 2 threads in the order given: (5 + 3 + 1, 4 + 3) = (9, 7): 16 / 18
    assert s.round_robin(cost, np.arange(5), 2) == pytest.approx(16 / 18)
    # a work queue in the same order: 5 | 4, 3 -> thread 2 (4 < 5): 5 | 7, 3 -> thread 1: 8 | 7, 1 -> 8 | 8
    assert s.greedy(cost, 2, np.arange(5)) == pytest.approx(1.0)
    # the queue in a bad order (cheap first): 1 | 3, 3 -> t1: 4 | 3, 4 -> t2: 4 | 7, 5 -> t1: 9 | 7
    assert s.greedy(cost, 2, np.arange(5)[::-1]) == pytest.approx(16 / 18)
    assert s.round_robin(cost, np.arange(5), 1) == 1.0 and s.greedy(cost, 5) == pytest.approx(16 / 25)


@needs_c
@pytest.mark.slow
def test_kernel_benchmark_script(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "k.json"
    subprocess.run([sys.executable, str(root / "tools" / "bench" / "bench_raster.py"), "--kernels", "--quick",
                    "--repeats", "1", "--json", str(out), "--plot", str(tmp_path / "k.png")], check=True, cwd=root)
    row = json.loads(out.read_text())["rows"][0]
    assert row["fragments"] > 100_000 and row["speedup_kernels_cpu"]["median"] > 0
    assert (tmp_path / "k.png").stat().st_size > 0
