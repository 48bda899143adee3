"""The documentation: the site builds with `mkdocs build --strict`, the scene-file page names everything a scene
file can hold, the README is short and current, and every command has a page."""
from __future__ import annotations

import importlib
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PARSERS = {"ev3dgs-sim": "ev3dgs.cli.sim", "ev3dgs-ingest": "ev3dgs.cli.ingest", "ev3dgs": "ev3dgs.cli.main"}


def test_mkdocs_build_strict(tmp_path):
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install 'ev3dgs[docs]'); the site cannot be built")
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(site), "-f", "mkdocs.yml"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert r.returncode == 0, f"mkdocs build --strict failed:\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}"
    assert (site / "schema" / "index.html").is_file()
    # the option reference was generated from the parsers on every command page
    train = (site / "commands" / "ev3dgs-train" / "index.html").read_text()
    assert "--iterations" in train and "cli-reference" not in train


def _complete_scene():
    """A scene with every optional part and attribute set, written through ev3dgs.schema."""
    from ev3dgs import schema
    from ev3dgs.events import Events

    rng = np.random.default_rng(0)
    W, H, N, S, M = 8, 6, 2, 3, 1
    eye = lambda *shape: np.tile(np.eye(4), shape + (1, 1))  # noqa: E731
    exposure = np.array([[0, 5000], [10000, 15000]], np.int64)
    pose_t = exposure[:, :1] + np.array([0, 2500, 5000], np.int64)[None]
    img = lambda n: rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8)  # noqa: E731
    n_ev = 50
    events = Events(np.sort(rng.integers(0, 15000, n_ev)).astype(np.int64), rng.integers(0, W, n_ev),
                    rng.integers(0, H, n_ev), rng.choice([-1, 1], n_ev))
    return schema.Scene(
        name="all", source="test", config={"a": 1}, created="2026-01-01T00:00:00+00:00",
        camera=schema.Camera(W, H, K=np.array([[5.0, 0, 4], [0, 5.0, 3], [0, 0, 1]]), distortion=np.zeros(5),
                             background=(1.0, 1.0, 1.0)),
        events=events,
        sensor=schema.EventSensor(0.2, 0.2, "RGGB", 100.0, log_knee=1e-3, count_convention="random_phase",
                                  camera_raw_matrix=np.eye(3)),
        train=schema.Train(img(N), exposure, eye(N, S), pose_t, img(N), eye(N), transfer="srgb"),
        test=schema.Test(img(M), eye(M)),
        points=schema.Points(rng.normal(size=(4, 3)).astype(np.float32), rng.integers(0, 256, (4, 3), dtype=np.uint8)),
        imu=schema.Imu(np.arange(3, dtype=np.int64), np.zeros((3, 3), np.float32), np.zeros((3, 3), np.float32),
                       np.zeros(3, np.float32)),
        bounds=np.array([[-1.0, -1, -1], [1, 1, 1]]),
    )


def _names_in_file(path: Path) -> set[str]:
    """Every group, dataset and attribute name in an HDF5 file, walked with h5py (independent of validate)."""
    names: set[str] = set()

    def visit(name, obj):
        names.add(name.rsplit("/", 1)[-1])
        names.update(obj.attrs.keys())

    with h5py.File(path, "r") as f:
        names.update(f.attrs.keys())
        f.visititems(visit)
    return names


def test_schema_page_names_every_dataset_and_attribute(tmp_path):
    from ev3dgs import schema

    path = schema.write(_complete_scene(), tmp_path / "all.h5")
    schema.validate(path)  # the complete scene is valid: it is what validate checks
    names = _names_in_file(path)
    # and the layout table validate itself iterates over (groups and their datasets)
    for group, items in schema._PARTS.items():
        names.add(group)
        names.update(item[0] for item in items)
    names.update(n for n, _ in schema._EVENT_DTYPES)
    assert {"format", "version", "K", "log_knee", "transfer", "temperature", "sharp_poses"} <= names
    page = (DOCS / "schema.md").read_text()
    missing = sorted(n for n in names if f"`{n}`" not in page and f"`/{n}`" not in page)
    assert not missing, f"docs/schema.md does not document: {missing}"
    for value in (*schema.COLOR_FILTERS[1:], *schema.COUNT_CONVENTIONS, *schema.TRANSFERS, schema.FORMAT):
        assert f"`{value}`" in page, f"docs/schema.md does not name the value {value!r}"


def test_readme_short_and_current():
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines (at most 200)"
    body = [ln for ln in lines if ln.strip() and not ln.startswith("# ")]
    assert body[0].startswith("```"), "README.md must start with the make demo / make test block"
    block = body[1:body.index("```", 1)] if "```" in body[1:] else []
    commands = [ln.split("#")[0].strip() for ln in block if ln.split("#")[0].strip()]
    assert commands == ["make demo", "make test"], commands
    assert all("#" in ln for ln in block), "each command in the first block is explained"
    assert not re.search(r"\bround", text, re.IGNORECASE), "README.md speaks of rounds"
    assert not re.search(r"\b[0-9a-f]{40}\b", text) and not re.search(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7}\b",
                                                                        text), "README.md names a commit hash"
    assert "../shared" not in text


def test_no_paths_outside_the_repo():
    for p in [ROOT / "README.md", ROOT / "mkdocs.yml", *DOCS.rglob("*.md"), *DOCS.rglob("*.py")]:
        assert "../shared" not in p.read_text(), p


def _commands():
    import argparse

    out = []
    for prog, module in PARSERS.items():
        parser = importlib.import_module(module).build_parser()
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        out += [(prog, name) for name in sub.choices]
    return out


def test_every_command_has_a_page():
    commands = _commands()
    assert len(commands) >= 16
    nav = (ROOT / "mkdocs.yml").read_text().split("\nnav:", 1)[1]
    for prog, name in commands:
        page = DOCS / "commands" / f"{prog}-{name}.md"
        assert page.is_file(), f"no page for `{prog} {name}`: {page.relative_to(ROOT)}"
        text = page.read_text()
        assert f"<!-- cli-reference: {prog} {name} -->" in text, f"{page.name} lacks its generated option reference"
        assert f"commands/{prog}-{name}.md" in nav, f"{page.name} is not in mkdocs.yml's nav"

