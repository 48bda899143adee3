"""Table-I-style fidelity benchmark (issue 13): the built-in scenes x {naive, blur-only, blur+event, information
oracle, sharp oracle} x seeds, scored E2NeRF/EvaGaussians-style on blur views (each training view's sharp
mid-exposure frame, rendered at its pose) and novel views (/test), PSNR and SSIM, mean +- std over seeds. The
information oracle trains on every sharp sub-frame of every exposure at its own pose (a file derived from the
scene's render cache: derived_scenes.py), the most any deblurring could recover.

    python tools/bench/bench_fidelity.py            # 4 scenes, 24+8 views at 96x72, 17 sub-frames, 1000 steps, 3 seeds
    python tools/bench/bench_fidelity.py --quick    # lego, 1 seed, 12+4 views at 96x72, 400 steps (<= 10 min, 2 cores)

Runs go --jobs at a time (default: one per CPU core), each in its own process with one thread (CPU training is
bitwise the same for any thread count, so the table does not depend on --jobs); they are ordered seed by seed, so
an interrupted run leaves whole seeds behind. Datasets are made once with make-dataset (Blender) into a cache folder (--cache, default
tools/results/fidelity_cache; a scene whose file exists is reused) with the dataset seed 0 for every training
seed, so the seeds measure the trainer's variance. Training runs in-process, one variant after the other
(TrainConfig defaults apart from iterations, init_points and seed: blur space, event log domain and count
convention come from the scene file). Writes JSON (every run's metrics.json plus the summary) and a plot
(PSNR per variant per scene, error bars = std over seeds) into tools/results/, and prints the table.
Runs are resumable: a run folder with a metrics.json from the same settings and the same trainer code (a hash
of ev3dgs/train and ev3dgs/splat) is not trained again.

Event-weight sweep (issue 13 item 5): ``--event-weights 1 2 4 8 16`` replaces the blur+event variant by one
blur+event variant per omega = k / 625 (named ``blur+event@k``), e.g.

    python tools/bench/bench_fidelity.py --quick --scenes lego ficus --seeds 2 --variants blur-only blur+event \
        --event-weights 1 2 4 8 16 --json tools/results/bench_event_weight.json
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from derived_scenes import SUBFRAMES  # noqa: E402
from ev3dgs.sim.dataset import make_dataset  # noqa: E402
from ev3dgs.sim.scenes import builtin_scenes, load_scene, resolve_render  # noqa: E402
from ev3dgs.train.config import DENSIFY_FROM, EVENT_WEIGHTS, FLOOR_STATS, TrainConfig  # noqa: E402
from ev3dgs.errors import InputError  # noqa: E402
from ev3dgs.train.evaluate import evaluate  # noqa: E402
from ev3dgs.train.jobs import default_jobs, run_parallel  # noqa: E402
from ev3dgs.train.layout import variant_overrides  # noqa: E402
from ev3dgs.train.lpips import load_lpips  # noqa: E402
from ev3dgs.train.trainer import Trainer  # noqa: E402

# events.floor = "mean", events.huber = 0, densify.from = "all": what the studies' tables of the noise norm were
# measured with (docs/fidelity.md); the default is the chi-square floor, a Huber penalty at 3 and densification
# from the blur term. Variants are written in train.toml's shape (ev3dgs.train.layout.variant_overrides: a
# term's table turns it on, ``False`` turns it off).
MEAN_FLOOR_TOML = {"events": {"floor": "mean", "huber": 0.0}, "densify": {"from": "all"}}
VARIANTS_TOML = {
    "naive": {"naive": True}, "blur-only": {"events": False}, "blur+event": {},
    # plain 3DGS on all 17 sharp sub-frames of every exposure at their own poses (the most any deblurring
    # could recover from these exposures), scored on the scene's own views: see INFO_VARIANTS
    "info-oracle": {"oracle": True},
    "oracle": {"oracle": True}, "blur+event-map": {"threshold_map": {"weights": "posterior"}},
    "blur+event-mapprior": {"threshold_map": {}},
    "blur+event-hdr": {"hdr": {}}, "blur+event-sh": {"sh_interval": 33},
    "blur+event-hdr-sh": {"hdr": {}, "sh_interval": 33}, "oracle-sh": {"oracle": True, "sh_interval": 33},
    "blur+event-edi": {"edi_prior": {"weight": 8 / 625}},
    "blur+event-hdr-sh-edi": {"hdr": {}, "sh_interval": 33, "edi_prior": {"weight": 8 / 625}},
    # each view's sub-poses from its motion, at most 2 px apart, up to 17
    "blur+event-px2": {"blur": {"subposes": 17, "subpose_px": 2.0}},
    # a learned camera response before the sRGB decode, alone and with [hdr]
    "blur+event-response": {"response": {}},
    "blur+event-hdr-response": {"hdr": {}, "response": {}},
    # the events at their weight omega whatever the frames' noise
    "blur+event-fn0": {"events": {"frame_noise": 0.0}},
    # the mean floor, no penalty, densification from the whole loss: the noise norm's settings before the
    # chi-square floor became its default
    "blur+event-mean": MEAN_FLOOR_TOML}
# the same as TrainConfig keyword overrides (what the jobs, the run folders' cache checks and the tests use)
MEAN_FLOOR = variant_overrides(MEAN_FLOOR_TOML)
VARIANTS = {name: variant_overrides(v) for name, v in VARIANTS_TOML.items()}
# variants trained on a scene file derived from the scene's render cache (derived_scenes.py: the kind named)
INFO_VARIANTS = {"info-oracle": "info"}
DEFAULT_VARIANTS = ("naive", "blur-only", "blur+event", "info-oracle", "oracle")
# The full table is sized so that a 2-core CPU finishes it in about an hour (60 runs, two at a time); the
# issue's example size (128x96, 3000 steps) is ~4x that: --size 128x96 --steps 3000.
FULL = dict(scenes=None, seeds=3, iterations=1000, render=dict(width=96, height=72, views=24, test_views=8,
                                                               subframes=17, samples=16))
QUICK = dict(scenes=["lego"], seeds=1, iterations=400, render=dict(width=96, height=72, views=12, test_views=4,
                                                                    subframes=17, samples=8))
VIEWS = ("blur_view", "novel_view")


OMEGA_UNIT = 1.0 / 625.0  # --event-weights are in units of the trainer's default omega (Ev3DGS's 1/625)


EVAL_ONLY = ("evaluate.py", "metrics.py", "lpips.py")  # scoring code: a change there re-scores, never retrains


def code_hash(scoring: bool = False) -> str:
    """sha256 (first 16 hex) of the trainer's and renderer's sources without the scoring modules (``scoring``:
    of the scoring modules alone). A cached run made by other training code is trained again; one scored by
    other scoring code is only evaluated again."""
    h = hashlib.sha256()
    for sub in ("ev3dgs/train", "ev3dgs/splat"):
        for f in sorted((ROOT / sub).rglob("*.py")):
            if (f.name in EVAL_ONLY) != scoring:
                continue
            h.update(str(f.relative_to(ROOT)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def make_variants(names: list[str], event_weights: list[float] | None) -> dict[str, dict]:
    """{variant name: TrainConfig overrides}; with ``event_weights`` blur+event becomes one variant per weight."""
    out = {}
    for n in names:
        if n == "blur+event" and event_weights:
            for k in event_weights:
                out[f"blur+event@{k:g}"] = dict(event_weight=k * OMEGA_UNIT)
        else:
            out[n] = VARIANTS[n]
    return out


# the SH schedule the studies' documented tables were trained with (the degree raised every 1000 steps:
# view-independent colour throughout a 1000-step run); they keep it, and the mean floor (MEAN_FLOOR), whatever
# the trainer's defaults
STUDY_SH_INTERVAL = 1000


def study_overrides(overrides: dict) -> dict:
    """A study variant's TrainConfig overrides with the SH schedule and the event-term settings the studies'
    tables were trained with (STUDY_SH_INTERVAL, MEAN_FLOOR), unless the variant sets its own."""
    return {"sh_interval": STUDY_SH_INTERVAL, **MEAN_FLOOR, **overrides}


# the settings the command line can give every variant that does not set its own (--sh-interval, --event-norm,
# --frame-noise, --event-floor, --event-huber, --densify-from), and the suffix of their run folders
RUN_SUFFIX = {"sh_interval": "_sh{}", "event_norm": "_{}", "frame_noise": "_fn{:g}", "event_floor": "_floor{}",
              "event_huber": "_huber{:g}", "densify_from": "_densify{}"}


def make_jobs(scenes: list[str], paths: dict, variants: dict, seeds: int, cache: Path, given: dict | None = None,
              derived: dict | None = None, **common) -> list[dict]:
    """One job per (seed, scene, variant), seed-major (an interrupted run leaves whole seeds). ``given``:
    {setting of RUN_SUFFIX: value or None}, the settings given on the command line: each that is not None
    trains every variant that does not set its own, in run folders of their own (RUN_SUFFIX: ``_shN``,
    ``_NORM``, ``_fnSIGMA``, ...), so that the default's cached runs stay beside them. ``derived``: {scene:
    {kind: file}} for INFO_VARIANTS, which train on that file and are scored on the scene's own."""
    given = given or {}
    if set(given) - set(RUN_SUFFIX):
        raise ValueError(f"make_jobs: no run-folder suffix for {sorted(set(given) - set(RUN_SUFFIX))}")
    fill = {k: given[k] for k in RUN_SUFFIX if given.get(k) is not None}   # in RUN_SUFFIX's order
    suffix = "".join(RUN_SUFFIX[k].format(v) for k, v in fill.items())
    jobs = []
    for seed in range(seeds):
        for name in scenes:
            for variant, overrides in variants.items():
                tag = variant.replace("+", "_").replace("@", "_w") + suffix
                kind = INFO_VARIANTS.get(variant)
                jobs.append({"scene": name, "scene_path": str(paths[name] if kind is None else derived[name][kind]),
                             "variant": variant, "seed": seed, "overrides": {**fill, **overrides}, **common,
                             "eval_scene": None if kind is None else str(paths[name]),
                             "out": str(cache / "runs" / Path(paths[name]).stem / f"{tag}_s{seed}")})
    return jobs


def build_scene(name: str, render: dict, cache: Path, quiet: bool, keep_cache: bool = False) -> Path:
    """The scene file of built-in ``name`` in ``cache``, made (Blender) unless it exists; ``keep_cache``: with
    its render cache beside it (the sharp sub-frames INFO_VARIANTS are derived from)."""
    spec = load_scene(name)
    r = resolve_render(spec, **render)
    tag = f"{spec.name}_{r.width}x{r.height}_v{r.views}t{r.test_views}s{r.subframes}p{r.samples}"
    path = cache / f"{tag}.h5"
    if not path.exists():
        t = time.perf_counter()
        make_dataset(spec, r, path, seed=0, quiet=quiet, keep_cache=keep_cache)
        print(f"  dataset {tag}: {time.perf_counter() - t:.0f} s", flush=True)
    return path


def derive_scenes(name: str, path: Path, render: dict, cache: Path, quiet: bool) -> dict[str, Path]:
    """{kind: file} of the scene files derived from ``path``'s render cache (derived_scenes.py), in
    ``cache``/derived/; a scene file made without its render cache is rendered again (checked to give the
    same frames) to get it."""
    from derived_scenes import derived_scenes, ensure_render_cache

    spec = load_scene(name)
    r = resolve_render(spec, **render)
    ensure_render_cache(path, lambda out: make_dataset(spec, r, out, seed=0, quiet=True, keep_cache=True), quiet)
    return derived_scenes(name, path, cache / "derived" / path.stem)


def run_one(scene: Path, overrides: dict, seed: int, iterations: int, init_points: int, out: Path,
            lpips_weights=None, eval_scene: Path | None = None) -> dict:
    """Train ``scene`` into ``out`` and score it (cached: see the module doc). ``eval_scene``: score on that
    file instead of the training one (a study that trains on a derived file with the same views); a cached
    run scored on another file is scored again, not trained again."""
    cfg = TrainConfig(scene=str(scene), iterations=iterations, init_points=init_points, seed=seed,
                      checkpoint_every=max(iterations, 1), threads=1, **overrides)
    done = out / "metrics.json"
    code, scoring = code_hash(), code_hash(scoring=True)
    scored_on = None if eval_scene is None else str(eval_scene)

    def score(run: dict) -> dict:   # evaluate, record with the run's training facts, write metrics.json
        m = evaluate(out, lpips_weights=lpips_weights, write_images=False,
                     **({} if eval_scene is None else {"scene": eval_scene, "other_scene": True}))
        m |= run | {"scoring_code": scoring} | ({"scored_on": scored_on} if scored_on else {})
        done.write_text(json.dumps(m, indent=2))
        return m

    if done.exists() and (out / "config.json").exists():
        old = TrainConfig.load(out / "config.json")
        cached = json.loads(done.read_text())
        if not old.differences(cfg, ignore=("checkpoint_every", "threads")) and cached.get("code") == code:
            if (cached.get("scoring_code") == scoring and (lpips_weights is None or cached.get("lpips"))
                    and cached.get("scored_on") == scored_on):
                return cached
            # trained by this code, scored by other code, without LPIPS or on another file: score again, do not
            # retrain
            return score({k: cached.get(k) for k in ("train_seconds", "code")})
    t = time.perf_counter()
    Trainer(cfg, out, quiet=True).fit()
    return score({"train_seconds": time.perf_counter() - t, "code": code})


def merged_runs(paths: list[Path], have: set, ap) -> list[dict]:
    """The runs of earlier summary JSONs not in ``have`` ((scene, variant, seed) keys), first file first."""
    out = []
    for p in paths:
        try:
            extra = json.loads(Path(p).read_text())["runs"]
            keys = [(r["scene"], r["variant"], r["seed"]) for r in extra]
        except (OSError, ValueError, KeyError, TypeError) as e:
            ap.error(f"--merge {p}: not a bench_fidelity summary ({e})")
        for key, r in zip(keys, extra):
            if key not in have:
                have.add(key)
                out.append(r)
    return out


def _run_job(job: dict) -> dict:
    """One run in a pool worker (a fresh process: torch and numba pinned to one thread there)."""
    import torch

    torch.set_num_threads(1)
    t = time.perf_counter()
    m = run_one(Path(job["scene_path"]), job["overrides"], job["seed"], job["iterations"], job["init_points"],
                Path(job["out"]), job["lpips_weights"],
                None if job.get("eval_scene") is None else Path(job["eval_scene"]))
    return {"scene": job["scene"], "variant": job["variant"], "seed": job["seed"], "metrics": m,
            "wall": time.perf_counter() - t}


def run_jobs(jobs: list[dict], n_jobs: int, quiet: bool) -> list[dict]:
    """Run ``jobs`` ``n_jobs`` at a time; results in job order."""
    def report(r):
        if not quiet:
            bv, nv = (r["metrics"].get(v, {}).get("psnr") for v in VIEWS)
            print(f"  {r['scene']} {r['variant']:14s} seed {r['seed']}: blur view {bv:.2f} dB, "
                  f"novel view {nv:.2f} dB ({r['wall']:.0f} s)", flush=True)
        return r

    return run_parallel(_run_job, jobs, n_jobs, report)


def summarise(runs: list[dict], variants=VARIANTS) -> dict:
    """{scene: {variant: {view: {"psnr": [mean, std], "ssim": [mean, std], "seeds": n}}}} plus "average"
    over scenes (mean of the per-scene means; std = std over seeds of the scene-averaged value)."""
    table: dict = {}
    for r in runs:
        cell = table.setdefault(r["scene"], {}).setdefault(r["variant"], {})
        for view in VIEWS:
            if view in r["metrics"]:
                for k in ("psnr", "ssim", "lpips"):
                    if k in r["metrics"][view]:
                        cell.setdefault(view, {}).setdefault(k, {})[r["seed"]] = r["metrics"][view][k]
    out: dict = {}
    for scene, variants in table.items():
        for variant, views in variants.items():
            for view, ks in views.items():
                for k, by_seed in ks.items():
                    v = np.array(list(by_seed.values()))
                    out.setdefault(scene, {}).setdefault(variant, {}).setdefault(view, {})[k] = \
                        [float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0]
                    out[scene][variant][view]["seeds"] = len(v)
    scenes = list(table)
    avg: dict = {}
    for variant in variants:
        for view in VIEWS:
            for k in ("psnr", "ssim", "lpips"):
                per_seed = {}
                for s in scenes:
                    for seed, val in table[s].get(variant, {}).get(view, {}).get(k, {}).items():
                        per_seed.setdefault(seed, []).append(val)
                full = [np.mean(v) for v in per_seed.values() if len(v) == len(scenes)]
                if full:
                    a = np.array(full)
                    avg.setdefault(variant, {}).setdefault(view, {})[k] = \
                        [float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else 0.0]
    out["average"] = avg
    return out


def targets(avg: dict) -> dict:
    """The issue-13 targets on the scene average (None where a variant is missing)."""
    def get(v, view):
        return avg.get(v, {}).get(view, {}).get("psnr")
    be, nv, bo, orc = (get(v, "blur_view") for v in ("blur+event", "naive", "blur-only", "oracle"))
    res = {}
    if be and nv:
        res["blur_view: blur+event - naive >= 3 dB"] = round(be[0] - nv[0], 2)
    if be and bo:
        diff = be[0] - bo[0]
        res["blur_view: blur+event - blur-only >= 0.5 dB"] = round(diff, 2)
        res["  ... and > 2 std over seeds"] = bool(diff > 2 * max(be[1], bo[1]) and be[1] + bo[1] > 0)
    for view in VIEWS:
        b, o, i = get("blur+event", view), get("oracle", view), get("info-oracle", view)
        if b and o:
            res[f"{view}: oracle - blur+event <= 1 dB"] = round(o[0] - b[0], 2)
        if b and i:   # what perfect deblurring would add, and where the information bound sits
            res[f"{view}: info-oracle - blur+event"] = round(i[0] - b[0], 2)
        if i and o:
            res[f"{view}: oracle - info-oracle"] = round(o[0] - i[0], 2)
    return res


def format_table(summary: dict, variants=VARIANTS) -> str:
    rows = [f"{'scene':10s} {'variant':14s} {'blur PSNR':>14s} {'blur SSIM':>9s} {'novel PSNR':>14s} {'novel SSIM':>10s}"]
    names = list(variants)
    for scene, by_variant in summary.items():
        for variant in names:
            c = by_variant.get(variant)
            if not c:
                continue
            cols = []
            for view in VIEWS:
                p, s = c.get(view, {}).get("psnr"), c.get(view, {}).get("ssim")
                cols.append(f"{p[0]:7.2f} ± {p[1]:4.2f}" if p else f"{'-':>14s}")
                cols.append(f"{s[0]:9.4f}" if s else f"{'-':>9s}")
            rows.append(f"{scene:10s} {variant:14s} {cols[0]:>14s} {cols[1]:>9s} {cols[2]:>14s} {cols[3]:>10s}")
    return "\n".join(rows)


def plot(summary: dict, png: Path, variants=VARIANTS) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(summary)
    fig, axes = plt.subplots(1, 2, figsize=(max(6, 2.2 * len(scenes) + 2), 3.4), sharey=False)
    width = 0.8 / len(variants)
    for ax, view in zip(axes, VIEWS):
        for i, variant in enumerate(variants):
            xs, ys, es = [], [], []
            for j, s in enumerate(scenes):
                p = summary[s].get(variant, {}).get(view, {}).get("psnr")
                if p:
                    xs.append(j + (i - (len(variants) - 1) / 2) * width)
                    ys.append(p[0])
                    es.append(p[1])
            ax.bar(xs, ys, width, yerr=es, capsize=2, label=variant)
        ax.set_xticks(range(len(scenes)))
        ax.set_xticklabels(scenes, fontsize=8)
        ax.set_title(view.replace("_", " ") + " PSNR (dB)", fontsize=9)
        lo = min((c.get(view, {}).get("psnr", [99])[0] for s in scenes for c in summary[s].values()), default=0)
        ax.set_ylim(max(0, lo - 3), None)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="lego, one seed, 96x72, 400 steps (<= 10 minutes on 2 cores; default: off, the full 4-scene table)")
    ap.add_argument("--scenes", nargs="+", help="built-in scene names (default: all built-in scenes)")
    ap.add_argument("--seeds", type=int, help="number of training seeds, run as 0..N-1 (default 3; --quick 1)")
    ap.add_argument("--iterations", "--steps", type=int, help="training steps per run (default 1000; --quick 400)")
    ap.add_argument("--event-weights", type=float, nargs="+",
                    help="sweep omega: one blur+event variant per value, in units of 1/625 (e.g. 1 2 4 8 16; "
                         "default: none, blur+event at the trainer's default omega)")
    ap.add_argument("--size", metavar="WxH", help="image size in pixels (default 96x72)")
    ap.add_argument("--views", type=int, help="training views per scene (default 24; --quick 12)")
    ap.add_argument("--test-views", type=int, help="novel (test) views per scene (default 8; --quick 4)")
    ap.add_argument("--jobs", type=int, default=default_jobs(),
                    help="runs at a time, one thread each (default: the CPU cores here, %(default)s)")
    ap.add_argument("--init-points", type=int, default=5000, help="random initial Gaussians (default %(default)s)")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(DEFAULT_VARIANTS),
                    help=f"variants to run (default: {' '.join(DEFAULT_VARIANTS)})")
    ap.add_argument("--cache", type=Path, default=ROOT / "tools/results/fidelity_cache",
                    help="datasets and run folders (default %(default)s)")
    ap.add_argument("--json", type=Path, help="summary JSON (default tools/results/bench_fidelity[_quick].json)")
    ap.add_argument("--plot", type=Path, help="PSNR bar plot (default tools/results/bench_fidelity[_quick].png)")
    ap.add_argument("--lpips-weights", type=Path, help="LPIPS v0.1 weights file passed to evaluate (see ev3dgs eval "
                    "--help; default: none, no LPIPS)")
    ap.add_argument("--merge", nargs="+", type=Path, default=[], metavar="EARLIER.json",
                    help="add the runs of earlier summaries to the table and plot (a run of this invocation wins "
                         "over one with the same scene, variant and seed; default: none)")
    ap.add_argument("--sh-interval", type=int, metavar="N",
                    help="train every variant that does not set its own with --sh-interval N (default: the "
                         "trainer's, auto; 1000 keeps the colours view-independent through 1000 steps)")
    ap.add_argument("--event-norm", choices=tuple(EVENT_WEIGHTS),
                    help="train every variant that does not set its own with this event norm (default: the "
                         "trainer's, noise; count is the norm of the event-weight table in the docs)")
    ap.add_argument("--frame-noise", type=float, metavar="SIGMA",
                    help="train every variant that does not set its own with --frame-noise SIGMA (8-bit levels; "
                         "default: the trainer's, auto; 0 is how the lowlight rows of the option tables in the "
                         "docs were made)")
    ap.add_argument("--event-floor", choices=FLOOR_STATS,
                    help="train every variant that does not set its own with this --event-floor (default: the "
                         "trainer's, chi2 under the noise norm; mean is what the option tables in the docs were "
                         "measured with)")
    ap.add_argument("--event-huber", type=float, metavar="C",
                    help="train every variant that does not set its own with --event-huber C (default: the "
                         "trainer's, 3 under the noise norm)")
    ap.add_argument("--densify-from", choices=DENSIFY_FROM,
                    help="train every variant that does not set its own with this --densify-from (default: the "
                         "trainer's, blur under the noise norm)")
    ap.add_argument("--quiet", action="store_true", help="no per-run lines, only the table (default: off)")
    a = ap.parse_args(argv)
    if a.lpips_weights:
        try:
            load_lpips(a.lpips_weights)  # a bad file fails now, not after the first training run
        except InputError as e:
            ap.error(str(e))
    preset = dict(QUICK if a.quick else FULL)
    render = dict(preset["render"])
    if a.size:
        try:
            w, h = (int(v) for v in a.size.lower().split("x"))
        except ValueError:
            ap.error(f"--size must be WxH, got {a.size!r}")
        if w < 8 or h < 8:
            ap.error("--size must be at least 8x8")
        render.update(width=w, height=h)
    for key in ("views", "test_views"):
        if getattr(a, key) is not None:
            if getattr(a, key) < 1:
                ap.error(f"--{key.replace('_', '-')} must be >= 1")
            render[key] = getattr(a, key)
    if a.jobs < 1:
        ap.error("--jobs must be >= 1")
    if a.sh_interval is not None and a.sh_interval < 1:
        ap.error("--sh-interval must be >= 1")
    if a.frame_noise is not None and not 0 <= a.frame_noise <= 255:
        ap.error("--frame-noise must be in [0, 255]")
    if a.event_huber is not None and not 0 <= a.event_huber < float("inf"):
        ap.error("--event-huber must be a number >= 0 (0: off)")
    preset["render"] = render
    if a.event_weights and any(not (w >= 0) for w in a.event_weights):
        ap.error("--event-weights must be >= 0")
    if any(v in INFO_VARIANTS for v in a.variants) and render["subframes"] != SUBFRAMES:
        ap.error(f"the info oracle is derived from {SUBFRAMES} rendered sub-frames per exposure")
    if a.event_weights and "blur+event" not in a.variants:
        ap.error("--event-weights needs the blur+event variant")
    variants = make_variants(a.variants, a.event_weights)
    scenes = a.scenes or preset["scenes"] or builtin_scenes()
    seeds = a.seeds or preset["seeds"]
    iterations = a.iterations or preset["iterations"]
    suffix = "_quick" if a.quick else ""
    js = a.json or ROOT / f"tools/results/bench_fidelity{suffix}.json"
    png = a.plot or ROOT / f"tools/results/bench_fidelity{suffix}.png"
    a.cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    info = any(v in INFO_VARIANTS for v in variants)
    paths = {name: build_scene(name, render, a.cache, a.quiet, keep_cache=info) for name in scenes}
    derived = {name: derive_scenes(name, paths[name], render, a.cache, a.quiet) for name in scenes} if info else {}
    given = {k: getattr(a, k) for k in RUN_SUFFIX}
    jobs = make_jobs(scenes, paths, variants, seeds, a.cache, given, derived, iterations=iterations,
                     init_points=a.init_points, lpips_weights=a.lpips_weights and str(a.lpips_weights))
    runs = [{k: v for k, v in r.items() if k != "wall"} for r in run_jobs(jobs, a.jobs, a.quiet)]
    this = len(runs)
    runs += merged_runs(a.merge, {(r["scene"], r["variant"], r["seed"]) for r in runs}, ap)
    for r in runs[this:]:   # merged variants join the table
        variants.setdefault(r["variant"], VARIANTS.get(r["variant"], {}))
    order = list(VARIANTS)  # table and plot in VARIANTS' order (an --event-weights variant after them)
    variants = {k: variants[k] for k in sorted(variants, key=lambda k: order.index(k) if k in order else len(order))}
    summary = summarise(runs, variants)
    scenes = list(dict.fromkeys([*scenes, *(r["scene"] for r in runs)]))
    result = {"settings": {"quick": a.quick, "scenes": scenes, "seeds": seeds, "iterations": iterations,
                           "init_points": a.init_points, "render": render, "dataset_seed": 0, "jobs": a.jobs,
                           **given, "variants": list(variants), "variant_overrides": variants, "code": code_hash(),
                           "merged": [str(p) for p in a.merge]},
              "summary": summary, "targets": targets(summary["average"]),
              "blurry_input": {r["scene"]: r["metrics"].get("blurry_input", {}).get("psnr") for r in runs},
              "runs": [{k: v for k, v in r.items() if k != "metrics"} |
                       {"metrics": {k: r["metrics"].get(k) for k in (*VIEWS, "blurry_input", "train_seconds")}}
                       for r in runs],
              "seconds": time.perf_counter() - t0}
    js.parent.mkdir(parents=True, exist_ok=True)
    js.write_text(json.dumps(result, indent=2))
    plot({k: v for k, v in summary.items() if k != "average"}, png, variants)
    print(format_table(summary, variants))
    for k, v in result["targets"].items():
        print(f"{k}: {v}")
    print(f"done in {result['seconds']:.0f} s -> {js}, {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
