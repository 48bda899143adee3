"""make-dataset end to end with Blender (bpy). One small run is in the fast suite; the rest are slow."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.cli import sim as sim_cli
from ev3dgs.geometry import project
from ev3dgs.sim.dataset import make_dataset
from ev3dgs.sim.scenes import load_scene, resolve_render

import importlib.util

if importlib.util.find_spec("bpy") is None:
    pytest.skip("bpy is not installed", allow_module_level=True)


def small(name="lego", **kw):
    spec = load_scene(name)
    return spec, resolve_render(spec, quick=True, **{"views": 2, "test_views": 1, "width": 64, "height": 48,
                                                     "samples": 4, **kw})


def check_scene(path, views, subframes):
    schema.validate(path, require_complete=True)
    sc = schema.read(path)
    tr = sc.train
    assert len(tr) == views and tr.poses.shape == (views, subframes, 4, 4)
    ev = sc.events.load()
    assert len(ev) > 0
    inside = np.zeros(len(ev), bool)
    for start, end in tr.exposure:
        inside |= (ev.t >= start) & (ev.t <= end)
    assert inside.all()                                     # every event falls inside an exposure window
    for v in range(views):
        assert not np.allclose(tr.poses[v, 0], tr.poses[v, -1])           # the camera shakes
        assert tr.exposure[v, 0] <= tr.pose_t[v].min() and tr.pose_t[v].max() <= tr.exposure[v, 1]
        blurry, sharp = np.asarray(tr.images[v], float), np.asarray(tr.sharp[v], float)
        assert np.abs(blurry - sharp).max() > 20 and np.abs(blurry - sharp).mean() > 0.2  # visible blur
    # the object is where K and the stored poses say: the bounds centre projects inside every image
    centre = np.asarray(sc.bounds).mean(axis=0)
    for pose in tr.sharp_poses:
        uv, depth = project(sc.camera.K, pose, centre[None])
        assert depth[0] > 0 and 0 <= uv[0, 0] < sc.camera.width and 0 <= uv[0, 1] < sc.camera.height
    return sc


def test_quick_dataset_is_valid(tmp_path):
    spec, render = small()
    stats = make_dataset(spec, render, tmp_path / "lego.h5", quiet=True)
    sc = check_scene(tmp_path / "lego.h5", 2, render.subframes)
    assert stats.views_rendered == 3 and stats.events == len(sc.events)
    assert sc.test.images.shape == (1, 48, 64, 3)
    assert sc.camera.background == pytest.approx((1.0, 1.0, 1.0))
    assert sc.config["render"]["width"] == 64 and sc.config["scene"] == "lego"
    # the default render device, auto, resolved by the worker: said in the stats and the file's provenance
    assert render.device == "auto" and stats.render_device in ("cpu", "cuda", "optix")
    assert sc.config["render_device"] == stats.render_device and sc.config["render"]["device"] == "auto"
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # cache removed, no temp files


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ficus", "materials", "lowlight"])
def test_each_builtin_scene(tmp_path, name):
    spec, render = small(name)
    make_dataset(spec, render, tmp_path / f"{name}.h5", quiet=True)
    sc = check_scene(tmp_path / f"{name}.h5", 2, render.subframes)
    assert sc.sensor.refractory_us == (spec.sensor.dvs.refractory.period_us if spec.sensor.dvs.refractory else 0)


@pytest.mark.slow
def test_even_subframes_render_the_midpoint_separately(tmp_path):
    spec, render = small(subframes=4, views=1, test_views=0)
    make_dataset(spec, render, tmp_path / "s.h5", quiet=True)
    sc = check_scene(tmp_path / "s.h5", 1, 4)
    assert not any(np.allclose(sc.train.sharp_poses[0], p) for p in sc.train.poses[0])


@pytest.mark.slow
def test_rerun_uses_the_cache(tmp_path):
    spec, render = small()
    first = make_dataset(spec, render, tmp_path / "a.h5", quiet=True, keep_cache=True)
    again = make_dataset(spec, render, tmp_path / "a.h5", quiet=True)
    assert first.views_rendered == 3 and again.views_rendered == 0 and again.views_cached == 3


@pytest.mark.slow
def test_kill_9_leaves_no_scene_file_and_resumes(tmp_path):
    out = tmp_path / "k.h5"
    cmd = [str(Path(sys.executable).with_name("ev3dgs-sim")), "make-dataset", "--scene", "lego", "--quick",
           "--views", "4", "--test-views", "0", "--size", "64x48", "--samples", "4", "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and not list(tmp_path.glob(".k.cache-*/view_*.npz")):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists()
    cached = len(list(tmp_path.glob(".k.cache-*/view_*.npz")))
    assert cached >= 1
    r = subprocess.run(cmd[:-1], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert f"{4 - cached} views rendered, {cached} from cache" in r.stdout
    check_scene(out, 4, 17)


@pytest.mark.slow
def test_user_blend_file(tmp_path):
    blend = tmp_path / "user.blend"
    script = (
        "import bpy\n"
        "bpy.ops.wm.read_factory_settings(use_empty=True)\n"
        "bpy.ops.mesh.primitive_monkey_add(size=1.2)\n"
        "mat = bpy.data.materials.new('m')\n"
        "bpy.context.object.data.materials.append(mat)\n"
        "sun = bpy.data.objects.new('sun', bpy.data.lights.new('sun', 'SUN'))\n"
        "bpy.context.scene.collection.objects.link(sun)\n"
        f"bpy.ops.wm.save_as_mainfile(filepath={str(blend)!r})\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True, capture_output=True)
    spec, render = small()
    make_dataset(spec, render, tmp_path / "u.h5", blend=blend, quiet=True)
    sc = check_scene(tmp_path / "u.h5", 2, render.subframes)
    assert sc.config["blend"] == str(blend)
    assert np.allclose(np.asarray(sc.bounds).mean(axis=0), 0, atol=0.3)


@pytest.mark.parametrize("args,match", [
    (["--scene", "lego", "--blend", "/nonexistent.blend"], ".blend file not found"),
    (["--scene", "lego", "--size", "4x4"], "render size"),
    (["--scene", "lego", "--workers", "0"], "--workers"),
    (["--scene", "nosuch"], "unknown scene"),
    (["--scene", "lego", "--subframes", "1"], "subframes"),
])
def test_bad_arguments_exit_2(tmp_path, capsys, args, match):
    assert sim_cli.main(["make-dataset", *args, "--out", str(tmp_path / "x.h5"), "--quick"]) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1
    assert not (tmp_path / "x.h5").exists()


def test_denoise_prefilter_option(tmp_path, monkeypatch, capsys):
    """--denoise-prefilter reaches the render settings of make-dataset and record; a bad value is a usage
    error (exit 2, naming the option); the CLI's choices are the scene schema's."""
    import ev3dgs.sim.dataset as dataset
    import ev3dgs.sim.record as record_mod
    from ev3dgs.sim.scenes import PREFILTERS

    assert sim_cli.PREFILTERS == PREFILTERS
    got = {}
    monkeypatch.setattr(dataset, "make_dataset", lambda spec, render, out, **kw: got.setdefault("make", render))
    monkeypatch.setattr(record_mod, "record", lambda *a, **kw: got.setdefault("record", kw))
    out = str(tmp_path / "x.h5")
    assert sim_cli.main(["make-dataset", "--scene", "lego", "--out", out, "--quiet"]) == 0
    assert got.pop("make").denoise_prefilter == "accurate"
    assert sim_cli.main(["make-dataset", "--scene", "lego", "--quick", "--out", out, "--quiet"]) == 0
    assert got.pop("make").denoise_prefilter == "fast"
    assert sim_cli.main(["make-dataset", "--scene", "lego", "--quick", "--denoise-prefilter", "accurate",
                         "--out", out, "--quiet"]) == 0
    assert got.pop("make").denoise_prefilter == "accurate"
    rec = str(tmp_path / "r.aedat4")
    assert sim_cli.main(["record", "--scene", "lego", "--out", rec, "--denoise-prefilter", "fast", "--quiet"]) == 0
    assert got.pop("record")["denoise_prefilter"] == "fast"
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        sim_cli.main(["make-dataset", "--scene", "lego", "--denoise-prefilter", "slow", "--out", out])
    assert e.value.code == 2 and "denoise-prefilter" in capsys.readouterr().err
