"""`make demo` (ev3dgs/demo.py, issue 52 item 3): the kernels compiled once before the trainings, one progress
line per variant while they run (redrawn on a terminal, a line per tenth when piped), and a second run over an
existing demo folder that says what it reuses or why it starts afresh. The whole demo runs only at its test
size, and only in the slow tests."""
import io
import json
import os
import queue
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ev3dgs import demo

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------- progress

def test_progress_line_steps_loss_elapsed_eta():
    now = 1000.0
    st = {"start": now - 70, "t0": now - 60, "step0": 0, "step": 300, "loss": 0.0123}
    # 60 s for 300 steps since the first report: 0.2 s a step, 1200 steps left -> 240 s; 70 s since the start
    assert demo.progress_line("blur+event", st, 1500, now) == \
        "blur+event     300/1500 steps ( 20 %)  loss 0.01230  1:10 elapsed, ETA 4:00"
    st = {"start": now - 70, "t0": now - 60, "step0": 100, "step": 300, "loss": 0.0123}
    # resumed at step 100: 200 steps in 60 s, 1200 left -> 360 s
    assert demo.progress_line("blur+event", st, 1500, now).endswith("1:10 elapsed, ETA 6:00")
    assert demo.progress_line("naive", None, 1500, now) == "naive       waiting"
    assert demo.progress_line("naive", {"done": True, "elapsed": 3725.0}, 1500, now) == \
        "naive       done: 1500/1500 steps in 1:02:05"


def _feed(q, names, iterations):
    for step in range(1, iterations + 1):
        for n in names:
            q.put((n, step, 1.0 / step))
    for n in names:
        q.put((n, -1, None))


def test_progress_piped_prints_a_line_per_tenth_and_done():
    q, out = queue.Queue(), io.StringIO()
    names = ["blur-only", "naive"]
    _feed(q, names, 50)
    with demo.Progress(names, 50, q, stream=out, tty=False):
        pass
    lines = out.getvalue().splitlines()
    assert "\x1b" not in out.getvalue()
    for n in names:
        mine = [ln for ln in lines if ln.startswith(f"{n} ")]
        assert len(mine) == 11, mine     # 10 %, 20 %, ..., 100 %, done
        assert [f"{p:3d} %" in ln for p, ln in zip(range(10, 101, 10), mine)] == [True] * 10
        assert mine[-1].startswith(f"{n:11s} done: 50/50 steps in ")


def test_progress_on_a_terminal_redraws_in_place():
    q, out = queue.Queue(), io.StringIO()
    names = ["blur+event", "blur-only", "naive"]
    with demo.Progress(names, 20, q, stream=out, tty=True):
        _feed(q, names[:1], 20)
        q.put(("blur-only", 7, 0.5))
        time.sleep(1.2)                   # at least one redraw while "running"
    text = out.getvalue()
    assert "\x1b[3F" in text               # back up over the three lines before redrawing them
    last = text.split("\x1b[3F")[-1].split("\n")
    assert [ln.removeprefix("\x1b[2K")[:11].strip() for ln in last if ln] == names
    assert "done: 20/20" in last[0] and "7/20 steps" in last[1] and "waiting" in last[2]


# -------------------------------------------------------------------------- a second make demo

def _fake_demo(out: Path, wanted: dict, runs=()):
    """demo_out as a finished earlier demo would leave it (a small scene file under the demo scene's name)."""
    from ev3dgs.blob_scene import blob_scene

    out.mkdir(parents=True, exist_ok=True)
    blob_scene(out / "lego.h5", 32, 24, views=3, subframes=3, n=60, backend="reference", name="lego")
    (out / "demo.json").write_text(json.dumps(wanted))
    for name, iterations in runs:
        run = out / "runs" / name
        run.mkdir(parents=True)
        (run / "config.json").write_text(json.dumps({"scene": str(out / "lego.h5"), "iterations": iterations}))
        (run / "model.pt").write_bytes(b"m")
        (run / "metrics.json").write_text("{}")


def test_plan_of_a_second_demo(tmp_path):
    wanted = demo.settings("lego", 0, 1500, dict(demo.DEMO_RENDER))
    out = tmp_path / "demo_out"
    assert demo.plan(out, wanted) == ("new", [], "")
    assert demo.describe_plan(out, "new", [], "") == f"demo: writing into {out}/"
    _fake_demo(out, wanted, runs=[("naive", 1500), ("blur-only", 300)])
    mode, done, why = demo.plan(out, wanted)
    assert (mode, done) == ("reuse", ["naive"])        # blur-only ran 300 steps: trained again
    assert demo.describe_plan(out, mode, done, why) == (
        f"demo: {out}/ holds this demo's dataset and the finished runs naive: reusing them, training "
        "blur-only, blur+event (pass --fresh to start afresh)")
    mode, done, why = demo.plan(out, wanted, fresh=True)
    assert demo.describe_plan(out, mode, done, why) == (
        f"demo: {out}/ holds an earlier demo, but --fresh was given: starting afresh (its dataset and runs are "
        "made again and replace the old ones)")
    other = demo.settings("lego", 1, 1500, dict(demo.DEMO_RENDER))
    mode, done, why = demo.plan(out, other)
    assert mode == "afresh" and why == "its dataset was made with other settings: seed 0 (now 1)"
    longer = demo.settings("lego", 0, 3000, dict(demo.DEMO_RENDER))
    assert demo.plan(out, longer)[:2] == ("reuse", [])   # the dataset is the same; every run trains again
    (out / "lego.h5").write_bytes(b"cut")
    assert demo.plan(out, wanted)[2] == "its dataset lego.h5 is missing or incomplete"


def test_compile_kernels_once_in_this_process(monkeypatch, tmp_path, capsys):
    import torch

    from ev3dgs import numba_cache
    from ev3dgs.train import trainer

    fits = []

    class FakeTrainer:
        def __init__(self, cfg, run_dir, quiet=False):
            fits.append((cfg.iterations, cfg.threads, quiet))

        def fit(self, **kw):
            return {}

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(trainer, "Trainer", FakeTrainer)
    monkeypatch.setattr(numba_cache, "_NOTIFIED", set())
    monkeypatch.setattr(numba_cache, "missing_from_cache", lambda modules: ["rasterize_tiles"])
    assert demo.compile_kernels(tmp_path / "s.h5", 0, quiet=False)
    out = capsys.readouterr()
    assert out.out.startswith("demo: compiling the CPU rasterizer kernels once for the three trainings")
    assert fits == [(2, 1, True)]
    from ev3dgs.splat.cpu import announce_compile

    announce_compile()                       # the trainer's own notice: already given in this process
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(numba_cache, "missing_from_cache", lambda modules: [])
    assert not demo.compile_kernels(tmp_path / "s.h5", 0, quiet=False)
    assert capsys.readouterr().out == "" and len(fits) == 1


# ------------------------------------------------------------------------------ the whole demo

@pytest.mark.slow
def test_test_size_demo_compiles_once_and_a_second_run_reuses(tmp_path):
    """From an empty numba cache: one compile notice for the rasterizer, progress lines while training, the
    table; run again: the dataset and the three runs are reused, nothing is trained or rendered again."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "ev3dgs.demo", "--test-size", "--out", str(tmp_path / "d")]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    assert r.returncode == 0, r.stderr
    both = r.stdout + r.stderr
    assert both.count("compiling the CPU rasterizer kernels") == 1, both
    assert [ln.split()[0] for ln in r.stdout.splitlines() if " done: 20/20 steps" in ln] != []
    assert "blurry input" in r.stdout
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "d").rglob("*") if p.is_file()}
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[0] == (
        f"demo: {tmp_path / 'd'}/ holds this demo's dataset and the finished runs naive, blur-only, blur+event: "
        "reusing them, nothing to train (pass --fresh to start afresh)")
    after = {p: p.stat().st_mtime_ns for p in before}
    assert {p for p in before if before[p] != after[p]} <= {tmp_path / "d" / "demo.json",
                                                              tmp_path / "d" / "comparison.json"}


def test_ctrl_c_says_the_same_command_continues(tmp_path, monkeypatch, capsys):
    out = tmp_path / "d"

    def interrupted(path, *a, **k):
        path.mkdir(parents=True, exist_ok=True)
        (path / "demo.json").write_text("{}")     # the dataset was made
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "run", interrupted)
    assert demo.main(["--out", str(out)]) == 130
    assert capsys.readouterr().err == ("error: interrupted; the same command continues: it reuses the dataset and "
                                       "the finished runs, and resumes the others from their last checkpoints\n")
