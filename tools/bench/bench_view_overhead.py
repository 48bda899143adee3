"""What `ev3dgs train --view` costs the training: the same run (same scene, seed, settings) with and without
the live viewer, alternated A B A B ... in one process, one torch thread. The viewer runs its real viser server
with no client, and with a websocket client that receives every message the browser would get (a Python
stand-in for the browser: a browser renders on the user's GPU, here it would compete for the same 2 cores).
Also the cost of one update measured on its own (CPU time of all threads, a client receiving), divided by
the CPU time of `every` training steps: the overhead that the noisy whole-run ratios bound from above.
Reports the per-run wall and process CPU time of Trainer.fit (CPU time is far less sensitive to other
processes on a shared machine), the ratios with/without, the time spent inside the on_step hook,
and whether the two runs' losses are identical (the viewer must not change the training).

    python tools/bench/bench_view_overhead.py --scene demo_out/lego.h5 --iterations 300 --pairs 3 \
        --json tools/results/bench_view_overhead.json --plot tools/results/bench_view_overhead.png
"""
from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"
os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402


class Client:
    """Receives (and counts) what the viewer sends, in a thread, like a connected browser's websocket."""

    def __init__(self, port: int):
        import threading

        import viser
        from websockets.sync.client import connect

        self.bytes = 0
        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None)
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self):
        try:
            for msg in self.ws:
                self.bytes += len(msg)
        except Exception:
            pass

    def close(self):
        self.ws.close()
        self.thread.join(timeout=5)


def one_run(scene: str, iterations: int, every: int | None, out: Path, client: bool = False) -> dict:
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.trainer import Trainer

    cfg = TrainConfig(scene=scene, iterations=iterations, threads=1, seed=0, checkpoint_every=10**9)
    trainer = Trainer(cfg, out, quiet=True)
    hook, viewer, hook_s = None, None, 0.0
    if every is not None:
        from ev3dgs.view.data import load_scene
        from ev3dgs.view.live import LiveUpdate
        from ev3dgs.view.server import Viewer

        viewer = Viewer("127.0.0.1", 0)
        viewer.show_scene(load_scene(scene))
        cl = Client(viewer.port) if client else None
        live = LiveUpdate(viewer, every, iterations)

        def hook(tr, rec):
            nonlocal hook_s
            t = time.perf_counter()
            live(tr, rec)
            hook_s += time.perf_counter() - t
    losses = []

    def record(tr, rec):
        losses.append(rec["loss"])
        if hook is not None:
            hook(tr, rec)

    t0, c0 = time.perf_counter(), time.process_time()
    trainer.fit(on_step=record)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    received = 0
    if viewer is not None:
        if cl is not None:
            time.sleep(1.0)  # let the last update arrive
            received = cl.bytes
            cl.close()
        viewer.stop()
    return {"wall_s": wall, "cpu_s": cpu, "hook_s": hook_s, "losses": losses, "gaussians": len(trainer.model),
            "updates": 0 if every is None else live.updates, "received_bytes": received}


def update_cost(scene: str, model, repeats: int = 30) -> dict:
    """Wall and process CPU time (all threads: the caller's, viser's, the receiving client's) of one viewer
    update (the on_step hook's work: splat arrays + send) with a client connected, averaged over `repeats`;
    measured without training beside it, so that other work in the process does not blur it."""
    from ev3dgs.view.data import load_scene, splat_arrays
    from ev3dgs.view.server import Viewer

    viewer = Viewer("127.0.0.1", 0)
    viewer.show_scene(load_scene(scene))
    cl = Client(viewer.port)
    time.sleep(1.0)
    b0 = cl.bytes
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        viewer.show_splats(splat_arrays(model))
    time.sleep(1.0)  # let the sends finish (their CPU time is counted; the 1 s idle wait costs ~0, see notes)
    wall, cpu = time.perf_counter() - t0 - 1.0, time.process_time() - c0
    sent = cl.bytes - b0
    cl.close()
    viewer.stop()
    return {"gaussians": len(model), "repeats": repeats, "wall_per_update_s": wall / repeats,
            "cpu_per_update_s": cpu / repeats, "bytes_per_update": sent / repeats}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="demo_out/lego.h5")
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--variants", nargs="+", default=["100", "100+client", "10+client"],
                    help="--view-every values, +client: with a receiving websocket client; off: no viewer (A/A)")
    ap.add_argument("--json", default="tools/results/bench_view_overhead.json")
    ap.add_argument("--plot", default="tools/results/bench_view_overhead.png")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        one_run(args.scene, 20, None, Path(tmp) / "warm")  # numba compilation, caches
        for pair in range(args.pairs):
            base = one_run(args.scene, args.iterations, None, Path(tmp) / f"a{pair}")
            row = {"pair": pair, "without_s": base["wall_s"], "without_cpu_s": base["cpu_s"]}
            for every in args.variants:
                # "off": a second run without the viewer (an A/A control: the spread of identical runs)
                n, client = (None, False) if every == "off" else (int(every.split("+")[0]), every.endswith("+client"))
                v = one_run(args.scene, args.iterations, n, Path(tmp) / f"b{pair}_{n}{client}", client)
                row[f"with_every_{every}_s"] = v["wall_s"]
                row[f"ratio_every_{every}"] = v["wall_s"] / base["wall_s"]
                row[f"cpu_ratio_every_{every}"] = v["cpu_s"] / base["cpu_s"]
                row[f"hook_every_{every}_s"] = v["hook_s"]
                row[f"updates_every_{every}"] = v["updates"]
                row[f"received_bytes_every_{every}"] = v["received_bytes"]
                row[f"same_losses_every_{every}"] = v["losses"] == base["losses"]
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = {}
    for every in args.variants:
        r = [row[f"ratio_every_{every}"] for row in rows]
        h = [row[f"hook_every_{every}_s"] / row[f"with_every_{every}_s"] for row in rows]
        c = [row[f"cpu_ratio_every_{every}"] for row in rows]
        summary[f"every_{every}"] = {"ratio_median": statistics.median(r), "ratio_min": min(r), "ratio_max": max(r),
                                     "cpu_ratio_median": statistics.median(c), "cpu_ratio_min": min(c),
                                     "cpu_ratio_max": max(c),
                                     "hook_share_median": statistics.median(h),
                                     "all_losses_identical": all(row[f"same_losses_every_{every}"] for row in rows)}
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.trainer import Trainer

    with tempfile.TemporaryDirectory() as tmp:  # a model of the size the runs above ended with
        tr = Trainer(TrainConfig(scene=args.scene, iterations=1, threads=1, seed=0), Path(tmp), quiet=True)
        cost = update_cost(args.scene, tr.model)
    step_cpu = statistics.median(row["without_cpu_s"] for row in rows) / args.iterations
    step_wall = statistics.median(row["without_s"] for row in rows) / args.iterations
    cost["step_cpu_s"], cost["step_wall_s"] = step_cpu, step_wall
    for every in sorted({int(v.split("+")[0]) for v in args.variants if v != "off"} | {1, 100}):
        cost[f"overhead_every_{every}"] = cost["cpu_per_update_s"] / (every * step_cpu)
    summary["update_cost"] = cost
    result = {"scene": args.scene, "iterations": args.iterations, "pairs": args.pairs, "torch_threads": 1,
              "rows": rows, "summary": summary}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(json.dumps(summary, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for k, every in enumerate(args.variants):
        r = [row[f"ratio_every_{every}"] for row in rows]
        c = [row[f"cpu_ratio_every_{every}"] for row in rows]
        ax.plot([k - 0.1] * len(r), r, "o", color="C0", label="wall time" if k == 0 else None)
        ax.plot([k + 0.1] * len(c), c, "s", color="C1", label="process CPU time" if k == 0 else None)
    ax.axhline(1.05, color="r", ls="--", lw=0.8, label="5% budget")
    ax.axhline(1.0, color="k", lw=0.5)
    ax.set_xticks(range(len(args.variants)), [f"every {e}" for e in args.variants], fontsize=7)
    ax.set_ylabel("training time with / without --view")
    ax.set_title(f"{Path(args.scene).name}, {args.iterations} steps, {args.pairs} pairs", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.plot, dpi=100)


if __name__ == "__main__":
    main()
