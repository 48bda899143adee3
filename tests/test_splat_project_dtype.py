"""project_cpu's kernels read float32 inputs directly (every element as float64) and write float32 outputs:
bitwise the results of the float64 path (float32 inputs made float64, outputs and gradients rounded to float32
after), which is what the wrapper did before with copies. Any product left in float32 (an input read without
promotion) or any rounding in another place shows up as a differing bit."""
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.splat.project_cpu import project_sh_cpu


def _inputs(seed, n, C, deg):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.2 + 1e-3
    opac = torch.rand(n, generator=g)
    sh = torch.randn(n, (deg + 1) ** 2, 3, generator=g) * 0.3
    vms = torch.eye(4).repeat(C, 1, 1)
    vms[:, 0, 3] = torch.linspace(-0.05, 0.05, C)
    vms[:, 2, 3] = 0.5
    K = torch.tensor([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
    return means, quats, scales, opac, sh, vms, K


def _run(tensors, deg, weights):
    means, quats, scales, opac, sh, vms, K = [t.clone().requires_grad_(t.dtype.is_floating_point and i not in (3, 6))
                                                 for i, t in enumerate(tensors)]
    m2d, conics, depths, colors, radii = project_sh_cpu(means, quats, scales, opac, sh, vms, K, 64, 48,
                                                        sh_degree=deg)
    outs = (m2d, conics, depths, colors)
    loss = sum((o * w.to(o.dtype)).sum() for o, w in zip(outs, weights))
    loss.backward()
    return [o.detach() for o in outs] + [radii], [means.grad, quats.grad, scales.grad, sh.grad, vms.grad]


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2 ** 31), n=st.integers(1, 300), C=st.integers(1, 4), deg=st.integers(0, 3))
def test_float32_inputs_equal_the_float64_path_rounded(seed, n, C, deg):
    t32 = _inputs(seed, n, C, deg)
    g = torch.Generator().manual_seed(seed + 1)
    weights = [torch.randn(C, n, 2, generator=g), torch.randn(C, n, 3, generator=g), torch.randn(C, n, generator=g),
               torch.randn(C, n, 3, generator=g)]
    # the float64 path: the same float32 values made float64, and the output gradients float32 values too
    t64 = [t.double() for t in t32]
    w64 = [w.double() for w in weights]
    out32, grad32 = _run(t32, deg, weights)
    out64, grad64 = _run(t64, deg, w64)
    for a, b in zip(out32[:4], out64[:4]):
        assert a.dtype == torch.float32 and torch.equal(a, b.float())
    assert torch.equal(out32[4], out64[4])
    for a, b in zip(grad32, grad64):
        assert torch.equal(a, b.float())
    assert np.isfinite(grad32[0].numpy()).all()


@pytest.mark.parametrize("deg", [None, 3])
def test_float64_inputs_stay_float64(deg):
    t = [x.double() for x in _inputs(0, 50, 2, 3)]
    m2d, conics, depths, colors, radii = project_sh_cpu(*t[:4], t[4] if deg else None, t[5], t[6], 64, 48,
                                                        sh_degree=deg)
    assert m2d.dtype == conics.dtype == depths.dtype == torch.float64
    assert (colors is None) == (deg is None) and (colors is None or colors.dtype == torch.float64)


def test_an_input_changed_in_place_before_the_backward_is_an_error():
    """The kernels read the float32 inputs without copying them: a parameter changed in place between the
    forward and the backward must not silently give gradients at the changed values."""
    means, quats, scales, opac, sh, vms, K = _inputs(1, 20, 1, 1)
    means.requires_grad_(True)
    leaf = means
    m2d, _, _, _, _ = project_sh_cpu(leaf, quats, scales, opac, sh, vms, K, 64, 48, sh_degree=1)
    with torch.no_grad():
        leaf.add_(0.01)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        m2d.sum().backward()
