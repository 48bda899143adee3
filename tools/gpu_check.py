"""The GPU check: run on a machine with a CUDA GPU and no network, with ev3dgs and gsplat carried as wheels.

    python tools/gpu_check.py --wheels WHEELDIR [--scene-small S.h5 --scene-large L.h5] [--steps 3000 30000]
                              [--deadline-minutes M] [--cpu-baseline-steps N] [--plan davis346] [--skip-done J]
                              [--keep-models DIR]

tools/gpu_device_run.sh runs it in two parts on a device machine (docs/gpu.md, "The DAVIS346 check").

1. environment: python, torch and its CUDA, the GPU's name, nvcc and ninja (gsplat compiles its kernels on first
   use: nvcc and ninja must be on PATH);
2. with --wheels: ``pip install --no-index --find-links WHEELDIR ev3dgs[cuda]`` (nothing from the network;
   WHEELDIR holds the ev3dgs wheel, gsplat's and every dependency the machine lacks), or with --no-deps every
   wheel in WHEELDIR as it is;
3. gsplat's kernels built (or loaded from torch's extension cache), timed;
4. the tests marked ``gpu`` (the real kernels against the reference backend and against gsplat's torch
   emulation; training on the cuda backend against the cpu backend), with pytest;
5. training on the cuda backend, timed: each step count x each scene (96x72 and 346x260; without --scene-* a
   synthetic blob scene of that size is made, no Blender needed) x each variant (naive / blur-only /
   blur+event / oracle), or with --plan the plan's runs in its order (davis346: docs/gpu.md), then PSNR/SSIM on
   the blur views and the novel views; per run ms per step (median and quartiles, CUDA events: no host
   synchronisation added), wall time, peak GPU memory, Gaussians; --keep-models copies the trained models;
   with --cpu-baseline-steps the cpu backend is timed first
   on the same scenes and machine (the first variant given), so the speed-up is a ratio inside one run. Written to
   tools/results/gpu_<gpu name>.json after every run (a run that fails is recorded with its error and the rest
   go on). With --deadline-minutes a run that would end past the deadline is cut there: it is scored at the
   step it reached (``steps_done`` < ``steps``, ``cut_by_deadline``), and later runs are skipped.

``--dry-run`` checks the same path on the CPU (cpu backend, a few steps, a small synthetic scene, no install)
and writes the JSON marked ``"dry_run": true``: tests/test_gpu_check.py runs it.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SIZES = {"small": (96, 72), "large": (346, 260)}
VARIANTS = {"naive": dict(naive=True), "blur-only": dict(event_loss=False), "blur+event": dict(),
            "oracle": dict(oracle=True)}
DEFAULT_VARIANTS = ("naive", "blur-only", "blur+event")
# --plan davis346: (size, variant, steps) in the order they run, so that a deadline cuts the least needed: the
# 30 000-step blur+event run at 346x260, its 3000-step run and blur-only's (the cpu backend's 3000-step run is
# the PSNR reference), the 96x72 step (per-step comparison), then naive and the sharp oracle as time allows
PLANS = {"davis346": (("large", "blur+event", 30000), ("large", "blur+event", 3000), ("large", "blur-only", 3000),
                      ("small", "blur+event", 3000), ("large", "naive", 3000), ("large", "oracle", 3000))}
# what a trained run folder keeps for scoring elsewhere (--keep-models): the model, its settings and log, not the
# optimiser checkpoint
MODEL_FILES = ("config.json", "model.pt", "metrics.json", "log.jsonl", "trajectory.npz", "response.json")
GPU_TESTS = ("test_gsplat_parity.py", "test_gpu_train.py")
# --event-floor / --densify-from choices, as ev3dgs.train.config's FLOOR_STATS / DENSIFY_FROM (not imported: the
# check runs before the wheel it installs)
FLOOR_STATS, DENSIFY_FROM = ("mean", "median", "chi2"), ("all", "blur")


class DeadlineReached(Exception):
    """Raised from the step callback when the check's deadline has passed."""


def environment() -> dict:
    import torch

    env = {"python": platform.python_version(), "platform": platform.platform(), "torch": torch.__version__,
           "torch_cuda": torch.version.cuda, "cuda_available": torch.cuda.is_available(),
           "nvcc": shutil.which("nvcc"), "ninja": shutil.which("ninja")}
    if env["cuda_available"]:
        env["gpu"] = torch.cuda.get_device_name(0)
        env["gpu_memory_gib"] = torch.cuda.get_device_properties(0).total_memory / 2**30
    try:
        import numpy

        env["numpy"] = numpy.__version__
    except ImportError:
        env["numpy"] = None
    try:
        import gsplat  # lazy: importing compiles nothing

        env["gsplat"] = gsplat.__version__
    except Exception as e:  # noqa: BLE001
        env["gsplat"] = None
        env["gsplat_error"] = f"{type(e).__name__}: {e}"
    return env


def install_command(wheels: str, no_deps: bool = False) -> list[str]:
    """pip, never the network: ev3dgs[cuda] resolved from the folder, or (no_deps) every wheel in it as it is,
    for a machine whose own packages stand in for some dependencies (opencv-python-headless for
    opencv-contrib-python-headless, say)."""
    if no_deps:
        return [sys.executable, "-m", "pip", "install", "--no-index", "--no-deps",
                *sorted(str(p) for p in Path(wheels).glob("*.whl"))]
    return [sys.executable, "-m", "pip", "install", "--no-index", "--find-links", str(wheels), "ev3dgs[cuda]"]


def synthetic_scene(path: Path, width: int, height: int, views: int = 6, subframes: int = 5, n: int = 300,
                    seed: int = 0) -> Path:
    """A blob cloud seen from a shaky orbit (ev3dgs.blob_scene): a scene file made without Blender."""
    from ev3dgs.blob_scene import blob_scene

    return blob_scene(path, width, height, views=views, subframes=subframes, n=n, seed=seed,
                      source="tools/gpu_check.py")


def step_statistics(ms: list[float]) -> dict:
    """Median and quartiles of the per-step times (ms), the first step left out (its time includes kernel
    compilation / loading) when there are others."""
    import numpy as np

    x = np.asarray(ms[1:] if len(ms) > 1 else ms, dtype=np.float64)
    if not len(x):
        return {"ms_per_step_median": None, "ms_per_step_q25": None, "ms_per_step_q75": None}
    q25, med, q75 = np.percentile(x, [25, 50, 75])
    return {"ms_per_step_median": float(med), "ms_per_step_q25": float(q25), "ms_per_step_q75": float(q75)}


class StepClock:
    """Per-step times without synchronising with the device inside the run: on CUDA an event recorded on the
    stream after each step (read back once, at the end), on the CPU the host clock."""

    def __init__(self, cuda: bool, clock=time.perf_counter):
        import torch

        self.cuda, self.torch, self.clock, self.marks = cuda, torch, clock, []

    def mark(self) -> None:
        if self.cuda:
            ev = self.torch.cuda.Event(enable_timing=True)
            ev.record()
            self.marks.append(ev)
        else:
            self.marks.append(self.clock())

    def step_ms(self) -> list[float]:
        """Times between consecutive marks, in ms (the first: from the clock's start mark)."""
        if self.cuda:
            self.torch.cuda.synchronize()
            return [a.elapsed_time(b) for a, b in zip(self.marks, self.marks[1:])]
        return [1e3 * (b - a) for a, b in zip(self.marks, self.marks[1:])]


def time_training(scene: str, variant: str, steps: int, device: str, backend: str, init_points: int,
                  workdir: Path, deadline: float | None = None, options: dict | None = None,
                  keep_models: Path | None = None) -> dict:
    """Train one variant for `steps` steps (cut at `deadline`, a time.perf_counter() value); time each step
    (StepClock: no host synchronisation added to the run), then PSNR/SSIM on the blur views (the sharp frames
    of the training views) and the novel views. ``options``: TrainConfig settings given on the command line
    (--sh-interval, --event-floor, --event-huber, --densify-from; one left out or None: the trainer's default).
    ``keep_models``: copy the run's MODEL_FILES to keep_models/<run name>/ (to score elsewhere, e.g. LPIPS)."""
    import torch

    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    cfg = TrainConfig(scene=scene, iterations=steps, init_points=init_points, seed=0, device=device, backend=backend,
                      checkpoint_every=max(steps, 1), **VARIANTS[variant],
                      **{k: v for k, v in (options or {}).items() if v is not None})
    run = workdir / f"{Path(scene).stem}_{variant}_{steps}_{backend}"
    clock = StepClock(device == "cuda")
    marks = {}

    def on_step(tr, rec):
        clock.mark()
        now = time.perf_counter()
        marks.setdefault("first", now)
        marks["last"] = now
        marks["steps"] = tr.step
        if deadline is not None and now > deadline and tr.step < steps:
            raise DeadlineReached

    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    trainer = Trainer(cfg, run, quiet=True)
    clock.mark()  # the start of the first step
    cut = False
    try:
        trainer.fit(on_step=on_step)
    except DeadlineReached:
        cut = True
        trainer.save_model()  # score the model at the step it reached
    if device == "cuda":
        torch.cuda.synchronize()
    fit = time.perf_counter() - t0
    ms = clock.step_ms()
    m = evaluate(run, write_images=False, device=device)
    done = marks["steps"]
    out = {"variant": variant, "backend": backend, "steps": steps, "steps_done": done, "cut_by_deadline": cut,
           "fit_seconds": fit, "wall_seconds": time.perf_counter() - t0, "first_step_seconds": marks["first"] - t0,
           "ms_per_step": 1e3 * (marks["last"] - marks["first"]) / max(1, done - 1), **step_statistics(ms),
           "gaussians": len(trainer.model), "test_psnr": m["test"]["psnr"], "test_ssim": m["test"]["ssim"]}
    for view in ("blur_view", "novel_view"):
        if view in m:
            out[f"{view}_psnr"], out[f"{view}_ssim"] = m[view]["psnr"], m[view]["ssim"]
    if device == "cuda":
        out["peak_gpu_memory_mib"] = torch.cuda.max_memory_allocated() / 2**20
    if keep_models is not None:
        dest = Path(keep_models) / run.name
        dest.mkdir(parents=True, exist_ok=True)
        for name in MODEL_FILES:
            if (run / name).exists():
                shutil.copy2(run / name, dest / name)
        out["model_dir"] = str(dest)
    return out


def build_kernels() -> dict:
    """Import gsplat's compiled extension: the first time on a machine this compiles it (nvcc, ninja;
    MAX_JOBS parallel jobs, TORCH_CUDA_ARCH_LIST or the present GPU's architecture), later it loads it."""
    t0 = time.perf_counter()
    try:
        from gsplat.cuda._backend import _C

        ok, err = _C is not None, None if _C is not None else "gsplat built no extension (no CUDA toolkit?)"
    except Exception as e:  # noqa: BLE001
        ok, err = False, f"{type(e).__name__}: {e}"
    return {"ok": ok, "error": err, "seconds": time.perf_counter() - t0, "max_jobs": os.environ.get("MAX_JOBS"),
            "arch_list": os.environ.get("TORCH_CUDA_ARCH_LIST")}


def run_gpu_tests(dry_run: bool) -> dict:
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "gpu", "-o", "addopts=",
           *[str(REPO / "tests" / f) for f in GPU_TESTS]]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    tail = (res.stdout + res.stderr).strip().splitlines()[-1:] or [""]
    summary = tail[0]
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|skipped|error|errors|deselected)", summary)}
    return {"command": " ".join(cmd), "returncode": res.returncode, "summary": summary, "counts": counts,
            "seconds": time.perf_counter() - t0, "output_tail": (res.stdout + res.stderr)[-4000:]}


def gpu_slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_") or "gpu"


def write_json(path: Path, result: dict) -> None:
    """Atomically (ev3dgs.outputs.atomic_path): a check killed mid-write leaves the previous complete file."""
    from ev3dgs.outputs import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=2))


def plan_runs(steps, sizes, variants, cpu_baseline_steps: int, plan: str | None = None,
              dry_run: bool = False) -> list[tuple[str, str, int, str]]:
    """(size, variant, steps, backend): first the cpu-backend baseline of the first variant (a few steps per
    size), then the cuda runs: with ``plan`` (a PLANS key) its runs in its order (``sizes`` keeps those of the
    sizes given), else shortest step count first, variants in the order given, so a deadline cuts the last
    ones. ``dry_run``: a plan's step counts divided by 1000 (at least 1), its order kept."""
    if plan is not None:
        variants = [v for _, v, _ in PLANS[plan]]
    runs = [(size, variants[0], cpu_baseline_steps, "cpu") for size in sizes] if cpu_baseline_steps else []
    if plan is not None:
        return runs + [(size, v, max(1, n // 1000) if dry_run else n, "cuda") for size, v, n in PLANS[plan]
                       if size in sizes]
    return runs + [(size, v, n, "cuda") for n in sorted(steps) for v in variants for size in sizes]


def completed_runs(path) -> set[tuple[str, str, int, str]]:
    """(size, variant, steps, backend) of the runs an earlier result made: finished, cut at its deadline (the
    steps reached in the time given are its answer; run again it would be cut again) or failed; none when the
    file does not exist."""
    if not Path(path).exists():
        return set()
    return {(x["size"], x["variant"], x["steps"], x["backend"]) for x in json.loads(Path(path).read_text())["runs"]}


def merge(paths) -> dict:
    """One result from several invocations on the same GPU (a check run in parts): the runs of all, in order;
    the skips no later part made up for; the last invocation's tests; the longest kernel build (the compile,
    not a later part's load of the cached build); each part's settings and duration."""
    parts = [json.loads(Path(p).read_text()) for p in paths]
    gpus = {r["gpu"] for r in parts}
    if len(gpus) != 1:
        raise ValueError(f"the files come from different GPUs ({', '.join(sorted(gpus))})")
    out = dict(parts[0])
    out["runs"] = [x for r in parts for x in r["runs"]]
    done = {(x["size"], x["variant"], x["steps"], x["backend"]) for x in out["runs"]
            if "error" not in x and not x.get("cut_by_deadline")}
    out["skipped"] = [x for r in parts for x in r.get("skipped", [])
                      if (x["size"], x["variant"], x["steps"], x["backend"]) not in done]
    tested = [r for r in parts if "gpu_tests" in r]
    if tested:
        out["gpu_tests"] = tested[-1]["gpu_tests"]
    out["kernels"] = max((r["kernels"] for r in parts if "kernels" in r), key=lambda k: k["seconds"], default=None)
    out["parts"] = [{k: r.get(k) for k in ("steps", "variants", "plan", "skip_done", "deadline_minutes", "seconds")}
                    for r in parts]
    return out


def plot(result: dict, path: Path) -> None:
    """ms/step (bars, log scale) and test PSNR per image size and variant, cuda beside the cpu baseline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in result["runs"] if "error" not in r]
    keys = sorted({(r["width"], r["height"]) for r in runs})
    series = sorted({(r["backend"], r["variant"], r["steps"]) for r in runs}, key=lambda k: (k[0] != "cpu", k))
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / max(1, len(series))
    for j, (be, v, n) in enumerate(series):
        pts = [next((r for r in runs if (r["width"], r["height"]) == k and (r["backend"], r["variant"], r["steps"])
                     == (be, v, n) and not r.get("cut_by_deadline")), None) for k in keys]
        xs = [i + (j - (len(series) - 1) / 2) * width for i in range(len(keys))]
        label = f"{be} {v}, {n} steps"
        ax[0].bar(xs, [r["ms_per_step"] if r else 0 for r in pts], width, label=label, color=f"C{j}")
        if be != "cpu":  # a few baseline steps say nothing about the fit
            ax[1].bar(xs, [r["test_psnr"] if r else 0 for r in pts], width, label=label, color=f"C{j}")
    for a, ylabel in zip(ax, ("ms per step", "test PSNR (dB)")):
        a.set_xticks(range(len(keys)), [f"{w}x{h}" for w, h in keys])
        a.set_ylabel(ylabel)
    ax[0].set_yscale("log")
    ax[1].set_ylim(bottom=min([r["test_psnr"] for r in runs if r["backend"] != "cpu"] or [10]) - 3)
    ax[0].legend(fontsize=7)
    fig.suptitle(f"ev3dgs training on {result['gpu']} (gsplat {result['environment'].get('gsplat')}, "
                 f"torch {result['environment']['torch']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wheels", help="folder of wheels to install from with --no-index (ev3dgs, gsplat, missing deps)")
    ap.add_argument("--no-deps", action="store_true",
                    help="with --wheels: install every wheel in the folder without resolving dependencies")
    ap.add_argument("--scene-small", help="96x72 scene file (default: a synthetic one)")
    ap.add_argument("--scene-large", help="346x260 scene file (default: a synthetic one)")
    ap.add_argument("--steps", type=int, nargs="+", help="step counts (default 3000 30000; dry run 3)")
    ap.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--plan", choices=list(PLANS),
                    help="run this list of (size, variant, steps) in its order instead of --steps x --variants "
                         "(davis346: blur+event 30000 steps at 346x260, then 3000 steps of blur+event and "
                         "blur-only, blur+event at 96x72, naive and the sharp oracle at 346x260)")
    ap.add_argument("--skip-done", metavar="JSON",
                    help="leave out the runs this earlier result made, finished, cut or failed (a check in two "
                         "invocations: the second goes on where the first's deadline stopped; --merge combines "
                         "them); a missing file leaves out nothing")
    ap.add_argument("--keep-models", metavar="DIR",
                    help="copy each trained run's model, settings, log and metrics to DIR/<run>/ (e.g. $OUT on a "
                         "device machine, to compute LPIPS elsewhere)")
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--init-points", type=int, default=20000)
    ap.add_argument("--sh-interval", type=int, metavar="N",
                    help="raise the SH degree every N steps (default: the trainer's, auto; the H100 table in "
                         "docs/gpu.md used 1000)")
    ap.add_argument("--event-floor", choices=FLOOR_STATS,
                    help="the event term's floor (default: the trainer's, chi2; the H100 table in docs/gpu.md "
                         "used mean)")
    ap.add_argument("--event-huber", type=float, metavar="C",
                    help="the event term's Huber penalty (default: the trainer's, 3; the H100 table used 0)")
    ap.add_argument("--densify-from", choices=DENSIFY_FROM,
                    help="which loss decides densification (default: the trainer's, blur; the H100 table used all)")
    ap.add_argument("--cpu-baseline-steps", type=int, default=0,
                    help="first time the cpu backend for this many steps per scene, with the first variant given (the "
                         "speed-up as a ratio measured on the same machine)")
    ap.add_argument("--deadline-minutes", type=float,
                    help="stop training at this many minutes after the start: the run in progress is scored at the "
                         "step it reached, later runs are skipped")
    ap.add_argument("--skip-tests", action="store_true", help="do not run the gpu-marked tests")
    ap.add_argument("--json", help="output (default tools/results/gpu_<gpu name>.json)")
    ap.add_argument("--cpu-reference", action="store_true",
                    help="the same runs on the cpu backend of a CPU machine, full size (the reference a GPU run's "
                         "PSNR is compared with): no install, no kernels, no gpu tests; default steps 3000")
    ap.add_argument("--dry-run", action="store_true",
                    help="CPU path: no install, cpu backend, 3 steps (unless --steps), small synthetic scenes")
    ap.add_argument("--workdir", help="where scenes and runs go (default: a temporary folder)")
    ap.add_argument("--plot", help="also draw ms/step and PSNR per size and variant to this PNG")
    ap.add_argument("--merge", nargs="+", metavar="JSON",
                    help="combine the results of several invocations on the same GPU into --json (and --plot); "
                         "runs nothing")
    args = ap.parse_args(argv)
    if (args.deadline_minutes is not None and args.deadline_minutes < 0) or args.cpu_baseline_steps < 0 \
            or any(n < 1 for n in args.steps or [1]) or args.init_points < 1 \
            or (args.sh_interval is not None and args.sh_interval < 1) \
            or (args.event_huber is not None and not 0 <= args.event_huber < float("inf")):
        ap.error("--steps, --init-points and --sh-interval must be >= 1, --deadline-minutes, --event-huber and "
                 "--cpu-baseline-steps >= 0")
    options = {k: getattr(args, k) for k in ("sh_interval", "event_floor", "event_huber", "densify_from")}
    if args.merge:
        if not args.json:
            ap.error("--merge needs --json")
        try:
            result = merge(args.merge)
        except (OSError, ValueError, KeyError, TypeError) as e:  # unreadable, not JSON, not a check's result
            print(f"--merge: {e if isinstance(e, ValueError) else f'{type(e).__name__}: {e}'}", file=sys.stderr)
            return 2
        write_json(Path(args.json), result)
        if args.plot:
            plot(result, Path(args.plot))
        print(f"wrote {args.json}")
        return 0
    if args.dry_run and args.cpu_reference:
        ap.error("--dry-run and --cpu-reference are different checks: give one")
    on_cpu = args.dry_run or args.cpu_reference
    if args.cpu_reference:
        args.skip_tests = True
    start = time.perf_counter()
    deadline = None if args.deadline_minutes is None else start + 60 * args.deadline_minutes

    if args.wheels and not on_cpu:
        cmd = install_command(args.wheels, args.no_deps)
        print("installing:", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
    env = environment()
    print(json.dumps(env, indent=1), flush=True)
    if not on_cpu:
        if not env["cuda_available"]:
            print("no CUDA device: use --dry-run on a CPU machine", file=sys.stderr)
            return 2
        if env["gsplat"] is None:
            print(f"gsplat does not import ({env.get('gsplat_error')}): give --wheels", file=sys.stderr)
            return 2
    device, backend = ("cpu", "cpu") if on_cpu else ("cuda", "cuda")
    steps = args.steps or ([3] if args.dry_run else [3000] if args.cpu_reference else [3000, 30000])
    label = "dry_run" if args.dry_run else "cpu_reference" if args.cpu_reference else env.get("gpu", "gpu")
    out = Path(args.json or REPO / "tools" / "results" / f"gpu_{gpu_slug(label)}.json")
    result = {"dry_run": args.dry_run, "cpu_reference": args.cpu_reference, "environment": env,
              "gpu": env.get("gpu", "none (dry run)" if args.dry_run else "none (cpu reference)"),
              "device": device, "backend": backend, "steps": steps, "variants": args.variants, "plan": args.plan,
              "skip_done": args.skip_done,
              "deadline_minutes": args.deadline_minutes, **options, "runs": [], "skipped": []}
    if not on_cpu:
        result["kernels"] = build_kernels()
        print("gsplat kernels:", result["kernels"], flush=True)
        write_json(out, result)
    if not args.skip_tests:
        result["gpu_tests"] = run_gpu_tests(args.dry_run)
        print("gpu tests:", result["gpu_tests"]["summary"], flush=True)
        write_json(out, result)
    failures = 0
    with tempfile.TemporaryDirectory() as tmp:
        from ev3dgs import schema

        work = Path(args.workdir or tmp)
        scenes = {}
        for key in args.sizes:
            w, h = SIZES[key]
            given = getattr(args, f"scene_{key}")
            if given:
                scenes[key] = given
            else:  # the dry run keeps it small: a few views at 1/4 of the size
                ww, hh = (w // 4, h // 4) if args.dry_run else (w, h)
                scenes[key] = str(synthetic_scene(work / f"blobs_{ww}x{hh}.h5", ww, hh,
                                                  views=3 if args.dry_run else 6))
        init_points = 500 if args.dry_run else args.init_points
        planned = plan_runs(steps, list(scenes), args.variants, args.cpu_baseline_steps, args.plan, args.dry_run)
        done = completed_runs(args.skip_done) if args.skip_done else set()
        for key, variant, n, be in planned:
            scene = scenes[key]
            dev, be = (device, backend) if be == "cuda" else ("cpu", "cpu")  # the dry run: cpu for both
            if (key, variant, n, be) in done:
                continue
            if deadline is not None and time.perf_counter() >= deadline:
                result["skipped"].append({"size": key, "variant": variant, "steps": n, "backend": be,
                                          "why": "past the deadline"})
                continue
            cam = schema.read(scene).camera
            try:
                r = time_training(scene, variant, n, dev, be, init_points, work / "runs", deadline, options,
                                  keep_models=args.keep_models)
            except Exception as e:  # noqa: BLE001 - recorded, and the other runs go on
                failures += 1
                r = {"variant": variant, "backend": be, "steps": n,
                     "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()[-3000:]}
                print(f"{cam.width}x{cam.height} {variant} {n} steps ({be}) FAILED: {r['error']}", flush=True)
            else:
                cut = f" (cut at step {r['steps_done']})" if r["cut_by_deadline"] else ""
                print(f"{cam.width}x{cam.height} {be:4s} {variant:10s} {n:6d} steps{cut}: "
                      f"{r['ms_per_step_median']:8.2f} ms/step (median; quartiles {r['ms_per_step_q25']:.2f}-"
                      f"{r['ms_per_step_q75']:.2f}), {r['fit_seconds']:7.1f} s, {r['gaussians']} Gaussians, test "
                      f"PSNR {r['test_psnr']:.2f} dB", flush=True)
            r.update(scene=Path(scene).name, size=key, width=cam.width, height=cam.height)
            result["runs"].append(r)
            write_json(out, result)
    result["seconds"] = time.perf_counter() - start
    write_json(out, result)
    if args.plot:
        plot(result, Path(args.plot))
    print(f"wrote {out}")
    # pytest: 0 all passed/skipped, 5 nothing collected (gsplat missing: the module skips)
    tests_ok = args.skip_tests or result["gpu_tests"]["returncode"] in ((0, 5) if args.dry_run else (0,))
    kernels_ok = on_cpu or result["kernels"]["ok"]
    return 0 if tests_ok and kernels_ok and not failures else 1


if __name__ == "__main__":
    sys.exit(main())
