"""Study: a camera whose tone curve the scene does not declare, and what `train --learn-response` wins back.

One cell of study_event_term's sweep (default heldout_shake at threshold 0.05 with 10 % relative mismatch) is
copied with every frame (blurry, sharp and test) and the background colour passed through a contrast curve S
applied to the display values, d' = S(d) with S(x) = x^c / (x^c + (1 - x)^c) (c = --contrast; a camera's S-shaped
tone curve), re-quantised to 8 bits; the events are the cell's (the DVS sees the same light) and the file still
declares sRGB frames, as a user who does not know the camera's curve would. The trainer's sRGB decode is then wrong
by S^-1: the sub-poses' average and the events' log changes no longer describe the same light.

Variants, on the curved copy ("tone") and on the cell itself ("srgb", where sRGB is the truth and the curve has
nothing to find): blur-only, blur+event, blur+event with --learn-response, and the sharp oracle (tone only);
blur+event-hdr and blur+event-hdr-response add --hdr (give them with --variants). Each model is scored on its own
training file (its sharp and test frames carry the curve). For the learned curves the JSON gives the largest
difference between the learned h and the truth S^-1 at the knots.
Variants train with the studies' SH schedule and event floor (bench_fidelity.study_overrides: ``--sh-interval
1000``, ``--event-floor mean --event-huber 0 --densify-from all``) unless they set their own.

    python tools/studies/study_response.py --json tools/results/study_response.json \\
        --plot tools/results/study_response.png [--seeds 0 1] [--theta 0.05] [--mismatch 0.1] [--contrast 1.5]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "tools" / "bench"))
sys.path.insert(0, str(ROOT / "tools" / "studies"))

from pareto import save_json  # noqa: E402

# variant -> (TrainConfig overrides, on the sRGB cell too)
VARIANTS = {
    "blur-only": (dict(event_loss=False), False),
    "blur+event": (dict(event_norm="noise"), True),
    "blur+event-response": (dict(event_norm="noise", learn_response=True), True),
    "oracle": (dict(oracle=True), False),
    "blur+event-hdr": (dict(event_norm="noise", hdr=True), True),
    "blur+event-hdr-response": (dict(event_norm="noise", hdr=True, learn_response=True), True),
}
DEFAULT_VARIANTS = ("blur-only", "blur+event", "blur+event-response", "oracle")


def contrast_curve(x: np.ndarray, c: float) -> np.ndarray:
    """S(x) = x^c / (x^c + (1 - x)^c) on [0, 1]: S(0) = 0, S(1) = 1, S(1/2) = 1/2, slope c at 1/2."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    a, b = x ** c, (1.0 - x) ** c
    return a / (a + b)


def inverse_contrast_curve(y: np.ndarray, c: float) -> np.ndarray:
    """S^-1: the same family with 1/c (x^c/(1-x)^c = y/(1-y) <=> x/(1-x) = (y/(1-y))^(1/c))."""
    return contrast_curve(y, 1.0 / c)


def tone_scene(cell: Path, c: float, out: Path) -> Path:
    """Write (once) the cell with every 8-bit frame through S (``contrast_curve``), re-quantised."""
    if out.exists():
        return out
    from ev3dgs import schema

    lut = np.clip(np.rint(contrast_curve(np.arange(256) / 255.0, c) * 255.0), 0, 255).astype(np.uint8)
    sc = schema.read(cell)
    tr = replace(sc.train, images=lut[np.asarray(sc.train.images)], sharp=lut[np.asarray(sc.train.sharp)])
    te = replace(sc.test, images=lut[np.asarray(sc.test.images)])
    # the background the renders are composited over is a display value of the same camera
    cam = replace(sc.camera, background=tuple(float(v) for v in contrast_curve(np.asarray(sc.camera.background), c)))
    out.parent.mkdir(parents=True, exist_ok=True)
    schema.write(replace(sc, camera=cam, train=tr, test=te), out)
    return out


def _job(job: dict) -> dict:
    import torch

    from bench_fidelity import run_one

    torch.set_num_threads(1)
    t = time.perf_counter()
    out = Path(job["out"])
    m = run_one(Path(job["scene"]), job["overrides"], job["seed"], job["iterations"], job["init_points"], out)
    r = {k: job[k] for k in ("kind", "variant", "seed")} | {"metrics": m, "wall": time.perf_counter() - t}
    if (out / "response.json").exists():
        table = json.loads((out / "response.json").read_text())
        x = np.asarray(table["display"])
        truth = inverse_contrast_curve(x, job["contrast"]) if job["kind"] == "tone" else x
        err = np.abs(np.asarray(table["decoded_as"]) - truth)
        r["response"] = table | {"max_error": float(err.max()), "max_error_at_start": float(np.max(np.abs(x - truth))),
                                 # where the curve is found: the shadows (below mid-grey) and the rest
                                 "max_error_below_half": float(err[x < 0.5].max()),
                                 "max_error_from_half": float(err[x >= 0.5].max())}
    return r


def summarise(runs: list[dict]) -> dict:
    """{kind: study_attribution's per-variant summary of that kind's runs, plus the learned curves' errors}."""
    from study_attribution import summarise as per_variant

    out = {kind: per_variant([r for r in runs if r["kind"] == kind]) for kind in dict.fromkeys(r["kind"] for r in runs)}
    for r in runs:
        if "response" in r:
            d = out[r["kind"]][r["variant"]]
            for k in ("max_error", "max_error_below_half", "max_error_from_half", "max_error_at_start"):
                d.setdefault(f"response_{k}", []).append(r["response"][k])
    return out


def plot(summary: dict, runs: list[dict], contrast: float, png: Path) -> None:
    import matplotlib
    from study_attribution import psnr_bars

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [2, 1]})
    labels, bars = [], []
    for kind in ("tone", "srgb"):
        for v in VARIANTS:
            if v in summary.get(kind, {}):
                labels.append(f"{kind}: {v}")
                bars.append(summary[kind][v])
    psnr_bars(ax, labels, bars)
    xs = np.linspace(0, 1, 201)
    ax2.plot(xs, inverse_contrast_curve(xs, contrast), "k--", label="truth S^-1")
    ax2.plot(xs, xs, "k:", lw=0.8, label="sRGB as declared")
    for r in runs:
        if "response" in r and r["kind"] == "tone":
            ax2.plot(r["response"]["display"], r["response"]["decoded_as"], "-", alpha=0.7,
                     label=f"{r['variant']}, seed {r['seed']}")
    ax2.set_xlabel("display value in the file")
    ax2.set_ylabel("value the sRGB decode sees")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=120)


def main(argv=None) -> int:
    from bench_fidelity import study_overrides

    from study_attribution import add_run_args, render_settings
    from study_event_term import cell_name, make_cells

    from ev3dgs.train.jobs import default_jobs, run_parallel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "tools/scenes/heldout_shake.toml"))
    ap.add_argument("--theta", type=float, default=0.05, help="the cell's threshold (default %(default)s)")
    ap.add_argument("--mismatch", type=float, default=0.1, help="... and relative mismatch (default %(default)s)")
    ap.add_argument("--contrast", type=float, default=1.5, help="the tone curve's slope at mid-grey, > 0 "
                    "(default %(default)s)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS), choices=tuple(VARIANTS))
    add_run_args(ap)
    a = ap.parse_args(argv)
    if not a.contrast > 0:
        ap.error("--contrast must be > 0")
    render = render_settings(a)
    t0 = time.perf_counter()
    cache = Path(a.cache)
    name = cell_name(a.theta, a.mismatch)
    cell = make_cells(a.scene, [a.theta], [a.mismatch], render, cache, quiet=True)[name]
    scenes = {"tone": tone_scene(cell, a.contrast, cache / "derived" / f"tone_c{a.contrast:g}_{name}.h5"),
              "srgb": cell}
    jobs = []
    for seed in a.seeds:
        for v in a.variants:
            overrides, on_srgb = VARIANTS[v]
            for kind in ("tone", "srgb") if on_srgb else ("tone",):
                tag = f"tone_c{a.contrast:g}_{name}" if kind == "tone" else name
                jobs.append(dict(kind=kind, variant=v, seed=seed, scene=str(scenes[kind]),
                                 overrides=study_overrides(overrides),
                                 iterations=a.iterations, init_points=a.init_points, contrast=a.contrast,
                                 out=str(cache / "runs" / f"{tag}_{v}_s{seed}")))
    jobs.sort(key=lambda j: (j["seed"], "oracle" in j["variant"]))

    def report(r):
        m = r["metrics"]
        extra = f", curve off by {r['response']['max_error']:.3f}" if "response" in r else ""
        print(f"  {r['kind']:4s} {r['variant']:20s} seed {r['seed']}: blur view {m['blur_view']['psnr']:.2f}, "
              f"novel {m['novel_view']['psnr']:.2f} dB ({r['wall']:.0f} s{extra})", flush=True)

    runs = run_parallel(_job, jobs, a.jobs, report)
    summary = summarise(runs)
    save_json(a.json, {"settings": {**vars(a), "render": render}, "cores": default_jobs(), "summary": summary,
                       "runs": runs, "seconds": time.perf_counter() - t0})
    if a.plot:
        plot(summary, runs, a.contrast, Path(a.plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
