"""The render contract of the trainer's one call per step: rasterization(..., viewmat[C,4,4]) returns images
(C,H,W,D), alpha (C,H,W,1) and meta["means2d"] (C,N,2) whose .grad after backward holds every camera's
screen-space gradient, on every backend: checked against C single-camera calls."""
import numpy as np
import pytest
import torch

from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.splat.model import GaussianModel
from ev3dgs.splat.rasterize import _rasterization_loop, rasterization

W, H = 20, 16


def _scene(seed=0, n=40):
    rng = np.random.default_rng(seed)
    model = GaussianModel.from_points(rng.uniform(-0.5, 0.5, (n, 3)), rng.integers(0, 255, (n, 3)).astype(np.uint8),
                                      sh_degree=1, init_opacity=0.6)
    cams = np.stack([np.linalg.inv(look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.4]), [0, 0, 0]))
                     for a in (0.1, 0.4, 0.7)])
    return model, torch.as_tensor(cams, dtype=torch.float32), torch.as_tensor(intrinsics(W, H, 30), dtype=torch.float32)


def _call(model, vm, K, backend, fn=rasterization):
    return fn(model.means, model.quats_normalised, model.scales, model.opacities, model.sh, vm, K, W, H,
              sh_degree=1, background=torch.ones(3), backend=backend)


def _per_camera(model, vms, K, backend, weights):
    """Each camera on its own: images and the screen-space gradient of sum(w_c * image_c)."""
    images, grads = [], []
    for c, vm in enumerate(vms):
        img, _, meta = _call(model, vm, K, backend)
        meta["means2d"].retain_grad()
        (weights[c] * img).sum().backward()
        images.append(img.detach())
        grads.append(meta["means2d"].grad.clone())
        for p in model.params.values():
            p.grad = None
    return torch.stack(images), torch.stack(grads)


@pytest.mark.parametrize("backend", ["reference", "cpu", "loop"])
def test_batched_means2d_carries_every_cameras_gradient(backend):
    model, vms, K = _scene()
    weights = torch.rand(len(vms), H, W, 3, generator=torch.Generator().manual_seed(1))
    ref_backend = "reference" if backend == "loop" else backend
    want_img, want_grad = _per_camera(model, vms, K, ref_backend, weights)
    if backend == "loop":   # the per-camera loop a backend without a batched call goes through
        img, alpha, meta = _rasterization_loop(model.means, model.quats_normalised, model.scales, model.opacities,
                                               model.sh, vms, K, W, H, backend="reference", threads=None,
                                               sh_degree=1, background=torch.ones(3), render_mode="RGB",
                                               near_plane=0.01, far_plane=1e10, eps2d=0.3)
    else:
        img, alpha, meta = _call(model, vms, K, backend)
    assert img.shape == (3, H, W, 3) and alpha.shape == (3, H, W, 1)
    assert meta["means2d"].shape == (3, len(model), 2) and meta["radii"].shape[:2] == (3, len(model))
    if meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    (weights * img).sum().backward()
    assert torch.equal(img.detach(), want_img)   # the same arithmetic per camera
    assert meta["means2d"].grad is not None
    # one camera's backward is the same operations in the same order as its own call's: equal
    assert torch.equal(meta["means2d"].grad, want_grad)
