"""Numba's on-disk kernel cache, and a one-line notice while it is filled.

Every numba kernel in ev3dgs is compiled with ``cache=True``: the first process on a machine compiles it (the
CPU rasterizer's kernels take about a minute on 2 cores) and writes the machine code next to the module
(``__pycache__``), or, where the package folder is read-only, into numba's user-wide cache folder
(``$NUMBA_CACHE_DIR`` when set). Later processes load it in well under a second.

`notify_first_compile` tells the user, once per process and only when the cache does not hold a kernel yet,
that the pause which follows is a one-off compile and not a hang.
"""
from __future__ import annotations

import sys
from types import ModuleType

_NOTIFIED: set[str] = set()


def _dispatchers(modules: list[ModuleType]) -> list:
    """The top-level numba kernels of `modules` (functions inlined into others are never compiled alone)."""
    from numba.core.registry import CPUDispatcher

    out = []
    for m in modules:
        for value in vars(m).values():
            if isinstance(value, CPUDispatcher) and value.__module__ == m.__name__ \
                    and value.targetoptions.get("inline", "never") != "always":
                out.append(value)
    return out


def missing_from_cache(modules: list[ModuleType]) -> list[str]:
    """Names of the kernels in `modules` with no compiled entry in numba's cache for their current source
    (an empty list when all are cached, or when the cache cannot be inspected)."""
    missing = []
    for d in _dispatchers(modules):
        try:
            cache = d._cache                       # numba.core.caching.FunctionCache (cache=True)
            if not cache._cache_file._load_index():  # {} when absent or written for another source stamp
                missing.append(d.__qualname__)
        except Exception:                        # another numba layout: no notice rather than a wrong one
            return []
    return missing


def cache_folder(modules: list[ModuleType]) -> str | None:
    for d in _dispatchers(modules):
        try:
            return str(d._cache._cache_path)
        except Exception:
            return None
    return None


def notify_first_compile(key: str, modules: list[ModuleType], what: str, seconds: str) -> bool:
    """Print one line to stderr if any kernel of `modules` must be compiled (once per process and key).
    Returns whether it printed."""
    if key in _NOTIFIED:
        return False
    _NOTIFIED.add(key)
    if not missing_from_cache(modules):
        return False
    where = cache_folder(modules)
    print(f"ev3dgs: compiling the {what} (first run only, {seconds}; cached"
          f"{f' in {where}' if where else ''} for later runs)", file=sys.stderr, flush=True)
    return True
