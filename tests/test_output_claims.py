"""Two writers to one output (issue 53): every command claims its output before any work, so of two real
processes started together on the same --out exactly one writes it and the other refuses in one line (exit 2)
without touching it; publishing never replaces an output that appeared meanwhile; stale claims of killed
processes are cleared with a warning; temporaries a kill -9 left are removed by the next run.

The races are deterministic: each process runs with EV3DGS_TEST_PAUSE=claimed:FILE (ev3dgs.claims), so the one
that gets the claim stops right after taking it and waits until the test deletes FILE; the other one meets the
held claim whatever the scheduling. Kills use EV3DGS_TEST_PAUSE=publish:FILE: the process stops with its
temporary output complete, just before renaming it, and is killed there."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ev3dgs import claims
from ev3dgs.outputs import OutputError, atomic_path

from test_cli_uniform import FAST, scene, trained  # noqa: F401  (fixtures: a tiny scene and a trained run)

REPO = Path(__file__).resolve().parents[1]
MODULES = {"ev3dgs": "ev3dgs.cli.main", "ev3dgs-sim": "ev3dgs.cli.sim", "ev3dgs-ingest": "ev3dgs.cli.ingest",
           "demo": "ev3dgs.demo"}
HAS_BPY = __import__("importlib").util.find_spec("bpy") is not None


def _env(pause: str | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    env.pop(claims.PAUSE_ENV, None)
    if pause:
        env[claims.PAUSE_ENV] = pause
    return env


def _start(argv, pause=None, cwd=None) -> subprocess.Popen:
    tool, *rest = argv
    return subprocess.Popen([sys.executable, "-m", MODULES[tool], *rest], env=_env(pause), cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(cond, timeout=240.0, what="condition"):
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _finish(p: subprocess.Popen, timeout=600) -> tuple[int, str, str]:
    out, err = p.communicate(timeout=timeout)
    return p.returncode, out, err


def leftovers(folder: Path) -> list[str]:
    """Temporaries and claims anywhere under `folder`."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")
                  if ".tmp-" in p.name or p.name.endswith(".claim") or p.name == claims.RUN_LOCK)


# ------------------------------------------------------------------------------------------------ inputs

@pytest.fixture(scope="module")
def _inputs(scene, tmp_path_factory):  # noqa: F811
    d = tmp_path_factory.mktemp("claim-inputs")
    from ev3dgs.calib.synth import Truth, make_recording

    make_recording(d / "rec.aedat4", Truth(), seed=1, seconds=0.4)
    rng = np.random.default_rng(0)
    np.savez(d / "frames.npz", frames=rng.random((6, 12, 16), dtype=np.float32) * 0.8 + 0.1,
             t_us=np.arange(6, dtype=np.int64) * 1000)
    np.savez(d / "sub.npz", frames=rng.random((3, 12, 16, 3), dtype=np.float32))
    (d / "scene.toml").write_text('name = "tiny"\nbuilder = "lego"\n')
    return {"scene": scene, "rec": str(d / "rec.aedat4"), "frames": str(d / "frames.npz"), "sub": str(d / "sub.npz")}


@pytest.fixture
def inputs(_inputs, request):
    """The inputs, with a trained run only for the writers that read one (training it takes a while)."""
    name = getattr(request.node, "callspec", None) and request.node.callspec.params.get("name", "") or ""
    needs_run = name in ("eval", "view", "export") or name.startswith("render")
    return {**_inputs, "run": str(request.getfixturevalue("trained")) if needs_run else ""}


# name -> (argv with {out}, {scene}, {run}... placeholders, output name, check of the finished output)
def _h5(path: Path) -> None:
    from ev3dgs import schema

    schema.validate(path, require_complete=False)


def _folder(*names):
    def check(path: Path) -> None:
        assert path.is_dir() and set(names) <= {p.name for p in path.iterdir()}, sorted(os.listdir(path))
    return check


def _nonempty(path: Path) -> None:
    assert path.is_file() and path.stat().st_size > 0


def _frames(n):
    def check(path: Path) -> None:
        from ev3dgs.train.paths import _count_gif_frames, _count_video_frames

        if path.suffix == ".gif":
            assert _count_gif_frames(path) == n
        elif path.suffix == ".mp4":
            assert _count_video_frames(path) == n
        else:
            assert sorted(p.name for p in path.iterdir()) == [f"frame_{i:04d}.png" for i in range(n)]
    return check


def _run_folder(path: Path) -> None:
    assert {"model.pt", "ckpt.pt", "config.json", "log.jsonl"} <= {p.name for p in path.iterdir()}


def _evaluated(path: Path) -> None:
    assert json.loads((path / "metrics.json").read_text())["test"]["n"] > 0


WRITERS = {
    "train": (["ev3dgs", "train", "{scene}", "--out", "{out}", *FAST, "--quiet"], "run", _run_folder),
    "eval": (["ev3dgs", "eval", "{out}", "--quiet"], "evaluated", _evaluated),
    "render-mp4": (["ev3dgs", "render", "{run}", "--out", "{out}", "--frames", "3", "--quiet"], "o.mp4", _frames(3)),
    "render-gif": (["ev3dgs", "render", "{run}", "--out", "{out}", "--frames", "3", "--quiet"], "o.gif", _frames(3)),
    "render-png": (["ev3dgs", "render", "{run}", "--out", "{out}", "--frames", "3", "--quiet"], "frames",
                   _frames(3)),
    "export": (["ev3dgs", "export", "{run}", "--out", "{out}", "--quiet"], "m.ply", _nonempty),
    "view": (["ev3dgs", "view", "{run}", "--out", "{out}", "--rows", "1", "--quiet"], "fig.png", _nonempty),
    "export-dataset-e2nerf": (["ev3dgs", "export-dataset", "{scene}", "--format", "e2nerf", "--out", "{out}",
                               "--quiet"], "ds", _folder("README.txt")),
    "export-dataset-events-h5": (["ev3dgs", "export-dataset", "{scene}", "--format", "events-h5", "--out", "{out}",
                                  "--quiet"], "ds", _folder("README.txt", "events.h5")),
    "export-dataset-aedat4": (["ev3dgs", "export-dataset", "{scene}", "--format", "aedat4", "--out", "{out}",
                               "--quiet"], "ds", _folder("README.txt")),
    "export-dataset-transforms": (["ev3dgs", "export-dataset", "{scene}", "--format", "transforms", "--out",
                                   "{out}", "--quiet"], "ds", _folder("README.txt", "transforms.json")),
    "sim-events": (["ev3dgs-sim", "events", "{frames}", "--out", "{out}", "--quiet"], "ev.h5", _h5),
    "sim-blur": (["ev3dgs-sim", "blur", "{sub}", "--out", "{out}", "--quiet"], "blur.png", _nonempty),
    "calibrate": (["ev3dgs-sim", "calibrate", "{rec}", "--out", "{out}", "--bootstrap", "4", "--quiet"],
                  "sensor.toml", _nonempty),
    "compare": (["ev3dgs-sim", "compare", "{rec}", "--out", "{out}", "--quiet"], "report",
                _folder("compare.json", "compare.png")),
    "ingest-davis": (["ev3dgs-ingest", "davis", "{rec}", "--out", "{out}", "--no-poses", "--quiet"], "scene.h5",
                     _h5),
}
# these render in Blender (minutes): the race is run up to the claim, which comes before Blender starts
BLENDER = {
    "make-dataset": (["ev3dgs-sim", "make-dataset", "--scene", "lego", "--quick", "--out", "{out}", "--quiet"],
                     "lego.h5"),
    "record": (["ev3dgs-sim", "record", "--scene", "lego", "--seconds", "0.2", "--size", "32x24", "--out", "{out}",
                "--quiet"], "rec.aedat4"),
    "demo": (["demo", "--out", "{out}", "--iterations", "5"], "demo_out"),
}


def _argv(template, inputs, out) -> list[str]:
    return [a.format(out=out, **inputs) for a in template]


def _prepare(name, inputs, tmp_path) -> Path:
    out = tmp_path / "outputs" / WRITERS[name][1] if name in WRITERS else tmp_path / "outputs" / BLENDER[name][1]
    if name == "eval":
        import shutil

        shutil.copytree(inputs["run"], out)
    return out


def race(argv, tmp_path) -> tuple[list[subprocess.Popen], int, tuple[int, str, str]]:
    """Start two writers of the same output together, each pausing right after its claim; returns the
    processes, the index of the one that holds the claim, and the loser's (exit code, stdout, stderr)."""
    holds = [tmp_path / f"hold-{i}" for i in range(2)]
    procs = [_start(argv, f"claimed:{h}") for h in holds]
    try:
        _wait_for(lambda: any(p.poll() is not None for p in procs), what="the second writer to refuse")
        loser = next(i for i, p in enumerate(procs) if p.poll() is not None)
        winner = 1 - loser
        rc, out, err = _finish(procs[loser])
        assert rc == 2, (rc, err[-3000:])
        _wait_for(lambda: holds[winner].exists() or procs[winner].poll() is not None, what="the claim")
        assert holds[winner].exists(), _finish(procs[winner])[2][-3000:]
        assert int(holds[winner].read_text()) == procs[winner].pid
    except BaseException:
        for p in procs:
            p.kill()
            p.wait()
        raise
    return procs, winner, (rc, out, err)


def _assert_refusal(err: str, pid: int, out: Path) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err[-3000:]
    assert "is being written by another ev3dgs process" in lines[0] and f"pid {pid} on host " in lines[0], lines
    assert "Traceback" not in err


FAST_RACES = ("sim-events", "calibrate", "ingest-davis", "export-dataset-aedat4")  # the rest: make test-slow


def _params(names, fast):
    return [n if n in fast else pytest.param(n, marks=pytest.mark.slow) for n in names]


@pytest.mark.parametrize("name", _params(WRITERS, FAST_RACES))
def test_two_writers_one_output(name, inputs, tmp_path):
    """Both processes start together; the one that does not hold the claim exits 2 with one line naming the
    holder and writes nothing; the holder then finishes a complete output."""
    template, _, check = WRITERS[name]
    out = _prepare(name, inputs, tmp_path)
    before = sorted(os.listdir(out)) if out.is_dir() else None
    procs, winner, (_, _, err) = race(_argv(template, inputs, out), tmp_path)
    _assert_refusal(err, procs[winner].pid, out)
    if name == "eval":
        assert sorted(os.listdir(out)) == sorted(before + [claims.RUN_LOCK])  # the loser wrote nothing
    else:
        assert not out.exists() or name == "train"  # the holder is paused before writing anything
    (tmp_path / f"hold-{winner}").unlink()
    rc, _, err = _finish(procs[winner])
    assert rc == 0, err[-3000:]
    check(out)
    assert leftovers(out.parent) == [], leftovers(out.parent)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_BPY, reason="needs the Blender extra (bpy) to get past its check")
@pytest.mark.parametrize("name", list(BLENDER))
def test_blender_writers_claim_before_rendering(name, inputs, tmp_path):
    """make-dataset, record and the demo claim their output before Blender starts: the second writer refuses
    while the first is still paused at its claim (it is then killed, before any render); the next run clears
    the killed one's stale claim with a warning."""
    template, _ = BLENDER[name]
    out = _prepare(name, inputs, tmp_path)
    argv = _argv(template, inputs, out)
    procs, winner, (_, _, err) = race(argv, tmp_path)
    _assert_refusal(err, procs[winner].pid, out)
    assert not any(p.suffix in (".npz", ".h5", ".aedat4") for p in out.parent.rglob("*"))  # nothing rendered
    procs[winner].send_signal(signal.SIGKILL)
    procs[winner].wait()
    hold = tmp_path / "hold-again"
    p = _start(argv, f"claimed:{hold}")
    try:
        _wait_for(lambda: hold.exists() or p.poll() is not None, what="the claim")
        assert hold.exists(), _finish(p)[2][-3000:]
    finally:
        p.kill()
        _, _, err = _finish(p)
    assert f"removed the stale claim of a process that is not running any more (pid {procs[winner].pid} " in err


# ------------------------------------------------------------------------------------------------ kill -9

KILLED = {  # writer -> the temporary a kill -9 just before its rename leaves (glob beside the output)
    "render-png": ".frames.tmp-*",
    "render-mp4": ".o.mp4.tmp-*",
    "sim-events": ".ev.h5.tmp-*",
    "calibrate": ".sensor.toml.tmp-*",
    "export-dataset-aedat4": ".ds.tmp-*",
}


@pytest.mark.parametrize("force", [False, True], ids=["new", "force"])
@pytest.mark.parametrize("name", _params(KILLED, ("sim-events", "export-dataset-aedat4")))
def test_kill_9_mid_write_leaves_temporaries_the_next_run_removes(name, force, inputs, tmp_path):
    template, _, check = WRITERS[name]
    out = _prepare(name, inputs, tmp_path)
    argv = _argv(template, inputs, out)
    if force:  # an earlier output that the killed --force run was replacing
        assert _finish(_start(argv))[0] == 0
        argv = argv + ["--force"]
    hold = tmp_path / "hold"
    p = _start(argv, f"publish:{hold}")
    _wait_for(lambda: hold.exists() or p.poll() is not None, what="the write")
    assert hold.exists(), _finish(p)[2][-3000:]
    p.send_signal(signal.SIGKILL)
    p.wait()
    left = sorted(q.name for q in out.parent.glob(KILLED[name]))
    assert left == [KILLED[name].replace("*", str(p.pid)) + (".mp4" if name == "render-mp4" else "")], left
    assert (out.parent / f".{out.name}.claim").exists()  # the killed process's claim, now stale
    rc, _, err = _finish(_start(argv))
    assert rc == 0, err
    assert f"removed the stale claim of a process that is not running any more (pid {p.pid} " in err
    check(out)
    assert leftovers(out.parent) == [], leftovers(out.parent)


@pytest.mark.slow
def test_kill_9_during_training_leaves_a_stale_run_lock_the_next_run_clears(inputs, tmp_path):
    out = tmp_path / "run"
    argv = _argv(WRITERS["train"][0], inputs, out)
    hold = tmp_path / "hold"
    p = _start(argv, f"claimed:{hold}")
    _wait_for(lambda: hold.exists() or p.poll() is not None, what="the claim")
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert (out / claims.RUN_LOCK).exists()
    rc, _, err = _finish(_start(argv))
    assert rc == 0 and f"(pid {p.pid} on host" in err, err
    _run_folder(out)
    assert leftovers(out) == []


# ------------------------------------------------------------------------------------------------ in-process

def test_publish_never_replaces_an_output_that_appeared_meanwhile(tmp_path):
    out = tmp_path / "o.txt"
    claims.claim_output(out)
    try:
        out.write_text("someone else's")
        with pytest.raises(OutputError, match="appeared while this command was writing it"):
            with atomic_path(out) as tmp:
                tmp.write_text("mine")
        assert out.read_text() == "someone else's"
        assert sorted(os.listdir(tmp_path)) == [".o.txt.claim", "o.txt"]
    finally:
        claims.release_all()
    assert sorted(os.listdir(tmp_path)) == ["o.txt"]


def test_force_replaces_only_the_output_seen_when_claimed(tmp_path):
    out = tmp_path / "o.txt"
    out.write_text("old")
    claims.claim_output(out, force=True)
    try:
        with atomic_path(out) as tmp:
            tmp.write_text("new")
        assert out.read_text() == "new"
        out.unlink()
        out.write_text("made meanwhile")  # another file under the name: not the one --force was given for
        with pytest.raises(OutputError, match="appeared while"):
            with atomic_path(out) as tmp:
                tmp.write_text("newer")
        assert out.read_text() == "made meanwhile"
    finally:
        claims.release_all()


def test_rename_noreplace_refuses_files_and_folders(tmp_path):
    (tmp_path / "a").write_text("a")
    (tmp_path / "b").write_text("b")
    with pytest.raises(FileExistsError):
        claims.rename_noreplace(tmp_path / "a", tmp_path / "b")
    (tmp_path / "d1").mkdir()
    (tmp_path / "d2").mkdir()
    with pytest.raises(FileExistsError):
        claims.rename_noreplace(tmp_path / "d1", tmp_path / "d2")  # even an empty folder
    claims.rename_noreplace(tmp_path / "a", tmp_path / "c")
    assert (tmp_path / "c").read_text() == "a" and not (tmp_path / "a").exists()


def _claim_file(path: Path, **info) -> Path:
    base = claims._identity()
    base.update(info)
    f = path.with_name(f".{path.name}.claim")
    f.write_text(json.dumps(base))
    return f


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.mark.parametrize("how", ["dead pid", "reused pid", "before a reboot", "garbage"])
def test_stale_claims_are_cleared_with_a_warning(how, tmp_path):
    out = tmp_path / "o.txt"
    info = {"dead pid": {"pid": _dead_pid()},
            "reused pid": {"pid": os.getppid(), "start": -1},      # a live PID, another process's start time
            "before a reboot": {"pid": os.getppid(), "boot": "another-boot"}}.get(how)
    if info is None:
        f = out.with_name(".o.txt.claim")
        f.write_bytes(b"\x00garbage")
        os.utime(f, (time.time() - 60, time.time() - 60))
    else:
        _claim_file(out, **info)
    with pytest.warns(UserWarning, match="removed the stale claim"):
        c = claims.claim_output(out)
    assert c.owned()
    claims.release_all()
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("how", ["live process", "other host", "young and unreadable"])
def test_live_claims_are_refused(how, tmp_path):
    out = tmp_path / "o.txt"
    if how == "young and unreadable":
        out.with_name(".o.txt.claim").write_bytes(b"")
    else:
        _claim_file(out, pid=os.getppid(), start=claims._start_ticks(os.getppid()),
                    **({"host": "elsewhere"} if how == "other host" else {}))
    with pytest.raises(OutputError, match="is being written by another ev3dgs process") as e:
        claims.claim_output(out)
    if how == "other host":
        assert "if it is not running any more, delete" in str(e.value)
    assert not out.exists()


def test_a_forked_child_never_releases_its_parents_claim(tmp_path):
    out = tmp_path / "o.txt"
    c = claims.claim_output(out)
    try:
        pid = os.fork()
        if pid == 0:  # the child: what a worker pool's atexit would do
            claims.release_all()
            os._exit(0)
        os.waitpid(pid, 0)
        assert c.owned()
    finally:
        claims.release_all()
    assert not c.file.exists()


def test_remove_stale_temps_removes_folders_of_dead_processes(tmp_path):
    from ev3dgs.outputs import remove_stale_temps

    dead, live = _dead_pid(), os.getpid()
    for pid in (dead, live):
        (tmp_path / f".frames.tmp-{pid}").mkdir()
        (tmp_path / f".frames.tmp-{pid}" / "frame_0000.png").write_bytes(b"x")
    removed = remove_stale_temps(tmp_path, "frames")
    assert [p.name for p in removed] == [f".frames.tmp-{dead}"]
    assert sorted(os.listdir(tmp_path)) == [f".frames.tmp-{live}"]
