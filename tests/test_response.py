"""ev3dgs/train/response.py (--learn-response): the learned monotone camera response, and the trainer with it.

Independent references: the identity (logits 0) in exact binary arithmetic, the curve's own inverse, a curve
known in closed form (a piecewise-linear truth, which the family holds exactly), and the fixed-decode trainer.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.train.losses import HDR_MAX_DISPLAY, linear_to_srgb_torch, srgb_to_linear_hdr_torch, srgb_to_linear_torch
from ev3dgs.train.response import ResponseCurve

F64 = torch.float64


def _curve(logits) -> ResponseCurve:
    c = ResponseCurve(knots=len(logits), dtype=F64)
    with torch.no_grad():
        c.logits.copy_(torch.as_tensor(logits, dtype=F64))
    return c


def test_identity_at_start_is_exact():
    # every height 1/16 and every knot j/16 are exact binary fractions, so h and h^-1 are the identity bit for
    # bit on [0, 1] and below it (the trainer starts exactly where the fixed decode is)
    c = ResponseCurve(dtype=torch.float32)
    d = torch.cat([torch.linspace(-0.5, 1.0, 4097), torch.rand(10000, generator=torch.Generator().manual_seed(0))])
    assert torch.equal(c(d), d)
    assert torch.equal(c.inverse(d), d)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-4, 4), min_size=1, max_size=24),
       st.lists(st.floats(-0.5, 2.0), min_size=1, max_size=64))
def test_monotone_onto_and_inverse(logits, xs):
    c = _curve(logits)
    x = torch.tensor(xs, dtype=F64)
    y = c(x)
    # h maps [0, 1] onto [0, 1]: the ends are fixed for any logits (the softmax sums to 1 up to rounding)
    ends = c(torch.tensor([0.0, 1.0], dtype=F64))
    assert ends[0].item() == 0.0 and abs(ends[1].item() - 1.0) <= 1e-14
    # strictly increasing: on sorted inputs the outputs are sorted (ties only where inputs tie)
    xs_sorted, _ = torch.sort(x)
    ys = c(xs_sorted)
    assert torch.all(ys[1:] >= ys[:-1])
    # the inverse undoes h; the error bound: one rounding of each step, scaled by the steepest 1/slope
    # (a segment's height is >= e^-8 / 24 of the mean here)
    back = c.inverse(y)
    slope_min = c.heights().min().item() * c.knots
    assert torch.allclose(back, x, rtol=0, atol=64 * np.finfo(np.float64).eps / slope_min * (1 + x.abs().max().item()))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-60, 60), min_size=2, max_size=16))
def test_extreme_logits_give_finite_values_and_gradients(logits):
    # renders from below black to past --hdr's cap, through both decodes the trainer uses and back
    c = _curve(logits)
    x = torch.linspace(-1.0, HDR_MAX_DISPLAY + 1.0, 201, dtype=F64)
    z = c(x)
    loss = z.sum()
    for lin in (srgb_to_linear_torch(z), srgb_to_linear_hdr_torch(z)):
        loss = loss + (c.inverse(linear_to_srgb_torch(lin.mean(dim=0, keepdim=True))) ** 2).sum() + lin.log1p().sum()
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(c.logits.grad).all()


def _truth_frames(seed=0, k=5, hw=(12, 10)):
    """Sub-pose display values d_k (what a camera with response g writes for each sharp instant), the blurry
    frame that camera writes, and g's curve: g^-1 = a known piecewise-linear h (16 knots)."""
    gen = torch.Generator().manual_seed(seed)
    truth = _curve(torch.randn(16, generator=gen, dtype=F64) * 0.5)
    d = torch.rand(k, *hw, 3, generator=gen, dtype=F64) * 0.9 + 0.05
    with torch.no_grad():
        lin = srgb_to_linear_torch(truth(d))
        blurry = truth.inverse(linear_to_srgb_torch(lin.mean(dim=0)))
    return truth, d, blurry, lin


def _loss(curve, d, blurry, lin_true):
    """The two things the trainer asks of h: the blur model (mean in linear light, back through h^-1) matches
    the frame, and log-intensity changes between sub-poses match the events' (here exact)."""
    lin = srgb_to_linear_torch(curve(d))
    avg = curve.inverse(linear_to_srgb_torch(lin.mean(dim=0)))
    dlog = torch.log(lin[1:]) - torch.log(lin[:1])
    return ((avg - blurry) ** 2).mean() + ((dlog - (torch.log(lin_true[1:]) - torch.log(lin_true[:1]))) ** 2).mean()


def test_true_response_is_a_zero_of_the_loss_and_others_are_not():
    truth, d, blurry, lin = _truth_frames()
    at_truth = _curve(truth.logits.detach())
    loss = _loss(at_truth, d, blurry, lin)
    loss.backward()
    # zero loss at the truth up to the float64 rounding of the decode/encode chain, and a zero gradient
    assert loss.item() < 1e-28
    assert at_truth.logits.grad.abs().max().item() < 1e-12
    # the plain sRGB decode (the identity) and random other curves cost more
    assert _loss(ResponseCurve(dtype=F64), d, blurry, lin).item() > 1e-6
    gen = torch.Generator().manual_seed(1)
    for _ in range(5):
        other = _curve(truth.logits.detach() + torch.randn(16, generator=gen, dtype=F64) * 0.3)
        assert _loss(other, d, blurry, lin).item() > 1e-8


def test_gradient_descent_from_srgb_finds_the_response():
    # from the identity, the loss's own gradient leads to the true curve (16 parameters, a smooth problem):
    # the knots come within 1 % of the range of it, and closer than the start
    truth, d, blurry, lin = _truth_frames(seed=3)
    c = ResponseCurve(dtype=F64)
    opt = torch.optim.LBFGS([c.logits], lr=1.0, max_iter=400, tolerance_grad=1e-14, tolerance_change=0,
                            line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = _loss(c, d, blurry, lin)
        loss.backward()
        return loss

    start = (ResponseCurve(dtype=F64).values() - truth.values()).abs().max().item()
    opt.step(closure)
    err = (c.values() - truth.values()).abs().max().item()
    assert err < 0.01 and err < start / 10


def test_state_round_trip_and_table():
    c = _curve([0.3, -0.2, 0.1, 0.0])
    d = ResponseCurve(knots=4, dtype=F64)
    d.load_state_dict(c.state_dict())
    assert torch.equal(d.logits, c.logits)
    with pytest.raises(ValueError, match="logits"):
        ResponseCurve(knots=5).load_state_dict(c.state_dict())
    t = c.table()
    assert t["display"] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert np.all(np.diff(t["decoded_as"]) > 0) and t["decoded_as"][0] == 0.0
    json.dumps(t)
