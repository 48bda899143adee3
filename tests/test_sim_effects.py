"""Each optional sensor effect on its own, against its analytic behaviour."""
import math

import numpy as np
import pytest

from ev3dgs.logmap import safe_log
from ev3dgs.sim import DVSConfig, DVSSimulator, simulate_events
from ev3dgs.sim.config import ColorFilter, Leak, LowPass, Refractory, ShotNoise, ThresholdMismatch
from ev3dgs.sim.effects.color import cfa_channels, raw_matrix
from ev3dgs.sim.config import ISPConfig
from ev3dgs.sim.kernel import TOL
from ev3dgs.sim.effects.lowpass import PhotoreceptorLowPass, exact_ramp_step


def test_threshold_mismatch_statistics_and_effect_on_counts():
    cfg = DVSConfig(threshold_mismatch=ThresholdMismatch(sigma=0.03), reference="exact")
    sim = DVSSimulator(200, 250, cfg, seed=5)
    for c in (sim.c_on, sim.c_off):
        assert c.mean() == pytest.approx(0.2, abs=0.001)
        assert c.std() == pytest.approx(0.03, rel=0.03)
    assert abs(np.corrcoef(sim.c_on, sim.c_off)[0, 1]) < 0.02
    # a log rise of 2.0 gives each pixel exactly floor(2.0 / its own threshold) ON events
    H, W = 20, 25
    frames = 0.5 * np.exp(np.array([0.0, 2.0]))[:, None, None] * np.ones((1, H, W))
    sim = DVSSimulator(H, W, cfg, seed=5)
    ev = sim.feed(frames, np.array([0, 1000]))
    counts = np.bincount(ev.y.astype(int) * W + ev.x, minlength=H * W)
    assert np.array_equal(counts, np.floor((2.0 + TOL) / sim.c_on).astype(int))
    # frozen: the pattern stays the same for the whole run
    assert np.array_equal(DVSSimulator(H, W, cfg, seed=5).c_on, sim.c_on)


def test_threshold_mismatch_clips_at_minimum():
    sim = DVSSimulator(100, 100, DVSConfig(threshold_mismatch=ThresholdMismatch(sigma=0.5, min_threshold=0.05)))
    assert sim.c_on.min() >= 0.05 and sim.c_off.min() >= 0.05


def test_refractory_spacing_is_period_plus_one_threshold():
    # log slope r per us; threshold C -> crossings every C/r us; with period R each event holds the pixel
    # for R, then the reference restarts from the input, so events come every R + C/r us
    r, C, R = 1e-3, 0.2, 500.0
    T = 20_000
    t = np.arange(0, T + 1, 100)
    frames = (0.5 * np.exp(r * t))[:, None, None]
    free = simulate_events(frames, t)
    held = simulate_events(frames, t, DVSConfig(refractory=Refractory(period_us=R)))
    assert np.allclose(np.diff(free.t), C / r, atol=1.5)
    gaps = np.diff(held.t)
    assert np.allclose(gaps, R + C / r, atol=1.5)
    assert len(held) < len(free)


def test_refractory_blocks_noise_too():
    frames = np.full((2001, 3, 3), 0.01)
    ev = simulate_events(frames, np.arange(2001) * 100, DVSConfig(
        shot_noise=ShotNoise(rate_hz=400.0), refractory=Refractory(period_us=2000)), seed=1)
    for pix in range(9):
        tt = ev.t[(ev.y.astype(int) * 3 + ev.x) == pix]
        assert (np.diff(tt) >= 2000 - 1).all()


def test_leak_rate_on_a_static_scene():
    H, W, seconds = 30, 30, 100
    t = np.arange(0, seconds * 1_000_000 + 1, 50_000)
    frames = np.full((len(t), H, W), 0.4)
    cfg = DVSConfig(leak=Leak(rate_hz=0.5, rate_spread_decades=0.0, jitter_fraction=0.0))
    ev = simulate_events(frames, t, cfg)
    assert ev.off_count == 0
    counts = np.bincount(ev.y.astype(int) * W + ev.x, minlength=H * W)
    # 0.5 Hz * 100 s = 50 thresholds of drift from a random phase u in [0, 1): floor(50 + u) = 50, exactly
    assert set(np.unique(counts)) == {50}
    spread = simulate_events(frames, t, DVSConfig(leak=Leak(rate_hz=0.5, rate_spread_decades=0.3)), seed=2)
    assert len(spread) / (H * W * seconds) == pytest.approx(0.5, rel=0.05)  # mean rate is normalised
    assert np.bincount(spread.y.astype(int) * W + spread.x).std() > 5


@pytest.mark.parametrize("intensity", [0.0, 0.4, 1.0, 50.0])
def test_shot_noise_rate_vs_intensity(intensity):
    H, W, seconds = 40, 40, 20
    cfg = ShotNoise(rate_hz=2.0, white_fraction=0.25)
    t = np.arange(0, seconds * 1_000_000 + 1, 100_000)
    ev = simulate_events(np.full((len(t), H, W), intensity), t, DVSConfig(shot_noise=cfg), seed=3)
    expected = cfg.rate_hz * (1 - 0.75 * min(intensity, 1.0)) * H * W * seconds
    assert abs(len(ev) - expected) < 5 * math.sqrt(expected)
    assert abs(ev.on_count - ev.off_count) < 5 * math.sqrt(expected)
    assert (ev.t > 0).all() and len(np.unique(ev.t)) > 0.9 * len(ev)  # times spread, not on frame ticks


def test_exact_ramp_step_matches_fine_integration():
    y0, x0, x1, tau, dt = 0.3, 1.0, -0.5, 700.0, 1000.0
    y = y0
    steps = 200_000
    for q in range(steps):  # midpoint rule on tau*y' = x(t) - y
        tm = (q + 0.5) * dt / steps
        x = x0 + (x1 - x0) * tm / dt
        y += (x - y) * (dt / steps) / tau
    assert exact_ramp_step(y0, x0, x1, dt / tau) == pytest.approx(y, abs=1e-6)
    for h in (1e-9, 1e-5, 1e-2, 1.0, 50.0, 1e4):  # stable and finite for any step size
        v = exact_ramp_step(y0, x0, x1, h)
        assert np.isfinite(v) and min(y0, x0, x1) - 1e-12 <= v <= max(y0, x0, x1) + 1e-12


def test_fast_lowpass_step_matches_exact_reference():
    rng = np.random.default_rng(0)
    n = 10_000
    y0, x0, x1 = rng.normal(size=(3, n))
    intensity = rng.uniform(0, 3, n)
    lp = PhotoreceptorLowPass(LowPass(cutoff_hz=300))
    for dt in (10.0, 1000.0, 1e5):
        fast = lp.step(y0, x0, x1, intensity, dt)
        exact = exact_ramp_step(y0, x0, x1, dt / lp.tau_us(intensity))
        assert np.abs(fast - exact).max() < 1e-5


def test_lowpass_step_response_time_constant():
    # a log step of 1.0 at t=0; with threshold 0.1 the k-th ON event comes when 1 - exp(-t/tau) = 0.1 k
    cutoff, I1 = 100.0, 0.8
    cfg = DVSConfig(pos_threshold=0.1, lowpass=LowPass(cutoff_hz=cutoff), reference="exact")
    tau = 1e6 / (2 * math.pi * cutoff * (I1 + cfg.lowpass.dark_intensity) / (1 + cfg.lowpass.dark_intensity))
    t = np.concatenate([[-1], np.arange(0, 12_001, 20)])
    frames = np.concatenate([[I1 / math.e], np.full(len(t) - 1, I1)])[:, None, None]
    ev = simulate_events(frames, t, cfg)
    k = np.arange(1, len(ev) + 1)
    expected = -tau * np.log(1 - 0.1 * k)
    assert len(ev) == 9 and (ev.p == 1).all()
    assert np.allclose(ev.t, expected, rtol=0.01, atol=10)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("channel", [0, 1, 2])
def test_bayer_filter_pixels_see_only_their_channel(pattern, channel):
    # only one camera-raw channel brightens (by e: 5 events at 0.2); the frames are the linear sRGB of that raw
    H, W = 6, 8
    m = raw_matrix(ISPConfig())
    raw = np.full((2, 3), 0.5) / np.array(ISPConfig().white_balance)  # grey 0.5 in raw
    raw[1, channel] *= math.e
    lin = raw @ np.linalg.inv(m).T
    assert (lin >= 0).all()
    frames = lin[:, None, None, :] * np.ones((1, H, W, 1))
    ev = simulate_events(frames, np.array([0, 1000]), DVSConfig(color_filter=ColorFilter(pattern), reference="exact"))
    counts = np.zeros((H, W), int)
    np.add.at(counts, (ev.y, ev.x), 1)
    assert np.array_equal(counts, 5 * (cfa_channels(pattern, H, W) == channel))


def test_luminance_weights_without_a_filter():
    frames = np.full((2, 1, 3, 3), 0.5)
    for c in range(3):
        frames[1, 0, c, c] = 0.5 * math.e
    ev = simulate_events(frames, np.array([0, 1000]), DVSConfig(reference="exact"))
    counts = np.bincount(ev.x, minlength=3)
    expected = [math.floor((safe_log(np.array([0.5 + 0.5 * (math.e - 1) * w]))[0] - math.log(0.5)) / 0.2)
                for w in (0.2126, 0.7152, 0.0722)]
    assert list(counts) == expected
