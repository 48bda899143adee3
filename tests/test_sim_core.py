"""The DVS change detector against analytic answers and a brute-force second implementation."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.errors import InputError
from ev3dgs.logmap import DEFAULT_LOG_KNEE, safe_log
from ev3dgs.sim import DVSConfig, DVSSimulator, simulate_events
from ev3dgs.sim.config import Leak, LowPass, Refractory, ShotNoise, ThresholdMismatch
from ev3dgs.sim.kernel import TOL

EXACT = DVSConfig(reference="exact")  # reference = the first frame: deterministic counts for closed forms


def ramp(log_change, n_frames=2, duration_us=10_000, start=0.5, shape=(1, 1)):
    t = np.linspace(0, duration_us, n_frames).round().astype(np.int64)
    levels = start * np.exp(log_change * np.linspace(0, 1, n_frames))
    return (levels[:, None, None] * np.ones((1, *shape))).astype(np.float64), t


@pytest.mark.parametrize("n_frames", [2, 3, 11])
def test_linear_log_rise_gives_exact_on_events(n_frames):
    frames, t = ramp(1.1, n_frames)
    ev = simulate_events(frames, t, EXACT)
    expected = [k * 0.2 / 1.1 * 10_000 for k in range(1, 6)]
    assert len(ev) == 5 and (ev.p == 1).all()
    assert np.abs(ev.t - np.array(expected)).max() <= 1.0


def test_fall_gives_off_and_constant_gives_none():
    frames, t = ramp(-1.1)
    ev = simulate_events(frames, t, EXACT)
    assert len(ev) == 5 and (ev.p == -1).all()
    assert np.abs(ev.t - np.array([k * 0.2 / 1.1 * 1e4 for k in range(1, 6)])).max() <= 1.0
    assert len(simulate_events(np.full((5, 4, 4), 0.3), np.arange(5) * 1000)) == 0


def test_residual_carries_to_the_next_frame():
    # log steps of 0.15 per frame: nothing in the first interval, one event 1/3 into the second
    frames = (0.5 * np.exp(np.array([0.0, 0.15, 0.30])))[:, None, None] * np.ones((1, 1, 1))
    ev = simulate_events(frames, np.array([0, 1000, 2000]), EXACT)
    assert list(ev.p) == [1]
    assert abs(ev.t[0] - (1000 + 1000 * 0.05 / 0.15)) <= 1


def test_on_off_asymmetry():
    cfg = DVSConfig(pos_threshold=0.1, neg_threshold=0.3, reference="exact")
    up, t = ramp(0.65)
    down, _ = ramp(-0.65)
    assert simulate_events(up, t, cfg).on_count == 6
    assert simulate_events(down, t, cfg).off_count == 2


def naive_events(log_frames, t_us, c_on, c_off):
    """Second implementation: walk the linearly interpolated log signal of one pixel in 0.05 us steps."""
    out = []
    ref = log_frames[0]
    for j in range(1, len(t_us)):
        a, b = log_frames[j - 1], log_frames[j]
        steps = int((t_us[j] - t_us[j - 1]) * 20)
        for q in range(1, steps + 1):
            v = a + (b - a) * q / steps
            while v - ref >= c_on - TOL:
                ref += c_on
                out.append((t_us[j - 1] + q / 20, 1))
            while ref - v >= c_off - TOL:
                ref -= c_off
                out.append((t_us[j - 1] + q / 20, -1))
    return out


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.0, 3.0), min_size=2, max_size=8), st.floats(0.05, 0.5), st.floats(0.05, 0.5))
def test_matches_brute_force_walk(levels, c_on, c_off):
    frames = np.array(levels)[:, None, None]
    t = np.arange(len(levels), dtype=np.int64) * 200
    ev = simulate_events(frames, t, DVSConfig(pos_threshold=c_on, neg_threshold=c_off, reference="exact"))
    ref = naive_events(safe_log(np.array(levels)), t, c_on, c_off)
    assert len(ev) == len(ref) or min(  # a level landing exactly on a threshold may go either way
        abs((safe_log(np.array(levels))[-1] - safe_log(np.array(levels))[0]) % c) for c in (c_on, c_off)) < 1e-9
    if len(ev) == len(ref):
        assert list(ev.p) == [p for _, p in ref]
        assert np.abs(ev.t - np.array([t for t, _ in ref])).max(initial=0) <= 1.0


def test_timestamps_are_per_pixel_not_a_grid():
    # 100 pixels with different slopes: v2e would put them on max-events-per-pixel timestamps per frame
    slopes = np.linspace(0.3, 2.0, 100)
    frames = 0.4 * np.exp(np.stack([np.zeros(100), slopes]))[:, None, :]
    ev = simulate_events(frames, np.array([0, 10_000]))
    per_pixel_max = np.bincount(ev.x).max()
    assert len(np.unique(ev.t)) > 20 * per_pixel_max


def test_output_sorted_and_typed():
    rng = np.random.default_rng(1)
    frames = rng.uniform(0, 2, (6, 20, 30))
    ev = simulate_events(frames, np.arange(6) * 777)
    assert ev.t.dtype == np.int64 and ev.x.dtype == np.uint16 and ev.y.dtype == np.uint16 and ev.p.dtype == np.int8
    assert (np.diff(ev.t) >= 0).all() and set(np.unique(ev.p)) <= {-1, 1}
    assert ev.x.max() < 30 and ev.y.max() < 20


ALL_EFFECTS = DVSConfig(
    threshold_mismatch=ThresholdMismatch(), refractory=Refractory(period_us=300), leak=Leak(rate_hz=2.0),
    shot_noise=ShotNoise(rate_hz=20.0), lowpass=LowPass(cutoff_hz=200),
)


@pytest.mark.parametrize("cfg", [None, ALL_EFFECTS], ids=["clean", "all-effects"])
def test_chunked_equals_one_call(cfg):
    rng = np.random.default_rng(3)
    frames = rng.uniform(0, 4, (30, 12, 16)).astype(np.float32)
    t = np.cumsum(rng.integers(50, 3000, 30))
    whole = simulate_events(frames, t, cfg, seed=7)
    sim = DVSSimulator(12, 16, cfg, seed=7)
    cuts = [0, 1, 2, 9, 10, 23, 30]
    parts = [sim.feed(frames[a:b], t[a:b]) for a, b in zip(cuts, cuts[1:])]
    for name in "txyp":
        assert np.array_equal(np.concatenate([getattr(p, name) for p in parts]), getattr(whole, name))
    assert len(whole) > 0


def test_same_seed_same_output_and_seed_matters():
    rng = np.random.default_rng(4)
    frames = rng.uniform(0, 1, (10, 16, 16))
    t = np.arange(10) * 5000
    a = simulate_events(frames, t, ALL_EFFECTS, seed=1)
    b = simulate_events(frames, t, ALL_EFFECTS, seed=1)
    c = simulate_events(frames, t, ALL_EFFECTS, seed=2)
    assert all(np.array_equal(getattr(a, n), getattr(b, n)) for n in "txyp")
    assert not (len(a) == len(c) and np.array_equal(a.t, c.t))


@pytest.mark.parametrize("cfg", [None, ALL_EFFECTS], ids=["clean", "all-effects"])
def test_extreme_intensities_stay_finite(cfg):
    frames = np.array([np.zeros((4, 4)), np.ones((4, 4)), np.full((4, 4), 1e6), np.zeros((4, 4)),
                       np.full((4, 4), 1e-30), np.full((4, 4), 65535.0)])
    ev = simulate_events(frames, np.arange(6) * 100, cfg)
    assert len(ev) > 0 and (np.diff(ev.t) >= 0).all()
    assert ev.t.min() >= 0 and ev.t.max() <= 500


def test_safe_log_is_finite_and_c1_at_the_knee():
    k = DEFAULT_LOG_KNEE
    assert np.isfinite(safe_log(np.array([0.0, 1e-300, k, 1e300]))).all()
    assert safe_log(np.array([k]))[0] == pytest.approx(math.log(k))
    h = 1e-7
    left = (safe_log(np.array([k])) - safe_log(np.array([k - h])))[0] / h
    right = (safe_log(np.array([k + h])) - safe_log(np.array([k])))[0] / h
    assert left == pytest.approx(1 / k, rel=1e-4) and right == pytest.approx(1 / k, rel=1e-4)
    assert safe_log(np.array([2.0]))[0] == math.log(2.0)


def test_torch_safe_log_matches_and_has_finite_gradients():
    torch = pytest.importorskip("torch")
    from ev3dgs.logmap import safe_log_torch

    x = torch.tensor([0.0, 1e-12, 0.05, DEFAULT_LOG_KNEE, 0.5, 3.0, 1e4], dtype=torch.float64, requires_grad=True)
    y = safe_log_torch(x)
    y.sum().backward()
    assert torch.isfinite(x.grad).all()
    assert np.allclose(y.detach().numpy(), safe_log(x.detach().numpy()))


@pytest.mark.parametrize("frames,t,match", [
    (np.full((3, 2, 2), np.nan), [0, 1, 2], "NaN"),
    (np.full((3, 2, 2), -0.1), [0, 1, 2], "negative"),
    (np.ones((3, 2, 2)), [0, 2, 1], "increasing"),
    (np.ones((3, 2, 2)), [0, 1, 1], "increasing"),
    (np.ones((3, 2, 2)), [0, 1], "shape"),
    (np.ones((3, 2, 2, 4)), [0, 1, 2], "shape"),
    (np.ones((3, 2, 2), np.uint8), [0, 1, 2], "float"),
    (np.ones((3, 2, 2)), [0.0, 1.0, 2.0], "integer"),
    (np.ones((3, 2, 2)), np.array([0, 20, 10], np.uint64), "increasing"),  # np.diff would wrap around
    (np.ones((3, 2, 2)), np.array([5, 5, 6], np.uint64), "increasing"),
])
def test_bad_input_is_a_clear_error(frames, t, match):
    with pytest.raises(InputError, match=match):
        simulate_events(frames, np.asarray(t))


def test_float16_frames_are_upcast_not_a_crash():
    frames, t = ramp(1.1, 3)
    ev16 = simulate_events(frames.astype(np.float16), t, EXACT)
    ev32 = simulate_events(frames.astype(np.float16).astype(np.float32), t, EXACT)
    assert len(ev16) == 5 and np.array_equal(ev16.t, ev32.t)
    assert len(simulate_events(frames, t.astype(np.uint64), EXACT)) == 5


def test_chunk_must_continue_in_time():
    sim = DVSSimulator(2, 2)
    sim.feed(np.ones((2, 2, 2)), np.array([0, 10]))
    with pytest.raises(InputError, match="continue"):
        sim.feed(np.ones((1, 2, 2)), np.array([10]))


def test_report_names_only_configured_effects():
    frames, t = ramp(1.0, shape=(3, 3))
    clean = simulate_events(frames, t).report
    assert clean.effects == ()
    assert set(clean.seconds) <= {"intensity", "log", "crossings", "sort", "kernel_load"}
    full = simulate_events(frames, t, ALL_EFFECTS).report
    assert set(full.effects) == {"lowpass", "threshold_mismatch", "leak", "shot_noise", "refractory"}
    assert {"lowpass", "threshold_mismatch", "leak", "shot_noise"} <= set(full.seconds)
    assert full.frames == 2 and full.events >= 0


def test_restart_reinitialises_without_events_but_keeps_the_sensor():
    cfg = DVSConfig(threshold_mismatch=ThresholdMismatch())
    sim = DVSSimulator(3, 3, cfg, seed=1)
    c_on = sim.c_on.copy()
    sim.feed(np.full((2, 3, 3), 0.3), np.array([0, 100]))
    sim.restart()
    ev = sim.feed(np.full((2, 3, 3), 3.0), np.array([200, 300]))  # a jump to a new view: no events
    assert len(ev) == 0 and np.array_equal(sim.c_on, c_on)
    frames, _ = ramp(1.1, 2, shape=(3, 3))
    ev = sim.feed(frames * 6, np.array([400, 10_400]))
    assert len(ev) > 0 and ev.t.min() > 400
    sim.restart()  # a fresh random phase: the same ramp gives different (but equally many on average) events
    ev2 = sim.feed(frames * 6, np.array([10_500, 20_500]))
    assert len(ev2) > 0 and not np.array_equal(ev2.t - 10_100, ev.t)
    with pytest.raises(InputError):
        sim.feed(np.ones((1, 3, 3)), np.array([10_000]))
