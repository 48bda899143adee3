"""The sensor TOML that `calibrate` writes: [dvs] and effect tables that ev3dgs.sim.config loads as is,
each value with a comment giving its bootstrap standard error and where it comes from; what the recording
cannot pin down is a comment saying "not estimated" (the simulator then uses its own default, or leaves the
effect off), never a value."""
from __future__ import annotations

import tomllib
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .aps import Recording, load_recording, pair_counts
from .noise import NoiseFit, fit_noise
from .thresholds import ThresholdFit, Value, fit_thresholds


@dataclass
class Calibration:
    rec: Recording
    thresholds: ThresholdFit
    noise: NoiseFit

    def summary(self) -> dict:
        def v(x: Value):
            return {"value": x.value, "se": x.se, "note": x.note}

        th, nz = self.thresholds, self.noise
        return {
            "recording": self.rec.path, "frames": int(len(self.rec.t_mid)), "events": int(len(self.rec.events)),
            "pos_threshold": v(th.c_on), "neg_threshold": v(th.c_off), "mismatch_sigma": v(th.sigma),
            "mismatch_sigma_on": v(th.sigma_on), "mismatch_sigma_off": v(th.sigma_off), "dark_dn": v(th.dark), "log_knee": v(th.knee),
            "frame_noise_dn": th.frame_noise_dn, "threshold_pixels": th.pixels,
            "pairs_up": th.samples_up, "pairs_down": th.samples_down,
            "leak_hz": v(nz.leak_hz), "shot_noise_hz": v(nz.shot_hz), "white_fraction": v(nz.white_fraction),
            "static_on_hz": v(nz.on_rate_hz), "static_off_hz": v(nz.off_rate_hz),
            "refractory_us": v(nz.refractory_us), "static_pixels": nz.static_pixels,
            "hot_pixels": [list(h) for h in nz.hot], "notes": th.notes + nz.notes,
        }


def calibrate_recording(path, boot: int = 200, seed: int = 0, curve: tuple[float, float] | None = None
                        ) -> Calibration:
    """Fit thresholds, mismatch, (dark, knee), background activity, hot pixels and refractory period.
    curve = (dark DN, log knee) fixes the APS-to-log map instead of fitting it."""
    rec = load_recording(path)
    on, off = pair_counts(rec)
    # a first threshold fit gives the static mask and hot pixels; the final fit leaves hot pixels out
    th0 = fit_thresholds(rec, on, off, boot=0, seed=seed, curve=curve)
    from .noise import hot_pixels, static_mask, window_counts

    n_on, n_off, T = window_counts(rec)
    static = static_mask(rec, th0.curve, min(th0.c_on.value, th0.c_off.value))
    hot, _ = hot_pixels(rec, n_on, n_off, T, th0.curve, th0.c_on.value, th0.c_off.value, static)
    # the change lost while a pixel is held after each event (refractory period) is put back in the fit
    from .noise import refractory

    refr = refractory(rec, hot, rng=np.random.default_rng(seed + 1), boot=0).value or 0.0
    th = fit_thresholds(rec, on, off, exclude=hot, boot=boot, seed=seed, curve=curve, refractory_us=refr)
    nz = fit_noise(rec, th.curve, th.c_on.value, th.c_off.value, boot=boot, seed=seed)
    return Calibration(rec, th, nz)


def _num(x: float) -> str:
    return f"{x:.4g}" if abs(x) >= 1e-3 else f"{x:.3e}"


def _pm(x: Value, unit: str = "") -> str:
    se = f" +- {_num(x.se)}{unit}" if x.se is not None and x.se == x.se else " (no standard error)"
    return f"{se} (bootstrap s.e.){'; ' + x.note if x.note else ''}"


def to_toml(cal: Calibration) -> str:
    th, nz, rec = cal.thresholds, cal.noise, cal.rec
    dt = (rec.t_mid[-1] - rec.t_mid[0]) / max(rec.pairs, 1) / 1e3
    L = [f"# ev3dgs-sim calibrate: fitted to {rec.path}",
         f"# {len(rec.t_mid)} APS frames (every {dt:.1f} ms, exposure {int(rec.exposure_us.mean())} us), "
         f"{len(rec.events)} events, {rec.width}x{rec.height}",
         "# every +- is a bootstrap standard error over pixels; 'not estimated' = the recording does not pin it",
         f"# APS dark level {th.dark.value:.3g} DN{_pm(th.dark, ' DN')}",
         f"# full scale {rec.full_scale:g} DN; "
         f"frame noise {th.frame_noise_dn:.2g} DN (median over intensity bands)",
         f"# thresholds from {th.pixels} pixels, {th.samples_up} up and {th.samples_down} down frame pairs, "
         f"{th.events_used} events",
         "",
         "[aps]",
         f"dark_dn = {th.dark.value:.6g}   # read by ev3dgs-sim compare: the APS-to-intensity map",
         "",
         "[dvs]",
         f"pos_threshold = {_num(th.c_on.value)}   #{_pm(th.c_on)}",
         f"neg_threshold = {_num(th.c_off.value)}   #{_pm(th.c_off)}",
         *([f"log_knee = {_num(th.knee.value)}   #{_pm(th.knee, ' decades')}"] if th.knee.value is not None else
           [f"# log_knee: not estimated: {th.knee.note}"]),
         "# reference: not estimated; the simulator's default (random phase) applies"]
    if th.sigma.value is not None and th.sigma.value > 0:
        L += ["", "[dvs.threshold_mismatch]",
              f"sigma = {_num(th.sigma.value)}   #{_pm(th.sigma)}",
              f"# ON spread {_fmt(th.sigma_on)}; OFF spread {_fmt(th.sigma_off)}"]
    else:
        L += ["", f"# [dvs.threshold_mismatch] not estimated: ON {_fmt(th.sigma_on)}; OFF {_fmt(th.sigma_off)}"]
    r = nz.refractory_us
    if r.value is not None:
        L += ["", "[dvs.refractory]", f"period_us = {_num(r.value)}   #{_pm(r, ' us')}"]
    else:
        L += ["", f"# [dvs.refractory] not estimated: {r.note}"]
    if nz.leak_hz.value is not None:
        L += ["", "[dvs.leak]", f"rate_hz = {_num(nz.leak_hz.value)}   #{_pm(nz.leak_hz, ' Hz')}",
              "# rate_spread_decades, jitter_fraction: not estimated (a few events per pixel cannot); "
              "the simulator's defaults apply"]
    else:
        L += ["", f"# [dvs.leak] not estimated: {nz.leak_hz.note}"]
    if nz.shot_hz.value is not None:
        L += ["", "[dvs.shot_noise]", f"rate_hz = {_num(nz.shot_hz.value)}   #{_pm(nz.shot_hz, ' Hz')}"]
        if nz.white_fraction.value is not None:
            L += [f"white_fraction = {_num(nz.white_fraction.value)}   #{_pm(nz.white_fraction)}"]
        else:
            L += [f"# white_fraction: not estimated: {nz.white_fraction.note}"]
    else:
        L += ["", f"# [dvs.shot_noise] not estimated: {nz.shot_hz.note}"]
    L += [f"# static pixels: {nz.static_pixels}, ON {_fmt(nz.on_rate_hz, ' Hz')}, OFF {_fmt(nz.off_rate_hz, ' Hz')}",
          "", "# [dvs.lowpass] not estimated: no intensity step in the recording is resolved by its frames",
          "# [dvs.color_filter] not estimated: the frames are monochrome"]
    if nz.hot:
        shown = ", ".join(f"({x}, {y}, {h:.3g} Hz)" for x, y, h in nz.hot[:40])
        more = f" and {len(nz.hot) - 40} more" if len(nz.hot) > 40 else ""
        L += ["", f"# hot pixels (x, y, rate), left out of every fit; the simulator has no hot-pixel model: {shown}{more}"]
    else:
        L += ["", "# hot pixels: none found"]
    text = "\n".join(L) + "\n"
    check_toml(text)
    return text


def _fmt(v: Value, unit: str = "") -> str:
    if v.value is None:
        return f"not estimated ({v.note})"
    se = f" +- {_num(v.se)}" if v.se is not None and v.se == v.se else ""
    return f"{_num(v.value)}{se}{unit}"


def check_toml(text: str) -> None:
    """What we write must load with the simulator's own loader, alone and as a scene's [sensor] table."""
    from ..config import from_dict
    from ..errors import ConfigError
    from ..sim.config import SimConfig
    from ..sim.scenes import SceneSpec

    data = tomllib.loads(text)
    try:
        from_dict(SimConfig, data)
        from_dict(SceneSpec, {"name": "check", "sensor": data})
    except ConfigError as e:  # a bug of ours, not of the recording
        raise InputError(f"the fitted values are outside what the simulator accepts: {e}") from None
