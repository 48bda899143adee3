"""ms per blur+event training step against pixels and against Gaussians (log-log): `bench_train.py --scaling`.

The step is the trainer's on the cpu backend, on synthetic data: a random cloud (GaussianModel.random_in_bounds
in a unit cube, SH degree 3 all active), 5 sub-poses 1 degree apart, a random blurry target and random ON/OFF
event counts between the sub-poses, all 10 pairs; blur loss + the trainer's pose_event_loss, backward, one Adam
step per parameter, under the trainer's `reproducible()` (torch on one thread; the numba kernels on `threads`)."""
from __future__ import annotations

import sys
from pathlib import Path

import math
import statistics
import time

import numpy as np
import torch

from ev3dgs.splat.model import GaussianModel
from ev3dgs.splat.rasterize import rasterization
from ev3dgs.train.events import pair_list, pose_counts
from ev3dgs.train.losses import blur_loss, log_intensity, pose_event_loss
from ev3dgs.train.trainer import reproducible
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json

SUBPOSES = 5


def _viewmats(n: int) -> torch.Tensor:
    out = []
    for k in range(n):
        a = math.radians(1.0) * (k - n // 2)
        vm = torch.eye(4)
        vm[0, 0], vm[0, 2], vm[2, 0], vm[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
        vm[2, 3] = 3.0
        out.append(vm)
    return torch.stack(out)


def make_step(n: int, width: int, height: int):
    """One blur+event training step on n random Gaussians at width x height (SUBPOSES renders, Adam), as a
    closure taking the rasterizer's thread count (tools/studies/study_size.py uses it too)."""
    model = GaussianModel.random_in_bounds([[-0.6] * 3, [0.6] * 3], n, seed=0, sh_degree=3, init_opacity=0.3)
    model.active_sh_degree = 3
    opts = model.make_optimizers()
    f = 1.2 * width
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    vms = _viewmats(SUBPOSES)
    g = torch.Generator().manual_seed(0)
    target = torch.rand(height, width, 3, generator=g)
    pairs = pair_list(SUBPOSES, "all", g)
    counts = pose_counts(torch.randint(0, 3, (SUBPOSES - 1, 2, height, width), generator=g).float())

    def step(threads: int) -> None:
        with reproducible():
            stack, _, _ = rasterization(model.means, model.quats_normalised, model.scales, model.opacities,
                                        model.sh, vms, K, width, height, sh_degree=3, backend="cpu",
                                        threads=threads)
            loss = blur_loss(stack, target) + pose_event_loss(log_intensity(stack), counts, pairs, 0.2, 0.2) / 625
            loss.backward()
            for opt in opts.values():
                opt.step()
                opt.zero_grad(set_to_none=True)

    return step


def step_ms(n: int, width: int, height: int, threads: int, repeats: int = 5) -> float:
    run = make_step(n, width, height)

    def step():
        run(threads)

    step()  # warm-up (kernel load)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def run_scaling(threads: int, quick: bool, json_path: str, png_path: str) -> int:
    sizes = [(48, 36), (96, 72), (192, 144)] + ([] if quick else [(346, 260)])
    counts = [1000, 3000, 10000] + ([] if quick else [30000])
    by_pixels = []
    for w, h in sizes:
        ms = step_ms(6000, w, h, threads)
        by_pixels.append({"width": w, "height": h, "pixels": w * h, "gaussians": 6000, "ms": ms})
        print(f"6000 Gaussians at {w}x{h}: {ms:8.1f} ms/step")
    by_gaussians = []
    for n in counts:
        ms = step_ms(n, 96, 72, threads)
        by_gaussians.append({"width": 96, "height": 72, "pixels": 96 * 72, "gaussians": n, "ms": ms})
        print(f"{n} Gaussians at 96x72: {ms:8.1f} ms/step")
    out = {"threads": threads, "subposes": SUBPOSES, "by_pixels": by_pixels, "by_gaussians": by_gaussians}
    for rows, key in ((by_pixels, "pixels"), (by_gaussians, "gaussians")):  # log-log slope: cost ~ x^slope
        x, y = np.log([r[key] for r in rows]), np.log([r["ms"] for r in rows])
        out[f"slope_{key}"] = float(np.polyfit(x, y, 1)[0])
    save_json(json_path, out, f", threads {threads}")
    plot(out, png_path)
    return 0


def plot(out: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(8, 3.2))
    for a, key, rows, label in ((ax[0], "pixels", out["by_pixels"], "pixels (6k Gaussians)"),
                                (ax[1], "gaussians", out["by_gaussians"], "Gaussians (96x72)")):
        a.loglog([r[key] for r in rows], [r["ms"] for r in rows], "o-")
        for r in rows:
            a.annotate(f"{r['width']}x{r['height']}" if key == "pixels" else f"{r['gaussians'] // 1000}k",
                       (r[key], r["ms"]), fontsize=7, xytext=(3, -9), textcoords="offset points")
        a.set_xlabel(label + f"  (slope {out['slope_' + key]:.2f})")
        a.set_ylabel("ms per blur+event step")
        a.grid(True, which="both", lw=0.3)
    fig.suptitle(f"CPU step cost, {out['subposes']} sub-poses, numba threads {out['threads']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
