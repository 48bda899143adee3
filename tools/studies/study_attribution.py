"""Study: where the gap between blur+event and the sharp oracle comes from, one cause at a time.

One scene (default tools/scenes/heldout_shake.toml, 12 views at 96x72, 17 rendered sub-frames per exposure) is
trained under variants that each remove one cause of error, on the same frames, poses and seeds:

* ``info-oracle``: plain 3DGS on all 17 sharp sub-frames of every exposure at their own poses (the most any
  deblurring could recover from these exposures);
* ``oracle``: plain 3DGS on the sharp mid-exposure frame of each view (the evaluation's usual upper bound);
* ``info-oracle-sh``, ``oracle-sh``: both with ``--sh-interval 33``, the upper bounds of a trainer run with it;
* ``blur-ideal@17``: blur-only with 17 sub-poses (the rendered sub-frames' own poses) against the blurry frame the
  trainer's blur model would make from the sharp sub-frames (their sRGB decoded, averaged in linear light,
  encoded): no blur-model mismatch, no sub-pose discretisation, no frame noise;
* ``blur-only@17``: the same 17 sub-poses against the scene's real blurry frame (ISP, 8-bit, frame noise): the
  blur model's cost;
* scenes with frame noise (``[sensor.sensor_noise]``) add ``blur-clean@17`` (the ISP's blurry frame without the
  noise), splitting that cost into blur model and noise, and ``oracle-noisy``, the fair oracle: the sharp frames
  with the same frame noise as the blurry ones (the clean oracle is also a denoiser);
* ``blur-only``: 5 sub-poses (the default): the sub-pose discretisation's cost;
* ``blur+event`` (5 sub-poses), ``blur+event@17`` and ``blur+event@4pairs`` (4 random pose pairs per step
  instead of all 10) at one threshold cell (default 0.05 with 10 % relative mismatch): what the events add, what
  more sub-poses add to them, and what the pair selection costs;
* ``blur+event-fn0``: blur+event with ``--frame-noise 0``: the events at their weight omega, however much of
  the blur loss's error is the frames' noise (by default they weigh more as it comes down to that noise);
  ``blur+event-w4`` the same at 4 times omega (what a fixed heavier weight does);
* ``naive``: plain 3DGS on the blurry frame at the mid pose; with ``blur-only`` it says what the blur model adds
  over fitting the blurry frame as if it were sharp;
* noisy scenes also add ``blur-clean`` and ``naive-clean`` (5 sub-poses, and naive, on the noise-free blurry
  frames): whether the blur model's edge over naive depends on the frame noise;
* ``*@3000``: blur-only, blur+event and the oracle at 3x the steps (first seed only): the optimisation length.

The threshold and mismatch (quantisation) costs come from ``study_event_term.py`` on the same frames. Scenes are
shared with that study's cache (tools/results/event_term_cache), so its runs are reused; the derived scene
files (info-oracle, blur-ideal, and for noisy scenes blur-clean and sharp-noisy) are written there from the
render cache. Every model is scored on the cell's
scene file (blur views: the 12 sharp mid-exposure frames; novel views: /test).
Variants train with the studies' SH schedule and event floor (bench_fidelity.study_overrides: ``--sh-interval
1000``, ``--event-floor mean --event-huber 0 --densify-from all``) unless they set their own.

    python tools/studies/study_attribution.py --json tools/results/study_attribution.json \\
        --plot tools/results/study_attribution.png [--seeds 0 1] [--theta 0.05] [--mismatch 0.1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "tools" / "bench"))
sys.path.insert(0, str(ROOT / "tools" / "studies"))

from derived_scenes import SUBFRAMES, derived_scenes, render_cache  # noqa: E402
from pareto import save_json  # noqa: E402

# variant -> (training scene: "cell" | "free" (the events-free cell the sensor-free runs share) | "info" |
# "ideal", TrainConfig overrides, step multiplier, first seed only)
VARIANTS = {
    "info-oracle": ("info", dict(oracle=True), 1, False),
    "info-oracle-sh": ("info", dict(oracle=True, sh_interval=33), 1, False),
    "oracle-sh": ("free", dict(oracle=True, sh_interval=33), 1, False),
    "oracle": ("free", dict(oracle=True), 1, False),
    "oracle-noisy": ("noisy", dict(oracle=True), 1, False),
    "blur-ideal@17": ("ideal", dict(event_loss=False, subposes=SUBFRAMES), 1, False),
    "blur-clean@17": ("clean", dict(event_loss=False, subposes=SUBFRAMES), 1, False),
    "blur-only@17": ("free", dict(event_loss=False, subposes=SUBFRAMES), 1, False),
    "blur-only": ("free", dict(event_loss=False), 1, False),
    "blur-clean": ("clean", dict(event_loss=False), 1, False),
    "naive": ("free", dict(naive=True), 1, False),
    "naive-clean": ("clean", dict(naive=True), 1, False),
    "blur+event": ("cell", dict(event_norm="noise"), 1, False),
    "blur+event-fn0": ("cell", dict(event_norm="noise", frame_noise=0.0), 1, False),
    "blur+event-w4": ("cell", dict(event_norm="noise", frame_noise=0.0, event_weight=32 / 625), 1, False),
    "blur+event@17": ("cell", dict(event_norm="noise", subposes=SUBFRAMES), 1, False),
    "blur+event@4pairs": ("cell", dict(event_norm="noise", event_pairs=4), 1, False),
    "oracle@3000": ("free", dict(oracle=True), 3, True),
    "blur-only@3000": ("free", dict(event_loss=False), 3, True),
    "blur+event@3000": ("cell", dict(event_norm="noise"), 3, True),
}
# the table: (cause, the variant without it, the variant with it); the cost is the PSNR difference (negative:
# the cause helps)
STEPS = [
    ("information: one sharp frame per view instead of 17", "info-oracle", "oracle"),
    ("the same, both oracles with --sh-interval 33", "info-oracle-sh", "oracle-sh"),
    ("one blurry frame, ideal blur model, 17 sub-poses", "oracle", "blur-ideal@17"),
    ("frame noise in the sharp frames (oracle)", "oracle", "oracle-noisy"),
    ("blur model (ISP, 8-bit) against the ideal one", "blur-ideal@17", "blur-clean@17"),
    ("frame noise in the blurry frames (17 sub-poses)", "blur-clean@17", "blur-only@17"),
    ("blur model and frame noise against the ideal one", "blur-ideal@17", "blur-only@17"),
    ("5 sub-poses instead of 17 (blur-only)", "blur-only@17", "blur-only"),
    ("frame noise in the blurry frames (5 sub-poses)", "blur-clean", "blur-only"),
    ("frame noise in the blurry frames (naive)", "naive-clean", "naive"),
    ("blur model instead of naive, noisy frames", "naive", "blur-only"),
    ("blur model instead of naive, noise-free frames", "naive-clean", "blur-clean"),
    ("no events (5 sub-poses)", "blur+event", "blur-only"),
    ("events at omega whatever the frame noise (--frame-noise 0)", "blur+event", "blur+event-fn0"),
    ("events at 4 omega whatever the frame noise", "blur+event", "blur+event-w4"),
    ("no events (17 sub-poses)", "blur+event@17", "blur-only@17"),
    ("5 sub-poses instead of 17 (blur+event)", "blur+event@17", "blur+event"),
    ("4 random pairs per step instead of all", "blur+event", "blur+event@4pairs"),
    ("1000 steps instead of 3000 (blur+event)", "blur+event@3000", "blur+event"),
    ("1000 steps instead of 3000 (oracle)", "oracle@3000", "oracle"),
    ("1000 steps instead of 3000 (blur-only)", "blur-only@3000", "blur-only"),
]


def blur_model_residual(cell: Path, ideal: Path) -> dict:
    """Where the scene's blurry frames differ from the trainer's blur model of their sharp sub-frames: the
    PSNR between the two, and the share of the squared difference at pixels that some sub-frame sees above
    full scale (linear > 1: highlights the sharp frames clip) and at pixels the blurry frame saturates (255)."""
    from ev3dgs import schema

    real = np.asarray(schema.read(cell).train.images).astype(np.float64)
    model = np.asarray(schema.read(ideal).train.images).astype(np.float64)
    cache = render_cache(cell)
    hdr = np.stack([np.load(cache / f"view_{v:04d}.npz")["frames"][:SUBFRAMES].max(axis=(0, 3)) > 1.0
                    for v in range(len(real))])
    d2 = ((real - model) ** 2).sum(axis=-1)
    total = float(d2.sum()) or 1.0
    return {"psnr_db": float(10 * np.log10(255.0 ** 2 / np.mean((real - model) ** 2))),
            "pixels_above_full_scale": float(hdr.mean()),
            "share_above_full_scale": float(d2[hdr].sum() / total),
            "share_saturated": float(d2[(real >= 255).any(axis=-1)].sum() / total)}


BAND_SIGMA = 1.5   # px: the Gaussian low-pass that splits an error into coarse and fine detail


def band_split(pred: np.ndarray, truth: np.ndarray, sigma: float = BAND_SIGMA) -> dict:
    """Where renders ``pred`` differ from ``truth`` ((N, H, W, 3), any range, same scale): the PSNR (peak 1) of
    the error's low-pass part (a Gaussian of ``sigma`` px per image and channel) and of the rest, and the fine
    detail's energy in the renders over that in the truth (above 1: detail the truth does not have, as a model
    that deblurs the frames' noise renders). The two parts sum to the error."""
    from scipy.ndimage import gaussian_filter

    def low(x):
        return np.stack([gaussian_filter(im, (sigma, sigma, 0)) for im in x])

    p, t = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    err = p - t
    lo = low(err)
    hi_p, hi_t = p - low(p), t - low(t)
    return {"low_psnr": float(-10 * np.log10(np.mean(lo ** 2))),
            "high_psnr": float(-10 * np.log10(np.mean((err - lo) ** 2))),
            "fine_energy_ratio": float(np.mean(hi_p ** 2) / np.mean(hi_t ** 2))}


def novel_view_bands(run: Path, scene: Path) -> dict:
    """band_split of a finished run's renders of ``scene``'s test views against them, plus its Gaussian count."""
    import torch

    from ev3dgs import schema
    from ev3dgs.train.evaluate import load_run, render_views

    cfg, model = load_run(run, "cpu", scene=scene, other_scene=True)  # may be another file than the training scene
    sc = schema.read(scene)
    bg = sc.camera.background if sc.camera.background is not None else (0, 0, 0)
    pred = render_views(model, np.asarray(sc.test.poses), torch.as_tensor(sc.camera.K, dtype=model.dtype),
                        sc.camera.width, sc.camera.height, torch.as_tensor(bg, dtype=model.dtype), cfg.backend)
    return band_split(np.stack(pred) / 255.0, np.asarray(sc.test.images) / 255.0) | {
        "gaussians": int(model.means.shape[0])}


def _job(job: dict) -> dict:
    import torch

    from bench_fidelity import run_one

    torch.set_num_threads(1)
    t = time.perf_counter()
    train, score = Path(job["train_scene"]), Path(job["eval_scene"])
    m = run_one(train, job["overrides"], job["seed"], job["iterations"], job["init_points"], Path(job["out"]),
                eval_scene=None if score == train else score)
    bands = novel_view_bands(Path(job["out"]), score)
    return {**{k: job[k] for k in ("variant", "seed")}, "metrics": m, "bands": bands,
            "wall": time.perf_counter() - t}


def summarise(runs: list[dict]) -> dict:
    out: dict = {}
    for r in runs:
        d = out.setdefault(r["variant"], {"blur_view": [], "novel_view": [], "train_s": [], "seeds": []})
        for view in ("blur_view", "novel_view"):
            d[view].append(r["metrics"][view]["psnr"])
        for k, v in r.get("bands", {}).items():   # study_response's runs have none
            d.setdefault(k, []).append(v)
        d["train_s"].append(r["metrics"].get("train_seconds", float("nan")))
        d["seeds"].append(r["seed"])
    return out


def attribution(summary: dict) -> list[dict]:
    """Per step of STEPS: the cost (PSNR of the variant without the cause minus with it) per view kind, as the
    mean and the range over the seeds both variants ran with (paired by seed)."""
    rows = []
    for cause, better, worse in STEPS:
        if better not in summary or worse not in summary:
            continue
        row = {"cause": cause, "without": better, "with": worse}
        for view in ("blur_view", "novel_view"):
            a = dict(zip(summary[better]["seeds"], summary[better][view]))
            b = dict(zip(summary[worse]["seeds"], summary[worse][view]))
            diffs = [a[s] - b[s] for s in sorted(set(a) & set(b))]
            row[view] = [float(np.mean(diffs)), float(min(diffs)), float(max(diffs)), len(diffs)]
        rows.append(row)
    return rows


def psnr_bars(ax, labels: list[str], entries: list[dict]) -> None:
    """Blur-view and novel-view PSNR bars per entry (a summary's variant: lists per view), mean and range."""
    x = np.arange(len(labels))
    for k, (view, col) in enumerate((("blur_view", "C0"), ("novel_view", "C1"))):
        vals = [e[view] for e in entries]
        ax.bar(x + (k - 0.5) * 0.38, [np.mean(v) for v in vals], 0.38, color=col, label=view.replace("_", " "),
               yerr=[[np.mean(v) - min(v) for v in vals], [max(v) - np.mean(v) for v in vals]], capsize=2)
    lo = min(min(e[v]) for e in entries for v in ("blur_view", "novel_view"))
    ax.set_ylim(lo - 1.5, None)
    ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("PSNR (dB), mean and range over seeds")
    ax.legend(fontsize=8)


def plot(summary: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [v for v in VARIANTS if v in summary]
    fig, ax = plt.subplots(figsize=(10, 3.8))
    psnr_bars(ax, names, [summary[n] for n in names])
    fig.tight_layout()
    fig.savefig(png, dpi=120)


def add_run_args(ap) -> None:
    """The training, render, cache and output options the heldout_shake studies share."""
    from ev3dgs.train.jobs import default_jobs

    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--init-points", type=int, default=5000)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--size", default="96x72")
    ap.add_argument("--samples", type=int, default=8, help="Cycles samples per pixel (default %(default)s)")
    ap.add_argument("--jobs", type=int, default=default_jobs())
    ap.add_argument("--cache", default=str(ROOT / "tools/results/event_term_cache"))
    ap.add_argument("--json", required=True)
    ap.add_argument("--plot")


def render_settings(a) -> dict:
    """study_event_term's render of the scene (17 sub-frames per exposure) from ``add_run_args``' options."""
    w, h = (int(x) for x in a.size.split("x"))
    return dict(width=w, height=h, views=a.views, test_views=max(2, a.views // 3), subframes=SUBFRAMES,
                samples=a.samples)


def main(argv=None) -> int:
    from bench_fidelity import study_overrides

    from study_event_term import cell_name, make_cells

    from ev3dgs.train.jobs import default_jobs, run_parallel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "tools/scenes/heldout_shake.toml"))
    ap.add_argument("--theta", type=float, default=0.05, help="the events' cell: threshold (default 0.05)")
    ap.add_argument("--mismatch", type=float, default=0.1, help="... and relative mismatch (default 0.1)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=tuple(VARIANTS))
    add_run_args(ap)
    a = ap.parse_args(argv)
    render = render_settings(a)
    t0 = time.perf_counter()
    cache = Path(a.cache)
    # the first cell of study_event_term's default sweep is the file its sensor-free runs trained on: reused
    free_name = cell_name(0.05, 0.0)
    cells = make_cells(a.scene, [0.05, a.theta], [0.0, a.mismatch], render, cache, quiet=True)
    cell = cells[cell_name(a.theta, a.mismatch)]
    scenes = {"cell": cell, "free": cells[free_name], **derived_scenes(a.scene, cells[free_name], cache / "derived")}
    jobs = []
    for i, seed in enumerate(a.seeds):
        for v in a.variants:
            kind, overrides, mult, first_only = VARIANTS[v]
            if kind not in scenes or (first_only and i > 0):  # clean/noisy: scenes with frame noise only
                continue
            # the names study_event_term uses for the same runs, so that they are found in the cache
            tag = (f"{cell_name(a.theta, a.mismatch)}_" if kind == "cell" else
                   "sensor_free_" if kind == "free" else f"{kind}_")
            name = tag + v
            # scored on the file with the same frames: the cell for event runs, the sensor-free cell for the
            # rest (the study_event_term runs were scored there; its sharp and test frames are the cell's)
            jobs.append(dict(variant=v, seed=seed, train_scene=str(scenes[kind]),
                             eval_scene=str(cell if kind == "cell" else scenes["free"]),
                             overrides=study_overrides(overrides),
                             iterations=a.iterations * mult, init_points=a.init_points,
                             out=str(cache / "runs" / f"{name}_s{seed}")))
    # seed by seed (an interrupted study leaves whole seeds), the slow ones (17 sub-poses, 3x steps) first in
    # each, so two workers finish together
    jobs.sort(key=lambda j: (j["seed"], -(j["iterations"] * (3 if "@17" in j["variant"] else 1))))

    def report(r):
        m = r["metrics"]
        b = r["bands"]
        print(f"  {r['variant']:18s} seed {r['seed']}: blur view {m['blur_view']['psnr']:.2f}, "
              f"novel {m['novel_view']['psnr']:.2f} dB (coarse {b['low_psnr']:.2f}, fine {b['high_psnr']:.2f}; "
              f"fine detail x{b['fine_energy_ratio']:.2f} the truth's; {b['gaussians']} Gaussians; "
              f"{r['wall']:.0f} s)", flush=True)

    runs = run_parallel(_job, jobs, a.jobs, report)
    summary = summarise(runs)
    table = attribution(summary)
    for row in table:
        b, n = row["blur_view"], row["novel_view"]
        print(f"{row['cause']:55s} blur {b[0]:+.2f} ({b[1]:+.2f}..{b[2]:+.2f})  novel {n[0]:+.2f} "
              f"({n[1]:+.2f}..{n[2]:+.2f})  seeds {b[3]}")
    residual = blur_model_residual(scenes["free"], scenes["ideal"])
    print(f"blurry frames against the trainer's blur model of the sharp sub-frames: {residual['psnr_db']:.1f} dB; "
          f"{100 * residual['share_above_full_scale']:.1f} % of the squared difference at the "
          f"{100 * residual['pixels_above_full_scale']:.0f} % of pixels some sub-frame sees above full scale, "
          f"{100 * residual['share_saturated']:.0f} % at saturated pixels")
    save_json(a.json, {"settings": {**vars(a), "render": render}, "cores": default_jobs(), "summary": summary,
                       "attribution": table, "blur_model_residual": residual, "runs": runs,
                       "seconds": time.perf_counter() - t0})
    if a.plot:
        plot(summary, Path(a.plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
