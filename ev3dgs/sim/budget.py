"""Memory the noise effects will need, checked before they run.

Leak and shot noise add events in proportion to their rates, the pixel count and the time simulated, however
still the scene: (leak.rate_hz + shot_noise.rate_hz) x pixels x seconds is the expected count (the shot-noise
rate is its dark maximum, so this is an upper estimate). Each event costs EVENT_BYTES while it is generated,
collected and concatenated. A run whose estimate exceeds the memory available (MemAvailable on Linux; the
EV3DGS_MAX_MEMORY environment variable in bytes, or with a K/M/G suffix, overrides it) is refused in one line
before it starts, instead of growing until the system kills it.
"""
from __future__ import annotations

import os

from ..errors import ConfigError

EVENT_BYTES = 48          # t (8) + x, y (2 x 8) + p (1) per event, held about twice while parts are concatenated
_SUFFIX = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def available_bytes() -> int | None:
    """EV3DGS_MAX_MEMORY if set, else the memory the system can give without swapping; None if unknown."""
    env = os.environ.get("EV3DGS_MAX_MEMORY", "").strip().lower()
    if env:
        try:
            mult = _SUFFIX.get(env[-1], 1)
            return int(float(env[:-1] if env[-1] in _SUFFIX else env) * mult)
        except ValueError:
            raise ConfigError(f"EV3DGS_MAX_MEMORY={env!r}: expected bytes, e.g. 8G") from None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def noise_events(dvs, pixels: int, seconds: float) -> float:
    """Expected leak + shot-noise events (an upper estimate) of `pixels` over `seconds`."""
    rate = (dvs.leak.rate_hz if dvs.leak is not None else 0.0) + \
        (dvs.shot_noise.rate_hz if dvs.shot_noise is not None else 0.0)
    return rate * pixels * max(seconds, 0.0)


def check_noise_memory(dvs, pixels: int, seconds: float, limit: int | None = None) -> None:
    """Refuse (ConfigError, one line) a noise simulation whose events would not fit in memory."""
    n = noise_events(dvs, pixels, seconds)
    if not n:
        return
    limit = available_bytes() if limit is None else limit
    need = n * EVENT_BYTES
    if limit is not None and need > limit:
        raise ConfigError(f"the noise effects would make about {n:.3g} events ({need / 2**30:.3g} GiB) over "
                          f"{seconds:.3g} s x {pixels} pixels, more than the {limit / 2**30:.3g} GiB of memory "
                          "available: lower dvs.leak.rate_hz / dvs.shot_noise.rate_hz or simulate less time "
                          "(EV3DGS_MAX_MEMORY sets the limit)")
