"""A sensor TOML (the one `ev3dgs-sim calibrate` writes, or the one `ev3dgs-sim record` writes beside its
recording) -> the scene file's /events sensor model (schema.EventSensor), for `ev3dgs-ingest davis --sensor`.

The TOML is an ordinary simulator config: [dvs] thresholds and log_knee, and the effect tables
[dvs.threshold_mismatch] sigma, [dvs.refractory] period_us, [dvs.leak] rate_hz, [dvs.shot_noise] rate_hz,
[dvs.color_filter] pattern. As everywhere in the simulator, an effect table that is absent means the effect is
off: the scene file then stores 0 for it (calibrate leaves a table out when the recording does not show the
effect above its standard error). A real sensor's reference is wherever it last fired, so the count convention
is always random_phase, whatever `reference` the TOML names."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from .. import schema
from ..errors import ConfigError, InputError


def load_sensor_toml(path) -> schema.EventSensor:
    """The EventSensor a sensor TOML describes; InputError (one line) if it cannot be read or is not one."""
    from ..config import load_toml
    from ..sim.config import load_sim_config
    from ..sim.output import event_sensor

    path = Path(path)
    if not path.is_file():
        raise InputError(f"--sensor {path}: no such file")
    try:
        data = load_toml(path)
        if "dvs" not in data:
            raise InputError(f"--sensor {path}: no [dvs] table (a sensor TOML from `ev3dgs-sim calibrate` or "
                             "`ev3dgs-sim record` has one)")
        cfg = load_sim_config(path)
    except ConfigError as e:
        raise InputError(f"--sensor: {e}") from None
    es = event_sensor(cfg.dvs, cfg.isp)
    return dataclasses.replace(es, count_convention="random_phase")
