"""Tests for ev3dgs.splat.sh / model / strategy (CPU, fast)."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from ev3dgs.splat.model import GaussianModel, knn_mean_distance
from ev3dgs.splat.sh import C0, eval_sh, num_sh_bases, rgb_to_sh, sh_basis, sh_to_rgb
from ev3dgs.splat.strategy import DefaultStrategy, quat_to_rotmat

# ----------------------------------------------------------------------------- SH


def _textbook_real_sh(l: int, m: int, dirs: np.ndarray) -> np.ndarray:
    """Real SH from scipy's complex SH (which include the Condon-Shortley phase):
    Y_lm = sqrt2 (-1)^m Im Y_l^|m| (m<0), Y_l^0 (m=0), sqrt2 (-1)^m Re Y_l^m (m>0)."""
    theta = np.arccos(np.clip(dirs[:, 2], -1, 1))  # polar
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])  # azimuth
    y = sph_harm_y(l, abs(m), theta, phi)
    if m < 0:
        return math.sqrt(2) * (-1) ** m * y.imag
    if m == 0:
        return y.real
    return math.sqrt(2) * (-1) ** m * y.real


# 3DGS / gsplat sign convention: basis k = l^2 + l + m equals (-1)^m times the textbook real SH
# above, i.e. 3DGS drops the (-1)^m that cancels the Condon-Shortley phase (degree 1 is -y, z, -x).
SIGNS = np.array([(-1.0) ** m for l in range(4) for m in range(-l, l + 1)])


def _unit_dirs(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d = np.concatenate([d, np.eye(3), -np.eye(3), [[0, 0, 1e-3], [1, 1, 1]]])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _scipy_basis(degree: int, dirs: np.ndarray) -> np.ndarray:
    cols = [_textbook_real_sh(l, m, dirs) for l in range(degree + 1) for m in range(-l, l + 1)]
    return np.stack(cols, axis=1) * SIGNS[: num_sh_bases(degree)]


def test_sh_basis_matches_scipy():
    dirs = _unit_dirs(64)
    ours = sh_basis(3, torch.from_numpy(dirs)).numpy()
    np.testing.assert_allclose(ours, _scipy_basis(3, dirs), atol=1e-12)
    # gsplat / inria degree-1 literal form
    np.testing.assert_allclose(ours[:, 1:4], 0.4886025119029199 * np.stack([-dirs[:, 1], dirs[:, 2], -dirs[:, 0]], 1))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_eval_sh_against_scipy(degree):
    dirs = _unit_dirs(50, seed=degree)
    n = dirs.shape[0]
    rng = np.random.default_rng(10 + degree)
    sh = rng.normal(scale=0.5, size=(n, 16, 3))  # K=16 >= (degree+1)^2: extra bases ignored
    ref = np.einsum("nk,nkc->nc", _scipy_basis(degree, dirs), sh[:, : num_sh_bases(degree)])
    ref = np.maximum(ref + 0.5, 0.0)
    # un-normalised directions are normalised internally
    out = eval_sh(degree, torch.from_numpy(sh), torch.from_numpy(dirs * 3.7)).numpy()
    np.testing.assert_allclose(out, ref, atol=1e-10)
    assert (out >= 0).all()
    out32 = eval_sh(degree, torch.from_numpy(sh).float(), torch.from_numpy(dirs).float())
    assert out32.dtype == torch.float32 and (out32 >= 0).all()


def test_eval_sh_zero_direction_and_too_few_coeffs():
    sh = torch.randn(4, 16, 3, requires_grad=True)
    dirs = torch.zeros(4, 3, requires_grad=True)
    out = eval_sh(3, sh, dirs)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(sh.grad).all() and torch.isfinite(dirs.grad).all()
    torch.testing.assert_close(out, torch.clamp_min(C0 * sh[:, 0].detach() + 0.5, 0))
    with pytest.raises(ValueError):
        eval_sh(2, torch.zeros(3, 4, 3), torch.ones(3, 3))


def test_rgb_to_sh_roundtrip():
    rgb = torch.rand(20, 3)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb)
    out = eval_sh(0, rgb_to_sh(rgb)[:, None, :], torch.randn(20, 3))
    torch.testing.assert_close(out, rgb)


# -------------------------------------------------------------------------- model


def test_from_points_scale_rule_vs_brute_force():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(150, 3)) * np.array([1.0, 2.0, 0.5])
    rgb = rng.integers(0, 256, size=(150, 3), dtype=np.uint8)
    m = GaussianModel.from_points(xyz, rgb)
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    expect = np.log(np.sort(d, axis=1)[:, :3].mean(axis=1))
    ls = m.params["log_scales"].detach().double().numpy()
    np.testing.assert_allclose(ls, np.repeat(expect[:, None], 3, 1), rtol=1e-5, atol=1e-5)
    assert len(m) == 150 and m.params["shN"].shape == (150, 15, 3) and m.params["sh0"].shape == (150, 1, 3)
    torch.testing.assert_close(m.quats_normalised, torch.tensor([[1.0, 0, 0, 0]]).expand(150, 4))
    torch.testing.assert_close(m.opacities, torch.full((150,), 0.1))
    torch.testing.assert_close(sh_to_rgb(m.params["sh0"][:, 0]), torch.from_numpy(rgb / 255.0).float())
    assert m.sh.shape == (150, 16, 3) and m.active_sh_degree == 0
    assert not torch.allclose(m.params["shN"], torch.ones(1)) and (m.params["shN"] == 0).all()


def test_from_points_degenerate_inputs():
    one = GaussianModel.from_points(np.zeros((1, 3)), np.ones((1, 3)), sh_degree=1)
    assert torch.allclose(one.scales, torch.full((1, 3), 0.01))
    assert one.params["shN"].shape == (1, 3, 3)
    two = GaussianModel.from_points(np.array([[0.0, 0, 0], [0, 0, 2.0]]), np.zeros((2, 3)), sh_degree=0)
    torch.testing.assert_close(two.scales, torch.full((2, 3), 2.0))
    dup = GaussianModel.from_points(np.zeros((5, 3)), np.zeros((5, 3)))  # clamp 1e-7, then to [-12, 4]
    assert torch.isfinite(dup.params["log_scales"]).all() and (dup.params["log_scales"] >= -12).all()
    np.testing.assert_allclose(knn_mean_distance(np.zeros((4, 3))), 1e-7)


def test_random_in_bounds_inside_and_seeded():
    b = np.array([[-1.0, 0.0, 2.0], [1.0, 0.5, 5.0]])
    a1 = GaussianModel.random_in_bounds(b, 300, seed=3)
    a2 = GaussianModel.random_in_bounds(torch.tensor(b), 300, seed=3)
    a3 = GaussianModel.random_in_bounds(b, 300, seed=4)
    x = a1.means.detach()
    assert len(a1) == 300
    assert (x >= torch.tensor(b[0]).float()).all() and (x <= torch.tensor(b[1]).float()).all()
    for name in a1.params:
        torch.testing.assert_close(a1.params[name], a2.params[name])
    assert not torch.allclose(a1.means, a3.means)
    rgb = sh_to_rgb(a1.params["sh0"][:, 0])
    assert (rgb >= -1e-6).all() and (rgb <= 1 + 1e-6).all() and rgb.std() > 0.1


def test_activations_safe_for_extreme_values():
    m = GaussianModel.random_in_bounds([[0, 0, 0], [1, 1, 1]], 4, seed=0)
    with torch.no_grad():
        m.params["log_scales"].copy_(torch.tensor([[1e4] * 3, [-1e4] * 3, [0.0] * 3, [3.0, -11.0, 0.0]]))
        m.params["opacity_logits"].copy_(torch.tensor([1e4, -1e4, 0.0, 3.0]))
        m.params["quats"][0] = 0.0
    loss = m.scales.sum() + m.opacities.sum() + m.quats_normalised.sum() + torch.log(m.opacities).sum()
    loss = loss + torch.log1p(-m.opacities + 1e-12).sum() + torch.log(m.scales).sum()
    loss.backward()
    for t in (m.scales, m.opacities, m.quats_normalised):
        assert torch.isfinite(t).all()
    for p in m.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()
    assert m.scales.max() <= math.exp(4) * 1.0001 and m.scales.min() >= math.exp(-12) * 0.9999
    assert 0 < m.opacities.min() and m.opacities.max() < 1
    # in-range entries keep their gradient
    assert m.params["log_scales"].grad[3].abs().min() > 0 and m.params["opacity_logits"].grad[3] != 0


def test_state_dict_roundtrip():
    m = GaussianModel.random_in_bounds([[0, 0, 0], [1, 1, 1]], 10, seed=1)
    m.active_sh_degree = 2
    with torch.no_grad():
        m.params["shN"].normal_()
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    buf.seek(0)
    sd = torch.load(buf)
    other = GaussianModel.random_in_bounds([[0, 0, 0], [1, 1, 1]], 3, seed=2)
    other.load_state_dict(sd)
    assert len(other) == 10 and other.active_sh_degree == 2
    for name in m.params:
        torch.testing.assert_close(other.params[name], m.params[name])
        assert isinstance(other.params[name], torch.nn.Parameter)
    m2 = GaussianModel.from_state_dict(sd)
    torch.testing.assert_close(m2.sh, m.sh)


# ----------------------------------------------------------------------- strategy


def _info(n, grad=None, radii=None, w=100, h=50):
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.zeros(n, 2) if grad is None else torch.as_tensor(grad, dtype=torch.float32)
    r = torch.full((n,), 5, dtype=torch.int32) if radii is None else torch.as_tensor(radii, dtype=torch.int32)
    return {"means2d": means2d, "radii": r, "width": w, "height": h}


def _adam_warmup(model, opts):
    loss = sum((p.float() ** 2).sum() for p in model.parameters())
    loss.backward()
    for o in opts.values():
        o.step()
        o.zero_grad()


def _check_consistent(model, opts, state):
    n = len(model)
    for name, p in model.params.items():
        assert p.shape[0] == n
        assert opts[name].param_groups[0]["params"][0] is p
        st = opts[name].state.get(p)
        if st:
            assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    for v in state.values():
        assert v.shape == (n,)


def _six_gaussians():
    xyz = np.arange(18, dtype=np.float64).reshape(6, 3)
    m = GaussianModel.from_points(xyz, np.full((6, 3), 0.5))
    with torch.no_grad():
        m.params["log_scales"].fill_(math.log(0.005))  # small
        m.params["log_scales"][1] = math.log(0.05)  # large -> split
        m.params["opacity_logits"].fill_(0.0)
        m.params["opacity_logits"][2] = -8.0  # prune (opacity 3e-4)
    return m


def test_accumulation_two_renders_and_invisible():
    strat = DefaultStrategy()
    st = strat.initialize_state(3)
    g = [[2e-4, 0.0], [0.0, 4e-4], [1.0, 1.0]]
    infos = [_info(3, g, [3, 10, 0]), _info(3, g, [7, 0, 0], w=200)]
    assert strat.step_post_backward(GaussianModel.from_points(np.eye(3), np.ones((3, 3))), {}, st, 10, infos) == {}
    torch.testing.assert_close(st["count"], torch.tensor([2.0, 1.0, 0.0]))
    # grad scaled by (w/2, h/2): 2e-4*50 + 2e-4*100 ; 4e-4*25
    torch.testing.assert_close(st["grad2d"], torch.tensor([0.01 + 0.02, 0.01, 0.0]))
    torch.testing.assert_close(st["max_radius2d"], torch.tensor([max(3 / 100, 7 / 200), 10 / 100, 0.0]))
    # batched (C, N, 2) grads and gsplat-style per-axis radii (C, N, 2)
    st2 = strat.initialize_state(3)
    info = _info(3)
    info["means2d"] = torch.zeros(2, 3, 2, requires_grad=True)
    info["means2d"].grad = torch.tensor(g, dtype=torch.float32)[None].repeat(2, 1, 1)
    info["radii"] = torch.tensor([[[3, 1], [0, 0], [0, 0]], [[1, 1], [2, 9], [0, 0]]], dtype=torch.int32)
    strat.accumulate(st2, info)
    torch.testing.assert_close(st2["count"], torch.tensor([2.0, 1.0, 0.0]))
    torch.testing.assert_close(st2["max_radius2d"], torch.tensor([0.03, 0.09, 0.0]))


def test_step_pre_backward_retains_grad():
    x = torch.randn(4, 3, requires_grad=True)
    means2d = x[:, :2] * 2.0
    DefaultStrategy().step_pre_backward({"means2d": means2d})
    means2d.sum().backward()
    torch.testing.assert_close(means2d.grad, torch.ones(4, 2))


def test_clone_split_prune_counts_and_adam_rows():
    m = _six_gaussians()
    opts = m.make_optimizers()
    _adam_warmup(m, opts)
    # tag Adam rows with row id + 1 so we can follow them
    for name, p in m.params.items():
        ids = torch.arange(1, 7, dtype=torch.float32).reshape((6,) + (1,) * (p.dim() - 1))
        opts[name].state[p]["exp_avg"] = ids.expand_as(p).clone()
        opts[name].state[p]["exp_avg_sq"] = (ids * 10).expand_as(p).clone()
    steps_before = {n: opts[n].state[p]["step"].clone() for n, p in m.params.items()}
    means_before = m.means.detach().clone()
    strat = DefaultStrategy()
    st = strat.initialize_state(6)
    hi = [1e-5, 0.0]  # * (w/2 = 50) -> 5e-4 > grow_grad2d
    g = [hi, hi, [0.0, 0.0], [0.0, 0.0], [1e-7, 0.0], hi]
    radii = [5, 5, 5, 5, 5, 0]  # row 5 invisible -> no growth
    out = strat.step_post_backward(m, opts, st, 500, [_info(6, g, radii)])
    assert out == {"cloned": 1, "split": 1, "pruned": 1}
    # order: clone appends [0..5, 0']; split(1) -> [0,2,3,4,5,0', 1a,1b]; prune(2) -> [0,3,4,5,0',1a,1b]
    assert len(m) == 7
    _check_consistent(m, opts, st)
    rows = [1, 4, 5, 6, 1, 0, 0]  # id+1, zeros for split children
    for name, p in m.params.items():
        ea = opts[name].state[p]["exp_avg"].reshape(7, -1)
        torch.testing.assert_close(ea[:, 0], torch.tensor(rows, dtype=torch.float32))
        torch.testing.assert_close(opts[name].state[p]["exp_avg_sq"].reshape(7, -1)[:, 0],
                                   torch.tensor(rows, dtype=torch.float32) * 10)
        torch.testing.assert_close(opts[name].state[p]["step"], steps_before[name])
    torch.testing.assert_close(m.means[:5].detach(), means_before[[0, 3, 4, 5, 0]])
    assert (st["count"] == 0).all() and (st["grad2d"] == 0).all()
    # a real Adam step afterwards works with the new shapes
    before = {n: p.detach().clone() for n, p in m.params.items()}
    _adam_warmup(m, opts)
    for name, p in m.params.items():
        assert p.shape == before[name].shape and not torch.equal(p, before[name])
    _check_consistent(m, opts, st)


def test_no_refine_outside_schedule():
    strat = DefaultStrategy()
    for step in (499, 550, 15_000, 20_000):
        m = _six_gaussians()
        opts = m.make_optimizers()
        st = strat.initialize_state(6)
        out = strat.step_post_backward(m, opts, st, step, [_info(6, [[1.0, 0.0]] * 6)])
        assert out == {} and len(m) == 6
        if step >= strat.refine_stop:
            assert (st["count"] == 0).all()  # no accumulation after refine_stop


def test_split_samples_within_parent_gaussian():
    n = 300
    rng = np.random.default_rng(0)
    m = GaussianModel.from_points(rng.normal(size=(n, 3)), rng.random((n, 3)))
    q = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(n, 4))).float(), dim=-1)
    with torch.no_grad():
        m.params["quats"].copy_(q)
        m.params["log_scales"].copy_(torch.log(torch.tensor([0.3, 0.1, 0.02])).expand(n, 3))
        m.params["opacity_logits"].fill_(1.0)
    parent_means, parent_scales = m.means.detach().clone(), m.scales.detach().clone()
    opts = m.make_optimizers()
    strat = DefaultStrategy(seed=1)
    st = strat.initialize_state(n)
    strat.split(m, opts, st, torch.ones(n, dtype=torch.bool))
    assert len(m) == 2 * n
    _check_consistent(m, opts, st)
    rot = quat_to_rotmat(q)
    for s in range(2):
        child = m.means.detach()[s * n:(s + 1) * n]
        z = torch.einsum("nji,nj->ni", rot, child - parent_means) / parent_scales  # in parent frame
        assert (z.abs() < 3).float().mean() > 0.98 and z.abs().max() < 5
        assert abs(z.std().item() - 1.0) < 0.1 and z.mean().abs() < 0.1
    torch.testing.assert_close(m.scales, parent_scales.repeat(2, 1) / 1.6)
    torch.testing.assert_close(m.opacities, torch.full((2 * n,), torch.sigmoid(torch.tensor(1.0)).item()))
    torch.testing.assert_close(m.params["quats"].detach(), q.repeat(2, 1))


def test_size_prune_only_after_first_reset():
    for step, expect in ((600, 0), (3100, 2)):
        m = _six_gaussians()
        with torch.no_grad():
            m.params["opacity_logits"][2] = 0.0
            m.params["log_scales"][3] = math.log(0.5)  # > prune_scale3d * scene_scale
        opts = m.make_optimizers()
        strat = DefaultStrategy()
        st = strat.initialize_state(6)
        radii = [5, 5, 5, 5, 20, 5]  # row 4: 20/100 = 0.2 > 0.15 of the image
        out = strat.step_post_backward(m, opts, st, step, [_info(6, None, radii)])
        assert out == {"cloned": 0, "split": 0, "pruned": expect}
        _check_consistent(m, opts, st)
    # scene_scale rescales the 3D threshold
    m = _six_gaussians()
    with torch.no_grad():
        m.params["opacity_logits"][2] = 0.0
        m.params["log_scales"][3] = math.log(0.5)
    strat = DefaultStrategy(scene_scale=10.0)
    out = strat.step_post_backward(m, m.make_optimizers(), strat.initialize_state(6), 3100, [_info(6)])
    assert out["pruned"] == 0


def test_opacity_reset():
    m = _six_gaussians()
    opts = m.make_optimizers()
    _adam_warmup(m, opts)
    low = m.opacities[2].item()
    strat = DefaultStrategy()
    st = strat.initialize_state(6)
    strat.step_post_backward(m, opts, st, 3000, [_info(6)])
    assert (m.opacities <= strat.reset_value).all()
    assert m.opacities[1:].max() > strat.reset_value * 0.999  # capped, not zeroed
    p = m.params["opacity_logits"]
    assert opts["opacity_logits"].param_groups[0]["params"][0] is p
    assert (opts["opacity_logits"].state[p]["exp_avg"] == 0).all()
    assert low < strat.prune_opa and len(m) == 5  # the refine at step 3000 pruned row 2
    _adam_warmup(m, opts)
    _check_consistent(m, opts, st)


def _textbook_adam(p0: torch.Tensor, grads, lr: float, eps: float, b1: float = 0.9, b2: float = 0.999):
    """Kingma & Ba's Adam with bias correction, in float64: the independent oracle for make_optimizers."""
    p, m, v = p0.double().clone(), torch.zeros_like(p0, dtype=torch.float64), torch.zeros_like(p0, dtype=torch.float64)
    for t, g in enumerate(grads, 1):
        g = g.double()
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        p = p - lr * (m / (1 - b1 ** t)) / (torch.sqrt(v / (1 - b2 ** t)) + eps)
    return p


def _run_adam(threads: int):
    m = _six_gaussians()
    opts = m.make_optimizers(scene_scale=2.0)
    g = torch.Generator().manual_seed(3)
    grads = {n: [torch.randn(p.shape, generator=g) * 10.0 ** (k - 2) for k in range(5)] for n, p in m.params.items()}
    start = {n: p.detach().clone() for n, p in m.params.items()}
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for k in range(5):
            for n, p in m.params.items():
                p.grad = grads[n][k].clone()
                opts[n].step()
                opts[n].zero_grad(set_to_none=True)
    finally:
        torch.set_num_threads(old)
    return m, opts, start, grads


def test_make_optimizers_is_adam_and_thread_count_independent():
    m1, opts, start, grads = _run_adam(1)
    m2, _, _, _ = _run_adam(2)
    for n, p in m1.params.items():
        lr = opts[n].param_groups[0]["lr"]
        want = _textbook_adam(start[n], grads[n], lr, eps=1e-15)
        # float32 state and update: each step's update lr * m_hat / sqrt(v_hat) (|.| <= ~3 lr here) carries a
        # few float32 roundings (2^-24 relative); 5 steps, plus the rounding of p itself (values ~1)
        torch.testing.assert_close(p.detach().double(), want, rtol=1e-6, atol=5 * 8 * lr * 2.0 ** -24 + 1e-7)
        assert torch.equal(p, m2.params[n]), n  # element-wise kernel: bitwise the same on 1 and 2 threads
