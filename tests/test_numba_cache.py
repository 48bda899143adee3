"""The on-disk numba cache and the one-line notice before a first compile (ev3dgs.numba_cache)."""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap

from ev3dgs import numba_cache


def _module(tmp_path, monkeypatch, name):
    (tmp_path / f"{name}.py").write_text(textwrap.dedent("""
        from numba import njit

        @njit(cache=True)
        def helper(x):
            return x + 1

        @njit(cache=True, inline="always")
        def inlined(x):
            return x * 2

        @njit(cache=True)
        def entry(x):
            return helper(x) + inlined(x)
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    return importlib.import_module(name)


def test_missing_until_compiled_then_cached(tmp_path, monkeypatch):
    m = _module(tmp_path, monkeypatch, "nbc_probe_a")
    # inline="always" kernels are never compiled on their own: they are not asked for
    assert sorted(numba_cache.missing_from_cache([m])) == ["entry", "helper"]
    assert m.entry(3) == 10
    assert numba_cache.missing_from_cache([m]) == []


def test_notice_once_and_only_when_compiling(tmp_path, monkeypatch, capsys):
    m = _module(tmp_path, monkeypatch, "nbc_probe_b")
    assert numba_cache.notify_first_compile("probe-b", [m], "probe kernels", "a moment")
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "compiling the probe kernels" in err
    assert not numba_cache.notify_first_compile("probe-b", [m], "probe kernels", "a moment")  # once a process
    m.entry(1)
    assert not numba_cache.notify_first_compile("probe-b2", [m], "probe kernels", "a moment")  # cached now
    assert capsys.readouterr().err == ""


def test_simulator_first_process_compiles_second_loads(tmp_path):
    """Two fresh processes on an empty cache folder: the first says it compiles, the second says nothing."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    code = "from ev3dgs.sim.dvs import _warm_kernels; _warm_kernels()"
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    second = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert "compiling the event simulator kernels" in first.stderr
    assert "compiling" not in second.stderr
    assert any((tmp_path / "cache").rglob("*.nbi"))
