"""The package as a user installs it: a wheel built from the checkout, installed into a new venv outside the
repository, every command run from another directory.

Stage 1, the core install (no extras): the entry points report the wheel's version, the built-in scenes ship
in the wheel, make-dataset says in one line which extra it needs, and the train -> eval -> export-dataset ->
view chain runs on a scene file (core dependencies resolve to their newest releases: numpy 2 where it installs).
Stage 2, the same venv with the Blender extra: a --quick make-dataset of a built-in scene, 20 training steps,
eval, export-dataset and a view figure, all from a folder that is not the checkout.

This needs the package registry (pip resolves the dependencies; pip's cache makes repeated runs fast). It takes
a few minutes on 2 cores, most of it installing and compiling the CPU kernels once.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import venv
from pathlib import Path

import h5py
import pytest

ROOT = Path(__file__).resolve().parents[1]
TORCH = "torch==2.13.0"  # installed first, as `make setup` does: the core's range keeps it


def _run(cmd, cwd, env, ok=True, timeout=900):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if ok and r.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, cmd))} exited {r.returncode}\n{r.stdout[-3000:]}\n"
                             f"{r.stderr[-3000:]}")
    return r


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    # --no-build-isolation: build with this venv's setuptools (the build backend the project declares)
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", out, ROOT], ROOT,
         os.environ)
    (whl,) = out.glob("ev3dgs-*.whl")
    return whl


def test_wheel_holds_the_package_data(wheel):
    import zipfile

    names = set(zipfile.ZipFile(wheel).namelist())
    for scene in ("lego", "ficus", "materials", "lowlight"):
        assert f"ev3dgs/sim/builtin_scenes/{scene}.toml" in names
    assert "ev3dgs/py.typed" in names
    assert any(n.startswith("ev3dgs_blender/") for n in names)       # the code Blender workers run
    assert not any(n.startswith(("tests/", "tools/", "docs/")) for n in names)


def test_installed_wheel_runs_the_chain_from_another_directory(wheel, tmp_path):
    env_dir, work = tmp_path / "venv", tmp_path / "work"
    work.mkdir()
    venv.create(env_dir, with_pip=True)
    bin_ = env_dir / "bin"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env |= {"PATH": f"{bin_}{os.pathsep}{env['PATH']}", "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
            "OMP_NUM_THREADS": "2", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    pip = [bin_ / "python", "-m", "pip", "install", "-q"]
    _run(pip + [TORCH], work, env)
    _run(pip + [wheel], work, env)

    # stage 1: the core install
    version = re.match(r"ev3dgs-([^-]+)-", wheel.name).group(1)
    for exe in ("ev3dgs", "ev3dgs-sim", "ev3dgs-ingest"):
        assert _run([bin_ / exe, "--version"], work, env).stdout.split() == [exe, version]
    scenes = _run([bin_ / "ev3dgs-sim", "list-scenes"], work, env).stdout.split("\n\n")[0].split()
    assert scenes == ["ficus", "lego", "lowlight", "materials"]
    has_bpy = _run([bin_ / "python", "-c", "import importlib.util as u; print(u.find_spec('bpy') is not None)"],
                   work, env).stdout.strip()
    assert has_bpy == "False"  # Blender is an extra, not a core dependency
    r = _run([bin_ / "ev3dgs-sim", "make-dataset", "--scene", "ficus", "--quick", "--out", "f.h5"], work, env,
             ok=False)
    assert r.returncode == 2 and "ev3dgs[blender]" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (work / "f.h5").exists()

    sys.path.insert(0, str(ROOT / "tests"))
    try:
        from view_scene import make_scene
    finally:
        sys.path.remove(str(ROOT / "tests"))
    (work / "hand").mkdir()
    make_scene(work / "hand" / "scene.h5", with_imu=False)
    _chain(bin_, work, env, "hand/scene.h5", "hand")

    # stage 2: with the Blender extra
    _run(pip + [f"{wheel}[blender]"], work, env)
    r = _run([bin_ / "ev3dgs-sim", "make-dataset", "--scene", "ficus", "--quick", "--views", "3",
              "--test-views", "1", "--workers", "2", "--out", "made/ficus.h5", "--quiet"], work, env)
    with h5py.File(work / "made" / "ficus.h5") as f:
        assert f["train/images"].shape == (3, 72, 96, 3) and f["test/images"].shape[0] == 1
        assert f["events/t"].shape[0] > 0
    _chain(bin_, work, env, "made/ficus.h5", "made")


def _chain(bin_, work, env, scene, tag):
    """train 20 steps -> eval -> export-dataset -> view figure, run from a folder other than the run's."""
    run = f"{tag}/run"
    _run([bin_ / "ev3dgs", "train", scene, "--out", run, "--iterations", "20", "--set", "init_points=2000",
          "--quiet"], work, env)
    elsewhere = work / f"{tag}-elsewhere"
    elsewhere.mkdir()
    _run([bin_ / "ev3dgs", "eval", work / run, "--quiet"], elsewhere, env)
    metrics = json.loads((work / run / "metrics.json").read_text())
    assert any(k in metrics for k in ("test", "train_sharp"))
    _run([bin_ / "ev3dgs", "export-dataset", work / scene, "--format", "e2nerf", "--out", "e2nerf", "--quiet"],
         elsewhere, env)
    assert (elsewhere / "e2nerf" / "README.txt").is_file()
    _run([bin_ / "ev3dgs", "view", work / run, "--out", "view.png", "--quiet"], elsewhere, env)
    assert (elsewhere / "view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
