"""bench_fidelity's information oracle: the render cache it needs (derived_scenes.ensure_render_cache, which
renders a scene again when its file was made without one) and the jobs that train on the derived file and
score on the scene's own. The cells are test_study_attribution's tiny ones (random sub-frames beside their
render cache); a "render" here is a stand-in that writes a given file and cache, so no Blender is needed."""
from __future__ import annotations

import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
for sub in ("tools", "tools/bench", "tools/studies"):
    sys.path.insert(0, str(ROOT / sub))

import derived_scenes as ds  # noqa: E402
from test_study_attribution import make_cell  # noqa: E402

from ev3dgs import schema  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::ev3dgs.errors.SchemaWarning")


def _without_cache(tmp_path: Path, seed: int = 0) -> tuple[Path, Path]:
    """A cell's scene file alone in a folder (as bench_fidelity's cache holds files made without their render
    cache), and a folder holding the same file with its cache (what rendering it again makes)."""
    cell, _, _ = make_cell(tmp_path / f"made{seed}", "materials", seed=seed)
    alone = tmp_path / f"cache{seed}" / "lego_96x72.h5"
    alone.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(cell, alone)
    return alone, cell


def _render_as(source: Path):
    """A stand-in for make_dataset(..., keep_cache=True): ``source`` and its render cache under the name asked."""
    calls = []

    def make(out: Path):
        calls.append(out)
        shutil.copy(source, out)
        shutil.copytree(ds.render_cache(source), out.parent / f".{out.stem}.cache-0123")
    return make, calls


def test_a_file_without_its_render_cache_gets_it_from_a_render_of_the_same_frames(tmp_path):
    scene, source = _without_cache(tmp_path)
    before = scene.read_bytes()
    make, calls = _render_as(source)
    cache = ds.ensure_render_cache(scene, make)
    assert len(calls) == 1 and calls[0].parent != scene.parent          # rendered elsewhere, never over the file
    assert cache == ds.render_cache(scene) and cache.parent == scene.parent
    assert scene.read_bytes() == before                                   # the scene file is not replaced
    assert sorted(p.name for p in scene.parent.iterdir()) == [cache.name, scene.name]   # no temporary left
    for v in range(3):
        a, b = np.load(cache / f"view_{v:04d}.npz"), np.load(ds.render_cache(source) / f"view_{v:04d}.npz")
        assert np.array_equal(a["frames"], b["frames"]) and np.array_equal(a["poses"], b["poses"])
    assert ds.ensure_render_cache(scene, make) == cache and len(calls) == 1   # found now: no second render


def test_a_render_of_other_frames_is_refused_and_leaves_the_file_alone(tmp_path):
    scene, _ = _without_cache(tmp_path, seed=0)
    _, other = _without_cache(tmp_path, seed=1)     # another cell: other frames under the same name
    before = scene.read_bytes()
    make, _ = _render_as(other)
    with pytest.raises(SystemExit, match="other train images"):
        ds.ensure_render_cache(scene, make)
    assert scene.read_bytes() == before
    assert [p.name for p in scene.parent.iterdir()] == [scene.name]       # no cache adopted, no temporary left


def test_info_oracle_jobs_train_on_the_derived_file_and_score_on_the_scene(tmp_path):
    """The derived file (every sharp sub-frame at its pose) has 17 times the training images of the scene; the
    info oracle's model must be scored on the scene's own 24 blur views and its test views."""
    from bench_fidelity import DEFAULT_VARIANTS, VARIANTS, make_jobs

    scene, source = _without_cache(tmp_path)
    ds.ensure_render_cache(scene, _render_as(source)[0])
    derived = ds.derived_scenes("materials", scene, tmp_path / "cache0" / "derived" / scene.stem)
    assert len(schema.read(derived["info"]).train) == ds.SUBFRAMES * len(schema.read(scene).train)
    variants = {k: VARIANTS[k] for k in DEFAULT_VARIANTS}
    assert "info-oracle" in variants
    jobs = make_jobs(["lego"], {"lego": scene}, variants, 1, tmp_path, None, {"lego": derived}, iterations=10)
    by = {j["variant"]: j for j in jobs}
    assert by["info-oracle"]["scene_path"] == str(derived["info"])
    assert by["info-oracle"]["eval_scene"] == str(scene)
    assert by["info-oracle"]["overrides"] == {"oracle": True}
    assert by["info-oracle"]["out"] == str(tmp_path / "runs" / scene.stem / "info-oracle_s0")
    for name in ("naive", "blur-only", "blur+event", "oracle"):
        assert by[name]["scene_path"] == str(scene) and by[name]["eval_scene"] is None


def test_same_frames_allows_the_rounding_of_a_float_render_and_nothing_more():
    rng = np.random.default_rng(0)
    a = rng.integers(1, 255, (4, 30, 40, 3)).astype(np.uint8)
    flips = a.copy()
    idx = rng.choice(a.size, int(ds.RENDER_FLIP_SHARE * a.size), replace=False)   # the most it allows
    flips.reshape(-1)[idx] += 1
    assert ds.same_frames(a, a) and ds.same_frames(a, flips)
    more = flips.copy()
    more.reshape(-1)[np.setdiff1d(np.arange(a.size), idx)[0]] -= 1                  # one flip too many
    assert not ds.same_frames(a, more)
    two = a.copy()
    two.reshape(-1)[0] += 2                                                         # one value two levels off
    assert not ds.same_frames(a, two)
    assert not ds.same_frames(a, a[:3])


def test_a_render_that_rounds_a_few_values_the_other_way_is_the_same_render(tmp_path):
    """A glossy scene rendered again lands a few 8-bit values one level apart: its cache is adopted."""
    scene, source = _without_cache(tmp_path)
    moved = tmp_path / "moved" / source.name
    moved.parent.mkdir()
    shutil.copytree(ds.render_cache(source), moved.parent / ds.render_cache(source).name)
    sc = schema.read(source)
    images = np.asarray(sc.train.images).copy()
    images[0, 0, 0, 0] ^= 1                                                           # one level, one value
    schema.write(replace(sc, train=replace(sc.train, images=images)), moved)
    cache = ds.ensure_render_cache(scene, _render_as(moved)[0])
    assert cache.parent == scene.parent


def test_an_interrupted_render_resumes_from_its_cache_and_its_file_is_made_again(tmp_path):
    """A render stopped after writing its file (before the check): the next call makes the file again in the
    same temporary folder, where make_dataset would find the views it had already rendered."""
    scene, source = _without_cache(tmp_path)
    tmp = scene.parent / f".{scene.stem}.rerender"
    tmp.mkdir()
    (tmp / scene.name).write_bytes(b"an interrupted attempt's file")
    seen = []

    def make(out: Path):
        seen.append(out.exists())       # make_dataset refuses to replace a file: it must be gone
        _render_as(source)[0](out)
    assert ds.ensure_render_cache(scene, make).parent == scene.parent
    assert seen == [False] and not tmp.exists()
