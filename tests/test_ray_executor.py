"""make-dataset with the Ray executor gives the same scene file as the local process pool."""
import importlib.util

import h5py
import numpy as np
import pytest

ray = pytest.importorskip("ray")
if importlib.util.find_spec("bpy") is None:
    pytest.skip("bpy is not installed", allow_module_level=True)

from ev3dgs.sim.dataset import make_dataset  # noqa: E402
from ev3dgs.sim.scenes import load_scene, resolve_render  # noqa: E402


def _arrays(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_ray_matches_local_pool(tmp_path):
    spec = load_scene("lego")
    render = resolve_render(spec, quick=True, views=2, test_views=1, width=48, height=36, samples=2)
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="ERROR")  # never a running cluster
    try:
        stats = make_dataset(spec, render, tmp_path / "ray.h5", workers=2, seed=3, quiet=True, executor="ray")
        assert ray.is_initialized()  # a Ray instance the caller started is left running
    finally:
        ray.shutdown()
    make_dataset(spec, render, tmp_path / "local.h5", workers=1, seed=3, quiet=True)
    assert stats.views_rendered == 3 and stats.events > 0
    a, b = _arrays(tmp_path / "ray.h5"), _arrays(tmp_path / "local.h5")
    assert a.keys() == b.keys()
    for name in ("train/images", "train/sharp", "train/poses", "test/images", "test/poses"):
        assert name in a, sorted(a)
    assert any(name.startswith("events") for name in a), sorted(a)
    for name in a:  # rendering is deterministic (fixed Cycles seed): every array is bit-identical
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        assert np.array_equal(a[name], b[name]), name
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # cache removed, no temp files
