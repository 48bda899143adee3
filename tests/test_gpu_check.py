"""tools/gpu_check.py's CPU dry-run path: environment report, the gpu-marked tests run (and skip without CUDA),
synthetic scenes, a few training steps of each variant, the JSON marked as a dry run."""
import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
import gpu_check  # noqa: E402


def test_dry_run_writes_the_json(tmp_path, capsys):
    out = tmp_path / "gpu_dry.json"
    rc = gpu_check.main(["--dry-run", "--steps", "2", "--json", str(out), "--workdir", str(tmp_path / "work")])
    assert rc == 0
    r = json.loads(out.read_text())
    assert r["dry_run"] is True and r["device"] == "cpu" and r["backend"] == "cpu" and r["steps"] == [2]
    assert r["gpu"] == "none (dry run)" and r["environment"]["python"]
    assert r["gpu_tests"]["returncode"] in (0, 5) and "-m gpu" in r["gpu_tests"]["command"]
    if r["environment"]["gsplat"]:  # the gpu-marked parity tests were collected and skipped (no CUDA here)
        assert r["gpu_tests"]["counts"].get("skipped", 0) >= 2 and not r["gpu_tests"]["counts"].get("failed")
    runs = r["runs"]
    assert {(x["size"], x["variant"]) for x in runs} == {(s, v) for s in gpu_check.SIZES
                                                         for v in gpu_check.DEFAULT_VARIANTS}
    for x in runs:
        assert x["steps"] == 2 and x["ms_per_step"] > 0 and x["gaussians"] > 0 and x["test_psnr"] > 5
    assert {(x["width"], x["height"]) for x in runs} == {(24, 18), (86, 65)}  # a quarter of 96x72, 346x260


def test_install_command_never_reaches_the_network(tmp_path):
    cmd = gpu_check.install_command("/wheels")
    assert "--no-index" in cmd and cmd[cmd.index("--find-links") + 1] == "/wheels" and cmd[-1] == "ev3dgs[cuda]"
    for name in ("gsplat-1.5.3-py3-none-any.whl", "ev3dgs-0.2.0-cp312-cp312-linux_x86_64.whl", "notes.txt"):
        (tmp_path / name).write_text("")
    cmd = gpu_check.install_command(str(tmp_path), no_deps=True)
    assert "--no-index" in cmd and "--no-deps" in cmd and "--find-links" not in cmd
    assert [Path(c).name for c in cmd if c.endswith(".whl")] == ["ev3dgs-0.2.0-cp312-cp312-linux_x86_64.whl",
                                                                  "gsplat-1.5.3-py3-none-any.whl"]


def test_without_cuda_the_real_run_refuses(capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    assert gpu_check.main(["--skip-tests"]) == 2
    assert "--dry-run" in capsys.readouterr().err


def test_gpu_slug():
    assert gpu_check.gpu_slug("NVIDIA H100 80GB HBM3") == "nvidia_h100_80gb_hbm3"


def test_plan_runs_puts_the_baseline_first_and_the_longest_runs_last():
    plan = gpu_check.plan_runs([300, 30], ["small", "large"], ["blur+event", "naive"], cpu_baseline_steps=5)
    assert plan[:2] == [("small", "blur+event", 5, "cpu"), ("large", "blur+event", 5, "cpu")]
    assert [n for _, _, n, be in plan if be == "cuda"] == [30] * 4 + [300] * 4
    assert plan[2:4] == [("small", "blur+event", 30, "cuda"), ("large", "blur+event", 30, "cuda")]
    assert gpu_check.plan_runs([3], ["small"], ["naive"], 0) == [("small", "naive", 3, "cuda")]


def test_a_run_past_the_deadline_is_scored_where_it_stopped(tmp_path):
    import time

    scene = gpu_check.synthetic_scene(tmp_path / "b.h5", 24, 18, views=3)
    r = gpu_check.time_training(str(scene), "blur+event", 4, "cpu", "cpu", 300, tmp_path / "runs",
                                deadline=time.perf_counter())
    assert r["cut_by_deadline"] and r["steps_done"] == 1 and r["steps"] == 4 and r["test_psnr"] > 5


def test_trainer_options_reach_the_trainer_and_bad_ones_are_refused(tmp_path):
    """--sh-interval N, --event-floor, --event-huber, --densify-from (the H100 table's 1000 / mean / 0 / all) are
    the runs' settings; unset, the trainer's defaults. The choices are the trainer's."""
    from ev3dgs.train.config import DENSIFY_FROM, FLOOR_STATS, TrainConfig

    assert (gpu_check.FLOOR_STATS, gpu_check.DENSIFY_FROM) == (FLOOR_STATS, DENSIFY_FROM)
    scene = gpu_check.synthetic_scene(tmp_path / "b.h5", 24, 18, views=3)
    opts = dict(sh_interval=7, event_floor="mean", event_huber=0.0, densify_from="all")
    gpu_check.time_training(str(scene), "blur+event", 2, "cpu", "cpu", 100, tmp_path / "a", options=opts)
    gpu_check.time_training(str(scene), "blur+event", 2, "cpu", "cpu", 100, tmp_path / "d",
                            options=dict.fromkeys(opts))
    (a,), (d,) = (list((tmp_path / k).glob("*/config.json")) for k in ("a", "d"))
    given, default = TrainConfig.load(a), TrainConfig.load(d)
    assert (given.sh_interval, given.floor_stat, given.huber_c, given.densify_source) == (7, "mean", 0.0, "all")
    plain = TrainConfig(scene=str(scene), iterations=2)
    assert (default.sh_interval, default.floor_stat, default.huber_c, default.densify_source) == \
        (plain.sh_interval, plain.floor_stat, plain.huber_c, plain.densify_source) != (7, "mean", 0.0, "all")
    for bad in (["--sh-interval", "0"], ["--event-huber", "-1"], ["--event-floor", "mode"]):
        with pytest.raises(SystemExit):
            gpu_check.main(["--dry-run", *bad])


def test_past_the_deadline_every_run_is_skipped_and_a_failed_run_is_recorded(tmp_path, monkeypatch):
    out = tmp_path / "g.json"
    rc = gpu_check.main(["--dry-run", "--skip-tests", "--sizes", "small", "--deadline-minutes", "0", "--json",
                         str(out), "--workdir", str(tmp_path / "w")])
    r = json.loads(out.read_text())
    assert rc == 0 and r["runs"] == [] and len(r["skipped"]) == 3
    assert {x["why"] for x in r["skipped"]} == {"past the deadline"}

    real = gpu_check.time_training

    def flaky(scene, variant, *a, **k):
        if variant == "naive":
            raise RuntimeError("CUDA error: an illegal memory access was encountered")
        return real(scene, variant, *a, **k)

    monkeypatch.setattr(gpu_check, "time_training", flaky)
    rc = gpu_check.main(["--dry-run", "--skip-tests", "--sizes", "small", "--variants", "naive", "blur-only",
                         "--steps", "2", "--json", str(out), "--workdir", str(tmp_path / "w"),
                         "--plot", str(tmp_path / "g.png")])
    r = json.loads(out.read_text())
    assert rc == 1 and [x["variant"] for x in r["runs"]] == ["naive", "blur-only"]
    assert "illegal memory access" in r["runs"][0]["error"] and "traceback" in r["runs"][0]
    assert r["runs"][1]["steps_done"] == 2 and (tmp_path / "g.png").stat().st_size > 0


def test_merge_keeps_every_run_and_drops_skips_a_later_part_ran(tmp_path):
    def part(gpu, runs, skipped, tests=None):
        r = {"gpu": gpu, "environment": {"torch": "2.11", "gsplat": "1.5.3"}, "runs": runs, "skipped": skipped,
             "kernels": {"ok": True, "seconds": 50.0 if tests else 0.3}, "steps": [3000], "variants": ["naive"],
             "deadline_minutes": 5, "seconds": 9.0}
        if tests:
            r["gpu_tests"] = {"summary": tests}
        return r

    run = dict(size="small", variant="naive", steps=3000, backend="cuda", width=96, height=72, ms_per_step=5.0,
               test_psnr=25.0)
    a = part("H", [dict(run, variant="blur-only")], [dict(size="small", variant="naive", steps=3000, backend="cuda",
                                                          why="past the deadline")], tests="6 passed")
    b = part("H", [run], [dict(size="large", variant="naive", steps=3000, backend="cuda", why="past the deadline")])
    paths = []
    for i, p in enumerate((a, b)):
        paths.append(tmp_path / f"{i}.json")
        paths[-1].write_text(json.dumps(p))
    assert gpu_check.main(["--merge", *map(str, paths), "--json", str(tmp_path / "m.json"),
                           "--plot", str(tmp_path / "m.png")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert [x["variant"] for x in m["runs"]] == ["blur-only", "naive"]
    assert [x["size"] for x in m["skipped"]] == ["large"]  # small naive ran in the second part
    assert m["gpu_tests"]["summary"] == "6 passed" and m["kernels"]["seconds"] == 50.0 and len(m["parts"]) == 2
    paths[1].write_text(json.dumps(part("other GPU", [run], [])))
    assert gpu_check.main(["--merge", *map(str, paths), "--json", str(tmp_path / "x.json")]) == 2
    paths[1].write_text("{not json")
    assert gpu_check.main(["--merge", *map(str, paths), "--json", str(tmp_path / "x.json")]) == 2
    paths[1].write_text(json.dumps({"gpu": "H"}))  # not a check's result
    assert gpu_check.main(["--merge", *map(str, paths), "--json", str(tmp_path / "x.json")]) == 2
    assert not (tmp_path / "x.json").exists()


@pytest.mark.parametrize("bad", [["--steps", "0"], ["--deadline-minutes", "-1"], ["--cpu-baseline-steps", "-2"],
                                 ["--init-points", "0"]])
def test_impossible_parameters_exit_2(bad, capsys):
    with pytest.raises(SystemExit) as e:
        gpu_check.main(["--dry-run", *bad])
    assert e.value.code == 2 and "must be" in capsys.readouterr().err


def test_the_davis346_plan_runs_in_the_issue_order_and_the_dry_run_scales_it():
    plan = gpu_check.plan_runs([3000], ["small", "large"], ["naive"], 0, plan="davis346")
    assert plan == [("large", "blur+event", 30000, "cuda"), ("large", "blur+event", 3000, "cuda"),
                    ("large", "blur-only", 3000, "cuda"), ("small", "blur+event", 3000, "cuda"),
                    ("large", "naive", 3000, "cuda"), ("large", "oracle", 3000, "cuda")]
    dry = gpu_check.plan_runs([3000], ["small", "large"], ["naive"], 2, plan="davis346", dry_run=True)
    assert dry[:2] == [("small", "blur+event", 2, "cpu"), ("large", "blur+event", 2, "cpu")]
    assert [n for *_, n, be in dry if be == "cuda"] == [30, 3, 3, 3, 3, 3]
    assert gpu_check.plan_runs([1], ["small"], ["naive"], 0, plan="davis346") == [("small", "blur+event", 3000,
                                                                                   "cuda")]


def test_step_statistics_leave_out_the_first_step():
    import numpy as np

    ms = [900.0, 4.0, 1.0, 3.0, 2.0, 5.0]
    st = gpu_check.step_statistics(ms)
    assert (st["ms_per_step_q25"], st["ms_per_step_median"], st["ms_per_step_q75"]) == (2.0, 3.0, 4.0)
    assert st["ms_per_step_median"] == float(np.median(ms[1:]))
    assert gpu_check.step_statistics([7.0])["ms_per_step_median"] == 7.0
    assert gpu_check.step_statistics([])["ms_per_step_median"] is None


def test_step_clock_on_the_cpu_times_the_gaps_between_marks():
    t = iter([10.0, 10.5, 10.75, 11.75])
    clock = gpu_check.StepClock(cuda=False, clock=lambda: next(t))
    for _ in range(4):
        clock.mark()
    assert clock.step_ms() == [500.0, 250.0, 1000.0]


def test_a_run_reports_step_quartiles_both_views_and_keeps_its_model(tmp_path):
    """--keep-models: the model, settings, log and metrics of each run beside the JSON (scorable elsewhere:
    the copy evaluates to the same PSNR), not the optimiser checkpoint."""
    from ev3dgs.train.evaluate import evaluate

    scene = gpu_check.synthetic_scene(tmp_path / "b.h5", 24, 18, views=3)
    r = gpu_check.time_training(str(scene), "oracle", 4, "cpu", "cpu", 200, tmp_path / "runs",
                                keep_models=tmp_path / "models")
    assert r["steps_done"] == 4 and r["ms_per_step_q25"] <= r["ms_per_step_median"] <= r["ms_per_step_q75"]
    assert r["wall_seconds"] >= r["fit_seconds"] > 0
    for view in ("blur_view", "novel_view"):
        assert r[f"{view}_psnr"] > 5 and 0 < r[f"{view}_ssim"] <= 1
    kept = Path(r["model_dir"])
    assert kept.parent == tmp_path / "models" and (kept / "model.pt").is_file() and (kept / "config.json").is_file()
    assert not (kept / "ckpt.pt").exists() and (tmp_path / "runs" / kept.name / "ckpt.pt").exists()
    m = evaluate(kept, write_images=False, device="cpu", scene=scene)
    assert m["novel_view"]["psnr"] == pytest.approx(r["novel_view_psnr"], abs=1e-9)


def test_a_plan_past_its_deadline_is_skipped_in_order(tmp_path):
    out = tmp_path / "p.json"
    rc = gpu_check.main(["--dry-run", "--skip-tests", "--plan", "davis346", "--deadline-minutes", "0", "--json",
                         str(out), "--workdir", str(tmp_path / "w")])
    r = json.loads(out.read_text())
    assert rc == 0 and r["runs"] == [] and r["plan"] == "davis346"
    assert [(x["size"], x["variant"], x["steps"]) for x in r["skipped"]] == [
        (size, v, max(1, n // 1000)) for size, v, n in gpu_check.PLANS["davis346"]]
    # the second invocation of a check in two parts: the runs the first did not get to (a cut or failed run
    # is not run again)
    first = json.loads(out.read_text())
    first["runs"] = [dict(size="large", variant="blur+event", steps=30, backend="cpu", cut_by_deadline=False),
                     dict(size="large", variant="blur+event", steps=3, backend="cpu", cut_by_deadline=True),
                     dict(size="large", variant="blur-only", steps=3, backend="cpu", error="CUDA error")]
    (tmp_path / "first.json").write_text(json.dumps(first))
    rc = gpu_check.main(["--dry-run", "--skip-tests", "--plan", "davis346", "--skip-done", str(tmp_path / "first.json"),
                         "--deadline-minutes", "0", "--json", str(out), "--workdir", str(tmp_path / "w")])
    r = json.loads(out.read_text())
    assert rc == 0 and [(x["size"], x["variant"], x["steps"]) for x in r["skipped"]] == [
        ("small", "blur+event", 3), ("large", "naive", 3), ("large", "oracle", 3)]
    assert gpu_check.completed_runs(tmp_path / "none.json") == set()


@pytest.mark.slow
def test_the_device_script_runs_both_parts(tmp_path):
    """tools/gpu_device_run.sh with --dry-run on a CPU (pip and ninja's lookup stubbed: no install here): part 1
    runs the plan until its deadline, part 2 the runs part 1 did not get to; JSON, log and the models come back in
    OUT, the models as 15 MiB pieces that join into a tar."""
    import os
    import subprocess
    import tarfile

    shim = tmp_path / "bin"
    shim.mkdir()
    (shim / "python3").write_text(f"""#!/usr/bin/env bash
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then exit 0; fi
if [ "$1" = "-c" ]; then echo /nonexistent; exit 0; fi
exec {sys.executable} "$@"
""")
    (shim / "python3").chmod(0o755)
    out = tmp_path / "out"
    env = dict(os.environ, PATH=f"{shim}:{os.environ['PATH']}", OUT=str(out), GPU_STATE=str(tmp_path / "state"),
               GPU_CARRY=str(tmp_path / "carry"), GPU_CHECK_ARGS="--dry-run --skip-tests", PART1_MINUTES="0",
               PART2_MINUTES="30", OMP_NUM_THREADS="1")
    for part in ("1", "2"):
        res = subprocess.run(["bash", str(REPO / "tools" / "gpu_device_run.sh"), part], cwd=REPO, env=env,
                             capture_output=True, text=True)
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    p1, p2 = (json.loads((out / f"gpu_part{k}.json").read_text()) for k in (1, 2))
    assert p1["runs"] == [] and len(p1["skipped"]) == len(gpu_check.PLANS["davis346"])  # deadline 0: nothing ran
    assert [(x["size"], x["variant"]) for x in p2["runs"]] == [(s, v) for s, v, _ in gpu_check.PLANS["davis346"]]
    assert (out / "gpu_part2.log").read_text().count("steps") >= 6
    pieces = sorted(out.glob("models_part2.tgz.*"))
    assert pieces and all(p.stat().st_size <= 15 * 2**20 for p in pieces)
    (tmp_path / "m.tgz").write_bytes(b"".join(p.read_bytes() for p in pieces))
    with tarfile.open(tmp_path / "m.tgz") as t:
        names = t.getnames()
    assert sum(n.endswith("/model.pt") for n in names) == 6 and not any(n.endswith("ckpt.pt") for n in names)
    assert subprocess.run(["bash", str(REPO / "tools" / "gpu_device_run.sh"), "3"], cwd=REPO, env=env,
                          capture_output=True).returncode == 2


def test_the_cpu_reference_trains_the_given_scene_in_full_on_the_cpu_backend(tmp_path):
    """--cpu-reference: the runs a GPU check makes, on the cpu backend at full settings (the given scene, the
    given initial points: not the dry run's quarter-size scenes and 500 points), without install, kernels or
    tests."""
    from ev3dgs.train.config import TrainConfig

    scene = gpu_check.synthetic_scene(tmp_path / "s.h5", 24, 18, views=3)
    out = tmp_path / "ref.json"
    rc = gpu_check.main(["--cpu-reference", "--sizes", "small", "--scene-small", str(scene), "--variants",
                         "blur+event", "--steps", "2", "--init-points", "300", "--json", str(out), "--workdir",
                         str(tmp_path / "w"), "--keep-models", str(tmp_path / "m")])
    r = json.loads(out.read_text())
    assert rc == 0 and r["cpu_reference"] and not r["dry_run"] and r["gpu"] == "none (cpu reference)"
    assert "gpu_tests" not in r and "kernels" not in r and r["backend"] == "cpu"
    (run,) = r["runs"]
    assert (run["backend"], run["steps_done"], run["width"], run["height"]) == ("cpu", 2, 24, 18)
    cfg = TrainConfig.load(Path(run["model_dir"]) / "config.json")
    assert (cfg.init_points, cfg.backend, cfg.iterations) == (300, "cpu", 2)
    with pytest.raises(SystemExit):
        gpu_check.main(["--cpu-reference", "--dry-run"])
