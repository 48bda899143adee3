"""make-dataset --render-device: the option and the scene's [render] device reach Cycles' preferences; auto
falls back to the CPU where Cycles finds no GPU. The bpy tests run Blender in this process (no render), so, as
tests/test_blender.py's, they are marked slow; the default suite's tests/test_make_dataset.py quick dataset checks
that auto rendered on a device and said which."""
import importlib.util
from types import SimpleNamespace

import pytest

from ev3dgs.cli import sim as sim_cli
from ev3dgs.errors import ConfigError
from ev3dgs.sim.scenes import RENDER_DEVICES, Render, load_scene, resolve_render



def test_the_option_reaches_the_render_settings_and_bad_values_are_refused(tmp_path, monkeypatch, capsys):
    import ev3dgs.sim.dataset as dataset

    assert sim_cli.RENDER_DEVICES == RENDER_DEVICES == ("auto", "cpu", "cuda", "optix")
    got = []
    monkeypatch.setattr(sim_cli, "require_blender", lambda command: None)
    monkeypatch.setattr(dataset, "make_dataset", lambda spec, render, out, **kw: got.append(render)
                        or SimpleNamespace(seconds={}, path=out))
    out = str(tmp_path / "x.h5")
    assert sim_cli.main(["make-dataset", "--scene", "lego", "--out", out, "--quiet"]) == 0
    for dev in RENDER_DEVICES:
        assert sim_cli.main(["make-dataset", "--scene", "lego", "--render-device", dev, "--out", out, "--quiet"]) == 0
    assert [r.device for r in got] == ["auto", *RENDER_DEVICES]
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        sim_cli.main(["make-dataset", "--scene", "lego", "--render-device", "metal", "--out", out])
    assert e.value.code == 2 and "--render-device" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="render.device"):
        Render(device="gpu")
    assert resolve_render(load_scene("lego"), device="cuda").device == "cuda"


def test_the_device_is_not_part_of_the_render_cache_key():
    """A run resumed on another device keeps the views already rendered; every other setting changes the key."""
    from ev3dgs.sim.dataset import _cache_key

    spec = load_scene("lego")
    keys = {dev: _cache_key(spec, resolve_render(spec, device=dev), None, 0) for dev in RENDER_DEVICES}
    assert len(set(keys.values())) == 1
    assert _cache_key(spec, resolve_render(spec, samples=3), None, 0) != keys["auto"]


@pytest.fixture
def render_mod():
    pytest.importorskip("bpy")
    from ev3dgs_blender import render

    return render


def _cycles():
    import bpy

    return bpy.context.preferences.addons["cycles"].preferences, bpy.context.scene


def _gpus(kind):
    prefs, _ = _cycles()
    try:
        return [d for d in prefs.get_devices_for_type(kind) if d.type == kind]
    except (TypeError, ValueError):
        return []


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="bpy is not installed")
def test_cpu_and_auto_without_a_gpu_reach_cycles(render_mod):
    K = [[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]
    info = render_mod.init_scene(None, {}, None, 16, 12, K, 1, False, (0, 0, 0), 0, render_device="cpu")
    prefs, scene = _cycles()
    assert info["render_device"] == "cpu" and prefs.compute_device_type == "NONE" and scene.cycles.device == "CPU"
    if any(_gpus(k) for k in render_mod.AUTO_KINDS):
        pytest.skip("Cycles finds a GPU: the fallback cannot be seen")
    # auto: no GPU, so the CPU, and the same preferences
    info = render_mod.init_scene(None, {}, None, 16, 12, K, 1, False, (0, 0, 0), 0, render_device="auto")
    prefs, scene = _cycles()
    assert info["render_device"] == "cpu" and prefs.compute_device_type == "NONE" and scene.cycles.device == "CPU"
    # an explicit GPU that is not there is an error naming it, not a silent CPU render
    for dev in ("cuda", "optix"):
        with pytest.raises(RuntimeError, match=dev.upper()):
            render_mod.init_scene(None, {}, None, 16, 12, K, 1, False, (0, 0, 0), 0, render_device=dev)
    with pytest.raises(ValueError, match="render_device"):
        render_mod.init_scene(None, {}, None, 16, 12, K, 1, False, (0, 0, 0), 0, render_device="gpu")


class FakeDevice:
    def __init__(self, name, type_):
        self.name, self.type, self.use = name, type_, True


class FakePrefs:
    """The Cycles add-on preferences as setup_device uses them, with the GPUs a machine would have."""

    def __init__(self, gpus):
        self.gpus = gpus  # {kind: [names]}
        self.compute_device_type = "NONE"
        self.cpu = FakeDevice("CPU", "CPU")
        self.devices = {k: [FakeDevice(n, k) for n in names] for k, names in gpus.items()}

    def get_devices_for_type(self, kind):
        if kind not in ("CUDA", "OPTIX", "HIP", "ONEAPI"):
            raise TypeError(kind)
        return [*self.devices.get(kind, []), self.cpu]


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="bpy is not installed")
@pytest.mark.parametrize("gpus, asked, kind", [({"CUDA": ["H100"], "OPTIX": ["H100"]}, "auto", "CUDA"),
                                               ({"OPTIX": ["RTX"]}, "auto", "OPTIX"),
                                               ({"CUDA": ["H100"], "OPTIX": ["H100"]}, "optix", "OPTIX"),
                                               ({"CUDA": ["A", "B"]}, "cuda", "CUDA")])
def test_a_gpu_cycles_finds_is_selected_and_the_cpu_left_out(render_mod, monkeypatch, gpus, asked, kind):
    """With Cycles' device list standing in for a machine's GPUs: the kind asked for (auto: CUDA, then
    OptiX) becomes compute_device_type, its devices are used and the CPU is not, and the scene renders on the
    GPU; a GPU machine's auto never falls back to the CPU."""
    import bpy

    render_mod.init_scene(None, {}, None, 16, 12, [[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]], 1, False,
                          (0, 0, 0), 0, render_device="cpu")
    fake = FakePrefs(gpus)
    monkeypatch.setattr(render_mod, "_cycles_preferences", lambda: fake)
    assert render_mod.setup_device(asked) == kind.lower()
    assert fake.compute_device_type == kind and bpy.context.scene.cycles.device == "GPU"
    assert all(d.use for d in fake.devices[kind]) and not fake.cpu.use
    render_mod.setup_device("cpu")
    assert fake.compute_device_type == "NONE" and bpy.context.scene.cycles.device == "CPU"
