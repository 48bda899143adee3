"""One behaviour for every `ev3dgs-sim`, `ev3dgs-ingest` and `ev3dgs export-dataset` command that writes: an
existing output is refused (exit 2, one line, the old output byte-identical) before any expensive work unless
--force, --force replaces it, --quiet prints nothing on stdout. make-dataset and record render with a stand-in
for the Blender workers (ev3dgs.sim.dataset.render_all), so these tests need no bpy and take seconds; without bpy
both commands fail at once with one line naming the extra."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ev3dgs import __version__
from ev3dgs.cli import ingest as ingest_cli
from ev3dgs.cli import main as ev3dgs_cli
from ev3dgs.cli import sim as sim_cli
from ev3dgs.events import Events
from ev3dgs.io.aedat4.writer import write_aedat4
from ev3dgs.io.types import FrameData


def fake_render_all(jobs, init_kwargs, cache, workers, quiet, executor="local", address=None):
    """What the Blender workers return (frames (n, H, W, 3) float32, readback poses), drawn from the poses: a
    striped pattern that moves with the camera, so that the event simulator sees motion."""
    H, W = init_kwargs["height"], init_kwargs["width"]
    xx = np.arange(W) / W

    def frame(p):
        row = 0.15 + 0.7 * (0.5 + 0.5 * np.sin(2 * np.pi * (3 * xx + 2 * p[0, 3] + p[1, 3])))
        return np.broadcast_to(row[None, :, None], (H, W, 3))

    results = {}
    for key, poses in jobs.items():
        poses = np.asarray(poses, np.float64)
        results[key] = {"frames": np.stack([frame(p) for p in poses]).astype(np.float32), "poses": poses}
    return results, {"bounds": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]}, len(jobs)


@pytest.fixture
def fake_blender(monkeypatch):
    import ev3dgs.sim.dataset as dataset
    import ev3dgs.sim.record as record

    monkeypatch.setattr(dataset, "render_all", fake_render_all)
    monkeypatch.setattr(record, "render_all", fake_render_all)


def small_recording(path: Path) -> Path:
    """A 64x48 AEDAT 4.0 file: 2000 events and 2 full-size APS frames."""
    t = 1_000_000 + 100 * np.arange(2000, dtype=np.int64)
    rng = np.random.default_rng(0)
    ev = Events(t, rng.integers(0, 64, 2000).astype(np.uint16), rng.integers(0, 48, 2000).astype(np.uint16),
                rng.choice(np.array([-1, 1], np.int8), 2000))
    frames = [FrameData(timestamp=s, exposure_start=s, exposure_end=s + 10_000, frame_start=s - 500,
                        frame_end=s + 10_500, image=np.full((48, 64), 90, np.uint8)) for s in (1_040_000, 1_120_000)]
    write_aedat4(path, 64, 48, ev, frames, None)
    return path


def _events_input(tmp):
    rng = np.random.default_rng(1)
    np.savez(tmp / "frames.npz", frames=rng.uniform(0.1, 1.0, (4, 12, 16)).astype(np.float32),
             t_us=np.array([0, 1000, 2000, 3000], np.int64))
    np.savez(tmp / "sub.npz", frames=rng.uniform(0, 1, (3, 12, 16, 3)))


def _scene(tmp) -> Path:
    scene = tmp / "in" / "scene.h5"
    scene.parent.mkdir(exist_ok=True)
    if not scene.exists():
        _events_input(tmp)
        assert sim_cli.main(["events", str(tmp / "frames.npz"), "--out", str(scene), "--quiet"]) == 0
    return scene


def _e2nerf_folder(tmp) -> Path:
    from test_e2nerf import make_synthetic

    root = tmp / "e2nerf"
    if not root.exists():
        make_synthetic(root, np.random.default_rng(0))
    return root


# name: (main, argv builder (tmp, out) -> args, output name, is a folder, (module, attribute) of the expensive work)
def _calib_input(tmp: Path) -> Path:
    """A short recording with APS frames and events (no Blender), made once per test folder."""
    from ev3dgs.calib.synth import make_recording

    p = tmp / "in.aedat4"
    if not p.exists():
        make_recording(p, seed=0, seconds=0.5)
    return p


COMMANDS = {
    "sim events": (sim_cli.main, lambda tmp, out: (_events_input(tmp), ["events", str(tmp / "frames.npz"),
                                                                          "--out", str(out)])[1],
                   "ev.h5", False, ("ev3dgs.sim", "simulate_events")),
    "sim blur": (sim_cli.main, lambda tmp, out: (_events_input(tmp), ["blur", str(tmp / "sub.npz"),
                                                                        "--out", str(out)])[1],
                 "blur.png", False, ("ev3dgs.sim.blur", "blur_frames")),
    "sim make-dataset": (sim_cli.main, lambda tmp, out: ["make-dataset", "--scene", "lego", "--quick", "--size",
                                                         "32x24", "--views", "1", "--test-views", "1", "--subframes",
                                                         "3", "--out", str(out)],
                         "lego.h5", False, ("ev3dgs.sim.dataset", "render_all")),
    "sim record": (sim_cli.main, lambda tmp, out: ["record", "--scene", "lego", "--seconds", "0.2", "--fps", "10",
                                                   "--exposure-ms", "20", "--render-rate", "50", "--size", "32x24",
                                                   "--out", str(out)],
                   "rec.aedat4", False, ("ev3dgs.sim.record", "render_all")),
    "ingest davis": (ingest_cli.main, lambda tmp, out: ["davis", str(small_recording(tmp / "in.aedat4")),
                                                        "--no-poses", "--out", str(out)],
                     "davis.h5", False, ("ev3dgs.io.davis", "ingest_davis")),
    "ingest e2nerf": (ingest_cli.main, lambda tmp, out: ["e2nerf", str(_e2nerf_folder(tmp)), "--out", str(out)],
                      "e2.h5", False, ("ev3dgs.io.e2nerf", "import_e2nerf")),
    "export-dataset": (ev3dgs_cli.main, lambda tmp, out: ["export-dataset", str(_scene(tmp)), "--format",
                                                          "events-h5", "--out", str(out)],
                       "export", True, ("ev3dgs.schema", "read")),
    "sim calibrate": (sim_cli.main, lambda tmp, out: ["calibrate", str(_calib_input(tmp)), "--out", str(out)],
                      "s.toml", False, ("ev3dgs.calib.report", "calibrate_recording")),
    "sim compare": (sim_cli.main, lambda tmp, out: ["compare", str(_calib_input(tmp)), "--out", str(out)],
                    "report", True, ("ev3dgs.calib.compare", "compare_recording")),
}


def _existing(out: Path, folder: bool) -> dict[Path, bytes]:
    """Put an earlier output at `out`; returns its files and bytes."""
    if folder:
        out.mkdir()
        (out / "earlier.txt").write_bytes(b"earlier result")
        return {out / "earlier.txt": b"earlier result"}
    out.write_bytes(b"earlier result")
    return {out: b"earlier result"}


@pytest.mark.parametrize("name", COMMANDS)
def test_existing_output_is_refused_before_any_work(name, tmp_path, capsys, monkeypatch, fake_blender):
    main, argv, out_name, folder, (module, attr) = COMMANDS[name]
    out = tmp_path / out_name
    args = argv(tmp_path, out)
    before = _existing(out, folder)
    capsys.readouterr()

    def expensive(*a, **k):
        raise AssertionError(f"{name}: {module}.{attr} ran although the output exists")

    monkeypatch.setattr(importlib.import_module(module), attr, expensive)
    assert main(args) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.startswith("error: ") and cap.err.count("\n") == 1, cap.err
    assert str(out) in cap.err and "--force" in cap.err
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in out.parent.iterdir() if p.name.startswith(".")) == []   # no temporary left


@pytest.mark.parametrize("name", COMMANDS)
def test_force_replaces_and_quiet_prints_nothing(name, tmp_path, capsys, fake_blender):
    main, argv, out_name, folder, _ = COMMANDS[name]
    out = tmp_path / out_name
    args = argv(tmp_path, out)
    before = _existing(out, folder)
    capsys.readouterr()
    assert main([*args, "--force", "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "", cap.out
    if folder:
        assert not any(p.exists() for p in before) and any(out.iterdir())
    else:
        assert out.read_bytes() != b"earlier result" and out.stat().st_size > 100
    assert sorted(p.name for p in out.parent.iterdir() if p.name.startswith(".")) == []


@pytest.mark.parametrize("name", COMMANDS)
def test_summary_without_quiet(name, tmp_path, capsys, fake_blender):
    main, argv, out_name, _, _ = COMMANDS[name]
    out = tmp_path / out_name
    assert main(argv(tmp_path, out)) == 0
    text = capsys.readouterr().out
    assert str(out) in text and text.endswith("\n")


@pytest.mark.parametrize("existing", ["rec.trajectory.npz", "rec.calibration.toml", "rec.sensor.toml"])
def test_record_refuses_an_existing_ground_truth(existing, tmp_path, capsys, fake_blender):
    main, argv, _, _, _ = COMMANDS["sim record"]
    (tmp_path / existing).write_bytes(b"earlier ground truth")
    assert main(argv(tmp_path, tmp_path / "rec.aedat4")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and existing in err and "--force" in err
    assert (tmp_path / existing).read_bytes() == b"earlier ground truth"
    assert not (tmp_path / "rec.aedat4").exists()
    assert main([*argv(tmp_path, tmp_path / "rec.aedat4"), "--force", "--quiet"]) == 0
    assert (tmp_path / existing).read_bytes() != b"earlier ground truth"
    z = np.load(tmp_path / "rec.trajectory.npz")
    assert z["exposure"].shape == (2, 2) and z["c2w"].shape[1:] == (4, 4)


@pytest.mark.parametrize("command", ["make-dataset", "record"])
def test_without_bpy_blender_commands_fail_at_once(command, tmp_path, capsys, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "bpy" else real(name, *a))
    out = tmp_path / ("x.h5" if command == "make-dataset" else "x.aedat4")
    # the check comes first: even an unknown scene is not looked at
    assert sim_cli.main([command, "--scene", "no-such-scene", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {command} renders with Blender, which is not installed")
    assert "pip install 'ev3dgs[blender]'" in err and "bpy 5.0.1" in err
    assert list(tmp_path.iterdir()) == []


def test_no_command_module_imports_bpy():
    code = ("import sys\n"
            "import ev3dgs.cli.sim, ev3dgs.cli.ingest, ev3dgs.cli.main, ev3dgs.sim.dataset, ev3dgs.sim.record\n"
            "import ev3dgs.sim.executors, ev3dgs_blender.worker, ev3dgs_blender.shake\n"
            "ev3dgs.cli.sim.build_parser().parse_args(['make-dataset', '--scene', 'lego', '--out', 'x.h5'])\n"
            "assert 'bpy' not in sys.modules, 'bpy imported'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("main,prog", [(sim_cli.main, "ev3dgs-sim"), (ingest_cli.main, "ev3dgs-ingest")])
def test_version(main, prog, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"{prog} {__version__}"


@pytest.mark.parametrize("prog", ["ev3dgs-sim", "ev3dgs-ingest"])
def test_installed_entry_points_print_their_version(prog):
    exe = Path(sys.executable).with_name(prog)
    if not exe.exists():
        pytest.skip(f"{prog} is not installed as a script")
    r = subprocess.run([str(exe), "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == f"{prog} {__version__}"


def test_every_writing_subcommand_has_force_and_quiet():
    """The parametrised tests above cover every sub-command that writes; info and list-scenes write nothing."""
    import argparse

    covered = {n.split()[-1] for n in COMMANDS}
    for build in (sim_cli.build_parser, ingest_cli.build_parser):
        sub = next(a for a in build()._actions if isinstance(a, argparse._SubParsersAction))
        for cmd, p in sub.choices.items():
            opts = {o for a in p._actions for o in a.option_strings}
            if cmd in ("info", "list-scenes"):
                assert "--force" not in opts
                continue
            assert cmd in covered and {"--out", "--force", "--quiet"} <= opts, cmd
