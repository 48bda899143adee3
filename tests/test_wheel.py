"""The package as a user installs it: a wheel built from the checkout, installed into a new venv outside the
repository, every command run from another directory.

In the default run (no install, seconds): the wheel holds every package, module and data file of the source
tree (a package missing from the wheel, as ev3dgs.calib once was, fails here), and every module imports from
the unpacked wheel alone.

Marked slow (`make test-slow`; it needs the package registry and takes minutes on 2 cores, most of it
installing): every sub-command of the three entry points run once from the installed wheel (the test checks
that the list it runs is the parsers' list). Stage 1, the core install (no extras): versions, list-scenes, the
one-line refusals of make-dataset and record without Blender, events and blur on small inputs, calibrate and
compare on a small recording the test makes, ingest info / davis (the static-camera refusal and --no-poses) /
e2nerf, and train -> eval -> render -> export -> info -> validate -> export-dataset -> view on a scene file
(core dependencies resolve to their newest releases: numpy 2 where it installs). Stage 2, the same venv with
the Blender extra: a --quick make-dataset of a built-in scene and its chain, and a short record.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
TORCH = "torch==2.13.0"  # installed first, as `make setup` does: the core's range keeps it
SKIP = ("__pycache__",)
BUILD_OUTPUTS = (".pyc", ".so", ".pyd")   # compiled here; the wheel holds its own build of the extension


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


def source_files() -> list[str]:
    """Every file of ev3dgs/ and blender/ (as the wheel names them: blender/ -> ev3dgs_blender/), by a walk of
    the source tree, without caches and build outputs."""
    out = []
    for top, name in (("ev3dgs", "ev3dgs"), ("blender", "ev3dgs_blender")):
        for dirpath, dirnames, filenames in os.walk(ROOT / top):
            dirnames[:] = [d for d in dirnames if d not in SKIP]
            rel = Path(dirpath).relative_to(ROOT / top)
            for f in filenames:
                if not f.endswith(BUILD_OUTPUTS):
                    out.append((Path(name) / rel / f).as_posix())
    return sorted(out)


def test_wheel_holds_every_package_and_data_file(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = [f for f in source_files() if f not in names]
    assert not missing, f"not in the wheel: {missing}"
    folders = {str(Path(f).parent) for f in source_files()}
    assert "ev3dgs/sim/builtin_scenes" in folders and "ev3dgs/calib" in folders   # the walk saw them
    for scene in ("lego", "ficus", "materials", "lowlight"):
        assert f"ev3dgs/sim/builtin_scenes/{scene}.toml" in names
    assert any(n.startswith("ev3dgs/io/aedat4/_fast") and n.endswith(".so") for n in names)   # the C extension
    assert not any(n.startswith(("tests/", "tools/", "docs/")) for n in names)


def test_every_module_imports_from_the_unpacked_wheel(wheel, tmp_path):
    """Each module of the source tree imports from the wheel's files alone (the dev venv supplies the
    dependencies; the checkout is not on the path): a module the wheel lacks, or one that imports a package
    the wheel lacks, fails. ev3dgs_blender runs inside bpy and is only checked for presence above."""
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    modules = sorted({f[:-3].replace("/", ".").removesuffix(".__init__") for f in source_files()
                      if f.endswith(".py") and f.startswith("ev3dgs/")})
    code = ("import importlib, sys; sys.path.insert(0, sys.argv[1]); bad = []\n"
            "for m in sys.argv[2:]:\n"
            "    mod = importlib.import_module(m)\n"
            "    if not mod.__file__.startswith(sys.argv[1]): bad.append((m, mod.__file__))\n"
            "print(len(sys.argv) - 2, bad)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    r = _run([sys.executable, "-c", code, site, *modules], tmp_path, env)
    assert r.stdout.split()[0] == str(len(modules)) and r.stdout.strip().endswith("[]"), r.stdout


def sub_commands() -> set[tuple[str, str]]:
    """(entry point, sub-command) for every sub-command the three parsers define."""
    import argparse

    from ev3dgs.cli import ingest, main, sim

    out = set()
    for exe, mod in (("ev3dgs", main), ("ev3dgs-sim", sim), ("ev3dgs-ingest", ingest)):
        for a in mod.build_parser()._actions:
            if isinstance(a, argparse._SubParsersAction):
                out |= {(exe, c) for c in a.choices}
    return out


@pytest.mark.slow
def test_installed_wheel_runs_every_sub_command(wheel, tmp_path):
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
    ran: set[tuple[str, str]] = set()

    def cli(exe, sub, *args, cwd=work, ok=True):
        ran.add((exe, sub))
        return _run([bin_ / exe, sub, *args], cwd, env, ok=ok)

    # stage 1: the core install
    version = re.match(r"ev3dgs-([^-]+)-", wheel.name).group(1)
    for exe in ("ev3dgs", "ev3dgs-sim", "ev3dgs-ingest"):
        assert _run([bin_ / exe, "--version"], work, env).stdout.split() == [exe, version]
    scenes = cli("ev3dgs-sim", "list-scenes").stdout.split("\n\n")[0].split()
    assert scenes == ["ficus", "lego", "lowlight", "materials"]
    has_bpy = _run([bin_ / "python", "-c", "import importlib.util as u; print(u.find_spec('bpy') is not None)"],
                   work, env).stdout.strip()
    assert has_bpy == "False"  # Blender is an extra, not a core dependency
    for sub, args in (("make-dataset", ["--scene", "ficus", "--quick", "--out", "f.h5"]),
                      ("record", ["--scene", "ficus", "--out", "f.aedat4"])):
        r = cli("ev3dgs-sim", sub, *args, ok=False)
        assert r.returncode == 2 and "ev3dgs[blender]" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (work / "f.h5").exists() and not (work / "f.aedat4").exists()

    # events and blur on small frame stacks
    rng = np.random.default_rng(0)
    frames = (0.2 + 0.6 * rng.random((1, 24, 32)) * np.linspace(0.5, 1.5, 20)[:, None, None]).astype(np.float32)
    np.savez(work / "frames.npz", frames=frames, t_us=np.arange(20, dtype=np.int64) * 1000)
    cli("ev3dgs-sim", "events", "frames.npz", "--out", "ev.h5", "--quiet")
    with h5py.File(work / "ev.h5") as f:
        assert f["events/t"].shape[0] > 0
    np.savez(work / "sub.npz", frames=np.repeat(frames[:5, ..., None], 3, axis=-1))
    cli("ev3dgs-sim", "blur", "sub.npz", "--out", "blur.png", "--quiet")
    assert (work / "blur.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # calibrate and compare on a small synthetic recording; ingest info and davis on it
    from ev3dgs.calib.synth import make_recording

    make_recording(work / "rec.aedat4", seconds=1.0, seed=3)
    cli("ev3dgs-sim", "calibrate", "rec.aedat4", "--out", "sensor.toml", "--bootstrap", "5", "--quiet")
    assert "[dvs]" in (work / "sensor.toml").read_text()
    cli("ev3dgs-sim", "compare", "rec.aedat4", "--config", "sensor.toml", "--out", "cmp", "--quiet")
    assert json.loads((work / "cmp" / "compare.json").read_text())["real_events"] > 0
    assert "aedat4" in cli("ev3dgs-ingest", "info", "rec.aedat4").stdout
    cli("ev3dgs-ingest", "davis", "rec.aedat4", "--out", "rec.h5", "--no-poses", "--quiet")
    sys.path.insert(0, str(ROOT / "tests"))
    try:
        from test_ingest_static import make_davis
        from view_scene import make_scene
    finally:
        sys.path.remove(str(ROOT / "tests"))
    make_davis(work / "static.aedat4")
    r = cli("ev3dgs-ingest", "davis", "static.aedat4", "--out", "static.h5", ok=False)
    assert r.returncode == 2 and "the camera did not move" in r.stderr and r.stderr.count("\n") == 1, r.stderr

    (work / "hand").mkdir()
    make_scene(work / "hand" / "scene.h5", with_imu=False)
    _chain(cli, work, "hand/scene.h5", "hand", full=True)

    # stage 2: with the Blender extra
    _run(pip + [f"{wheel}[blender]"], work, env)
    cli("ev3dgs-sim", "make-dataset", "--scene", "ficus", "--quick", "--views", "3", "--test-views", "1",
        "--workers", "2", "--out", "made/ficus.h5", "--quiet")
    with h5py.File(work / "made" / "ficus.h5") as f:
        assert f["train/images"].shape == (3, 72, 96, 3) and f["test/images"].shape[0] == 1
        assert f["events/t"].shape[0] > 0
    _chain(cli, work, "made/ficus.h5", "made")
    cli("ev3dgs-sim", "record", "--scene", "lego", "--out", "rec/lego.aedat4", "--seconds", "0.3", "--size",
        "64x48", "--render-rate", "50", "--samples", "2", "--quiet")
    assert (work / "rec" / "lego.trajectory.npz").is_file()
    cli("ev3dgs-ingest", "davis", "rec/lego.aedat4", "--out", "rec/lego.h5", "--no-poses", "--quiet")

    assert ran == sub_commands(), f"not run: {sub_commands() - ran}"


def _chain(cli, work, scene, tag, full=False):
    """train 20 steps -> eval -> export-dataset -> view figure, run from a folder other than the run's; `full`:
    render, export, info, validate and ingest e2nerf of the export too."""
    run = f"{tag}/run"
    cli("ev3dgs", "train", scene, "--out", run, "--iterations", "20", "--set", "init_points=2000", "--quiet")
    elsewhere = work / f"{tag}-elsewhere"
    elsewhere.mkdir()
    cli("ev3dgs", "eval", work / run, "--quiet", cwd=elsewhere)
    metrics = json.loads((work / run / "metrics.json").read_text())
    assert any(k in metrics for k in ("test", "train_sharp"))
    cli("ev3dgs", "export-dataset", work / scene, "--format", "e2nerf", "--out", "e2nerf", "--quiet", cwd=elsewhere)
    assert (elsewhere / "e2nerf" / "README.txt").is_file()
    cli("ev3dgs", "view", work / run, "--out", "view.png", "--quiet", cwd=elsewhere)
    assert (elsewhere / "view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if full:
        cli("ev3dgs", "render", work / run, "--out", "orbit.gif", "--frames", "3", "--quiet", cwd=elsewhere)
        assert (elsewhere / "orbit.gif").read_bytes()[:3] == b"GIF"
        cli("ev3dgs", "export", work / run, "--out", "model.ply", "--quiet", cwd=elsewhere)
        assert (elsewhere / "model.ply").read_bytes()[:3] == b"ply"
        assert cli("ev3dgs", "info", work / scene, cwd=elsewhere).stdout.strip()
        cli("ev3dgs", "validate", work / scene, "--quiet", cwd=elsewhere)
        cli("ev3dgs-ingest", "e2nerf", "e2nerf", "--out", "back.h5", "--quiet", cwd=elsewhere)
        with h5py.File(elsewhere / "back.h5") as f, h5py.File(work / scene) as g:
            assert f["train/images"].shape == g["train/images"].shape
