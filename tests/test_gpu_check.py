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
    assert {(x["size"], x["variant"]) for x in runs} == {(s, v) for s in gpu_check.SIZES for v in gpu_check.VARIANTS}
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
