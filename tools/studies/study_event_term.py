"""Study: does the trainer use the events it is given? A threshold x mismatch sweep on one scene.

One scene (default tools/scenes/heldout_shake.toml) is rendered once; its events are simulated again for every
(threshold, relative mismatch) cell, symmetric thresholds theta with per-pixel spread sigma = rel * theta, the
frames and poses unchanged. Each cell is trained with blur+event under the noise-model event norm (the
default, ``--event-norm noise``) and, for comparison, under the older count norm (residual in events,
``--event-norm count``); blur-only and the sharp oracle do not see the events and are trained once per seed.
Blur-view and novel-view PSNR, mean over seeds; wall time per run.

    python tools/studies/study_event_term.py --json tools/results/study_event_term.json \\
        --plot tools/results/study_event_term.png [--thresholds 0.05 0.1 0.2 0.4] [--mismatch 0 0.1 0.4]
        [--seeds 0 1] [--iterations 1000] [--views 12] [--variants blur+event blur+event-count]
        [--merge EARLIER.json]

`make study-event-term` runs the noise norm, blur-only and the oracle on seeds 0 and 1, and the count norm on
seed 0 (tools/results/study_event_term_count.json), merged into one table and plot; then the noise norm with
per-pixel thresholds (``--threshold-map``, variant blur+event-map) at 10 % and 40 % mismatch, whose runs also
record how close the fitted thresholds came to the ones the simulator drew (tools/results/study_event_term_map.json);
then, at 10 % mismatch, radiance above full scale (``--hdr``) and a faster SH schedule (``--sh-interval 33``):
each alone at threshold 0.05 (tools/results/study_event_term_hdr05.json), both together with blur-only and the
oracle on the same schedule at every threshold (tools/results/study_event_term_hdr.json); last, the EDI prior
(``--edi-prior``) alone and with both options, at 10 % mismatch (tools/results/study_event_term_edi.json); and
both options with per-pixel thresholds at 10 % and 40 % (tools/results/study_event_term_hdr_map.json); and
the sub-poses: each view's count from its motion (``--subpose-px 2``, up to 17) with and without all three at
threshold 0.05 (tools/results/study_event_term_px2.json), all three with 17 sub-poses at every threshold of the
10 % row (tools/results/study_event_term_subposes.json).

Every variant is trained with the SH schedule and the event floor of the study's documented tables
(bench_fidelity.study_overrides: ``--sh-interval 1000``, the mean floor ``--event-floor mean --event-huber 0
--densify-from all``) unless it sets its own: the ``-robust`` variants use the trainer's default floor.

Runs go two at a time by default (one per core, one thread each) and are cached by settings and trainer code
in --cache (tools/bench/bench_fidelity.py's run_one), so an interrupted study resumes.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "tools" / "bench"))

from ev3dgs.train.layout import variant_overrides  # noqa: E402
from pareto import save_json  # noqa: E402

# Variants in train.toml's shape (ev3dgs.train.layout.variant_overrides: a term's table turns it on, False
# turns it off). The -map variants weigh the events by each pixel's fitted threshold spread (threshold_map.weights
# = "posterior"); the -mapprior ones by the mismatch prior, as without a map (the table's default).
MAP = {"threshold_map": {"weights": "posterior"}}
ROBUST_EVENTS = {"floor": "chi2", "huber": 3.0}   # [events] keys, with densify.from = "blur"
NOISE = {"events": {"norm": "noise"}}
HDR_SH = {"hdr": {}, "sh_interval": 33}
EDI = {"edi_prior": {"weight": 8 / 625}}


def _v(*parts: dict) -> dict:
    """Variant tables merged (a table given twice: its keys together)."""
    out: dict = {}
    for part in parts:
        for k, v in part.items():
            out[k] = {**out[k], **v} if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


VARIANTS_TOML = {
    "blur-only": {"events": False}, "blur+event": NOISE,
    "blur+event-count": {"events": {"norm": "count"}}, "oracle": {"oracle": True},
    "blur+event-map": _v(NOISE, MAP),
    # radiance above full scale ([hdr]) and the SH degree raised every 33 steps instead of 1000
    "blur-only-hdr": {"events": False, "hdr": {}}, "blur+event-hdr": _v(NOISE, {"hdr": {}}),
    "blur+event-sh": _v(NOISE, {"sh_interval": 33}),
    "blur+event-hdr-sh": _v(NOISE, HDR_SH),
    "blur-only-hdr-sh": _v({"events": False}, HDR_SH),
    "oracle-sh": {"oracle": True, "sh_interval": 33},
    "blur-only-sh": {"events": False, "sh_interval": 33},   # with blur+event-sh, oracle-sh: the default
                                                            # schedule (auto) at 1000 steps
    "blur+event-sh-mapprior": _v(NOISE, {"sh_interval": 33, "threshold_map": {}}),
    # the EDI prior (edi_prior.weight W, W in units of the noise norm's default event weight 8/625), faded
    # out over the first half of the run; alone and with both options above
    "blur+event-edi": _v(NOISE, EDI),
    "blur+event-hdr-sh-edi": _v(NOISE, HDR_SH, EDI),
    # both options with per-pixel thresholds, for the 40 % mismatch row
    "blur+event-hdr-sh-map": _v(NOISE, HDR_SH, MAP),
    # the same with 17 sub-poses per exposure (the rendered sub-frames' count) instead of 5
    "blur+event-hdr-sh-map@17": _v(NOISE, HDR_SH, {"blur": {"subposes": 17}}, MAP),
    # each view's sub-poses from its motion: at most 2 px apart, up to 17
    "blur+event-px2": _v(NOISE, {"blur": {"subposes": 17, "subpose_px": 2.0}}),
    "blur+event-hdr-sh-map-px2": _v(NOISE, HDR_SH, {"blur": {"subposes": 17, "subpose_px": 2.0}}, MAP),
    # the floor at which the penalised chi-square averages as expected, a Huber penalty beyond 3 standard
    # deviations and densification from the blur term
    "blur+event-sh-robust": _v(NOISE, {"sh_interval": 33, "events": ROBUST_EVENTS, "densify": {"from": "blur"}}),
    # the same with [hdr], per-pixel thresholds and 17 sub-poses: every option at once
    "blur+event-hdr-sh-map@17-robust": _v(NOISE, HDR_SH, {"blur": {"subposes": 17}}, MAP,
                                          {"events": ROBUST_EVENTS, "densify": {"from": "blur"}})}
VARIANTS = {name: variant_overrides(v) for name, v in VARIANTS_TOML.items()}
# the robust event term as TrainConfig overrides (what the tests and the plots compare with)
ROBUST = variant_overrides({"events": ROBUST_EVENTS, "densify": {"from": "blur"}})
# variants that never read the events: one run per seed, on the events-free cell
SENSOR_FREE = ("blur-only", "oracle", "blur-only-hdr", "blur-only-hdr-sh", "oracle-sh", "blur-only-sh")


def cell_name(theta: float, rel: float) -> str:
    return f"t{theta:g}_m{rel:g}"


def cell_dvs(spec, theta: float, rel: float):
    """The DVS settings of a cell: symmetric thresholds theta, per-pixel spread rel * theta (none at rel 0)."""
    from ev3dgs.sim.config import ThresholdMismatch

    return replace(spec.sensor.dvs, pos_threshold=theta, neg_threshold=theta,
                   threshold_mismatch=ThresholdMismatch(sigma=rel * theta) if rel > 0 else None)


def make_cells(scene: str, thetas, rels, render: dict, cache: Path, quiet: bool) -> dict:
    """{cell name: scene file}; the Blender render is done once and shared through its cache folder."""
    from ev3dgs.sim.dataset import _cache_key, make_dataset
    from ev3dgs.sim.scenes import load_scene, resolve_render

    spec = load_scene(scene)
    r = resolve_render(spec, **render)
    cache.mkdir(parents=True, exist_ok=True)
    base = cache / "base"
    base.mkdir(exist_ok=True)
    key = _cache_key(spec, r, None, 0)
    shared = base / f".scene.cache-{key}"
    out = {}
    for theta in thetas:
        for rel in rels:
            name = cell_name(theta, rel)
            path = cache / name / "scene.h5"
            out[name] = path
            if path.exists():
                continue
            path.parent.mkdir(exist_ok=True)
            link = path.parent / shared.name
            if shared.exists() and not link.exists():
                link.symlink_to(shared.resolve(), target_is_directory=True)
            cell = replace(spec, sensor=replace(spec.sensor, dvs=cell_dvs(spec, theta, rel)))
            t = time.perf_counter()
            make_dataset(cell, r, path, seed=0, quiet=quiet, keep_cache=True)
            if not shared.exists():   # the first cell rendered: its cache becomes the shared one
                (path.parent / shared.name).rename(shared)
                link.symlink_to(shared.resolve(), target_is_directory=True)
            print(f"  {name}: {time.perf_counter() - t:.0f} s", flush=True)
    return out


def map_accuracy(scene: str, theta: float, rel: float, run: Path) -> dict:
    """How well a --threshold-map run recovered the simulator's per-pixel thresholds: the run's fitted
    multipliers (its checkpoint) against the thresholds the simulator drew for the cell (the same scene,
    settings and dataset seed 0, drawn again), over all pixels and over those the counts said more about
    than the prior (posterior spread under half the prior's). RMS of (fitted - true) / nominal, against the
    nominal thresholds' own error (the true pattern's RMS)."""
    import torch

    from ev3dgs.sim.dvs import DVSSimulator
    from ev3dgs.sim.scenes import load_scene
    from ev3dgs.train.threshold_map import ThresholdMap

    spec = load_scene(scene)
    state = torch.load(run / "ckpt.pt", map_location="cpu", weights_only=True)["threshold_map"]
    n_views, _, h, w = state["stats"].shape
    tmap = ThresholdMap(rel, n_views, h, w, "cpu")
    tmap.load_state_dict(state)
    sim = DVSSimulator(h, w, cell_dvs(spec, theta, rel), seed=0, isp=spec.sensor.isp)   # the cells' seed
    truth = np.stack([sim.c_on, sim.c_off]).reshape(2, h, w) / theta
    fitted = tmap.multiplier.numpy()
    informed = tmap.spread.numpy() < 0.5 * rel

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))

    out = {"rms_error": rms(fitted - truth), "rms_nominal": rms(1 - truth), "informed_fraction": float(informed.mean()),
           "rms_error_informed": None, "rms_nominal_informed": None, "correlation_informed": None}
    if informed.sum() >= 2:   # none where the calibration finds the model's error swamping the pattern
        out.update(rms_error_informed=rms((fitted - truth)[informed]), rms_nominal_informed=rms((1 - truth)[informed]),
                   correlation_informed=float(np.corrcoef(fitted[informed], truth[informed])[0, 1]))
    return out


def blur_fit(run: Path) -> dict:
    """How well a run's model reproduces its training frames through the trainer's own blur model: its
    sub-pose renders of every training view decoded (with the --hdr continuation if the run used it),
    averaged as the trainer averages them (losses.blur_average) and clipped, against the blurry frames: PSNR,
    the share of the squared misfit at saturated pixels (255), and the brightest render as a multiple of full
    scale."""
    import torch

    from ev3dgs.splat.rasterize import rasterization
    from ev3dgs.train.data import load_train_data
    from ev3dgs.train.evaluate import load_run
    from ev3dgs.train.losses import blur_average, srgb_to_linear_hdr_torch, srgb_to_linear_torch

    cfg, m = load_run(run)
    data = load_train_data(cfg.scene, cfg.subposes, subpose_px=cfg.subpose_px)
    decode = srgb_to_linear_hdr_torch if cfg.hdr else srgb_to_linear_torch
    sq = sat = 0.0
    brightest = 0.0
    with torch.no_grad():
        for v in range(data.n_views):
            poses = data.viewmats[v][:data.sub_count(v)]
            stack, _, _ = rasterization(m.means, m.quats_normalised, m.scales, m.opacities, m.sh, poses, data.K,
                                        data.width, data.height, sh_degree=m.active_sh_degree,
                                        background=data.background, backend="cpu")
            lin = decode(stack)
            err = (blur_average(stack, data.blur_space, linear=lin).clamp(0, 1) - data.images[v].to(stack.dtype)) ** 2
            sq += err.sum().item()
            sat += err[data.images[v] >= 1].sum().item()
            brightest = max(brightest, lin.max().item())
    n = data.n_views * data.height * data.width * 3
    return {"psnr": float(-10 * np.log10(sq / n)), "saturated_share": sat / sq, "brightest_linear": brightest}


def _job(job: dict) -> dict:
    import torch

    from bench_fidelity import run_one

    torch.set_num_threads(1)
    t = time.perf_counter()
    m = run_one(Path(job["scene_path"]), job["overrides"], job["seed"], job["iterations"], job["init_points"],
                Path(job["out"]))
    out = {**{k: job[k] for k in ("cell", "variant", "seed")}, "metrics": m, "wall": time.perf_counter() - t}
    if job["overrides"].get("threshold_map") and job["rel"] > 0:
        out["map"] = map_accuracy(job["scene"], job["theta"], job["rel"], Path(job["out"]))
    if job["blur_fit"] and not job["overrides"].get("oracle"):
        out["blur_fit"] = blur_fit(Path(job["out"]))
    return out


def summarise(runs: list[dict]) -> dict:
    table: dict = {}
    for r in runs:
        cell = table.setdefault(r["cell"], {}).setdefault(r["variant"], {"blur_view": [], "novel_view": [],
                                                                          "train_s": []})
        for view in ("blur_view", "novel_view"):
            cell[view].append(r["metrics"][view]["psnr"])
        cell["train_s"].append(r["metrics"].get("train_seconds", float("nan")))
    out = {}
    for c, vs in table.items():
        for v, d in vs.items():
            out.setdefault(c, {})[v] = {k: [float(np.mean(x)), float(np.std(x, ddof=1)) if len(x) > 1 else 0.0,
                                            len(x)] for k, x in d.items() if x}
    return out


# line style per event variant in the plot; variants without one take the next of EXTRA_STYLES
STYLES = {"blur+event": "-", "blur+event-count": ":", "blur+event-map": "-.",
          "blur+event-hdr-sh": (0, (5, 1, 1, 1)), "blur+event-edi": (0, (1, 1)),
          "blur+event-hdr-sh-edi": (0, (3, 1, 1, 1, 1, 1)), "blur+event-hdr-sh-map": (0, (8, 2))}
EXTRA_STYLES = ("--", (0, (2, 2)), (0, (6, 1, 1, 1, 1, 1, 1, 1)), (0, (4, 4)), (0, (1, 3)))


def plot(summary: dict, thetas, rels, png: Path, variants=None) -> list[str]:
    """PSNR against threshold, one line per (event variant, mismatch) and the sensor-free variants as
    horizontal lines; ``variants``: only these event variants (default: every one in the summary). Returns
    the legend's labels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 3.8), sharey=False)
    for ax, view in zip(axes, ("blur_view", "novel_view")):
        for v, col, ls in (("blur-only", "k", "--"), ("oracle", "k", ":"), ("blur-only-hdr-sh", "C4", "--"),
                           ("oracle-sh", "C4", ":")):
            if v in summary.get("sensor_free", {}):
                ax.axhline(summary["sensor_free"][v][view][0], color=col, ls=ls, lw=1,
                           label=v if view == "blur_view" else None)
        present = {v for c, table in summary.items() if c != "sensor_free" for v in table}
        shown = [v for v in (variants or sorted(present)) if v in present]
        extra = iter(EXTRA_STYLES * len(shown))
        styles = {v: STYLES.get(v) or next(extra) for v in shown}
        for rel, col in zip(rels, ("C0", "C1", "C2", "C3", "C4")):
            for var, ls in styles.items():
                ys = [summary.get(cell_name(t, rel), {}).get(var, {}).get(view, [np.nan])[0] for t in thetas]
                if np.isfinite(ys).any():
                    ax.plot(thetas, ys, linestyle=ls, color=col, marker="o", ms=3,
                            label=f"{var}, mismatch {rel:g}" if view == "blur_view" else None)
        ax.set_xscale("log")
        ax.set_xticks(thetas, [f"{t:g}" for t in thetas])
        ax.minorticks_off()
        ax.set_xlabel("contrast threshold")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(view.replace("_", " "))
    fig.legend(loc="center right", fontsize=6)   # beside the panels: the curves stay visible
    fig.tight_layout(rect=(0, 0, 0.8, 1))
    fig.savefig(png, dpi=120)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    plt.close(fig)
    return labels


def main(argv=None) -> int:
    from bench_fidelity import study_overrides

    from ev3dgs.train.jobs import default_jobs, run_parallel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "tools/scenes/heldout_shake.toml"))
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.4])
    ap.add_argument("--mismatch", type=float, nargs="+", default=[0.0, 0.1, 0.4])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--variants", nargs="+", default=["blur-only", "blur+event", "blur+event-count", "oracle"],
                    choices=tuple(VARIANTS))
    ap.add_argument("--event-weights", type=float, nargs="+",
                    help="replace blur+event by one variant per weight k (omega = k / 625, named blur+event@k)")
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--init-points", type=int, default=5000)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--size", default="96x72")
    ap.add_argument("--jobs", type=int, default=default_jobs())
    ap.add_argument("--cache", default=str(ROOT / "tools/results/event_term_cache"))
    ap.add_argument("--merge", nargs="+", default=[],
                    help="earlier JSON outputs of this study whose runs join the summary and the plot (e.g. the "
                         "count norm on fewer seeds)")
    ap.add_argument("--plot-variants", nargs="+", metavar="VARIANT",
                    help="event variants the plot draws (default: all in the summary, merged ones included)")
    ap.add_argument("--blur-fit", action="store_true",
                    help="also score each run's model through its own blur model against the training frames "
                         "(blur_fit in the JSON; about 10 s per run)")
    ap.add_argument("--json", required=True)
    ap.add_argument("--plot")
    a = ap.parse_args(argv)
    w, h = (int(x) for x in a.size.split("x"))
    render = dict(width=w, height=h, views=a.views, test_views=max(2, a.views // 3), subframes=17, samples=8)
    t0 = time.perf_counter()
    cells = make_cells(a.scene, a.thresholds, a.mismatch, render, Path(a.cache), quiet=True)
    first = next(iter(cells.values()))
    params = {cell_name(t, r): (t, r) for t in a.thresholds for r in a.mismatch}
    variants = dict(VARIANTS)
    names = list(a.variants)
    if a.event_weights and "blur+event" in names:
        i = names.index("blur+event")
        extra = {f"blur+event@{k:g}": dict(event_norm="noise", event_weight=k / 625) for k in a.event_weights}
        names[i:i + 1] = list(extra)
        variants.update(extra)
    jobs = []
    for seed in a.seeds:
        for v in names:
            targets = [("sensor_free", first)] if v in SENSOR_FREE else list(cells.items())
            for cname, path in targets:
                theta, rel = params.get(cname, (None, 0.0))
                jobs.append(dict(cell=cname, variant=v, seed=seed, scene_path=str(path),
                                 overrides=study_overrides(variants[v]),
                                 iterations=a.iterations, init_points=a.init_points,
                                 out=str(Path(a.cache) / "runs" / f"{cname}_{v}_s{seed}"), scene=a.scene,
                                 theta=theta, rel=rel, blur_fit=a.blur_fit))

    def report(r):
        m = r["metrics"]
        print(f"  {r['cell']:14s} {r['variant']:17s} seed {r['seed']}: blur view {m['blur_view']['psnr']:.2f}, "
              f"novel {m['novel_view']['psnr']:.2f} dB ({r['wall']:.0f} s)", flush=True)

    runs = run_parallel(_job, jobs, a.jobs, report)
    import json

    have = {(r["cell"], r["variant"], r["seed"]) for r in runs}
    for other in a.merge:
        extra = [r for r in json.loads(Path(other).read_text())["runs"]
                 if (r["cell"], r["variant"], r["seed"]) not in have]
        have |= {(r["cell"], r["variant"], r["seed"]) for r in extra}
        runs += extra
    summary = summarise(runs)

    res = {"settings": {**vars(a), "render": render}, "cores": default_jobs(),
           "summary": summary, "runs": runs, "seconds": time.perf_counter() - t0}
    save_json(a.json, res)
    if a.plot:
        cells = [c.split("_m") for c in summary if c != "sensor_free"]   # this run's cells and the merged ones
        plot(summary, sorted({float(t[1:]) for t, _ in cells} | set(a.thresholds)),
             sorted({float(r) for _, r in cells} | set(a.mismatch)), Path(a.plot), a.plot_variants)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
