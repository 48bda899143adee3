"""Rasterizer forward+backward time per backend, all in one run (ratios are what count on a shared box).

    python tools/bench/bench_raster.py [--quick] --json tools/results/bench_raster.json [--plot ...]
    python tools/bench/bench_raster.py --fragments [--json tools/results/bench_raster_fragments.json]
    python tools/bench/bench_raster.py --kernels [--quick] [--json tools/results/bench_raster_kernels.json]

Workloads: 10k Gaussians at 200x200 and 50k at 400x400 (--quick: the first only); a random cloud in front
of the camera (z 4 +- 0.5, scales 0.01-0.04, opacity 0.1-0.9, f = 1.1 W), the workload of our reference
notes. Each row: median ms of forward + backward (loss = image mean), as wall time ("ms") and as this
process's CPU time ("cpu_ms": the number to compare on a shared, loaded box; with --threads 1 it is the
code's own cost, with more threads it adds up the threads), and max |image - reference image| (the
reference renders every workload once, for the comparison, even where it is too slow to time often).

--fragments: where the fragments go (tools/bench/fragments.py) for the 10k @ 200x200 cloud and one camera of
the 346x260 blur+event step's scene (tools/bench/bench_train_scaling.make_step) with 10k and 50k Gaussians;
the forward and backward kernels' CPU time per composited fragment (one thread, median of --repeats, also in
cycles at the clock /proc/cpuinfo reports); 1- and 2-thread forward+backward timed alternately (parallel
efficiency T1 / (2 T2), wall time); and the tile schedule's load balance for 2, 8 and 16 threads from the
per-tile costs (visited pixels).

--kernels: the `cpu` backend's two tile-kernel implementations in the same run, alternating call by call:
the C SIMD kernels (ev3dgs/splat/cpu_simd.py, float32) and the numba kernels (cpu_simd.KERNEL = "numba").
Per workload (10k @ 200x200 cloud; without --quick also one camera of the 346x260 step scene with 50k
Gaussians): forward+backward of the whole rasterization call (CPU time) and of the kernels alone (thread CPU
time around the forward and backward kernel calls), one thread, with the ratio numba / C per pair of
alternated runs (min / median / max); composited fragments and each kernel's cycles per fragment at the
/proc/cpuinfo clock; and the C kernels' 2-thread parallel efficiency T1 / (2 T2) from wall times of the
kernels alone, 1 and 2 threads alternated, with the ratio of the CPU time both threads spent to one thread's
(near 1 with a low efficiency: the threads waited for a core held by other work).
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
sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/bench/: fragments.py, bench_train_scaling.py
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


def run(backend, params, viewmat, K, size, threads, height=None):
    leaves = [p.clone().requires_grad_(True) for p in params]
    image, alpha, _ = rasterization(*leaves, viewmat, K, size, height or size, backend=backend, threads=threads)
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
    ap.add_argument("--fragments", action="store_true",
                    help="fragment statistics, per-fragment kernel cost and thread analysis instead (default: off)")
    ap.add_argument("--kernels", action="store_true",
                    help="C SIMD kernels against numba kernels, alternating (default: off)")
    args = ap.parse_args(argv)
    if args.kernels:
        json_path = args.json if args.json != ap.get_default("json") else "tools/results/bench_raster_kernels.json"
        plot_path = args.plot if args.plot != ap.get_default("plot") else "tools/results/bench_raster_kernels.png"
        return run_kernels(args.repeats, args.quick, json_path, plot_path)
    if args.fragments:
        json_path = args.json if args.json != ap.get_default("json") else "tools/results/bench_raster_fragments.json"
        plot_path = args.plot if args.plot != ap.get_default("plot") else "tools/results/bench_raster_fragments.png"
        return run_fragments(args.repeats, json_path, plot_path)
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


def clock_mhz() -> float | None:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("cpu MHz"):
                    return float(line.split(":")[1])
    except OSError:
        pass
    return None


def kernel_times(params, viewmat, K, width, height, repeats):
    """Median CPU time (s) of the forward and backward kernels in forward+backward runs on one thread."""
    import ev3dgs.splat.cpu as cpu

    spent = {"_forward": [], "_backward": []}
    real = cpu._parallel

    def timed(kernel, *a):
        t0 = time.thread_time()
        out = real(kernel, *a)
        name = getattr(kernel, "__name__", "")
        if name in spent:
            spent[name].append(time.thread_time() - t0)
        return out

    cpu._parallel = timed
    try:
        run("cpu", params, viewmat, K, width, 1, height)
        for v in spent.values():
            v.clear()
        for _ in range(repeats):
            run("cpu", params, viewmat, K, width, 1, height)
    finally:
        cpu._parallel = real
    return {k: statistics.median(v) for k, v in spent.items()}


def step_scene(n, width, height):
    """One camera (the middle sub-pose) of make_step's scene, projected: (means, quats, scales, opacities,
    colours), viewmat, K as rasterization() takes them, SH evaluated to colours."""
    from bench_train_scaling import SUBPOSES, _viewmats

    from ev3dgs.splat.model import GaussianModel
    from ev3dgs.splat.sh import eval_sh

    model = GaussianModel.random_in_bounds([[-0.6] * 3, [0.6] * 3], n, seed=0, sh_degree=3, init_opacity=0.3)
    model.active_sh_degree = 3
    f = 1.2 * width
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    vm = _viewmats(SUBPOSES)[SUBPOSES // 2]
    with torch.no_grad():
        campos = torch.linalg.inv(vm)[:3, 3]
        colors = eval_sh(3, model.sh, model.means - campos).clamp_min(0)
        params = [t.detach().clone() for t in (model.means, model.quats_normalised, model.scales, model.opacities)]
    return params + [colors.detach().clone()], vm, K


def run_fragments(repeats, json_path, plot_path) -> int:
    from fragments import fragment_stats, schedule_efficiency

    from ev3dgs.splat.cpu import set_numba_threads
    from ev3dgs.splat.project import project_gaussians

    torch.set_num_threads(1)
    mhz = clock_mhz()
    rows = []
    for name, n, w, h in (("cloud", 10_000, 200, 200), ("step scene", 10_000, 346, 260),
                          ("step scene", 50_000, 346, 260)):
        params, vm, K = cloud(n, w) if name == "cloud" else step_scene(n, w, h)
        with torch.no_grad():
            pr = project_gaussians(params[0], params[1], params[2], params[3], vm, K, w, h)
        st = fragment_stats(pr.means2d, pr.conics, params[4], params[3], pr.depths, pr.radii, w, h)
        per_tile = st.pop("per_tile")
        set_numba_threads(1)
        kt = kernel_times(params, vm, K, w, h, repeats)
        comp = st["composited"]
        row = {"scene": name, "gaussians": n, "width": w, "height": h, **st,
               "forward_ns_per_fragment": 1e9 * kt["_forward"] / comp,
               "backward_ns_per_fragment": 1e9 * kt["_backward"] / comp,
               "schedule_efficiency": {str(t): schedule_efficiency(per_tile["visited"], per_tile["list_length"], t)
                                       for t in (2, 8, 16)},
               "per_tile_visited": per_tile["visited"]}
        if mhz:
            row["forward_cycles_per_fragment"] = row["forward_ns_per_fragment"] * mhz / 1e3
            row["backward_cycles_per_fragment"] = row["backward_ns_per_fragment"] * mhz / 1e3
        # 1 and 2 threads alternately, wall time of forward+backward (the kernels' own threads)
        t1, t2 = [], []
        run("cpu", params, vm, K, w, 2, h)
        for _ in range(repeats):
            for th, acc in ((1, t1), (2, t2)):
                t0 = time.perf_counter()
                run("cpu", params, vm, K, w, th, h)
                acc.append(time.perf_counter() - t0)
        eff = sorted(a / (2 * b) for a, b in zip(t1, t2))
        row["efficiency_2t"] = {"min": eff[0], "median": statistics.median(eff), "max": eff[-1]}
        rows.append(row)
        print(f"{name} {n} @ {w}x{h}: {comp} fragments ({st['fragments_per_pixel']:.1f}/px), "
              f"below 1/255 {100 * st['share_below_cut']:.1f} %, behind T<1e-4 {100 * st['share_behind']:.1f} %, "
              f"forward {row['forward_ns_per_fragment']:.1f} ns/fragment, backward "
              f"{row['backward_ns_per_fragment']:.1f} ns/fragment, "
              f"T1/(2 T2) median {row['efficiency_2t']['median']:.2f}"
              f", schedule 8/16 threads {row['schedule_efficiency']['8']['by_list_length']:.2f}/"
              f"{row['schedule_efficiency']['16']['by_list_length']:.2f}")
    save_json(json_path, {"clock_mhz": mhz, "rows": rows}, ", one thread unless stated")
    if plot_path:
        plot_fragments(rows, plot_path)
    return 0


class KernelClock:
    """Thread CPU time and wall time spent in the tile kernels (either implementation) and the fragments
    the C forward composited, while installed."""

    def __init__(self):
        import ev3dgs.splat.cpu as cpu
        import ev3dgs.splat.cpu_simd as cs

        self.cpu, self.cs = cpu, cs
        self.real = (cpu._parallel, cs.forward, cs.backward)
        self.reset()

    def reset(self):
        self.cpu_s = {"forward": 0.0, "backward": 0.0}
        self.wall_s = 0.0
        self.process_s = 0.0  # CPU time of all the process's threads
        self.fragments = 0

    def _timed(self, name, fn, *a, **kw):
        t0, w0, p0 = time.thread_time(), time.perf_counter(), time.process_time()
        out = fn(*a, **kw)
        self.wall_s += time.perf_counter() - w0
        self.process_s += time.process_time() - p0
        self.cpu_s[name] += time.thread_time() - t0
        return out

    def __enter__(self):
        real_parallel, real_fwd, real_bwd = self.real
        names = {"_forward": "forward", "_backward": "backward"}

        def parallel(kernel, *a):
            name = names.get(getattr(kernel, "__name__", ""))
            return self._timed(name, real_parallel, kernel, *a) if name else real_parallel(kernel, *a)

        def fwd(*a, **kw):
            out = self._timed("forward", real_fwd, *a, **kw)
            frag_n = a[11][2]
            if len(frag_n) == (len(a[0]) if a[0] is not None else len(kw["ids"])):
                self.fragments = int(frag_n.sum())
            return out

        self.cpu._parallel = parallel
        self.cs.forward = fwd
        self.cs.backward = lambda *a, **kw: self._timed("backward", real_bwd, *a, **kw)
        return self

    def __exit__(self, *exc):
        self.cpu._parallel, self.cs.forward, self.cs.backward = self.real


def _spread(values):
    v = sorted(values)
    return {"min": v[0], "median": statistics.median(v), "max": v[-1]}


def run_kernels(repeats, quick, json_path, plot_path) -> int:
    import ev3dgs.splat.cpu_simd as cs

    if not cs.available():
        print("error: the C rasterizer extension is not built (python setup.py build_ext --inplace)", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    mhz = clock_mhz()
    workloads = [("cloud", 10_000, 200, 200)] + ([] if quick else [("step scene", 50_000, 346, 260)])
    rows = []
    kinds = ("simd", "numba")
    for name, n, w, h in workloads:
        params, vm, K = cloud(n, w) if name == "cloud" else step_scene(n, w, h)
        res = {k: {"call_cpu": [], "fwd_cpu": [], "bwd_cpu": []} for k in kinds}
        fragments = 0
        with KernelClock() as clock:
            for k in kinds:  # warm-up (numba's cache load)
                cs.KERNEL = k
                run("cpu", params, vm, K, w, 1, h)
            for _ in range(repeats):
                for k in kinds:
                    cs.KERNEL = k
                    clock.reset()
                    c0 = time.process_time()
                    run("cpu", params, vm, K, w, 1, h)
                    res[k]["call_cpu"].append(time.process_time() - c0)
                    res[k]["fwd_cpu"].append(clock.cpu_s["forward"])
                    res[k]["bwd_cpu"].append(clock.cpu_s["backward"])
                    if k == "simd":
                        fragments = clock.fragments
            # the C kernels' wall time at 1 and 2 threads, alternated
            cs.KERNEL = "simd"
            walls, cpus = {1: [], 2: []}, {1: [], 2: []}
            run("cpu", params, vm, K, w, 2, h)
            for _ in range(repeats):
                for th in (1, 2):
                    clock.reset()
                    run("cpu", params, vm, K, w, th, h)
                    walls[th].append(clock.wall_s)
                    cpus[th].append(clock.process_s)
        cs.KERNEL = "simd"
        row = {"scene": name, "gaussians": n, "width": w, "height": h, "fragments": fragments}
        for k in kinds:
            for key, vals in res[k].items():
                row[f"{k}_{key}_ms"] = _spread([1e3 * v for v in vals])
            kern = [f + b for f, b in zip(res[k]["fwd_cpu"], res[k]["bwd_cpu"])]
            row[f"{k}_kernels_cpu_ms"] = _spread([1e3 * v for v in kern])
            for part in ("fwd", "bwd"):
                ns = [1e9 * v / max(fragments, 1) for v in res[k][f"{part}_cpu"]]
                row[f"{k}_{part}_ns_per_fragment"] = _spread(ns)
                if mhz:
                    row[f"{k}_{part}_cycles_per_fragment"] = _spread([v * mhz / 1e3 for v in ns])
        for key in ("call_cpu", "fwd_cpu", "bwd_cpu"):
            row[f"speedup_{key}"] = _spread([a / b for a, b in zip(res["numba"][key], res["simd"][key])])
        row["speedup_kernels_cpu"] = _spread([(a1 + a2) / (b1 + b2) for a1, a2, b1, b2 in
                                              zip(res["numba"]["fwd_cpu"], res["numba"]["bwd_cpu"],
                                                  res["simd"]["fwd_cpu"], res["simd"]["bwd_cpu"])])
        row["simd_efficiency_2t"] = _spread([a / (2 * b) for a, b in zip(walls[1], walls[2])])
        # the CPU time 2 threads spend against 1 (1: no extra work; a low efficiency with this near 1 means the
        # threads waited for a core, not that the kernels do more work in parallel)
        row["simd_cpu_2t_over_1t"] = _spread([b / a for a, b in zip(cpus[1], cpus[2])])
        rows.append(row)
        cyc = (f", cycles/fragment fwd {row['simd_fwd_cycles_per_fragment']['median']:.1f} vs "
               f"{row['numba_fwd_cycles_per_fragment']['median']:.1f}, bwd "
               f"{row['simd_bwd_cycles_per_fragment']['median']:.1f} vs "
               f"{row['numba_bwd_cycles_per_fragment']['median']:.1f}") if mhz else ""
        sp = row["speedup_kernels_cpu"]
        print(f"{name} {n} @ {w}x{h}: {fragments} fragments; kernels fwd+bwd C "
              f"{row['simd_kernels_cpu_ms']['median']:.2f} ms, numba {row['numba_kernels_cpu_ms']['median']:.2f} ms: "
              f"x{sp['median']:.2f} ({sp['min']:.2f}-{sp['max']:.2f}); whole call "
              f"x{row['speedup_call_cpu']['median']:.2f} ({row['speedup_call_cpu']['min']:.2f}-"
              f"{row['speedup_call_cpu']['max']:.2f}){cyc}; C T1/(2 T2) median "
              f"{row['simd_efficiency_2t']['median']:.2f} (CPU time 2 threads / 1: "
              f"{row['simd_cpu_2t_over_1t']['median']:.2f})")
    save_json(json_path, {"clock_mhz": mhz, "isa": cs.isa(), "repeats": repeats, "rows": rows},
              ", one thread unless stated, C vs numba kernels alternated")
    if plot_path:
        plot_kernels(rows, plot_path)
    return 0


def plot_kernels(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.2))
    parts = [("fwd_cpu", "forward kernel"), ("bwd_cpu", "backward kernel"), ("call_cpu", "whole call")]
    for i, r in enumerate(rows):
        for j, (key, label) in enumerate(parts):
            for k, kind in enumerate(("numba", "simd")):
                v = r[f"{kind}_{key}_ms"]
                x = i * 4 + j + 0.4 * k
                ax.bar(x, v["median"], width=0.4, color=("C0", "C1")[k], label=kind if (i, j) == (0, 0) else None)
                ax.errorbar(x, v["median"], yerr=[[v["median"] - v["min"]], [v["max"] - v["median"]]], color="k",
                            capsize=2, lw=0.8)
    ax.set_xticks([i * 4 + j + 0.2 for i in range(len(rows)) for j in range(3)],
                  [f"{lab}\n{r['gaussians'] // 1000}k {r['width']}x{r['height']}" for r in rows for _, lab in parts],
                  fontsize=6)
    ax.set_ylabel("ms CPU time, one thread")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_fragments(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    for r in rows:
        v = sorted(r["per_tile_visited"], reverse=True)
        ax[0].plot(v, label=f"{r['scene']} {r['gaussians'] // 1000}k @ {r['width']}x{r['height']}")
        ax[1].plot([2, 8, 16], [r["schedule_efficiency"][str(t)]["by_list_length"] for t in (2, 8, 16)], "o-")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("tiles, most expensive first")
    ax[0].set_ylabel("pixels visited per tile")
    ax[0].legend(fontsize=7)
    ax[1].set_xlabel("threads")
    ax[1].set_ylabel("schedule efficiency (model)")
    ax[1].set_ylim(0, 1.05)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
