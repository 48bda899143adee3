"""LPIPS cost and precision (ev3dgs/train/lpips.py): seconds per image pair for the AlexNet and VGG16 trunks at
the sizes this project evaluates, next to PSNR + SSIM of the same pair (ratios measured in one run), and the
float32 network's relative difference from the same network in float64.

    python tools/bench/bench_lpips.py                     # -> tools/results/bench_lpips.json, .png
    python tools/bench/bench_lpips.py --run RUN_FOLDER    # also `evaluate` on a trained run without / with LPIPS

The weights are random, in the reference state-dict layout (He-scaled convs, non-negative lin layers): nothing
can be downloaded here, and the cost of a forward pass does not depend on the weights' values, so the timings
hold for the real weights; the LPIPS values themselves mean nothing perceptually and are not reported.
One torch thread (timings on a shared machine are compared only as ratios inside one run).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from ev3dgs.train.lpips import SCALE, SHIFT, expected_shapes, load_lpips  # noqa: E402
from ev3dgs.train.metrics import psnr, ssim_metric  # noqa: E402

SIZES = [(64, 48), (128, 96), (346, 260), (640, 480)]  # tests, bench_fidelity, DAVIS346, a VGA frame


def random_weights(net: str, path: Path, seed: int = 0) -> Path:
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for key, shape in expected_shapes(net).items():
        if key.startswith("net.") and key.endswith("weight"):
            sd[key] = torch.randn(shape, generator=g) * (2 / float(np.prod(shape[1:]))) ** 0.5
        elif key.startswith("net."):
            sd[key] = 0.1 * torch.randn(shape, generator=g)
        elif key.startswith("lin"):
            sd[key] = torch.rand(shape, generator=g)
    sd["scaling_layer.shift"] = torch.tensor(SHIFT).view(1, 3, 1, 1)
    sd["scaling_layer.scale"] = torch.tensor(SCALE).view(1, 3, 1, 1)
    torch.save(sd, path)
    return path


def timed(fn, reps: int) -> list[float]:
    fn()  # warm-up (oneDNN primitive creation)
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def stats(ts: list[float]) -> dict:
    return {"median_s": statistics.median(ts), "min_s": min(ts), "max_s": max(ts), "reps": len(ts)}


def per_pair(tmp: Path, reps: int) -> list[dict]:
    rng = np.random.default_rng(0)
    rows = []
    for net in ("alex", "vgg"):
        path = random_weights(net, tmp / f"{net}.pth")
        lp32, lp64 = load_lpips(path), load_lpips(path, dtype=torch.float64)
        for w, h in SIZES:
            a, b = (rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(2))
            t_lp = timed(lambda: lp32.distance(a, b), reps)
            t_ref = timed(lambda: (psnr(a, b), ssim_metric(a, b)), reps)
            pairs = [tuple(rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(2)) for _ in range(3)]
            rel = max(abs(lp32.distance(x, y) / lp64.distance(x, y) - 1) for x, y in pairs)
            row = {"net": net, "width": w, "height": h, "lpips": stats(t_lp), "psnr_ssim": stats(t_ref),
                   "lpips_over_psnr_ssim": statistics.median(t_lp) / statistics.median(t_ref),
                   "float32_vs_float64_max_rel": rel}
            rows.append(row)
            print(f"{net:4s} {w}x{h}: LPIPS {1e3 * row['lpips']['median_s']:8.1f} ms "
                  f"[{1e3 * row['lpips']['min_s']:.1f}, {1e3 * row['lpips']['max_s']:.1f}]  PSNR+SSIM "
                  f"{1e3 * row['psnr_ssim']['median_s']:7.1f} ms  ratio {row['lpips_over_psnr_ssim']:5.2f}  "
                  f"float32 vs float64 {rel:.1e}", flush=True)
    return rows


def end_to_end(run: Path, tmp: Path, reps: int) -> dict:
    """`evaluate` on a copy of a trained run (its config and model; metrics.json lands in the copy)."""
    from ev3dgs.train.evaluate import evaluate

    copy = tmp / "run"
    copy.mkdir()
    for name in ("config.json", "model.pt", "trajectory.npz"):
        if (run / name).is_file():
            shutil.copy2(run / name, copy / name)
    weights = random_weights("alex", tmp / "alex_e2e.pth")
    out = {}
    for label, lw in (("without", None), ("with_alex", weights)):
        ts = timed(lambda: evaluate(copy, lpips_weights=lw, device="cpu", write_images=False), reps)
        out[label] = stats(ts)
    m = json.loads((copy / "metrics.json").read_text())
    out["views"] = sum(m[k]["n"] for k in ("test", "train_sharp", "blurry_input") if k in m)
    out["ratio"] = out["with_alex"]["median_s"] / out["without"]["median_s"]
    print(f"evaluate {run.name}: {out['without']['median_s']:.2f} s without LPIPS, "
          f"{out['with_alex']['median_s']:.2f} s with (x{out['ratio']:.2f}, {out['views']} image pairs)")
    return out


def plot(rows: list[dict], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for net, style in (("alex", "o-"), ("vgg", "s-")):
        r = [x for x in rows if x["net"] == net]
        px = [x["width"] * x["height"] for x in r]
        med = np.array([x["lpips"]["median_s"] for x in r]) * 1e3
        err = np.array([[m - x["lpips"]["min_s"] * 1e3, x["lpips"]["max_s"] * 1e3 - m] for m, x in zip(med, r)]).T
        ax.errorbar(px, med, yerr=err, fmt=style, capsize=3, label=f"LPIPS {net} (float32)")
    r = [x for x in rows if x["net"] == "alex"]
    ax.plot([x["width"] * x["height"] for x in r], [x["psnr_ssim"]["median_s"] * 1e3 for x in r], "k--",
            label="PSNR + SSIM (float64)")
    ax.set(xscale="log", yscale="log", xlabel="pixels per image", ylabel="ms per image pair (1 thread)",
           title="LPIPS cost per image pair (median, bars: min-max)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=5, help="timed repetitions per measurement (default %(default)s)")
    ap.add_argument("--run", type=Path, help="a trained run folder to time `evaluate` on (default: none)")
    ap.add_argument("--json", type=Path, default=ROOT / "tools/results/bench_lpips.json",
                    help="output JSON (default tools/results/bench_lpips.json)")
    ap.add_argument("--plot", type=Path, default=ROOT / "tools/results/bench_lpips.png",
                    help="output plot (default tools/results/bench_lpips.png)")
    a = ap.parse_args(argv)
    if a.reps < 1:
        ap.error("--reps must be >= 1")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        rows = per_pair(Path(tmp), a.reps)
        e2e = end_to_end(a.run, Path(tmp), max(1, a.reps // 2)) if a.run else None
    result = {"settings": {"reps": a.reps, "threads": 1, "torch": torch.__version__, "sizes": SIZES},
              "per_pair": rows, "evaluate": e2e}
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(result, indent=2))
    plot(rows, a.plot)
    print(f"-> {a.json}, {a.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
