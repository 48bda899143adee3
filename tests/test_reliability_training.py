"""Reliability of training (issue 18): bitwise reproducible runs for any thread count, and safe resume.

Reproducibility is checked bit for bit (torch.equal, no tolerance): two runs with the same seed must leave
the same model, optimizer moments, densification statistics and RNG states, with any torch / numba thread
count, for the `reference` and `cpu` backends. The scene is made here without a renderer or the simulator
(procedural images, random events) at 61x47 with 5 sub-poses, so several tensors of a step exceed torch's
parallel grain (32768 elements): with more than one torch thread, torch's element-wise and reduction kernels
would split them differently per thread count (measured: pow, sigmoid, mean, a matmul's gradient) if the
trainer did not pin them. Densification is made to run every few steps so clone, split (its RNG), prune
and the opacity reset are all exercised.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch

from ev3dgs import schema
from ev3dgs.cli import main as cli
from ev3dgs.errors import ConfigError
from ev3dgs.events import Events
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.train.config import TrainConfig
from ev3dgs.train.trainer import Trainer

W, H = 61, 47  # odd sizes: torch's per-thread chunks then end off its SIMD width


def _images(rng, n):
    """Smooth colour fields with a few soft blobs: something for the losses to fit, cheap to make."""
    yy, xx = np.mgrid[0:H, 0:W] / max(W, H)
    out = []
    for _ in range(n):
        img = 0.3 + 0.2 * np.stack([np.sin(3 * xx + c) * np.cos(2 * yy - c) for c in rng.uniform(0, 3, 3)], -1)
        for _ in range(4):
            cx, cy, r = rng.uniform(0, 1), rng.uniform(0, 0.75), rng.uniform(0.05, 0.15)
            img += rng.uniform(0.2, 0.5, 3) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / r ** 2)[..., None]
        out.append((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    return np.stack(out)


def make_scene(path: Path, name: str = "tiny", views: int = 4, samples: int = 5) -> str:
    rng = np.random.default_rng(0)
    poses, pose_t, exposure = [], [], []
    for v in range(views):
        az = 2 * np.pi * v / views
        eye = 3.0 * np.array([np.cos(az), np.sin(az), 0.5])
        drift = rng.normal(0, 0.2, 3)
        t = v * 150_000 + np.linspace(0, 100_000, samples).astype(np.int64)
        poses.append([look_at(eye + drift * (k / (samples - 1) - 0.5), [0, 0, 0]) for k in range(samples)])
        pose_t.append(t)
        exposure.append((t[0], t[-1]))
    n_ev = 20_000
    t = np.sort(rng.integers(0, views * 150_000, n_ev))
    ev = Events(t=t, x=rng.integers(0, W, n_ev), y=rng.integers(0, H, n_ev), p=rng.choice([-1, 1], n_ev))
    sc = schema.Scene(
        name=name, source="test", camera=schema.Camera(W, H, K=intrinsics(W, H, 50), background=(1.0, 1.0, 1.0)),
        events=ev, sensor=schema.EventSensor(), bounds=np.array([[-0.7] * 3, [0.7] * 3]),
        train=schema.Train(images=_images(rng, views), exposure=np.array(exposure), poses=np.array(poses),
                           pose_t=np.array(pose_t)))
    schema.write(sc, path)
    return str(path)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> str:
    return make_scene(tmp_path_factory.mktemp("scene") / "tiny.h5")


def _config(scene, backend, **kw) -> TrainConfig:
    base = dict(scene=scene, iterations=10, subposes=5, init_points=600, sh_degree=1, sh_interval=3,
                checkpoint_every=1000, seed=7, device="cpu", backend=backend)
    base.update(kw)
    return TrainConfig(**base)


def _train(cfg: TrainConfig, out: Path, torch_threads: int, numba_threads: int) -> dict:
    """Train with the given thread counts; returns the final checkpoint's payload (every tensor of the
    model, the optimizers, the densification state and the RNGs) and the log without timings."""
    torch.set_num_threads(torch_threads)
    numba.set_num_threads(min(numba_threads, numba.config.NUMBA_NUM_THREADS))
    try:
        tr = Trainer(cfg, out, quiet=True)
        # densify early and often: clone, split (random children), prune and opacity reset all happen
        last = cfg.iterations
        tr.strategy.refine_start, tr.strategy.refine_every, tr.strategy.refine_stop = 2, 3, last
        # the opacity reset at the last refinement (after its prune, so the model is not emptied)
        tr.strategy.reset_every, tr.strategy.grow_grad2d, tr.strategy.grow_scale3d = 3 * ((last - 1) // 3), 2e-5, 0.05
        tr.strategy.prune_opa = 0.095
        tr.fit()
    finally:
        torch.set_num_threads(max(1, os.cpu_count() or 1))
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    state = torch.load(out / "ckpt.pt", weights_only=True)
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    state["log"] = [{k: v for k, v in r.items() if k != "seconds"} for r in log]
    return state


def assert_bitwise_equal(a, b, path="") -> None:
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            assert_bitwise_equal(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_bitwise_equal(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert torch.equal(a, b), f"{path} differs (max {(a.double() - b.double()).abs().max().item():.3g})"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


@pytest.mark.parametrize("backend,iterations,points", [
    ("cpu", 10, 600),
    ("reference", 6, 300),  # the dense torch oracle is ~10x slower per step
    pytest.param("reference", 10, 600, marks=pytest.mark.slow),
])
def test_same_seed_same_bits_for_any_thread_count(scene, tmp_path, backend, iterations, points):
    cfg = _config(scene, backend, iterations=iterations, init_points=points)
    one = _train(cfg, tmp_path / "a", torch_threads=1, numba_threads=1)
    again = _train(cfg, tmp_path / "b", torch_threads=1, numba_threads=1)
    assert_bitwise_equal(one, again)
    # the run really densified and moved (otherwise equality would prove little)
    assert any(r.get("cloned", 0) + r.get("split", 0) > 0 for r in one["log"])
    assert any(r.get("pruned", 0) > 0 for r in one["log"])
    assert one["model"]["means"].shape[0] not in (0, points)
    # other torch and numba thread counts, and --threads (numba kernels; torch outside the steps)
    two = _train(TrainConfig(**{**cfg.__dict__, "threads": 2}), tmp_path / "c", torch_threads=2, numba_threads=2)
    assert two["config"]["threads"] == 2
    two["config"]["threads"] = None
    assert_bitwise_equal(one, two)


def _python(argv: list[str], **env) -> subprocess.CompletedProcess:
    """A fresh Python process with ``env`` on top of this one's (fixed at process start, as numba needs)."""
    full = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", **env}
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True, env=full, timeout=600)


def _run_env(args: list[str], **env) -> subprocess.CompletedProcess:
    return _python(["-m", "ev3dgs.cli.main", *args], **env)


def test_thread_environment_does_not_change_a_bit(scene, tmp_path):
    """NUMBA_NUM_THREADS / OMP_NUM_THREADS fixed at process start (the robust way to change numba's pool)."""
    common = [scene, "--iterations", "6", "--set", "init_points=600", "--set", "sh_degree=1", "--set",
              "blur.subposes=5", "--backend", "cpu", "--seed", "3", "--quiet"]
    r1 = _run_env(["train", *common, "--out", str(tmp_path / "t1")], NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    r2 = _run_env(["train", *common, "--out", str(tmp_path / "t2")], NUMBA_NUM_THREADS="2", OMP_NUM_THREADS="2")
    assert r1.returncode == 0 and r2.returncode == 0, r1.stderr + r2.stderr
    a = torch.load(tmp_path / "t1" / "ckpt.pt", weights_only=True)
    b = torch.load(tmp_path / "t2" / "ckpt.pt", weights_only=True)
    assert_bitwise_equal(a, b)


FIRST_RENDER = """
import torch
torch.set_num_threads(1)
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.splat.model import GaussianModel
from ev3dgs.splat.rasterize import rasterization

m = GaussianModel.random_in_bounds([[-0.5] * 3, [0.5] * 3], 50, seed=0, sh_degree=0)
vm = torch.as_tensor(look_at([0.0, -3.0, 0.5], [0, 0, 0]), dtype=torch.float32)
K = torch.as_tensor(intrinsics(32, 24, 50.0), dtype=torch.float32)
rasterization(m.means, m.quats_normalised, m.scales, m.opacities, m.sh, vm, K, 32, 24, sh_degree=0,
              backend="cpu", threads=1)
print(torch.get_num_threads())
"""


def test_the_first_render_of_a_process_leaves_torch_on_its_thread_count():
    """numba's OpenMP pool starts at a process's first numba.set_num_threads, and starting it sets OpenMP's
    thread count, which is torch's, to NUMBA_NUM_THREADS. The render before a training's first loss did that,
    so the first step's torch reductions ran on NUMBA_NUM_THREADS threads and summed in another order (on a
    96x72 scene the event term's floor estimate came out one bit apart, and the runs from there). A render
    with one thread in a fresh process whose pool has two leaves torch on its one thread."""
    r = _python(["-c", FIRST_RENDER], NUMBA_NUM_THREADS="2", OMP_NUM_THREADS="1")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "1"


# ------------------------------------------------------------------------------------------------ resume
def _cli(capsys, *args) -> tuple[int, str]:
    capsys.readouterr()
    rc = cli.main([str(a) for a in args])
    return rc, capsys.readouterr().err


def _base(scene, run, *extra):
    return ["train", scene, "--out", run, "--set", "init_points=300", "--set", "sh_degree=1", "--set",
            "blur.subposes=3", "--backend", "cpu", "--threads", "1", "--quiet", *extra]


def _steps(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]


def assert_one_line_error(rc: int, err: str, *needles: str) -> None:
    assert rc == 2, err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for n in needles:
        assert n in err, (n, err)


@pytest.fixture(scope="module")
def finished_run(scene, tmp_path_factory):
    """A 6-step run with checkpoints every 3 steps, made through the CLI with non-default options."""
    run = tmp_path_factory.mktemp("runs") / "run"
    assert cli.main(_base(scene, str(run), "--iterations", "6", "--set", "checkpoint_every=3", "--seed", "4")) == 0
    return run


def _copy(run: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(run, dst)
    return dst


@pytest.mark.parametrize("flags,diff", [
    (["--seed", "5"], "seed: saved 4 vs given 5"),
    (["--seed", "0"], "seed: saved 4 vs given 0"),          # given, although equal to the CLI default
    (["--set", "blur.subposes=4"], "subposes: saved 3 vs given 4"),
    (["--set", "sh_degree=2", "--seed", "9"], "sh_degree: saved 1 vs given 2; seed: saved 4 vs given 9"),
    (["--set", "poses.frame=camera"], "pose_frame: saved 'world' vs given 'camera'"),
])
def test_resume_with_other_settings_is_refused(scene, finished_run, tmp_path, capsys, flags, diff):
    run = _copy(finished_run, tmp_path / "run")
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "9", *flags)
    assert_one_line_error(rc, err, diff, "--iterations")
    assert _steps(run) == list(range(1, 7))  # nothing touched


def test_resume_on_another_scene_is_refused(scene, finished_run, tmp_path, capsys):
    run = _copy(finished_run, tmp_path / "run")
    other = make_scene(tmp_path / "other.h5", name="other", views=3)
    rc, err = _cli(capsys, "train", other, "--out", run, "--resume", "--iterations", "9")
    assert_one_line_error(rc, err, "scene: saved", "other.h5")
    # the same settings through the library: the checkpoint itself knows its scene
    cfg = TrainConfig.load(run / "config.json")
    tr = Trainer(TrainConfig(**{**cfg.__dict__, "scene": other, "iterations": 9}), run, quiet=True)
    with pytest.raises(ConfigError, match="scene: saved") as e:
        tr.fit(resume=True)
    assert "\n" not in str(e.value)


class Killed(Exception):
    pass


def _kill_at(step):
    def on_step(trainer, rec):
        if trainer.step == step:
            raise Killed
    return on_step


def test_resume_extends_and_rolls_the_log_back(scene, tmp_path, capsys):
    run = tmp_path / "run"
    assert cli.main(_base(scene, str(run), "--iterations", "6", "--set", "checkpoint_every=3", "--seed", "4")) == 0
    cfg = TrainConfig.load(run / "config.json")
    with pytest.raises(Killed):  # the same run again, killed at step 5: checkpoint at 3, log 1..5
        Trainer(cfg, run, quiet=True).fit(on_step=_kill_at(5))
    with open(run / "log.jsonl", "a") as f:  # and a line torn by the kill
        f.write('{"step": 6, "lo')
    assert torch.load(run / "ckpt.pt", weights_only=True)["step"] == 3
    # options not given (subposes 5, sh-degree 3, seed 0, init-points 20000 by default) do not count; --threads
    # and --iterations may change
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "8", "--threads", "2", "--quiet")
    assert rc == 0, err
    assert _steps(run) == list(range(1, 9))
    saved = TrainConfig.load(run / "config.json")
    assert (saved.iterations, saved.threads, saved.seed, saved.subposes) == (8, 2, 4, 3)


def test_resume_keeps_the_sh_schedule_the_run_started_with(scene, tmp_path, capsys):
    """--sh-interval auto is fixed when the run is made (iterations / 30): extending the run to 2x the steps
    keeps the saved interval, where a fresh run of that length would get twice it."""
    run = tmp_path / "run"
    assert cli.main(_base(scene, str(run), "--iterations", "60", "--set", "checkpoint_every=30")) == 0
    assert TrainConfig.load(run / "config.json").sh_interval == 2
    assert TrainConfig(scene=scene, iterations=120).sh_interval == 4
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "120")
    assert rc == 0, err
    assert TrainConfig.load(run / "config.json").sh_interval == 2 and _steps(run) == list(range(1, 121))


def test_resume_past_the_requested_iterations_is_refused(scene, finished_run, tmp_path, capsys):
    run = _copy(finished_run, tmp_path / "run")
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "4")
    assert_one_line_error(rc, err, "step 6", "--iterations 4")


def test_resume_before_the_first_checkpoint_restarts_cleanly(scene, tmp_path, capsys):
    run = tmp_path / "run"
    cfg = TrainConfig(scene=scene, iterations=4, init_points=300, sh_degree=1, subposes=3, checkpoint_every=100,
                      device="cpu", backend="cpu", threads=1)
    with pytest.raises(Killed):
        Trainer(cfg, run, quiet=True).fit(on_step=_kill_at(2))
    assert not (run / "ckpt.pt").exists() and _steps(run) == [1, 2]
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "4", "--quiet")
    assert rc == 0, err
    assert f"no checkpoint in {run}: starting from step 0" in err
    assert _steps(run) == [1, 2, 3, 4]


def test_a_fresh_run_replaces_the_old_log_and_checkpoint(scene, finished_run, tmp_path, capsys):
    run = _copy(finished_run, tmp_path / "run")
    assert cli.main(_base(scene, str(run), "--iterations", "2", "--set", "checkpoint_every=100", "--force")) == 0
    assert _steps(run) == [1, 2]
    assert torch.load(run / "ckpt.pt", weights_only=True)["step"] == 2


@pytest.mark.parametrize("damage", ["text", "truncated", "empty"])
def test_damaged_checkpoint_is_one_line(scene, finished_run, tmp_path, capsys, damage):
    run = _copy(finished_run, tmp_path / "run")
    ckpt = run / "ckpt.pt"
    data = ckpt.read_bytes()
    ckpt.write_bytes({"text": b"this is not a checkpoint\n", "truncated": data[: len(data) // 2],
                      "empty": b""}[damage])
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "9")
    assert_one_line_error(rc, err, str(ckpt), "not a readable checkpoint")


@pytest.mark.parametrize("edit,needle", [
    ({"iterations": "300"}, "iterations"),
    ({"colour": 1}, "unknown config key colour"),
    ({"scene": None}, "scene"),
])
def test_bad_config_json_is_one_line(scene, finished_run, tmp_path, capsys, edit, needle):
    run = _copy(finished_run, tmp_path / "run")
    cfg = json.loads((run / "config.json").read_text())
    cfg.update(edit)
    (run / "config.json").write_text(json.dumps(cfg))
    rc, err = _cli(capsys, "train", scene, "--out", run, "--resume", "--iterations", "9")
    assert_one_line_error(rc, err, "config.json", needle)
    rc, err = _cli(capsys, "eval", run)
    assert_one_line_error(rc, err, needle)


def test_variants_side_by_side_equal_one_after_the_other(scene, tmp_path):
    """compare_variants(jobs=2) (what `make demo` does: one-thread worker processes) gives the checkpoints and
    scores of running the variants one after the other in this process."""
    from ev3dgs.train.compare import compare_variants

    sc = schema.read(scene)                         # the tiny scene with sharp frames to score against
    sc.train.sharp = np.asarray(sc.train.images)[:, ::-1].copy()
    sc.train.sharp_poses = np.asarray(sc.train.poses)[:, len(sc.train.poses[0]) // 2]
    scene = str(tmp_path / "scored.h5")
    schema.write(sc, scene)
    base = _config(scene, "cpu", iterations=6)
    seq = compare_variants(scene, tmp_path / "seq", base, variants=("naive", "blur+event"), jobs=1)
    par = compare_variants(scene, tmp_path / "par", base, variants=("naive", "blur+event"), jobs=2)
    assert list(par) == ["naive", "blur+event"]
    for name in seq:
        strip = lambda m: {k: v for k, v in m.items() if k != "run"}                    # noqa: E731
        assert strip(seq[name]["metrics"]) == strip(par[name]["metrics"])
        assert seq[name]["gaussians"] == par[name]["gaussians"]
        a, b = (torch.load(d / name / "ckpt.pt", weights_only=True) for d in (tmp_path / "seq", tmp_path / "par"))
        assert_bitwise_equal(a["model"] if "model" in a else a, b["model"] if "model" in b else b)
