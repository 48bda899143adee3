"""Study (issue 16): why does `--refine-poses` not halve the rotation error?  Collects finished
tools/investigations/study_refine.py results (same scene, field of view and 1 deg / 2 % perturbation, different image sizes
and step counts) and sets the after/before ratios of the two pose measures side by side:

* rotation: the median orientation error of the training cameras (deg, gauge-aligned);
* reprojection: the median image displacement of the scene points (px), the quantity the photometric loss
  actually sees.

If refinement drives the reprojection error down much further than the rotation error, the loss has found
a camera that explains the images about as well as the true one with a different split between rotation and
translation: the split is weakly observable (a 1 deg turn and a sideways shift of ~tan(1 deg) x distance move
a distant image almost alike; only parallax across the object's depth separates them). The ratios against
image width and steps show whether finer pixels or longer training separate them better.

    python tools/investigations/refine_observability.py STUDY.json [STUDY.json ...] \
        [--json tools/results/refine_observability.json] [--plot tools/results/refine_observability.png]

Reads JSON only: no training here.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402


def _refine_key(runs: dict, lr: float | None) -> str:
    keys = [k for k in runs if k.startswith("perturbed + refine")]
    if lr is not None:
        keys = [k for k in keys if f"(lr {lr:g})" in k]
    if not keys:
        raise SystemExit(f"error: no refined run (lr {lr}) in the study; runs: {sorted(runs)}")
    return keys[0]


def rows_of(path: str, lr: float | None) -> list[dict]:
    d = json.loads(Path(path).read_text())
    studies = d["per_seed"] if "per_seed" in d else [d]
    rows = []
    for s in studies:
        key = _refine_key(s["runs"], lr)
        before, after = s["pose_errors_before"], s["runs"][key]["pose_errors_after"]
        w, h = (int(v) for v in s["size"].split("x"))
        rows.append({
            "source": Path(path).name, "size": s["size"], "width_px": w, "height_px": h,
            "fov_deg": s.get("fov_deg"), "views": s.get("views"), "iterations": s["iterations"],
            "seed": s["seed"], "run": key,
            "rotation_deg_before": before["rotation_deg_median"],
            "rotation_deg_after": after["rotation_deg_median"],
            "reprojection_px_before": before["reprojection_px_median"],
            "reprojection_px_after": after["reprojection_px_median"],
            "centre_error_before": before["centre_error_median"],
            "centre_error_after": after["centre_error_median"],
        })
        r = rows[-1]
        r["rotation_ratio"] = r["rotation_deg_after"] / r["rotation_deg_before"]
        r["reprojection_ratio"] = r["reprojection_px_after"] / r["reprojection_px_before"]
        r["centre_ratio"] = r["centre_error_after"] / r["centre_error_before"]
    return rows


def groups(rows: list[dict]) -> list[dict]:
    """Mean and sample standard deviation (ddof 1; 0 for one seed) per (size, iterations)."""
    out = []
    for key in sorted({(r["width_px"], r["height_px"], r["iterations"]) for r in rows}):
        rs = [r for r in rows if (r["width_px"], r["height_px"], r["iterations"]) == key]
        g = {"size": f"{key[0]}x{key[1]}", "width_px": key[0], "iterations": key[2],
             "seeds": [r["seed"] for r in rs]}
        for m in ("rotation_ratio", "reprojection_ratio", "centre_ratio", "rotation_deg_after",
                  "reprojection_px_after"):
            v = np.array([r[m] for r in rs])
            g[m] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                    "values": v.tolist()}
        out.append(g)
    return out


def plot(summary: list[dict], png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for its, marker in zip(sorted({g["iterations"] for g in summary}), "osd^v"):
        gs = sorted((g for g in summary if g["iterations"] == its), key=lambda g: g["width_px"])
        x = [g["width_px"] for g in gs]
        for m, colour, label in (("rotation_ratio", "C0", "rotation"), ("reprojection_ratio", "C1",
                                                                         "reprojection")):
            ax.errorbar(x, [g[m]["mean"] for g in gs], yerr=[g[m]["std"] for g in gs], color=colour,
                        marker=marker, capsize=3, label=f"{label}, {its} steps")
    ax.axhline(0.5, color="grey", ls=":", lw=1, label="target: halved")
    ax.axhline(1.0, color="grey", ls="-", lw=0.5)
    ax.set_xlabel("image width, px (same 40 deg field of view)")
    ax.set_ylabel("median error after / before refinement")
    ax.set_ylim(0, 1.2)
    ax.legend(fontsize=7)
    ax.set_title("--refine-poses: rotation vs reprojection error (lego, 1 deg + 2 %)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=120)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("studies", nargs="+", help="study_refine.py result JSON files (no default)")
    p.add_argument("--pose-lr", type=float, default=3e-3,
                   help="which refined run of each study to take, by its learning rate (default 3e-3)")
    p.add_argument("--json", default="tools/results/refine_observability.json",
                   help="results (default tools/results/refine_observability.json)")
    p.add_argument("--plot", default="tools/results/refine_observability.png",
                   help="figure (default tools/results/refine_observability.png)")
    a = p.parse_args(argv)
    rows = [r for s in a.studies for r in rows_of(s, a.pose_lr)]
    summary = groups(rows)
    save_json(a.json, {"rows": rows, "summary": summary, "command": "python tools/investigations/refine_observability.py "
                       + " ".join(sys.argv[1:] if argv is None else argv)})
    plot(summary, a.plot)
    for g in summary:
        print(f"{g['size']:>6} {g['iterations']:>5} steps seeds {g['seeds']}: rotation x"
              f"{g['rotation_ratio']['mean']:.2f} (+-{g['rotation_ratio']['std']:.2f}), reprojection x"
              f"{g['reprojection_ratio']['mean']:.2f} (+-{g['reprojection_ratio']['std']:.2f}), centre x"
              f"{g['centre_ratio']['mean']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
