"""The `cpu` backend's vectorised kernels (cpu.py, cpu_backward.py): the polynomial exp against float64
math.exp within its stated bound, the images against the scalar kernels they replaced (_cpu_legacy, kept for
this comparison) bitwise in the exact (libm) mode and within the bound derived from the exp's error in the
default mode, the libm fallback beyond the polynomial's domain, and the fragment counting tool."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import ev3dgs.splat.cpu as cpu
from ev3dgs.splat import _cpu_legacy
from ev3dgs.splat.cpu_tiles import EXP_REL_ERR, SIGMA_POLY_MAX, exp_neg
from ev3dgs.splat.rasterize import rasterization

from test_splat_backends import render, scene

F64 = torch.float64
BG = (0.2, 0.4, 0.6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, SIGMA_POLY_MAX), min_size=1, max_size=64))
def test_polynomial_exp_within_its_bound(dtype, values):
    s = np.array(values, dtype)
    got = exp_neg(s).astype(np.float64)
    want = np.array([math.exp(-float(v)) for v in s])  # of the rounded input, in float64 (0.5 ulp64)
    assert np.all(np.abs(got - want) <= EXP_REL_ERR[np.dtype(dtype).itemsize] * want)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_polynomial_exp_dense_grid_and_range_ends(dtype):
    # every reduction interval k = 0..15 and both ends of each (the 2^-k selects, the Taylor truncation)
    s = np.concatenate([np.linspace(0.0, SIGMA_POLY_MAX, 200_001), (np.arange(16) + 0.5) * math.log(2.0)])
    s = s[s <= SIGMA_POLY_MAX].astype(dtype)
    want = np.exp(-s.astype(np.float64))
    rel = np.abs(exp_neg(s) - want) / want
    assert rel.max() <= EXP_REL_ERR[np.dtype(dtype).itemsize]


def legacy_render(monkeypatch, *args, **kw):
    with monkeypatch.context() as m:
        m.setattr(cpu, "rasterize_cpu", _cpu_legacy.rasterize_cpu_legacy)
        return render("cpu", *args, **kw)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("hard", [False, True])
def test_exact_mode_image_is_bitwise_the_scalar_kernels(monkeypatch, dtype, hard):
    """EV3DGS_CPU_EXP=libm: the same exp and the same per-pixel operations in the same order as the scalar
    kernel, so the same image bit for bit (the gradients sum in another order: checked below)."""
    params, vm, K = scene(400, 64, seed=4, dtype=dtype, hard=hard)
    old = legacy_render(monkeypatch, params, vm, K, 64, 48)
    monkeypatch.setenv(cpu.EXP_ENV, "libm")
    new = render("cpu", params, vm, K, 64, 48)
    assert torch.equal(old[0], new[0]) and torch.equal(old[1], new[1])


def _bound(image, params, dtype):
    """The default mode against the exact one: a relative alpha error eps (the exp's, EXP_REL_ERR) moves a
    pixel by at most 2 eps max|colour, background| (cpu_tiles, derivation above EXP_REL_ERR); both are then
    rounded differently, at most 3 n u (n composited layers <= the 400 Gaussians) of the same maximum."""
    u = 2.0 ** -53 if dtype == F64 else 2.0 ** -24
    eps = EXP_REL_ERR[8 if dtype == F64 else 4]
    cmax = max(float(params[4].abs().max()), max(BG))
    return 2 * eps * cmax + 3 * 400 * u * cmax


@pytest.mark.parametrize("seed", range(3))
def test_default_mode_within_the_exp_bound_float64(monkeypatch, seed):
    params, vm, K = scene(400, 64, seed=seed, dtype=F64)
    monkeypatch.setenv(cpu.EXP_ENV, "libm")
    exact = render("cpu", params, vm, K, 64, 48)
    monkeypatch.delenv(cpu.EXP_ENV)
    poly = render("cpu", params, vm, K, 64, 48)
    old = legacy_render(monkeypatch, params, vm, K, 64, 48)
    assert float((poly[0] - exact[0]).abs().max()) <= _bound(exact[0], params, F64)
    # gradients: the alpha error is amplified at most by 1 / T_min = 1e4 through the recovered
    # transmittance; the scalar kernel's gradients sum in another order (n u each): 1e-9 relative as in
    # test_splat_backends' float64 comparisons
    for x, y, z in zip(poly[2], exact[2], old[2]):
        scale = max(float(z.abs().max()), 1.0)
        assert float((x - z).abs().max()) <= 1e-9 * scale and float((y - z).abs().max()) <= 1e-9 * scale


def test_opacities_beyond_the_polynomial_domain_use_libm(monkeypatch):
    """sigma_max = ln(255 o) > SIGMA_POLY_MAX for o > e^10 / 255: such Gaussians take libm's exp (the
    polynomial's 2^-k covers k <= 15 only); the image still matches the scalar kernel within the bound."""
    params, vm, K = scene(200, 48, seed=6, dtype=F64)
    params[3][:50] = 500.0  # alpha = min(0.99, o e^-sigma): reaches 1/255 out to sigma = ln(255 * 500) = 11.8
    old = legacy_render(monkeypatch, params, vm, K, 48, 40)
    new = render("cpu", params, vm, K, 48, 40)
    assert float((old[0] - new[0]).abs().max()) <= _bound(old[0], params, F64)


def test_too_many_entries_in_one_tile_is_refused(monkeypatch):
    params, vm, K = scene(50, 32, seed=1, dtype=torch.float32)
    monkeypatch.setattr(cpu, "MAX_TILE_ENTRIES", 3)
    with pytest.raises(ValueError, match="Gaussians reach one"):
        render("cpu", params, vm, K, 32, 32)


def test_fragment_counts_against_a_brute_force_compositor():
    """tools/bench/fragments.py: composited fragments equal a per-pixel brute force of the reference rules."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
    from fragments import fragment_stats

    from ev3dgs.splat.project import project_gaussians

    params, vm, K = scene(80, 24, seed=3, dtype=torch.float32)
    W, H = 24, 20
    with torch.no_grad():
        pr = project_gaussians(params[0], params[1], params[2], params[3], vm, K, W, H)
    stats = fragment_stats(pr.means2d, pr.conics, params[4], params[3], pr.depths, pr.radii, W, H)
    m, q = pr.means2d.double().numpy(), pr.conics.double().numpy()
    o, r, d = params[3].double().numpy(), pr.radii.numpy(), pr.depths.double().numpy()
    order = [g for g in np.argsort(d, kind="stable") if r[g] > 0]
    n = 0
    for y in range(H):
        for x in range(W):
            T = 1.0
            for g in order:
                dx, dy = x - m[g, 0], y - m[g, 1]
                s = 0.5 * (q[g, 0] * dx * dx + q[g, 2] * dy * dy) + q[g, 1] * dx * dy
                if s < 0:
                    continue
                a = min(0.99, o[g] * math.exp(-s))
                if a < 1 / 255:
                    continue
                if T * (1 - a) < 1e-4:
                    break
                T *= 1 - a
                n += 1
    # float32 kernel against a float64 brute force: a fragment within rounding of a cut-off may differ
    assert abs(stats["composited"] - n) <= 2 and stats["composited"] > 100
    assert stats["fragments_per_pixel"] == pytest.approx(stats["composited"] / (W * H))
