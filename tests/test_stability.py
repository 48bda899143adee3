"""Hard-case numerical stability: every numeric entry point driven with extreme inputs.

Each test asserts that outputs (and, for the differentiable parts, gradients of every input) contain no NaN
or Inf, and that nothing raises except the documented errors (ev3dgs.errors.Ev3dgsError subclasses for bad
input, TrainingError for the trainer's NaN guard). Hypothesis runs under the "ev3dgs-stability" profile
below: derandomized (reproducible in CI), no deadline, a modest number of examples per test.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from ev3dgs.errors import Ev3dgsError, InputError
from ev3dgs.logmap import DEFAULT_LOG_KNEE, safe_log, safe_log_torch

settings.register_profile(
    "ev3dgs-stability",
    deadline=None,
    max_examples=30,
    derandomize=True,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
PROFILE = settings.get_profile("ev3dgs-stability")  # applied per test: the global profile stays untouched


def few(n: int):
    return settings(PROFILE, max_examples=n)


def assert_finite(x, what="value"):
    a = x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)
    if a.dtype.kind in "fc":
        bad = ~np.isfinite(a)
        assert not bad.any(), f"{what}: {int(bad.sum())} non-finite entries, e.g. {a[bad][:5]}"


def assert_grads_finite(named: dict, allow_none: tuple = ()):
    """Finite gradients for every input. Names in allow_none may have no .grad at all: the reference
    rasterizer's graph is disconnected from the geometry when no Gaussian is visible (a zero gradient)."""
    for name, t in named.items():
        if t.grad is None and name in allow_none:
            continue
        assert t.grad is not None, f"no gradient reached {name}"
        assert_finite(t.grad, f"grad of {name}")


def grad_or_zero(t):
    return torch.zeros_like(t) if t.grad is None else t.grad


# ===================================================================================== safe_log
KNEE = DEFAULT_LOG_KNEE
F64_SUB = 5e-324
F32_SUB = float(np.float32(1e-45))
SPECIAL_VALUES = [0.0, -0.0, F64_SUB, 1e-310, 1e-300, 1e-30, KNEE, np.nextafter(KNEE, 0.0), np.nextafter(KNEE, 1.0),
                  0.5, 1.0, 65535.0, 1e6, 1e30, 1e300, np.finfo(np.float64).max, -1e-300, -1.0]


@pytest.mark.parametrize("value", SPECIAL_VALUES)
def test_safe_log_numpy_special_values_float64(value):
    for x in (np.float64(value), np.array([value]), np.array([[value, 1.0], [0.0, value]])):
        with np.errstate(over="ignore"):  # x / knee overflows in the discarded lane for x near float max
            out = safe_log(x)
        assert_finite(out, f"safe_log({value!r})")
    # continuity with the pure log at and around the knee, and the documented value at 0
    assert float(safe_log(np.array([0.0]))[0]) == pytest.approx(math.log(KNEE) - 1.0)
    assert float(safe_log(np.array([KNEE]))[0]) == pytest.approx(math.log(KNEE), abs=1e-15)


@pytest.mark.parametrize("value", [0.0, F32_SUB, 1e-38, float(np.float32(KNEE)), 1.0, 65535.0, 1e6, 3e38, -1.0])
def test_safe_log_numpy_float32(value):
    x = np.array([value, 1.0, 0.0], dtype=np.float32)
    with np.errstate(over="ignore"):  # x / knee overflows in the discarded lane for x near float max
        out = safe_log(x)
    assert out.dtype == np.float32
    assert_finite(out, f"safe_log(float32 {value!r})")


@few(40)
@given(st.lists(st.floats(min_value=0.0, max_value=1e300, allow_subnormal=True), min_size=1, max_size=40),
       st.floats(min_value=1e-6, max_value=1.0))
def test_safe_log_is_finite_monotone_and_matches_torch(values, knee):
    x = np.sort(np.array(values, dtype=np.float64))
    out = safe_log(x, knee)
    assert_finite(out, "safe_log")
    assert np.all(np.diff(out) >= 0), "safe_log must be non-decreasing"
    t = torch.tensor(x, requires_grad=True)
    y = safe_log_torch(t, knee)
    assert_finite(y, "safe_log_torch")
    np.testing.assert_allclose(y.detach().numpy(), out, rtol=1e-12, atol=1e-12)
    y.sum().backward()
    g = t.grad.numpy()
    assert_finite(g, "grad safe_log_torch")
    assert np.all(g > 0) and np.all(g <= 1.0 / knee * (1 + 1e-12)), "slope must be in (0, 1/knee]"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_safe_log_torch_values_and_grads_at_extremes(dtype):
    fi = torch.finfo(dtype)
    vals = [0.0, -0.0, fi.tiny, fi.tiny / 4, fi.eps, KNEE, 1.0, 65535.0, 1e6, fi.max / 2, fi.max, -1.0, -100.0]
    if dtype == torch.float64:
        vals += [F64_SUB, 1e-300, 1e300]
    t = torch.tensor(vals, dtype=dtype, requires_grad=True)
    y = safe_log_torch(t)
    assert_finite(y, "safe_log_torch")
    y.sum().backward()
    assert_finite(t.grad, "grad safe_log_torch")
    assert torch.all(t.grad > 0)
    # knee boundaries: just below, at and just above the knee agree (C1-smooth)
    k = torch.tensor(KNEE, dtype=dtype)
    around = torch.stack([torch.nextafter(k, torch.zeros_like(k)), k, torch.nextafter(k, torch.ones_like(k))])
    around.requires_grad_(True)
    v = safe_log_torch(around)
    v.sum().backward()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert float((v.max() - v.min()).detach()) < tol
    assert float(around.grad.max() - around.grad.min()) < 1e-3 * (1.0 / KNEE)


# ===================================================================================== low-pass step
def _psi_reference(h: np.ndarray) -> np.ndarray:
    """1 - (1 - exp(-h)) / h, accurate everywhere (series below 0.1)."""
    h = np.asarray(h, dtype=np.float64)
    series = h / 2 - h**2 / 6 + h**3 / 24 - h**4 / 120 + h**5 / 720 - h**6 / 5040
    direct = 1.0 - (-np.expm1(-np.maximum(h, 0.1))) / np.maximum(h, 0.1)
    return np.where(h < 0.1, series, direct)


@few(40)
@given(st.lists(st.floats(min_value=-12, max_value=6), min_size=1, max_size=16),
       st.floats(-30, 30), st.floats(-30, 30), st.floats(-30, 30))
def test_exact_ramp_step_stable_for_h_from_1e_12_to_1e6(log10_h, y0, x0, x1):
    from ev3dgs.sim.effects.lowpass import exact_ramp_step

    h = 10.0 ** np.array(log10_h)
    y = exact_ramp_step(np.full(h.shape, y0), np.full(h.shape, x0), np.full(h.shape, x1), h)
    assert_finite(y, "exact_ramp_step")
    # the step is a convex combination of y0, x0 and x1
    lo, hi = min(y0, x0, x1), max(y0, x0, x1)
    assert np.all(y >= lo - 1e-9) and np.all(y <= hi + 1e-9)
    # against the accurate reference: the response to a unit ramp from rest is psi(h)
    psi = exact_ramp_step(0.0, 0.0, 1.0, h)
    np.testing.assert_allclose(psi, _psi_reference(h), rtol=1e-7, atol=1e-300)
    # and a step from x0 = x1 relaxes by phi = 1 - exp(-h)
    phi = exact_ramp_step(0.0, 1.0, 1.0, h)
    np.testing.assert_allclose(phi, -np.expm1(-h), rtol=1e-12)


def test_exact_ramp_step_scalar_extremes_and_switch_point():
    from ev3dgs.sim.effects.lowpass import exact_ramp_step

    for h in (1e-12, 1e-9, np.nextafter(1e-4, 0), 1e-4, np.nextafter(1e-4, 1), 1.0, 30.0, 700.0, 1e6):
        for args in ((0.0, 0.0, 1.0), (1.0, -1.0, 2.0), (-20.0, 5.0, 5.0)):
            v = exact_ramp_step(*args, h)
            assert np.isfinite(v)
    below = exact_ramp_step(0.0, 0.0, 1.0, np.nextafter(1e-4, 0))
    above = exact_ramp_step(0.0, 0.0, 1.0, 1e-4)
    assert abs(above - below) / above < 1e-9  # no jump where the series takes over


# ===================================================================================== DVS simulator
EFFECT_NAMES = ("threshold_mismatch", "refractory", "leak", "shot_noise", "lowpass", "color_filter")
RANGES = {"unit": 1.0, "16bit": 65535.0, "hdr": 1e6}


def _dvs_config(effects: dict, threshold: float, knee: float = DEFAULT_LOG_KNEE):
    from ev3dgs.sim.config import (ColorFilter, DVSConfig, Leak, LowPass, Refractory, ShotNoise,
                                   ThresholdMismatch)

    make = {"threshold_mismatch": lambda: ThresholdMismatch(sigma=0.05, min_threshold=1e-3),
            "refractory": lambda: Refractory(period_us=50.0),
            "leak": lambda: Leak(rate_hz=1.0),
            "shot_noise": lambda: ShotNoise(rate_hz=5.0),
            "lowpass": lambda: LowPass(cutoff_hz=300.0),
            "color_filter": lambda: ColorFilter("GRBG")}
    kw = {name: make[name]() for name, on in effects.items() if on}
    return DVSConfig(pos_threshold=threshold, neg_threshold=threshold, log_knee=knee, **kw)


def _check_events(ev, t_lo, t_hi, H, W):
    n = len(ev)
    assert len(ev.x) == len(ev.y) == len(ev.p) == n
    if n:
        assert ev.t.min() >= t_lo and ev.t.max() <= t_hi
        assert np.all(np.diff(ev.t) >= 0), "events must be time-sorted"
        assert ev.x.max() < W and ev.y.max() < H
        assert set(np.unique(ev.p).tolist()) <= {-1, 1}


def _frames_for(kind: str, scale: float, T: int, H: int, W: int, rng: np.random.Generator, dtype):
    if kind == "zero":
        f = np.zeros((T, H, W, 3))
    elif kind == "saturated":
        f = np.full((T, H, W, 3), scale)
    elif kind == "constant":  # empty intervals: nothing changes
        f = np.broadcast_to(rng.uniform(0, scale, (1, H, W, 3)), (T, H, W, 3)).copy()
    elif kind == "jump":  # black -> full range -> black: thousands of events per pixel at small thresholds
        f = np.zeros((T, H, W, 3))
        f[1::2] = scale
    else:  # random over the whole range, with exact zeros and full-scale pixels mixed in
        f = rng.uniform(0, scale, (T, H, W, 3))
        f[rng.random(f.shape) < 0.2] = 0.0
        f[rng.random(f.shape) < 0.2] = scale
    return f.astype(dtype)


@few(40)
@given(effects=st.fixed_dictionaries({n: st.booleans() for n in EFFECT_NAMES}),
       kind=st.sampled_from(["zero", "saturated", "constant", "jump", "random"]),
       rng_name=st.sampled_from(sorted(RANGES)),
       threshold=st.sampled_from([1e-3, 0.2, 10.0]),
       spacing=st.sampled_from([1, 1000, 10**9]),
       T=st.integers(2, 4), H=st.integers(1, 4), W=st.integers(1, 5),
       dtype=st.sampled_from([np.float32, np.float64]),
       t0=st.sampled_from([0, 2**40]),
       seed=st.integers(0, 2**16))
def test_simulator_extreme_inputs_every_effect(effects, kind, rng_name, threshold, spacing, T, H, W, dtype, t0,
                                               seed):
    from ev3dgs.sim import DVSSimulator, simulate_events

    cfg = _dvs_config(effects, threshold)
    rng = np.random.default_rng(seed)
    frames = _frames_for(kind, RANGES[rng_name], T, H, W, rng, dtype)
    t = t0 + spacing * np.arange(T, dtype=np.int64)
    ev = simulate_events(frames, t, cfg, seed=seed)
    _check_events(ev, t[0], t[-1], H, W)
    rep = ev.report
    assert rep.frames == T and rep.events == len(ev)
    assert all(np.isfinite(s) and s >= 0 for s in rep.seconds.values())
    if kind in ("zero", "saturated", "constant") and not (effects["leak"] or effects["shot_noise"]):
        assert len(ev) == 0, "an unchanging scene without leak or shot noise gives no events"
    if kind == "jump" and threshold == 1e-3 and not (effects["refractory"] or effects["lowpass"]):
        assert len(ev) >= 1000 * H * W, "a full-range jump at a 1e-3 threshold gives thousands of events per pixel"
    # chunked feeding gives exactly the same events, and the state stays finite
    sim = DVSSimulator(H, W, cfg, seed=seed)
    parts = [sim.feed(frames[i:i + 1], t[i:i + 1]) for i in range(T)]
    from ev3dgs.events import Events

    chunked = Events.concatenate(parts)
    for a in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(getattr(chunked, a), getattr(ev, a))
    assert_finite(sim.ref, "simulator reference")
    assert_finite(sim.signal_prev, "simulator signal")
    if sim.blocked_until.size:
        assert_finite(sim.blocked_until, "refractory state")


@pytest.mark.parametrize("threshold", [1e-3, 10.0])
@pytest.mark.parametrize("all_effects", [False, True])
def test_simulator_thousands_of_events_per_pixel(threshold, all_effects):
    from ev3dgs.sim import simulate_events

    effects = {n: all_effects for n in EFFECT_NAMES}
    effects["refractory"] = False  # the refractory hold would (correctly) swallow the burst
    cfg = _dvs_config(effects, threshold)
    H, W = 3, 4
    frames = np.zeros((3, H, W, 3))
    frames[1] = 1e6  # HDR jump: ~20 log units
    t = np.array([0, 1, 2], dtype=np.int64)  # 1-us frame spacing: all the burst within one microsecond
    ev = simulate_events(frames, t, cfg)
    _check_events(ev, 0, 2, H, W)
    if threshold == 1e-3:
        per_pixel = len(ev) / (H * W)
        # up and back down, ~18 log units each way / 1e-3 (the 1-us photoreceptor low-pass and the colour
        # filter's dimmer channels take some of it when the effects are on)
        assert per_pixel > (5_000 if all_effects else 2 * 15_000), per_pixel
        on = ev.p > 0
        assert on.sum() > 0 and (~on).sum() > 0


def test_simulator_many_empty_intervals_and_huge_spacing():
    from ev3dgs.sim import DVSSimulator
    from ev3dgs.sim.config import DVSConfig, Leak, LowPass, Refractory

    cfg = DVSConfig(leak=Leak(rate_hz=0.01), lowpass=LowPass(), refractory=Refractory())
    sim = DVSSimulator(2, 2, cfg)
    frames = np.full((50, 2, 2), 0.5)
    t = np.cumsum(np.r_[0, np.full(49, 10**10)]).astype(np.int64)  # ~3 hours between frames
    ev = sim.feed(frames, t)
    _check_events(ev, t[0], t[-1], 2, 2)
    assert_finite(sim.ref)
    assert len(ev) > 0  # leak over hours of a static scene does fire


@pytest.mark.parametrize("bad", ["nan", "inf", "negative", "duplicate_t", "int_frames", "backwards"])
def test_simulator_rejects_bad_input_with_input_error(bad):
    from ev3dgs.sim import DVSSimulator

    frames = np.full((3, 2, 2), 0.5)
    t = np.array([0, 10, 20], dtype=np.int64)
    if bad == "nan":
        frames[1, 0, 0] = np.nan
    elif bad == "inf":
        frames[2, 1, 1] = np.inf
    elif bad == "negative":
        frames[0, 0, 1] = -1e-9
    elif bad == "duplicate_t":
        t = np.array([0, 10, 10])
    elif bad == "int_frames":
        frames = (frames * 255).astype(np.uint16)
    sim = DVSSimulator(2, 2)
    if bad == "backwards":
        sim.feed(frames, t)
    with pytest.raises(InputError):
        sim.feed(frames, t)


# ===================================================================================== blur / ISP
MOSAICS = ["none", "RGGB", "BGGR", "GRBG", "GBRG"]


@few(30)
@given(mosaic=st.sampled_from(MOSAICS),
       kind=st.sampled_from(["zero", "saturated", "hdr", "u8_black", "u8_white", "u8_random", "random"]),
       S=st.integers(1, 3), H=st.integers(2, 6), W=st.integers(2, 6),
       iso=st.sampled_from([None, 1.0, 100.0, 1e5, 1e6]),   # the ends of its physical range
       seed=st.integers(0, 1000))
def test_blur_frames_extremes(mosaic, kind, S, H, W, iso, seed):
    from ev3dgs.sim.blur import blur_frames
    from ev3dgs.sim.config import ISPConfig, SensorNoise

    rng = np.random.default_rng(seed)
    shape = (S, H, W, 3)
    frames = {"zero": lambda: np.zeros(shape),
              "saturated": lambda: np.ones(shape),
              "hdr": lambda: np.where(rng.random(shape) < 0.5, 1e6, 0.0),
              "u8_black": lambda: np.zeros(shape, np.uint8),
              "u8_white": lambda: np.full(shape, 255, np.uint8),
              "u8_random": lambda: rng.integers(0, 256, shape).astype(np.uint8),
              "random": lambda: rng.uniform(0, 2.0, shape).astype(np.float32)}[kind]()
    noise = None if iso is None else SensorNoise(iso=iso)
    out = blur_frames(frames, ISPConfig(mosaic=mosaic), noise, seed=seed)
    assert out.dtype == np.uint8 and out.shape == (H, W, 3)
    if noise is None and kind in ("zero", "u8_black"):
        assert out.max() == 0
    if noise is None and kind in ("saturated", "u8_white", "hdr") and mosaic == "none":
        if kind != "hdr":
            assert out.min() >= 254  # white stays white


@pytest.mark.parametrize("mosaic", MOSAICS)
@pytest.mark.parametrize("value", [0.0, 1e-300, 1.0, 65535.0, 1e6, 1e300])
def test_isp_forward_inverse_extremes(mosaic, value):
    from ev3dgs.sim.config import ISPConfig
    from ev3dgs.sim.isp import forward_isp, inverse_isp, linear_to_srgb, srgb_to_linear

    cfg = ISPConfig(mosaic=mosaic)
    img = np.full((4, 6, 3), value)
    img[0, 0] = 0.0
    raw = inverse_isp(img, cfg)
    assert_finite(raw, "inverse_isp")
    out = forward_isp(raw, cfg)
    assert out.dtype == np.uint8 and out.shape == (4, 6, 3)
    # raw far out of range (both signs) is clipped as a sensor saturates, not propagated
    wild = np.where(np.indices(raw.shape).sum(0) % 2 == 0, -1e300, 1e300)
    assert forward_isp(wild, cfg).dtype == np.uint8
    lin = srgb_to_linear(np.clip(img, 0, 1))
    assert_finite(lin)
    s = linear_to_srgb(img)
    assert_finite(s)
    assert s.min() >= 0 and s.max() <= 1


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0])
def test_isp_rejects_non_finite_or_negative_with_input_error(bad):
    from ev3dgs.sim.blur import blur_frames
    from ev3dgs.sim.isp import forward_isp, inverse_isp

    img = np.full((2, 2, 3), 0.5)
    img[1, 1, 2] = bad
    with pytest.raises(InputError):
        inverse_isp(img)
    with pytest.raises(InputError):
        blur_frames(img[None])
    if not bad < 0:
        with pytest.raises(InputError):
            forward_isp(img)


# ===================================================================================== rasterization
GAUSS_KINDS = ["normal", "tiny", "huge", "transparent", "nearly_transparent", "opaque", "camera_inside",
               "degenerate", "at_near", "just_past_near", "behind", "off_screen", "zero_quat", "nan_mean",
               "inf_mean", "huge_colour"]
NEAR = 0.01
GEOMETRY = ("means", "quats", "scales", "opacities")


def _gaussian_row(kind: str, rng: np.random.Generator):
    mean = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(1.5, 4.0)])
    q = rng.normal(size=4)
    scale = rng.uniform(0.05, 0.5, 3)
    op = rng.uniform(0.2, 0.9)
    col = rng.uniform(0, 1, 3)
    if kind == "tiny":
        scale = np.full(3, 1e-8)
    elif kind == "huge":
        scale = np.full(3, 1e4)
    elif kind == "transparent":
        op = 0.0
    elif kind == "nearly_transparent":
        op = 1e-9
    elif kind == "opaque":
        op = 1.0
    elif kind == "camera_inside":
        mean = np.array([0.0, 0.0, 0.02])
        scale = np.full(3, 1.0)
    elif kind == "degenerate":
        scale = np.array([1e-12, 1e-12, rng.uniform(0.1, 1.0)])
    elif kind == "at_near":
        mean[2] = NEAR
    elif kind == "just_past_near":
        mean[2] = NEAR * (1 + 1e-6)
        mean[:2] *= 1e-3
    elif kind == "behind":
        mean[2] = -rng.uniform(0.0, 3.0)
    elif kind == "off_screen":
        mean[0] = rng.choice([-1.0, 1.0]) * 1e6
    elif kind == "zero_quat":
        q = np.zeros(4)
    elif kind == "nan_mean":
        mean[rng.integers(3)] = np.nan
    elif kind == "inf_mean":
        mean[rng.integers(3)] = rng.choice([-np.inf, np.inf])
    elif kind == "huge_colour":
        col = rng.uniform(-1e3, 1e3, 3)
    return mean, q, scale, op, col


def _render(rows, backend, dtype, W, H, bg, render_mode="RGB", cam_rot=None):
    from ev3dgs.geometry import intrinsics
    from ev3dgs.splat.rasterize import rasterization

    means, quats, scales, ops, cols = (torch.tensor(np.array(a), dtype=dtype, requires_grad=True)
                                       for a in zip(*rows))
    vm = torch.eye(4, dtype=dtype)
    if cam_rot is not None:
        vm[:3, :3] = torch.as_tensor(cam_rot, dtype=dtype)
    K = torch.as_tensor(intrinsics(W, H, 60.0), dtype=dtype)
    background = torch.tensor(bg, dtype=dtype, requires_grad=True)
    image, alpha, meta = rasterization(means, quats, scales, ops, cols, vm, K, W, H, near_plane=NEAR,
                                       background=background, render_mode=render_mode, backend=backend)
    return image, alpha, meta, {"means": means, "quats": quats, "scales": scales, "opacities": ops,
                                "colors": cols, "background": background}


@few(40)
@given(kinds=st.lists(st.sampled_from(GAUSS_KINDS), min_size=1, max_size=7),
       backend=st.sampled_from(["cpu", "reference"]),
       dtype=st.sampled_from([torch.float32, torch.float64]),
       W=st.integers(1, 20), H=st.integers(1, 20),
       bg=st.sampled_from([(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.2, 0.5, 0.9)]),
       render_mode=st.sampled_from(["RGB", "RGB+D"]),
       seed=st.integers(0, 2**16))
def test_rasterization_extreme_gaussians_values_and_grads(kinds, backend, dtype, W, H, bg, render_mode, seed):
    rng = np.random.default_rng(seed)
    rows = [_gaussian_row(k, rng) for k in kinds]
    image, alpha, meta, inputs = _render(rows, backend, dtype, W, H, bg, render_mode)
    D = 4 if render_mode == "RGB+D" else 3
    assert image.shape == (H, W, D) and alpha.shape == (H, W, 1)
    assert_finite(image, "image")
    assert_finite(alpha, "alpha")
    assert float(alpha.detach().min()) >= 0.0 and float(alpha.detach().max()) <= 1.0
    radii = meta["radii"]
    bad_rows = torch.tensor([k in ("nan_mean", "inf_mean", "at_near", "behind", "transparent", "nearly_transparent",
                                   "off_screen") for k in kinds])
    assert torch.all(radii[bad_rows] == 0), "non-finite, behind-the-camera, transparent and off-screen rows are culled"
    weights = torch.as_tensor(np.random.default_rng(seed + 1).uniform(-1, 1, (H, W, D)), dtype=dtype)
    loss = (image * weights).sum() + 0.5 * alpha.sum()
    loss.backward()
    assert_grads_finite(inputs, allow_none=GEOMETRY)
    nonfinite = torch.tensor([k in ("nan_mean", "inf_mean") for k in kinds])
    if nonfinite.any():
        for name in ("means", "quats", "scales", "opacities", "colors"):
            g = grad_or_zero(inputs[name])[nonfinite]
            assert torch.all(g == 0), f"culled non-finite rows must get zero {name} gradient"


@few(25)
@given(kinds=st.lists(st.sampled_from([k for k in GAUSS_KINDS if k not in ("huge_colour",)]), min_size=1, max_size=6),
       W=st.integers(1, 18), H=st.integers(1, 18), seed=st.integers(0, 2**16))
def test_rasterization_cpu_matches_reference_on_extremes_float64(kinds, W, H, seed):
    rng = np.random.default_rng(seed)
    rows = [_gaussian_row(k, rng) for k in kinds]
    outs = {}
    for backend in ("cpu", "reference"):
        image, alpha, _, inputs = _render(rows, backend, torch.float64, W, H, (0.3, 0.6, 0.9))
        (image.sum() + alpha.sum()).backward()
        outs[backend] = (image.detach(), alpha.detach(), {k: grad_or_zero(v).clone() for k, v in inputs.items()})
    (ic, ac, gc), (ir, ar, gr) = outs["cpu"], outs["reference"]
    torch.testing.assert_close(ic, ir, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(ac, ar, rtol=1e-7, atol=1e-9)
    for name in ("colors", "opacities", "background"):
        torch.testing.assert_close(gc[name], gr[name], rtol=1e-5, atol=1e-7, msg=f"grad of {name}")


@pytest.mark.parametrize("backend", ["cpu", "reference"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("opacity", [0.0, 1e-9, 1.0 / 255.0 - 1e-7, 1.0])
def test_rasterization_uniform_scenes(backend, dtype, opacity):
    """All-transparent and all-opaque scenes, with the camera inside a huge Gaussian as well."""
    rng = np.random.default_rng(0)
    rows = [_gaussian_row("normal", rng) for _ in range(4)] + [_gaussian_row("camera_inside", rng)]
    rows = [(m, q, s, opacity, c) for (m, q, s, _, c) in rows]
    image, alpha, meta, inputs = _render(rows, backend, dtype, 12, 9, (0.25, 0.5, 0.75))
    assert_finite(image)
    assert_finite(alpha)
    if opacity < 1.0 / 255.0:
        assert torch.all(meta["radii"] == 0)
        assert float(alpha.detach().abs().max()) == 0.0
        torch.testing.assert_close(image, torch.tensor([0.25, 0.5, 0.75], dtype=dtype).expand(9, 12, 3))
    (image.sum() + alpha.sum()).backward()
    assert_grads_finite(inputs, allow_none=GEOMETRY)
    if opacity < 1.0 / 255.0:
        for name in GEOMETRY:
            assert float(grad_or_zero(inputs[name]).abs().max()) == 0.0


FINITE_EXTREMES = {  # (mean, quat, scales, opacity): finite but far outside any sane range
    "x_1e30": ([1e30, 0, 2], [1, 0, 0, 0], [0.1] * 3, 0.5),
    "x_3e38": ([3e38, 0, 2], [1, 0, 0, 0], [0.1] * 3, 0.5),
    "far_and_huge": ([0, 0, 1e9], [1, 0, 0, 0], [1e8] * 3, 0.5),
    "huge_at_near_plane": ([0, 0, 0.0101], [1, 2, 3, 4], [1e4] * 3, 1.0),
    "huge_needle": ([0, 0, 0.5], [1, 2, 3, 4], [1e4, 1e-12, 1e-12], 1.0),
    "huge_disc": ([0, 0, 0.5], [1, 2, 3, 4], [1e4, 1e4, 1e-12], 1.0),
    "scale_1e6": ([0, 0, 2], [1, 2, 3, 4], [1e6] * 3, 1.0),
    "scale_1e-30": ([0, 0, 2], [1, 2, 3, 4], [1e-30] * 3, 1.0),
    "quat_1e-30": ([0, 0, 2], [1e-30, 0, 0, 0], [0.3, 0.1, 0.01], 1.0),
    "quat_1e30": ([0, 0, 2], [1e30, 1e30, 0, 0], [0.3, 0.1, 0.01], 1.0),
    "just_past_near": ([1e-3, 0, 0.01 + 1e-9], [1, 0, 0, 0], [0.1] * 3, 0.9),
}


@pytest.mark.parametrize("backend", ["cpu", "reference"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", sorted(FINITE_EXTREMES))
def test_rasterization_finite_extremes(case, dtype, backend):
    m, q, s, o = (np.asarray(v, float) for v in FINITE_EXTREMES[case])
    rows = [(m, q, s, float(o), np.array([1.0, 0.5, 0.0]))] * 3 + [_gaussian_row("normal", np.random.default_rng(1))]
    image, alpha, meta, inputs = _render(rows, backend, dtype, 16, 12, (0.2, 0.3, 0.4))
    assert_finite(image, "image")
    assert_finite(alpha, "alpha")
    assert int(meta["radii"].min()) >= 0
    (image.sum() + alpha.sum()).backward()
    assert_grads_finite(inputs, allow_none=GEOMETRY)


# ===================================================================================== losses
def _renders(kind: str, K: int, H: int, W: int, rng, dtype=torch.float32):
    shape = (K, H, W, 3)
    if kind == "black":
        x = np.zeros(shape)
    elif kind == "white":
        x = np.ones(shape)
    elif kind == "negative":
        x = -rng.uniform(0, 5, shape)
    elif kind == "over":
        x = rng.uniform(1, 50, shape)
    elif kind == "huge":
        x = rng.uniform(-1e3, 1e3, shape)
    elif kind == "identical":  # nearly identical sub-frame poses: identical renders
        x = np.broadcast_to(rng.uniform(0, 1, (1, H, W, 3)), shape).copy()
    elif kind == "nearly_identical":
        x = np.clip(rng.uniform(0, 1, (1, H, W, 3)) + 1e-7 * rng.normal(size=shape), 0, 1)
    else:
        x = rng.uniform(-0.2, 1.2, shape)
    return torch.tensor(x, dtype=dtype, requires_grad=True)


RENDER_KINDS = ["black", "white", "negative", "over", "huge", "identical", "nearly_identical", "random"]


@few(40)
@given(kind=st.sampled_from(RENDER_KINDS), target=st.sampled_from(["black", "white", "random"]),
       K=st.integers(1, 5), H=st.integers(1, 14), W=st.integers(1, 14),
       space=st.sampled_from(["srgb", "linear"]), lam=st.sampled_from([0.0, 0.2, 1.0]),
       dtype=st.sampled_from([torch.float32, torch.float64]), seed=st.integers(0, 2**16))
def test_blur_loss_extreme_renders(kind, target, K, H, W, space, lam, dtype, seed):
    from ev3dgs.train.losses import blur_loss

    rng = np.random.default_rng(seed)
    r = _renders(kind, K, H, W, rng, dtype)
    tgt = {"black": torch.zeros(H, W, 3), "white": torch.ones(H, W, 3),
           "random": torch.rand(H, W, 3, generator=torch.Generator().manual_seed(seed))}[target]
    loss = blur_loss(r, tgt, lam, space)
    assert_finite(loss, "blur_loss")
    assert float(loss.detach()) >= -1e-6 * max(1.0, lam)  # MSE >= 0 and 1 - SSIM >= 0 (up to rounding)
    loss.backward()
    assert_grads_finite({"renders": r})


@few(30)
@given(kind=st.sampled_from(RENDER_KINDS), H=st.integers(1, 12), W=st.integers(1, 12),
       dtype=st.sampled_from([torch.float32, torch.float64]), seed=st.integers(0, 2**16))
def test_ssim_extremes(kind, H, W, dtype, seed):
    from ev3dgs.train.losses import ssim

    rng = np.random.default_rng(seed)
    a = _renders(kind, 1, H, W, rng, dtype)[0].detach().requires_grad_(True)
    b = _renders("random", 1, H, W, rng, dtype)[0]
    s = ssim(a, b)
    assert_finite(s, "ssim")
    s.backward()
    assert_grads_finite({"a": a})
    if kind in ("black", "white"):
        same = ssim(a.detach(), a.detach())
        assert float(same) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_srgb_conversions_extremes(dtype):
    from ev3dgs.train.losses import linear_to_srgb_torch, srgb_to_linear_torch

    fi = torch.finfo(dtype)
    vals = [0.0, -0.0, fi.tiny, 0.0031308, 0.04045, 0.5, 1.0, 2.0, 50.0, -1.0, -1e6, 1e6]
    for f, big in ((srgb_to_linear_torch, 1e10 if dtype == torch.float32 else 1e100),
                   (linear_to_srgb_torch, fi.max)):
        x = torch.tensor(vals + [big], dtype=dtype, requires_grad=True)
        y = f(x)
        assert_finite(y, f.__name__)
        y.sum().backward()
        assert_finite(x.grad, f"grad {f.__name__}")
        assert torch.all(x.grad >= 0)
    grid = torch.linspace(0, 1, 2001, dtype=dtype)
    back = linear_to_srgb_torch(srgb_to_linear_torch(grid))
    torch.testing.assert_close(back, grid, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
    assert torch.all(torch.diff(srgb_to_linear_torch(grid)) >= 0)


@few(40)
@given(kind=st.sampled_from(RENDER_KINDS), K=st.integers(2, 5), H=st.integers(1, 8), W=st.integers(1, 8),
       cf=st.sampled_from(["none", "RGGB", "BGGR", "GRBG", "GBRG"]),
       targets=st.sampled_from(["empty", "thousands", "mixed"]),
       theta=st.sampled_from([1e-3, 1e-2, 0.2, 5.0]), learn=st.booleans(),
       dtype=st.sampled_from([torch.float32, torch.float64]), seed=st.integers(0, 2**16),
       convention=st.sampled_from(["random_phase", "exact_reference"]))
def test_event_loss_extremes(kind, K, H, W, cf, targets, theta, learn, dtype, seed, convention):
    from ev3dgs.train.events import pair_list, pose_counts
    from ev3dgs.train.losses import log_intensity, pose_event_loss

    rng = np.random.default_rng(seed)
    r = _renders(kind, K, H, W, rng, dtype)
    log_l = log_intensity(r, cf)
    assert_finite(log_l, "log_intensity")
    if targets == "empty":
        bins = torch.zeros(K - 1, H, W)
    elif targets == "thousands":
        bins = torch.as_tensor(rng.choice([-1, 1], (K - 1, H, W)) * rng.integers(1000, 20000, (K - 1, H, W)),
                               dtype=torch.float32)
    else:
        bins = torch.as_tensor(rng.integers(-3, 4, (K - 1, H, W)), dtype=torch.float32)
    pairs = pair_list(K)
    counts = pose_counts(torch.stack([bins.clamp(min=0), (-bins).clamp(min=0)], dim=1))  # ON/OFF, cumulative
    if learn:  # learnable thresholds, parametrised as the trainer does (exp of a log threshold)
        lp = torch.tensor(math.log(theta), requires_grad=True)
        ln = torch.tensor(math.log(theta * 1.5), requires_grad=True)
        tp, tn = lp.exp(), ln.exp()
    else:
        tp, tn = theta, theta * 1.5
    loss = pose_event_loss(log_l, counts, pairs, tp, tn, convention)
    assert_finite(loss, "pose_event_loss")
    assert float(loss.detach()) >= 0
    loss.backward()
    assert_grads_finite({"renders": r})
    if learn:
        assert_grads_finite({"log theta_pos": lp, "log theta_neg": ln})
    if kind == "identical" and targets == "empty":
        # identical sub-frames: zero up to torch's SIMD-vs-scalar-tail rounding of the sRGB pow (1 ulp)
        assert float(loss.detach()) < 1e-6


def test_event_loss_with_raw_near_zero_threshold_tensors():
    from ev3dgs.train.events import pair_list
    from ev3dgs.train.losses import log_intensity, pose_event_loss

    r = torch.zeros(3, 4, 4, 3, requires_grad=True)  # black, identical sub-frames: delta == 0 exactly
    pairs = pair_list(3)
    tp = torch.tensor(1e-6, requires_grad=True)
    tn = torch.tensor(1e-6, requires_grad=True)
    no_events = torch.zeros(3, 2, 4, 4)
    for convention in ("random_phase", "exact_reference"):  # no events: both expect no change
        log_l = log_intensity(r)
        loss = pose_event_loss(log_l, no_events, pairs, tp, tn, convention)
        loss.backward()
        assert float(loss.detach()) == 0.0
        assert_grads_finite({"renders": r, "theta_pos": tp, "theta_neg": tn})
    empty = pose_event_loss(log_l, no_events, [], tp, tn)
    assert float(empty.detach()) == 0.0


# ===================================================================================== event binning
def _bins_reference(t, x, y, p, times, H, W):
    n_views, K = times.shape
    out = np.zeros((n_views, K - 1, H, W))
    for v in range(n_views):
        row = times[v]
        for ti, xi, yi, pi in zip(t, x, y, p):
            if ti < row[0] or ti > row[-1]:
                continue
            b = min(int(np.searchsorted(row, ti, side="right")) - 1, K - 2)
            out[v, b, yi, xi] += pi
    return out


@few(40)
@given(n=st.integers(0, 60), K=st.integers(2, 6), n_views=st.integers(1, 3),
       mode=st.sampled_from(["zero_length", "one_timestamp", "at_ends", "random", "duplicate_times"]),
       seed=st.integers(0, 2**16))
def test_bin_signed_events_hard_windows(n, K, n_views, mode, seed):
    from ev3dgs.train.events import bin_signed_events, sub_pose_times

    rng = np.random.default_rng(seed)
    H, W = 3, 4
    starts = rng.integers(0, 1000, n_views)
    if mode == "zero_length":
        exposure = np.stack([starts, starts], 1)
    else:
        exposure = np.stack([starts, starts + rng.integers(1, 500, n_views)], 1)
    times = sub_pose_times(exposure, K)
    if mode == "duplicate_times":
        times = np.sort(rng.integers(0, 50, (n_views, K)), axis=1)
    if mode == "one_timestamp":
        t = np.full(n, int(rng.choice(times.ravel())), np.int64)
    elif mode == "at_ends":
        t = np.sort(rng.choice(np.r_[times[:, 0], times[:, -1], times[:, -1] + 1], n)).astype(np.int64)
    else:
        t = np.sort(rng.integers(0, 1600, n)).astype(np.int64)
    x = rng.integers(0, W, n).astype(np.uint16)
    y = rng.integers(0, H, n).astype(np.uint16)
    p = rng.choice([-1, 1], n).astype(np.int8)
    t0, x0, p0 = t.copy(), x.copy(), p.copy()
    out = bin_signed_events(t, x, y, p, times, H, W)
    assert out.shape == (n_views, K - 1, H, W) and out.dtype == np.float32
    assert_finite(out)
    np.testing.assert_array_equal(out, _bins_reference(t, x, y, p, times, H, W))
    np.testing.assert_array_equal(t, t0)
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(p, p0)


def test_bin_signed_events_thousands_per_pixel_and_empty():
    from ev3dgs.train.events import bin_signed_events, pair_list, pair_targets

    n = 200_000
    t = np.full(n, 500, np.int64)  # all at one timestamp, all on one pixel
    x = np.zeros(n, np.uint16)
    y = np.zeros(n, np.uint16)
    p = np.ones(n, np.int8)
    times = np.array([[0, 500, 500, 1000], [500, 500, 500, 500], [600, 700, 800, 900]])
    out = bin_signed_events(t, x, y, p, times, 2, 2)
    assert out[0, 1, 0, 0] == 0 and out[0, 2, 0, 0] == n  # [500, 500) is empty, [500, 1000] holds them
    assert out[1, 2, 0, 0] == n  # zero-length exposure: the closed last bin
    assert out[2].sum() == 0
    empty = bin_signed_events(t[:0], x[:0], y[:0], p[:0], times, 2, 2)
    assert not empty.any()
    tg = pair_targets(torch.from_numpy(out[0]), pair_list(4))
    assert_finite(tg)
    assert float(tg.abs().max()) == n


def test_sub_pose_times_zero_length_and_huge_spans():
    from ev3dgs.train.events import sub_pose_times

    exp = np.array([[5, 5], [0, 10**15], [10**12, 10**12 + 1]])
    for K in (1, 2, 5, 64):
        times = sub_pose_times(exp, K)
        assert np.all(np.diff(times, axis=1) >= 0)
        assert np.all(times[:, 0] >= exp[:, 0]) and np.all(times[:, -1] <= exp[:, 1])
        if K > 1:
            np.testing.assert_array_equal(times[:, -1], exp[:, 1])
        assert np.all(times[0] == 5)


# ===================================================================================== poses
def _rot(axis, angle):
    from ev3dgs.geometry import rotvec_to_matrix

    axis = np.asarray(axis, float)
    return rotvec_to_matrix(axis / np.linalg.norm(axis) * angle)


def _assert_rigid(T):
    assert_finite(T, "pose")
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


@few(40)
@given(axis=st.tuples(*[st.floats(-1, 1)] * 3), angle=st.floats(0, math.pi),
       dangle=st.sampled_from([0.0, 1e-15, 1e-12, 1e-8, 1e-4, 0.0316, 0.05, math.pi - 1e-9, math.pi]),
       dt=st.sampled_from([1, 2, 10**9]), frac=st.floats(0, 1), zero_span=st.booleans())
def test_interpolate_pose_nearly_identical_and_zero_spans(axis, angle, dangle, dt, frac, zero_span):
    from ev3dgs.geometry import interpolate_pose

    assume(np.linalg.norm(axis) > 1e-3)
    A = np.eye(4)
    A[:3, :3] = _rot(axis, angle)
    A[:3, 3] = [1.0, -2.0, 3.0]
    B = np.eye(4)
    B[:3, :3] = _rot([0.3, -0.2, 0.9], dangle) @ A[:3, :3]
    B[:3, 3] = A[:3, 3] + 1e-12
    if zero_span:  # a duplicated sample time: [t0, t0, t1]
        poses, pose_t = np.stack([A, A, B]), np.array([0, 0, dt])
    else:
        poses, pose_t = np.stack([A, B]), np.array([0, dt])
    for t in (-1, 0, frac * dt, dt, dt + 1, np.nextafter(float(dt), 0.0)):
        T = interpolate_pose(poses, pose_t, t)
        _assert_rigid(T)
    np.testing.assert_allclose(interpolate_pose(poses, pose_t, 0), A, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(poses, pose_t, dt), B, atol=1e-12)


@few(40)
@given(q=st.tuples(*[st.floats(-1, 1)] * 4), a=st.floats(0, 1),
       rel=st.sampled_from(["identical", "opposite", "nearly_identical", "nearly_opposite", "at_switch",
                            "orthogonal"]))
def test_slerp_identical_and_opposite_quaternions(q, a, rel):
    from ev3dgs.geometry import matrix_to_quat, quat_to_matrix, slerp

    q0 = np.asarray(q)
    assume(np.linalg.norm(q0) > 1e-3)
    q0 = q0 / np.linalg.norm(q0)
    perp = np.array([-q0[1], q0[0], -q0[3], q0[2]])  # orthogonal to q0
    q1 = {"identical": q0, "opposite": -q0,
          "nearly_identical": q0 + 1e-12 * perp, "nearly_opposite": -q0 + 1e-12 * perp,
          "at_switch": math.cos(math.acos(0.9995)) * q0 + math.sin(math.acos(0.9995)) * perp,
          "orthogonal": perp}[rel]
    q1 = q1 / np.linalg.norm(q1)
    out = slerp(q0, q1, a)
    assert_finite(out, "slerp")
    assert np.linalg.norm(out) == pytest.approx(1.0, abs=1e-9)
    if rel in ("identical", "opposite"):
        assert abs(abs(float(np.dot(out, q0))) - 1.0) < 1e-12  # the same rotation
    R = quat_to_matrix(out)
    back = matrix_to_quat(R)
    assert_finite(back)
    assert abs(abs(float(np.dot(back, out))) - 1.0) < 1e-9


@pytest.mark.parametrize("angle", [0.0, 1e-300, 1e-9, 1e-8, np.nextafter(1e-8, 1), 1.0, math.pi - 1e-12, math.pi])
def test_rotation_conversions_at_the_branch_points(angle):
    from ev3dgs.geometry import matrix_to_quat, quat_to_matrix

    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [-1, 2, 0.5]):
        R = _rot(axis, angle)
        assert_finite(R)
        q = matrix_to_quat(R)
        assert_finite(q)
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-9)


# ===================================================================================== training steps
TW, TH = 24, 18


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """3 views of random blurry frames with 3 pose samples each and simulated events: tiny but complete."""
    from ev3dgs import schema
    from ev3dgs.events import Events
    from ev3dgs.geometry import intrinsics, look_at
    from ev3dgs.sim import DVSSimulator

    rng = np.random.default_rng(7)
    K = intrinsics(TW, TH, 55)
    views, S = 3, 3
    imgs, poses, pose_t, exposure, parts = [], [], [], [], []
    sim = DVSSimulator(TH, TW)
    for v in range(views):
        az = 2 * np.pi * v / views
        eye = 3.0 * np.array([np.cos(az), np.sin(az), 0.4])
        start = v * 200_000
        t = start + np.linspace(0, 100_000, S).astype(np.int64)
        poses.append(np.stack([look_at(eye + 0.05 * k, [0, 0, 0]) for k in range(S)]))
        pose_t.append(t)
        exposure.append((t[0], t[-1]))
        frames = rng.uniform(0, 1, (S, TH, TW, 3))
        frames[:, : TH // 2] = 0.0  # black half: the lin-log branch
        frames[:, -2:] = 1.0  # saturated rows
        sim.restart()
        parts.append(sim.feed(frames, t))
        imgs.append((rng.uniform(0, 1, (TH, TW, 3)) * 255).astype(np.uint8))
    ev = Events.concatenate(parts)
    sc = schema.Scene(
        name="tiny", source="test", camera=schema.Camera(TW, TH, K=K, background=(0.0, 0.0, 0.0)), events=ev,
        sensor=schema.EventSensor(), bounds=np.array([[-0.6] * 3, [0.6] * 3]),
        train=schema.Train(images=np.stack(imgs), exposure=np.array(exposure), poses=np.stack(poses),
                           pose_t=np.stack(pose_t)))
    path = tmp_path_factory.mktemp("stability") / "tiny.h5"
    schema.write(sc, path)
    assert len(ev) > 0
    return str(path)


@pytest.mark.parametrize("lr_factor", [1e3, 1e-6, 1e9])
@pytest.mark.parametrize("variant", ["plain", "learned_thresholds_linear"])
def test_training_with_extreme_learning_rates(tiny_scene, tmp_path, lr_factor, variant):
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.trainer import Trainer, TrainingError

    kw = dict(scene=tiny_scene, iterations=5, subposes=3, init_points=60, threads=1, seed=1, sh_degree=1,
              sh_interval=2, checkpoint_every=100, device="cpu", backend="cpu", event_weight=1.0)
    if variant != "plain":
        kw.update(learn_thresholds=True, blur_space="linear")
    tr = Trainer(TrainConfig(**kw), tmp_path / "run", quiet=True)
    for opt in tr.optimizers.values():
        for group in opt.param_groups:
            group["lr"] *= lr_factor
    tr.means_lr0 *= lr_factor  # the trainer re-derives the means lr from this every step
    if tr.term("events").threshold_opt is not None:
        for group in tr.term("events").threshold_opt.param_groups:
            group["lr"] *= lr_factor
    stopped = None
    for _ in range(5):
        try:
            rec = tr.train_step()
        except TrainingError as e:  # the documented NaN guard
            stopped = e
            break
        assert math.isfinite(rec["loss"]) and math.isfinite(rec["blur"]) and math.isfinite(rec["event"])
        for name, p in tr.model.params.items():
            assert_finite(p, f"parameter {name} after step {tr.step}")
        for name, th in tr.thresholds.items():
            assert_finite(th, f"threshold {name}")
    for name, p in tr.model.params.items():  # never a NaN silently in the parameters, stopped or not
        assert_finite(p, f"parameter {name}")
    print(f"lr x{lr_factor} {variant}: {tr.step} steps, stopped={stopped!r}")
    assert stopped is not None or tr.step == 5
    assert isinstance(stopped, (type(None), Ev3dgsError))
