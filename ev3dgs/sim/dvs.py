"""The DVS simulator: frames of linear intensity -> events with per-pixel timestamps.

Pipeline per frame: intensity (luminance, or the CFA channel) -> safe log (ev3dgs.logmap) -> optional
photoreceptor low-pass -> change detector (ev3dgs.sim.kernel) with optional mismatch, leak, shot noise and
refractory period. The first frame ever fed (and the first after restart()) only initialises the state:
the reference starts at a random phase within one threshold (DVSConfig.reference).
"""
from __future__ import annotations

import time
import zlib
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..events import Events
from .budget import check_noise_memory
from .config import DVSConfig, ISPConfig
from .effects.color import ColorFilterArray, luminance
from .effects.leak import LeakDrift
from .effects.lowpass import PhotoreceptorLowPass
from .effects.mismatch import draw_thresholds
from .effects.shot_noise import ShotNoiseSampler
from ..logmap import safe_log
from .kernel import EMPTY_F8, EMPTY_I1, EMPTY_I8, NEVER, interval_events, sort_interval, start_references


@dataclass
class SimReport:
    """What ran and where the time went. `seconds` has the core stages (intensity, log, crossings, sort)
    and one entry per effect that ran. Leak drift, the refractory hold and the emission of noise events
    happen inside the crossing kernel, so that part of their cost is counted in `crossings`; their own
    entries time their setup (per-pixel draws) and per-interval sampling."""

    effects: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)
    frames: int = 0
    events: int = 0


@dataclass
class SimulatedEvents(Events):
    report: SimReport | None = field(default=None, repr=False, compare=False)


def _effect_rng(seed: int, name: str) -> np.random.Generator:
    # one independent stream per effect: turning one effect on never changes another's randomness
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(name.encode())]))


_WARM = False


def _warm_kernels() -> float:
    """Load (or compile, the first time ever) every numba kernel for float32 and float64 input once per
    process, so that the first interval's stage and effect timings are not load times. Returns seconds."""
    global _WARM
    if _WARM:
        return 0.0
    _WARM = True
    from ..numba_cache import notify_first_compile
    from . import kernel
    from .config import Leak, LowPass, Refractory, ShotNoise
    from .effects import leak, lowpass, shot_noise

    notify_first_compile("sim", [kernel, leak, lowpass, shot_noise], "event simulator kernels", "about 10 s")

    t = time.perf_counter()
    every = DVSConfig(refractory=Refractory(), leak=Leak(), shot_noise=ShotNoise(rate_hz=1e4), lowpass=LowPass())
    for dtype in (np.float32, np.float64):
        frames = np.array([0.1, 0.9, 0.2], dtype)[:, None, None] * np.ones((1, 2, 2), dtype)
        for cfg in (None, every):
            DVSSimulator(2, 2, cfg).feed(frames, np.array([0, 100, 200]))
    return time.perf_counter() - t


class DVSSimulator:
    """Stateful: feeding a sequence in chunks gives exactly the events of feeding it at once.

    The report's `kernel_load` entry is the one-off cost of loading the compiled kernels (first simulator
    of a process only). `isp`: the camera's ISP, used only with a Bayer colour filter (each DVS pixel sees
    the camera-raw channel that ISP's inverse gives; default ISPConfig()). Every random stream (reference
    phase, mismatch, leak, noise) is a numpy Generator seeded from (seed, stream name): no thread dependence."""

    def __init__(self, height: int, width: int, config: DVSConfig | None = None, seed: int = 0,
                 isp: ISPConfig | None = None):
        load_s = _warm_kernels()
        if height <= 0 or width <= 0 or height > 65535 or width > 65535:
            raise InputError(f"impossible sensor size {width}x{height}")
        self.cfg = cfg = config or DVSConfig()
        self.height, self.width, self.seed = height, width, int(seed)
        P = height * width
        self.seconds: dict[str, float] = defaultdict(float)
        self.frames = 0
        self.n_events = 0
        if load_s:
            self.seconds["kernel_load"] = load_s
        t = time.perf_counter()
        self.c_on = np.full(P, cfg.pos_threshold)
        self.c_off = np.full(P, cfg.neg_threshold)
        if cfg.threshold_mismatch:
            self.c_on, self.c_off = draw_thresholds(cfg.threshold_mismatch, cfg.pos_threshold,
                                                    cfg.neg_threshold, P, _effect_rng(seed, "mismatch"))
            self._tick("threshold_mismatch", t)
        self.c_min = float(min(self.c_on.min(), self.c_off.min()))
        self.cfa = ColorFilterArray(cfg.color_filter.pattern, height, width, isp) if cfg.color_filter else None
        self.lowpass = PhotoreceptorLowPass(cfg.lowpass) if cfg.lowpass else None
        t = time.perf_counter()
        self.leak = LeakDrift(cfg.leak, P, _effect_rng(seed, "leak"), self.c_on) if cfg.leak else None
        if self.leak:
            self._tick("leak", t)
        self.noise = (ShotNoiseSampler(cfg.shot_noise, _effect_rng(seed, "shot_noise"), self.c_on, self.c_off,
                                       cfg.pos_threshold, cfg.neg_threshold) if cfg.shot_noise else None)
        self.refractory_us = float(cfg.refractory.period_us) if cfg.refractory else 0.0
        self.blocked_until = np.full(P, NEVER) if cfg.refractory else EMPTY_F8
        if cfg.refractory:
            self.seconds["refractory"] += 0.0
        # state
        self.t_prev: int | None = None
        self._restart = False
        self.ref = np.zeros(P)
        self._ref_rng = _effect_rng(seed, "reference") if cfg.reference == "random" else None
        self._phase = self._undecided = None
        self._n_undecided = 0
        self.signal_prev = self.log_prev = self.intensity_prev = None
        self._scratch = np.empty(P, np.int64)
        self._buf = (np.empty(P, np.int64), np.empty(P, np.uint16), np.empty(P, np.uint16), np.empty(P, np.int8))

    def restart(self) -> None:
        """Forget the signal (the camera jumped, e.g. to the next view of a dataset): the next frame fed
        initialises the reference again (at a fresh random phase, unless reference = "exact") and emits
        nothing. The sensor itself (threshold pattern, leak rates, noise streams) stays, and time must keep
        increasing."""
        self.signal_prev = self.log_prev = self.intensity_prev = None
        if self.blocked_until.shape[0]:
            self.blocked_until[:] = NEVER
        self._restart = True

    def _tick(self, key: str, t_start: float) -> float:
        now = time.perf_counter()
        self.seconds[key] += now - t_start
        return now

    @property
    def report(self) -> SimReport:
        return SimReport(self.cfg.effects, dict(self.seconds), self.frames, self.n_events)

    def _check(self, frames: np.ndarray, t_us: np.ndarray) -> None:
        H, W = self.height, self.width
        if frames.ndim not in (3, 4) or frames.shape[1:3] != (H, W) or (frames.ndim == 4 and frames.shape[3] != 3):
            raise InputError(f"frames must have shape (T, {H}, {W}) or (T, {H}, {W}, 3), got {frames.shape}")
        if not np.issubdtype(frames.dtype, np.floating):
            raise InputError(f"frames must be float linear intensity (1.0 = white), got dtype {frames.dtype}")
        if t_us.ndim != 1 or len(t_us) != len(frames):
            raise InputError(f"t_us must have shape ({len(frames)},), got {t_us.shape}")
        if not np.issubdtype(t_us.dtype, np.integer):
            raise InputError(f"t_us must be integer microseconds, got dtype {t_us.dtype}")
        if frames.size:
            lo, hi = frames.min(), frames.max()  # two SIMD reductions; NaN propagates into both
            if not (np.isfinite(lo) and np.isfinite(hi)):
                raise InputError("frames contain NaN or Inf")
            if lo < 0:
                raise InputError("frames contain negative intensities")
        if len(t_us) > 1 and (t_us[1:] <= t_us[:-1]).any():  # not np.diff: it wraps for unsigned ints
            raise InputError("t_us must be strictly increasing (no duplicate timestamps)")
        if self.t_prev is not None and len(t_us) and t_us[0] <= self.t_prev:
            raise InputError(f"t_us must continue after the last frame fed ({self.t_prev} us)")

    def feed(self, frames: np.ndarray, t_us: np.ndarray) -> Events:
        frames = np.asarray(frames)
        t_us = np.asarray(t_us)
        if frames.dtype == np.float16:  # numba has no float16 kernels: compute in float32
            frames = frames.astype(np.float32)
        self._check(frames, t_us)
        if len(t_us) and (int(t_us.max()) >= 2**62 or int(t_us.min()) < -2**62):
            raise InputError("t_us out of range (|t| must be below 2**62 us)")
        if self.cfa is not None and frames.ndim != 4:
            raise InputError("a Bayer colour filter needs colour frames of shape (T, H, W, 3)")
        if len(t_us):
            start = int(t_us.min()) if self.t_prev is None or self._restart else int(self.t_prev)
            check_noise_memory(self.cfg, self.height * self.width, (int(t_us.max()) - start) * 1e-6)
        parts = []
        knee = self.cfg.log_knee
        for frame, t1 in zip(frames, t_us.tolist()):
            t = time.perf_counter()
            intensity = self.cfa(frame) if self.cfa is not None else luminance(frame)
            t = self._tick("color_filter" if self.cfa is not None else "intensity", t)
            log_i = safe_log(intensity, knee)
            t = self._tick("log", t)
            self.frames += 1
            if self.t_prev is None or self._restart:  # the first frame only initialises
                self._restart = False
                self.signal_prev = self.log_prev = log_i
                self.intensity_prev = intensity
                self.ref = log_i.astype(np.float64)  # the reference accumulates: keep it in float64
                if self._ref_rng is not None:  # random phase, applied at each pixel's first move
                    self._phase = self._ref_rng.random(self.ref.shape[0])
                    self._undecided = np.arange(self.ref.shape[0], dtype=np.int64)
                    self._n_undecided = self.ref.shape[0]
                self.t_prev = t1
                continue
            dt = float(t1 - self.t_prev)
            signal = log_i
            if self.lowpass is not None:
                mean_i = 0.5 * (self.intensity_prev + intensity)
                signal = self.lowpass.step(self.signal_prev, self.log_prev, log_i, mean_i, dt)
                t = self._tick("lowpass", t)
            drift = EMPTY_F8
            if self.leak is not None:
                drift = self.leak.drift(dt)
                t = self._tick("leak", t)
            noise = (EMPTY_I8, EMPTY_F8, EMPTY_I1)
            if self.noise is not None:
                noise = self.noise.sample(self.intensity_prev, intensity, dt)
                t = self._tick("shot_noise", t)
            if self._n_undecided:
                # a pixel's direction: its signal change plus the leak's mean drift (not the jittered one)
                mean_drift = self.leak.mean_drift(dt) if self.leak is not None else EMPTY_F8
                self._n_undecided = start_references(self._undecided, self._n_undecided, self.signal_prev, signal,
                                                     mean_drift, self.ref, self.c_on, self.c_off, self._phase,
                                                     noise[0])
            n, self._buf = interval_events(
                self.signal_prev, signal, self.ref, self.c_on, self.c_off, self.c_min, drift, self.blocked_until,
                float(self.t_prev), dt, self.refractory_us, noise, self.width, self._buf, self._scratch)
            t = self._tick("crossings", t)
            parts.append(Events(*sort_interval(*self._buf, n, self.t_prev, dt)))
            self._tick("sort", t)
            self.n_events += n
            self.signal_prev, self.log_prev, self.intensity_prev = signal, log_i, intensity
            self.t_prev = t1
        return Events.concatenate(parts)


def simulate_events(frames, t_us, config: DVSConfig | None = None, seed: int = 0,
                    isp: ISPConfig | None = None) -> SimulatedEvents:
    """Events from a whole sequence of linear intensity frames (T, H, W) or (T, H, W, 3) at t_us (T,)."""
    frames = np.asarray(frames)
    if frames.ndim not in (3, 4):
        raise InputError(f"frames must have shape (T, H, W) or (T, H, W, 3), got {frames.shape}")
    sim = DVSSimulator(frames.shape[1], frames.shape[2], config, seed, isp)
    ev = sim.feed(frames, t_us)
    return SimulatedEvents(ev.t, ev.x, ev.y, ev.p, report=sim.report)
