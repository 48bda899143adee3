"""The cpu backend's backward replays the fragments its forward recorded (cpu._backward); with no
room for them (FRAGMENT_BUDGET) it recomputes them (the same kernel). The two are the same updates in the same
order, so their gradients must be bitwise equal: a fragment the forward records is exactly a pixel the
recomputing backward processes. Checked on random scenes, the hard cases (clamped alpha, opacities near 0 and
1, degenerate covariances), opaque layers that stop whole tiles early, float32 and float64, one and several
cameras."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import ev3dgs.splat.cpu as cpu
from test_splat_backends import render, scene
from test_splat_batched import cameras

F64 = torch.float64


def both(monkeypatch, *args, **kw):
    replay = render("cpu", *args, **kw)
    with monkeypatch.context() as m:
        m.setattr(cpu, "FRAGMENT_BUDGET", 0)
        recompute = render("cpu", *args, **kw)
    return replay, recompute


def assert_bitwise(a, b):
    (ia, aa, ga), (ib, ab, gb) = a, b
    assert torch.equal(ia, ib) and torch.equal(aa, ab)
    for x, y in zip(ga, gb):
        assert x is not None and torch.isfinite(x).all()
        assert torch.equal(x, y)


def opaque_layers(n, width, dtype):
    """Huge, nearly opaque Gaussians (alpha clamped at 0.99) in front of a random cloud: after two of them
    every pixel's transmittance is 1e-4, so whole tiles stop early (n_done == P) and the entries after the
    stop record no fragments (when written: 1123 of the 1162 entries of this scene came after a stop)."""
    params, vm, K = scene(n, width, seed=5, dtype=dtype)
    means, quats, scales, opac, colors = params
    means[:8, 2] = 1.0 + 0.01 * torch.arange(8, dtype=dtype)
    scales[:8] = 5.0
    opac[:8] = 0.999
    return [means, quats, scales, opac, colors], vm, K


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("case", ["random", "hard", "opaque"])
def test_replay_equals_recompute_bitwise(monkeypatch, dtype, case):
    if case == "opaque":
        params, vm, K = opaque_layers(400, 64, dtype)
    else:
        params, vm, K = scene(600, 64, seed=2, dtype=dtype, hard=case == "hard")
    assert_bitwise(*both(monkeypatch, params, vm, K, 64, 48))


def test_replay_equals_recompute_batched(monkeypatch):
    params, _, K = scene(500, 48, seed=3, dtype=torch.float32)
    vms = cameras(4, seed=1, dtype=torch.float32)
    assert_bitwise(*both(monkeypatch, params, vms, K, 48, 40))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 300), w=st.integers(1, 40), h=st.integers(1, 40))
def test_replay_equals_recompute_property(seed, n, w, h):
    params, vm, K = scene(n, max(w, h), seed=seed, dtype=torch.float32)
    replay = render("cpu", params, vm, K, w, h)
    old = cpu.FRAGMENT_BUDGET
    cpu.FRAGMENT_BUDGET = 0
    try:
        recompute = render("cpu", params, vm, K, w, h)
    finally:
        cpu.FRAGMENT_BUDGET = old
    assert_bitwise(replay, recompute)


def test_fragments_recorded_only_when_a_gradient_is_needed(monkeypatch):
    from ev3dgs.splat.rasterize import rasterization

    params, vm, K = scene(200, 32, seed=1, dtype=torch.float32)
    seen = []
    real = cpu._fragment_buffers

    def spy(*a, record, **kw):
        seen.append(record)
        return real(*a, record=record, **kw)

    monkeypatch.setattr(cpu, "_fragment_buffers", spy)
    with torch.no_grad():
        img_nograd = rasterization(*params, vm, K, 32, 32, backend="cpu")[0]
    img = render("cpu", params, vm, K, 32, 32, background=torch.zeros(3))[0]
    assert seen == [False, True]
    assert torch.equal(img_nograd, img)
