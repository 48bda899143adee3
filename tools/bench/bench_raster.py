"""Rasterizer forward+backward time per backend, all in one run (ratios are what count on a shared box).

    python tools/bench/bench_raster.py [--quick] --json tools/results/bench_raster.json [--plot ...]

Workloads: 10k Gaussians at 200x200 and 50k at 400x400 (--quick: the first only); a random cloud in front
of the camera (z 4 +- 0.5, scales 0.01-0.04, opacity 0.1-0.9, f = 1.1 W), the workload of our reference
notes. Each row: median ms of forward + backward (loss = image mean), as wall time ("ms") and as this
process's CPU time ("cpu_ms": the number to compare on a shared, loaded box; with --threads 1 it is the
code's own cost, with more threads it adds up the threads), and max |image - reference image| (the
reference renders every workload once, for the comparison, even where it is too slow to time often).
"""
from __future__ import annotations

import sys
from pathlib import Path

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from ev3dgs.splat.rasterize import cuda_available, rasterization  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402


def cloud(n: int, width: int, seed: int = 0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    z = 4 + (torch.rand(n, generator=g) - 0.5)
    f = 1.1 * width
    half = 0.5 * width / f * z
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * half[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g)
    scales = 0.01 + 0.03 * torch.rand(n, 3, generator=g)
    opac = 0.1 + 0.8 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (width - 1) / 2], [0, 0, 1.0]])
    to = lambda t: t.to(device)  # noqa: E731
    return [to(t) for t in (means, quats, scales, opac, colors)], to(torch.eye(4)), to(K)


def run(backend, params, viewmat, K, size, threads):
    leaves = [p.clone().requires_grad_(True) for p in params]
    image, alpha, _ = rasterization(*leaves, viewmat, K, size, size, backend=backend, threads=threads)
    image.mean().backward()
    if image.is_cuda:
        torch.cuda.synchronize()
    return image.detach().cpu()


def time_backend(backend, params, viewmat, K, size, repeats, threads):
    run(backend, params, viewmat, K, size, threads)  # warm-up (kernel load / JIT)
    times, cpu_times = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        image = run(backend, params, viewmat, K, size, threads)
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.process_time() - c0)
    return 1e3 * statistics.median(times), 1e3 * statistics.median(cpu_times), image


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the 10k @ 200x200 workload (default: off)")
    ap.add_argument("--repeats", type=int, default=5,
                    help="timed runs per backend and workload, median reported (default: 5; reference: a third)")
    ap.add_argument("--threads", type=int, default=1, help="torch/numba threads (default: 1)")
    ap.add_argument("--json", default="tools/results/bench_raster.json",
                    help="result file (default: tools/results/bench_raster.json)")
    ap.add_argument("--plot", default="tools/results/bench_raster.png",
                    help="bar chart, '' for none (default: tools/results/bench_raster.png)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    workloads = [(10_000, 200)] + ([] if args.quick else [(50_000, 400)])
    backends = ["reference", "cpu"] + (["cuda"] if cuda_available() else [])
    rows = []
    for n, size in workloads:
        params, viewmat, K = cloud(n, size)
        ref_ms, ref_cpu, ref_image = time_backend("reference", params, viewmat, K, size, max(1, args.repeats // 3),
                                         args.threads)
        for b in backends:
            if b == "reference":
                ms, cpu_ms, image = ref_ms, ref_cpu, ref_image
            elif b == "cuda":
                dev = [p.cuda() for p in params]
                ms, cpu_ms, image = time_backend(b, dev, viewmat.cuda(), K.cuda(), size, args.repeats,
                                                 args.threads)
            else:
                ms, cpu_ms, image = time_backend(b, params, viewmat, K, size, args.repeats, args.threads)
            diff = float((image - ref_image).abs().max())
            rows.append({"backend": b, "gaussians": n, "width": size, "height": size, "ms": ms,
                         "cpu_ms": cpu_ms, "max_abs_diff": diff})
            print(f"{b:9s} {n:>6d} Gaussians {size}x{size}: {ms:9.1f} ms fwd+bwd ({cpu_ms:9.1f} ms CPU)  "
                  f"(x{ref_ms / ms:5.1f} vs reference)  max|diff| {diff:.2e}")
    save_json(args.json, {"rows": rows}, f", torch/numba threads {args.threads}")
    if args.plot:
        plot(rows, args.plot)
    return 0


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3))
    labels = sorted({(r["gaussians"], r["width"]) for r in rows})
    for i, b in enumerate(sorted({r["backend"] for r in rows})):
        # CPU time for the CPU backends (wall time is the load's on a shared box), wall time for cuda
        vals = [next((r["ms"] if b == "cuda" else r["cpu_ms"] for r in rows
                      if r["backend"] == b and (r["gaussians"], r["width"]) == lab), 0)
                for lab in labels]
        ax.bar([j + 0.25 * i for j in range(len(labels))], vals, width=0.25, label=b)
    ax.set_xticks([j + 0.25 for j in range(len(labels))], [f"{n // 1000}k @ {w}px" for n, w in labels])
    ax.set_yscale("log")
    ax.set_ylabel("forward + backward, ms (CPU time; cuda: wall)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
