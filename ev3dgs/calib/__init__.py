"""Sim-to-real: fit the DVS model to a real recording (`calibrate`) and compare a re-simulation with it
(`compare`). One small module per step: aps (frames -> log intensity, masks, event counts between exposure
midpoints), thresholds, noise (background activity, hot pixels, refractory period), report (the sensor TOML),
compare (re-simulation and metrics), figure."""
from __future__ import annotations

__all__ = ["load_recording", "calibrate_recording"]


def __getattr__(name):  # lazy: importing ev3dgs.calib does not load numba kernels or matplotlib
    if name == "load_recording":
        from .aps import load_recording

        return load_recording
    if name == "calibrate_recording":
        from .report import calibrate_recording

        return calibrate_recording
    raise AttributeError(name)
