"""Every backend against `reference`, in values and gradients, including the hard cases."""

import numpy as np
import pytest
import torch

from ev3dgs.errors import InputError
from ev3dgs.splat.rasterize import cuda_available, rasterization

F64 = torch.float64


def scene(n, width, seed=0, dtype=F64, hard=False):
    g = torch.Generator().manual_seed(seed)
    z = 3 + 2 * torch.rand(n, generator=g)
    f = 1.1 * width
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * (0.5 * width / f * z)[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g)
    scales = 0.02 + 0.2 * torch.rand(n, 3, generator=g)
    opac = 0.05 + 0.9 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    if hard:
        means[0] = torch.tensor([0.0, 0.0, -1.0])          # behind the camera
        means[1] = torch.tensor([0.1, 0.0, 0.01])          # exactly at the near plane
        means[2] = torch.tensor([0.0, 0.1, 0.005])         # between camera and near plane
        scales[3] = 1e4                                    # huge
        scales[4] = 1e-8                                   # tiny
        scales[5] = torch.tensor([0.5, 1e-9, 1e-9])        # flat / degenerate covariance
        scales[6] = torch.tensor([0.3, 0.3, 1e-12])
        opac[7], opac[8], opac[9] = 1e-7, 1.0, 1 - 1e-7    # opacities near 0 and 1
        means[10], scales[10] = torch.tensor([0.0, 0.0, 0.0]), 2.0   # the camera inside a Gaussian
        means[11] = torch.tensor([1e3, 1e3, 2.0])          # far off-screen
        quats[12] = 0.0                                    # zero quaternion
    K = torch.tensor([[f, 0, (width - 1) / 2 + 0.3], [0, f, (width - 1) / 2 - 0.2], [0, 0, 1.0]], dtype=dtype)
    return [t.to(dtype) for t in (means, quats, scales, opac, colors)], torch.eye(4, dtype=dtype), K


def render(backend, params, viewmat, K, width, height, **kw):
    leaves = [p.clone().requires_grad_(True) for p in params]
    bg = kw.pop("background", torch.tensor([0.2, 0.4, 0.6], dtype=params[0].dtype))
    image, alpha, meta = rasterization(*leaves, viewmat, K, width, height, backend=backend, background=bg, **kw)
    w = torch.linspace(-1, 1, image.numel(), dtype=image.dtype).reshape(image.shape)
    loss = (image * w).sum() + (alpha**2).sum() + image.mean()
    loss.backward()
    return image.detach(), alpha.detach(), [leaf.grad for leaf in leaves]


def assert_same(a, b, atol=1e-10):
    (ia, aa, ga), (ib, ab, gb) = a, b
    assert torch.isfinite(ia).all() and torch.isfinite(aa).all()
    assert (ia - ib).abs().max() <= atol and (aa - ab).abs().max() <= atol
    for x, y in zip(ga, gb):
        assert torch.isfinite(x).all() and torch.isfinite(y).all()
        scale = max(float(x.abs().max()), 1.0)
        assert float((x - y).abs().max()) <= atol * scale


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("size", [(33, 21), (64, 48)])
def test_cpu_matches_reference_float64(seed, size):
    W, H = size
    params, vm, K = scene(300, W, seed)
    assert_same(render("reference", params, vm, K, W, H), render("cpu", params, vm, K, W, H))


@pytest.mark.parametrize("seed", range(3))
def test_hard_cases_match_and_stay_finite(seed):
    params, vm, K = scene(60, 40, seed, hard=True)
    assert_same(render("reference", params, vm, K, 40, 30), render("cpu", params, vm, K, 40, 30))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_hard_cases_finite_in_float32_and_64(dtype):
    params, vm, K = scene(40, 32, 1, dtype=dtype, hard=True)
    image, alpha, grads = render("cpu", params, vm, K, 32, 32)
    assert torch.isfinite(image).all() and all(torch.isfinite(g).all() for g in grads)


def test_depth_mode_sh_colours_and_background_gradient():
    params, vm, K = scene(150, 40, 5)
    g = torch.Generator().manual_seed(1)
    sh = torch.randn(150, 4, 3, generator=g, dtype=F64) * 0.3
    params = params[:4] + [sh]
    out = {}
    for b in ("reference", "cpu"):
        bg = torch.tensor([0.3, 0.1, 0.9], dtype=F64, requires_grad=True)
        leaves = [p.clone().requires_grad_(True) for p in params]
        image, alpha, _ = rasterization(*leaves, vm, K, 40, 40, sh_degree=1, background=bg, render_mode="RGB+D",
                                        backend=b)
        assert image.shape == (40, 40, 4)
        (image.sum() + image[..., 3].pow(2).mean()).backward()
        out[b] = (image.detach(), bg.grad, [x.grad for x in leaves])
    # float64, two implementations of the same sums: ~n u per composited pixel (n <= a few hundred layers),
    # gradients also through T recovered by division (amplification <= 1/T_min = 1e4): 1e-10 / 1e-9 relative.
    assert (out["reference"][0] - out["cpu"][0]).abs().max() < 1e-10
    assert torch.allclose(out["reference"][1], out["cpu"][1], atol=1e-10)
    for x, y in zip(out["reference"][2], out["cpu"][2]):
        assert torch.allclose(x, y, atol=1e-9 * max(1.0, float(x.abs().max())))


def test_empty_and_all_culled_scenes_return_the_background():
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    K = torch.tensor([[20.0, 0, 9.5], [0, 20.0, 9.5], [0, 0, 1]], dtype=F64)
    for n in (0, 5):
        means = torch.zeros(n, 3, dtype=F64)
        means[:, 2] = -1.0  # all behind the camera
        params = [means, torch.randn(n, 4, dtype=F64), torch.ones(n, 3, dtype=F64) * 0.1,
                  torch.full((n,), 0.5, dtype=F64), torch.rand(n, 3, dtype=F64)]
        for b in ("reference", "cpu"):
            image, alpha, grads = render(b, params, torch.eye(4, dtype=F64), K, 20, 20, background=bg)
            assert torch.allclose(image, bg.expand(20, 20, 3)) and (alpha == 0).all()
            assert all(g is None or torch.isfinite(g).all() for g in grads)


def test_thread_count_does_not_change_the_result():
    params, vm, K = scene(2000, 96, 7, dtype=torch.float32)
    a = render("cpu", params, vm, K, 96, 80, threads=1)
    b = render("cpu", params, vm, K, 96, 80, threads=2)
    assert torch.equal(a[0], b[0]) and all(torch.equal(x, y) for x, y in zip(a[2], b[2]))


def test_float32_close_to_float64():
    params, vm, K = scene(1000, 64, 3)
    a = render("cpu", params, vm, K, 64, 64)
    b = render("cpu", [p.float() for p in params], vm.float(), K.float(), 64, 64)
    # float32 u = 6e-8. A Gaussian's alpha carries ~10 u relative error after projection and exp(-sigma)
    # (sigma <= ln(255 o) ~ 5.5); compositing weights sum to <= 1 and the transmittance error grows at most
    # with -ln T_min = ln(1e4) ~ 9.2: ~10 u * 5.5 * 9.2 ~ 3e-5 < 1e-4 on any CPU (typically ~1e-6).
    assert (a[0] - b[0].double()).abs().max() < 1e-4


def test_tiny_analytic_scene_is_recovered_by_optimisation():
    # one red and one blue Gaussian; start from shifted, wrongly sized and too faint copies
    K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 15.5], [0, 0, 1]])
    vm = torch.eye(4)
    true = dict(means=torch.tensor([[-0.2, 0.1, 2.0], [0.25, -0.15, 2.5]]), log_scales=torch.log(torch.tensor(
        [[0.15, 0.1, 0.1], [0.1, 0.2, 0.1]])), opacity_logits=torch.tensor([2.0, 1.5]))
    colors = torch.tensor([[1.0, 0.1, 0.1], [0.1, 0.2, 1.0]])
    quats = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])

    def draw(p):
        img, _, _ = rasterization(p["means"], quats, p["log_scales"].exp(), torch.sigmoid(p["opacity_logits"]),
                                  colors, vm, K, 32, 32, backend="cpu", threads=1)
        return img

    target = draw(true)
    p = {k: (v + torch.tensor(d)).clone().requires_grad_(True) for (k, v), d in zip(true.items(), (
        [[0.06, -0.05, 0.0], [-0.05, 0.06, 0.0]], [[0.3, -0.2, 0.0], [-0.3, 0.2, 0.0]], [-1.5, -1.0]))}
    opt = torch.optim.Adam([p["means"], p["log_scales"], p["opacity_logits"]], lr=0.01)
    first = None
    for _ in range(600):
        opt.zero_grad()
        loss = ((draw(p) - target) ** 2).mean()
        first = first if first is not None else loss.item()
        loss.backward()
        opt.step()
    assert loss.item() < 1e-3 * first
    assert (p["means"][:, :2] - true["means"][:, :2]).abs().max() < 0.01


@pytest.mark.parametrize("kwargs,match", [
    (dict(backend="metal"), "unknown backend"),
    (dict(render_mode="D"), "render_mode"),
    (dict(width=0), "image size"),
])
def test_bad_arguments(kwargs, match):
    params, vm, K = scene(5, 16, 0)
    args = dict(width=16, height=16)
    args.update({k: v for k, v in kwargs.items() if k in args})
    with pytest.raises(InputError, match=match):
        rasterization(*params, vm, K, args["width"], args["height"],
                      **{k: v for k, v in kwargs.items() if k not in args})


def test_wrong_shapes_are_clear_errors():
    params, vm, K = scene(5, 16, 0)
    with pytest.raises(InputError, match="quats"):
        rasterization(params[0], params[1][:3], *params[2:], vm, K, 16, 16)


@pytest.mark.gpu
@pytest.mark.skipif(not cuda_available(), reason="needs CUDA and gsplat")
def test_cuda_matches_reference():
    params, vm, K = scene(2000, 128, 0, dtype=torch.float32)
    ref = render("reference", params, vm, K, 128, 96)
    dev = render("cuda", [p.cuda() for p in params], vm.cuda(), K.cuda(), 128, 96,
                 background=torch.tensor([0.2, 0.4, 0.6], device="cuda"))
    assert (ref[0] - dev[0].cpu()).abs().max() < 1e-3
    for x, y in zip(ref[2], dev[2]):
        assert torch.allclose(x, y.cpu(), atol=1e-3 * max(1.0, float(x.abs().max())), rtol=1e-2)


def test_densification_statistics_from_several_real_renders():
    from ev3dgs.splat.model import GaussianModel
    from ev3dgs.splat.strategy import DefaultStrategy

    rng = np.random.default_rng(0)
    xyz = rng.uniform(-0.5, 0.5, (200, 3))
    model = GaussianModel.from_points(xyz, rng.integers(0, 255, (200, 3)).astype(np.uint8), sh_degree=1)
    opt = model.make_optimizers()
    strat = DefaultStrategy(refine_start=0, refine_every=1, grow_grad2d=1e-9)
    state = strat.initialize_state(len(model))
    K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    infos, loss = [], 0.0
    for dz in (0.0, 0.05):  # two renders of one step, as the blur loss does
        vm = torch.eye(4)
        vm[2, 3] = 3.0 + dz
        image, _, info = rasterization(model.means, model.quats_normalised, model.scales, model.opacities,
                                       model.sh, vm, K, 64, 48, sh_degree=1, backend="cpu")
        strat.step_pre_backward(info)
        infos.append(info)
        loss = loss + image.mean()
    loss.backward()
    visible_both = (infos[0]["radii"] > 0) & (infos[1]["radii"] > 0)
    n_before = len(model)
    out = strat.step_post_backward(model, opt, state, step=1, infos=infos)
    assert visible_both.any() and out["cloned"] + out["split"] > 0
    assert len(model) == n_before + out["cloned"] + out["split"] * (strat.n_split - 1) - out["pruned"]
    for name, o in opt.items():
        assert o.param_groups[0]["params"][0] is model.params[name]


@pytest.mark.slow
def test_raster_benchmark_script(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, str(root / "tools" / "bench" / "bench_raster.py"), "--quick", "--repeats", "1",
                        "--json", str(tmp_path / "r.json"), "--plot", str(tmp_path / "r.png")],
                       capture_output=True, text=True, cwd=root)
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "r.json").read_text())["rows"]
    assert {r["backend"] for r in rows} >= {"reference", "cpu"}
    assert all(r["max_abs_diff"] <= 1e-4 and r["gaussians"] == 10_000 and r["width"] == 200 for r in rows)
    # both clocks recorded; a fwd+bwd of 10k Gaussians takes some CPU time, and one thread cannot use more
    # CPU than wall time (small slack: the two clocks are read at slightly different instants)
    assert all(0 < r["cpu_ms"] <= r["ms"] * 1.05 + 1.0 for r in rows)
