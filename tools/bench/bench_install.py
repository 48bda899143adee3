"""What an install costs: venv size and install time of the core package, core + the Blender extra, and the
full development install (`make setup`: every extra the tests need), each in a new venv from a wheel of the
checkout, with torch 2.13.0 (CPU build) installed first as the install docs say.

    python tools/bench/bench_install.py --json tools/results/bench_install.json [--keep DIR]

Sizes are what `du` counts under the venv (apparent bytes of every file). Install times depend on the package
cache and the network: they are reported, not compared.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import venv
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TORCH = "torch==2.13.0"


def _size(folder: Path) -> int:
    return sum(p.lstat().st_size for p in folder.rglob("*") if p.is_file() and not p.is_symlink())


def _pip(env_dir: Path, *args) -> float:
    t = time.perf_counter()
    subprocess.run([str(env_dir / "bin" / "python"), "-m", "pip", "install", "-q", *map(str, args)], check=True)
    return time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", default="tools/results/bench_install.json")
    ap.add_argument("--keep", type=Path, help="build the venvs in this folder and keep them (default: temporary)")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        base = a.keep or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                        str(base / "wheel"), str(ROOT)], check=True)
        (whl,) = (base / "wheel").glob("ev3dgs-*.whl")
        rows = []
        for name, extras, after in (("core", "", ()), ("core + blender", "[blender]", ()),
                                    ("development (make setup)", "[blender,view,docs,dev]", ("lpips==0.1.4",))):
            env_dir = base / ("venv-" + extras.strip("[]").replace(",", "-") if extras else "venv-core")
            venv.create(env_dir, with_pip=True)
            empty = _size(env_dir)
            seconds = _pip(env_dir, TORCH) + _pip(env_dir, f"{whl}{extras}")
            if after:
                seconds += _pip(env_dir, "--no-deps", *after)
            size = _size(env_dir)
            torch_size = _size(next((env_dir / "lib").glob("python*/site-packages/torch")))
            rows.append({"install": name, "extras": extras, "venv_bytes": size, "empty_venv_bytes": empty,
                         "torch_bytes": torch_size, "install_seconds": seconds})
            print(f"{name:26s} {size / 1e9:5.2f} GB (torch {torch_size / 1e9:.2f} GB), installed in {seconds:.0f} s",
                  flush=True)
    save_json(a.json, {"python": sys.version.split()[0], "torch": TORCH, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
