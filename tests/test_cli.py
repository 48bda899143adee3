"""The command lines: real files in, one-line errors with exit code 2, nothing half-written."""
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.cli import main as ev3dgs_main
from ev3dgs.cli import sim as sim_cli
from ev3dgs.sim import DVSConfig, simulate_events
from ev3dgs.sim.blur import blur_frames
from ev3dgs.sim.config import Leak


@pytest.fixture
def npz(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.uniform(0.05, 1.5, (6, 12, 20)).astype(np.float32)
    t_us = np.array([0, 500, 1000, 2500, 2600, 9000], np.int64)
    path = tmp_path / "seq.npz"
    np.savez(path, frames=frames, t_us=t_us)
    return path, frames, t_us


def test_events_command_writes_the_simulators_events(npz, tmp_path, capsys):
    path, frames, t_us = npz
    cfg = tmp_path / "fx.toml"
    cfg.write_text("[dvs]\npos_threshold = 0.15\n[dvs.leak]\nrate_hz = 3.0\n")
    out = tmp_path / "ev.h5"
    assert sim_cli.main([
        "events", str(path), "--out", str(out), "--config", str(cfg), "--seed", "4"]) == 0
    sc = schema.read(out, require_complete=False)
    direct = simulate_events(frames, t_us, DVSConfig(pos_threshold=0.15, leak=Leak(rate_hz=3.0)), seed=4)
    got = sc.events.load()
    assert len(got) == len(direct) > 0
    for n in "txyp":
        assert np.array_equal(getattr(got, n), getattr(direct, n))
    assert (sc.camera.width, sc.camera.height) == (20, 12)
    assert sc.sensor.pos_threshold == 0.15 and sc.sensor.color_filter == "none"
    assert sc.config["sim"]["dvs"]["leak"]["rate_hz"] == 3.0
    assert "events" in capsys.readouterr().out


def test_blur_command_matches_the_library(tmp_path):
    rng = np.random.default_rng(1)
    frames = rng.uniform(0, 1, (5, 8, 10, 3))
    np.savez(tmp_path / "sub.npz", frames=frames)
    out = tmp_path / "b.png"
    assert sim_cli.main(["blur", str(tmp_path / "sub.npz"), "--out", str(out), "--quiet"]) == 0
    png = cv2.cvtColor(cv2.imread(str(out)), cv2.COLOR_BGR2RGB)
    assert np.array_equal(png, blur_frames(frames))


def bad_inputs(tmp_path):
    f = np.ones((3, 4, 4), np.float32)
    t = np.array([0, 1, 2], np.int64)
    cases = {
        "missing-key": dict(frames=f),
        "nan": dict(frames=np.where(np.eye(4, dtype=bool), np.nan, f).astype(np.float32), t_us=t),
        "negative": dict(frames=-f, t_us=t),
        "unsorted": dict(frames=f, t_us=np.array([0, 2, 1])),
        "duplicate": dict(frames=f, t_us=np.array([0, 1, 1])),
        "wrong-shape": dict(frames=np.ones((3, 4, 4, 2), np.float32), t_us=t),
    }
    for name, arrays in cases.items():
        np.savez(tmp_path / f"{name}.npz", **arrays)
    (tmp_path / "corrupt.npz").write_bytes(b"PK\x03\x04 not really a zip")
    return [*cases, "corrupt"]


def test_bad_inputs_exit_2_with_one_line_and_keep_existing_output(tmp_path, capsys):
    out = tmp_path / "out.h5"
    out.write_bytes(b"precious")
    for name in bad_inputs(tmp_path):
        code = sim_cli.main(["events", str(tmp_path / f"{name}.npz"), "--out", str(out), "--force"])
        err = capsys.readouterr().err
        assert code == 2, name
        assert err.startswith("error: ") and err.count("\n") == 1, (name, err)
        assert out.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


@pytest.mark.parametrize("config,match", [
    ("[dvs]\npos_treshold = 0.1\n", "unknown config key dvs.pos_treshold"),
    ("[dvs]\npos_threshold = -1\n", "pos_threshold"),
    ("[dvs.refractory]\nperiod_us = 'soon'\n", "expected a number"),
    ("[dvs\n", "invalid TOML"),
    ("[camera]\n", "unknown config key camera"),
])
def test_bad_configs_exit_2(npz, tmp_path, capsys, config, match):
    path, _, _ = npz
    cfg = tmp_path / "c.toml"
    cfg.write_text(config)
    assert sim_cli.main(["events", str(path), "--out", str(tmp_path / "o.h5"), "--config", str(cfg)]) == 2
    assert match in capsys.readouterr().err
    assert not (tmp_path / "o.h5").exists()


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        sim_cli.main(["events"])
    assert e.value.code == 2 and capsys.readouterr().err.startswith("error: ")


def test_validate_and_info(npz, tmp_path, capsys):
    path, _, _ = npz
    out = tmp_path / "ev.h5"
    sim_cli.main(["events", str(path), "--out", str(out), "--quiet"])
    assert ev3dgs_main.main(["validate", str(out), "--partial"]) == 0
    assert ev3dgs_main.main(["validate", str(out)]) == 2  # an events-only file is not a training scene
    assert "/camera/K: missing" in capsys.readouterr().err
    assert ev3dgs_main.main(["info", str(out)]) == 0
    assert "events" in capsys.readouterr().out
    assert ev3dgs_main.main(["info", str(tmp_path / "nope.h5")]) == 2


def test_installed_entry_point_runs(npz, tmp_path):
    path, _, _ = npz
    exe = Path(sys.executable).with_name("ev3dgs-sim")
    r = subprocess.run([str(exe), "events", str(path), "--out", str(tmp_path / "e.h5")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([str(exe), "events", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x.h5")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr


def test_demo_runs_and_writes_a_valid_scene(tmp_path):
    from ev3dgs import demo

    result = demo.run(tmp_path, views=1, test_views=0, width=48, height=36, samples=2, quiet=True, train=False)
    schema.validate(result["path"], require_complete=True)
    assert result["events"] > 0
    png = cv2.imread(str(tmp_path / "lego_view0.png"))
    k = -(-demo.STRIP_MIN_PANEL // 48)           # each 48x36 panel enlarged k times, three panels side by side
    assert png.shape[1] == 3 * (k * 48 + 2 + 6) and png.shape[0] > k * 36 + 3 * demo._LINE   # 1 px frame, 6 apart


@pytest.mark.slow
def test_benchmark_script_writes_json_and_plot(tmp_path):
    import json

    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, str(root / "tools" / "bench" / "bench_sim.py"), "--repeats", "1",
                        "--json", str(tmp_path / "b.json"), "--plot", str(tmp_path / "b.png")],
                       capture_output=True, text=True, cwd=root)
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    modes = ("clean", "v2e-clean", "v2e-noisy", "all-noise")  # bench_sim.MODES
    assert {(r["motion_px_per_frame"], r["mode"]) for r in rows} == {(m, k) for m in (1, 4) for k in modes}
    clean = {r["motion_px_per_frame"]: r["events"] for r in rows if r["mode"] == "clean"}
    assert clean[4] > 2 * clean[1] > 0  # faster motion, more events
    assert (tmp_path / "b.png").stat().st_size > 1000


@pytest.mark.slow
def test_demo_whole_chain_small(tmp_path):
    from ev3dgs import demo

    result = demo.run(tmp_path, views=3, test_views=1, width=48, height=36, samples=2, quiet=True, iterations=20)
    comp = __import__("json").loads((tmp_path / "comparison.json").read_text())
    assert set(comp) == {"naive", "blur-only", "blur+event"}
    assert all(v["test_psnr"] > 5 for v in comp.values()) and result["events"] > 0
