"""`make demo`: the whole chain on the built-in default.

1. a --quick dataset of the lego scene (10 shaky views of 17 sub-frames over 100 ms exposures, 3 sharp test
   views, 96x72) rendered in Blender, with events and raw-domain blur;
2. three trainings on it: naive 3DGS on the blurry frames, the blur rendering loss alone, and blur + event
   rendering losses; the CPU rasterizer's kernels are compiled once before they start (not by three processes
   at once), and each training reports one progress line (steps, loss, elapsed, ETA) while they run;
3. evaluation on the sharp test views and the deblurred training views, printed as a table.
Everything lands in demo_out/ (scene, runs with metrics.json and side-by-side PNGs, a labelled strip per view,
demo.json with the settings). Run again over the same folder, it reuses the dataset and the finished runs
made with the same settings and says so; a folder made with other settings, or --fresh, starts afresh and says
that too.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from . import palette, schema
from .cli.common import write_atomic
from .sim.dataset import make_dataset
from .sim.scenes import load_scene, resolve_render
from .train.jobs import default_jobs

DEMO_RENDER = dict(views=10, test_views=3)
DEMO_ITERATIONS = 1500
# `--test-size`: the same chain in a few minutes (a check that everything runs, not a result)
TEST_SIZE = dict(views=3, test_views=1, width=48, height=36, samples=2)
TEST_ITERATIONS = 20
VARIANT_ORDER = ("naive", "blur-only", "blur+event")


def _say(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, flush=True)


# ----------------------------------------------------------------------------------- strips

STRIP_MIN_PANEL = 240     # px: each panel of a strip is enlarged (nearest neighbour) to at least this width
_FONT, _SCALE, _THICK = cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1
_LINE = 18                # px per text line


def _text_rows(lines: list[str], width: int) -> np.ndarray:
    """White rows of black text, one per line, left-aligned with a 4 px margin."""
    out = np.full((_LINE * len(lines) + 4, width, 3), 255, np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(out, line, (4, _LINE * (k + 1) - 4), _FONT, _SCALE, (0, 0, 0), _THICK, cv2.LINE_AA)
    return out


def _fit_lines(text: str, width: int) -> list[str]:
    """`text` broken into lines that fit `width` pixels in the strip's font."""
    words, lines = text.split(), [""]
    for w in words:
        trial = f"{lines[-1]} {w}".strip()
        if cv2.getTextSize(trial, _FONT, _SCALE, _THICK)[0][0] <= width - 8 or not lines[-1]:
            lines[-1] = trial
        else:
            lines.append(w)
    return lines


def _legend(width: int) -> np.ndarray:
    """One row: a red square "ON event (brighter)", a blue square "OFF event (darker)" (palette's colours)."""
    row = np.full((_LINE + 6, width, 3), 255, np.uint8)
    x = 4
    for rgb, label in ((palette.ON_RGB, "ON event (brighter)"), (palette.OFF_RGB, "OFF event (darker)")):
        cv2.rectangle(row, (x, 5), (x + 12, 17), tuple(int(c) for c in rgb), -1)
        cv2.putText(row, label, (x + 18, 16), _FONT, _SCALE, (0, 0, 0), _THICK, cv2.LINE_AA)
        x += 18 + cv2.getTextSize(label, _FONT, _SCALE, _THICK)[0][0] + 16
    return row


def view_strip(sc: schema.Scene, view: int) -> np.ndarray:
    """sharp | blurry | events of one training view, side by side (RGB uint8), each panel enlarged and labelled
    above, the event panel's window and counts below it, a polarity legend under the strip."""
    from .view import data

    W, H = sc.camera.width, sc.camera.height
    events = sc.events.load()
    t = np.asarray(events.t)
    start, end, window = data.event_window(np.asarray(sc.train.exposure, np.int64), view,
                                           lambda a, b: int(np.searchsorted(t, b) - np.searchsorted(t, a)), W, H)
    ev = events.window(start, end)
    on, off = data.polarity_counts(ev.x, ev.y, ev.p, W, H)
    panels = [(np.asarray(sc.train.images[view]), "blurry frame (the input)"),
              (data.event_image(on, off), f"events ({palette.legend_text()})")]
    if sc.train.sharp is not None:
        panels.insert(0, (np.asarray(sc.train.sharp[view]), "sharp frame (mid-exposure)"))
    k = max(1, -(-STRIP_MIN_PANEL // W))
    cols = []
    for img, label in panels:
        big = np.pad(np.repeat(np.repeat(img, k, axis=0), k, axis=1), ((1, 1), (1, 1), (0, 0)),
                     constant_values=160)   # a grey frame: a white background does not run into the page
        width = big.shape[1]
        under = (_fit_lines(f"{int(on.sum())} ON, {int(off.sum())} OFF; {window}", width)
                 if label.startswith("events") else [])
        col = [_text_rows(_fit_lines(label, width), width), big]
        if under:
            col.append(_text_rows(under, width))
        cols.append(col)
    # the same rows in every column: pad the label and caption rows to the tallest
    top = max(c[0].shape[0] for c in cols)
    bottom = max((c[2].shape[0] for c in cols if len(c) > 2), default=0)
    out = []
    for c in cols:
        w = c[1].shape[1]
        parts = [np.pad(c[0], ((0, top - c[0].shape[0]), (0, 0), (0, 0)), constant_values=255), c[1]]
        cap = c[2] if len(c) > 2 else np.full((0, w, 3), 255, np.uint8)
        parts.append(np.pad(cap, ((0, bottom - cap.shape[0]), (0, 0), (0, 0)), constant_values=255))
        out.append(np.pad(np.vstack(parts), ((0, 0), (3, 3), (0, 0)), constant_values=255))
    strip = np.hstack(out)
    title = _text_rows([f"training view {view}"], strip.shape[1])
    return np.vstack([title, strip, _legend(strip.shape[1])])


# ---------------------------------------------------------------------------------- dataset

def make_scene(out: Path, scene: str = "lego", seed: int = 0, quiet: bool = False, **overrides) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    spec = load_scene(scene)
    render = resolve_render(spec, quick=True, **overrides)
    path = out / f"{spec.name}.h5"
    # two Blender workers overlap one view's scene set-up and denoising with another's render (Cycles already
    # uses every core): 17.3 -> 16.2 s for the demo scene on 2 cores, the same file bit for bit
    stats = make_dataset(spec, render, path, seed=seed, quiet=quiet, workers=min(2, default_jobs()))
    write_strips(out, path)
    if not quiet:
        sec = stats.seconds
        sc = schema.read(path)
        print(f"dataset: {spec.name} --quick, {render.views} views x {render.subframes} sub-frames + "
              f"{render.test_views} test views at {render.width}x{render.height}: {len(sc.events)} events; "
              f"render {sec['render']:.0f} s, simulate+ISP+write {sec['simulate'] + sec['isp'] + sec['write']:.2f} s")
    return path


def write_strips(out: Path, path: Path) -> None:
    sc = schema.read(path)
    for v in range(len(sc.train)):
        png = cv2.imencode(".png", cv2.cvtColor(view_strip(sc, v), cv2.COLOR_RGB2BGR))[1]
        write_atomic(out / f"{sc.name}_view{v}.png", png.tobytes())


# ---------------------------------------------------------------------------- what is there

def settings(scene: str, seed: int, iterations: int, overrides: dict) -> dict:
    """What demo.json records: a demo folder is reused only when these are the same."""
    return {"scene": scene, "seed": seed, "iterations": iterations,
            "render": {k: overrides[k] for k in sorted(overrides) if overrides[k] is not None}}


def plan(out: Path, wanted: dict, fresh: bool = False) -> tuple[str, list[str], str]:
    """(mode, the finished runs to keep, why) for a demo with settings `wanted` in `out`: mode "new" (nothing
    there), "reuse" (this demo's dataset, and those runs), or "afresh" (`why` says what was found)."""
    record = out / "demo.json"
    earlier = out.is_dir() and (record.is_file() or any(out.glob("*.h5")) or (out / "runs").is_dir())
    if not earlier:
        return "new", [], ""
    if fresh:
        return "afresh", [], "--fresh was given"
    try:
        old = json.loads(record.read_text())
    except (OSError, ValueError):
        return "afresh", [], "it holds no readable demo.json (the settings it was made with are unknown)"
    dataset_keys = [k for k in wanted if k != "iterations"]   # the runs check their own iterations below
    if not isinstance(old, dict) or any(old.get(k) != wanted[k] for k in dataset_keys):
        old = old if isinstance(old, dict) else {}
        diff = ", ".join(f"{k} {old.get(k)!r} (now {wanted[k]!r})" for k in dataset_keys
                         if old.get(k) != wanted[k])
        return "afresh", [], f"its dataset was made with other settings: {diff}"
    path = out / f"{load_scene(wanted['scene']).name}.h5"
    try:
        schema.validate(path, warn=False)
    except Exception:  # noqa: BLE001 - a missing, damaged or half-written dataset is made again
        return "afresh", [], f"its dataset {path.name} is missing or incomplete"
    done = []
    for name in VARIANT_ORDER:
        run = out / "runs" / name
        try:
            cfg = json.loads((run / "config.json").read_text())
        except (OSError, ValueError):
            continue
        if (run / "model.pt").is_file() and (run / "metrics.json").is_file() and \
                cfg.get("iterations") == wanted["iterations"]:
            done.append(name)
    return "reuse", done, ""


def describe_plan(out: Path, mode: str, done: list[str], why: str) -> str:
    if mode == "new":
        return f"demo: writing into {out}/"
    if mode == "afresh":
        return (f"demo: {out}/ holds an earlier demo, but {why}: starting afresh (its dataset and runs are made "
                "again and replace the old ones)")
    todo = [n for n in VARIANT_ORDER if n not in done]
    kept = (f"the finished runs {', '.join(done)}" if done else
            "no finished run of these settings")
    return (f"demo: {out}/ holds this demo's dataset and {kept}: reusing them"
            + (f", training {', '.join(todo)}" if todo else ", nothing to train")
            + " (pass --fresh to start afresh)")


# ------------------------------------------------------------------------- kernels, progress

def compile_kernels(scene_path: Path, seed: int, quiet: bool) -> bool:
    """Compile the CPU rasterizer's numba kernels here, once, before the trainings start in their own
    processes (which then load them from numba's cache instead of each compiling them at the same time).
    Does nothing when they are cached or the trainings run on CUDA. Returns whether it compiled."""
    import tempfile

    import torch

    from . import numba_cache
    from .splat import cpu

    if torch.cuda.is_available():
        return False
    from .splat import cpu_backward, cpu_tiles, project_cpu

    modules = [cpu, cpu_tiles, cpu_backward, project_cpu]
    if not numba_cache.missing_from_cache(modules):
        return False
    _say(quiet, "demo: compiling the CPU rasterizer kernels once for the three trainings (first run only, about "
                "a minute on 2 cores; cached for later runs)")
    numba_cache._NOTIFIED.add("splat-cpu")   # this process's notice is the line above
    from .train.config import TrainConfig
    from .train.trainer import Trainer

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ev3dgs-demo-compile-") as tmp:
        cfg = TrainConfig(scene=str(scene_path), iterations=2, init_points=200, seed=seed, checkpoint_every=2,
                          threads=1, sh_degree=0)
        Trainer(cfg, tmp, quiet=True).fit()
    _say(quiet, f"demo: kernels compiled in {time.perf_counter() - t0:.0f} s")
    return True


def _fmt_time(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def progress_line(name: str, state: dict | None, iterations: int, now: float) -> str:
    """One variant's line: steps, loss, elapsed and ETA (the elapsed time per step so far x steps left)."""
    if state is None:
        return f"{name:11s} waiting"
    if state.get("done"):
        return f"{name:11s} done: {iterations}/{iterations} steps in {_fmt_time(state['elapsed'])}"
    step, elapsed = state["step"], now - state.get("start", state["t0"])
    # the rate since the first report (the worker's start-up and data loading come before it)
    rate = (step - state.get("step0", 0)) / (now - state["t0"]) if now > state["t0"] else 0.0
    eta = (iterations - step) / rate if rate > 0 else float("nan")
    loss = f"loss {state['loss']:.5f}" if state.get("loss") is not None else "loss -"
    return (f"{name:11s} {step:>6d}/{iterations} steps ({100 * step / iterations:3.0f} %)  {loss}  "
            f"{_fmt_time(elapsed)} elapsed, ETA {_fmt_time(eta) if eta == eta else '-'}")


class Progress:
    """The trainings' progress, from a queue the workers put (name, step, loss) on: on a terminal the lines
    are redrawn in place twice a second; piped, one line per variant at every tenth of its steps."""

    def __init__(self, names: list[str], iterations: int, queue, stream=None, tty: bool | None = None):
        self.names, self.iterations, self.queue = names, iterations, queue
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty() if tty is None else tty
        self.state: dict[str, dict] = {}
        self._stop = threading.Event()
        self._drawn = 0
        self.start = time.perf_counter()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._drain()
        if self.tty:
            self._redraw()

    def _drain(self) -> None:
        import queue as _q

        while True:
            try:
                name, step, loss = self.queue.get_nowait()
            except (_q.Empty, EOFError, OSError):
                return
            now = time.perf_counter()
            st = self.state.setdefault(name, {"start": self.start, "t0": now, "step0": step, "step": 0,
                                              "loss": None, "printed": 0})
            if step < 0:        # the worker's "finished"
                st.update(done=True, elapsed=now - st["start"])
                if not self.tty:
                    self._print(progress_line(name, st, self.iterations, now))
                continue
            st.update(step=step, loss=loss)
            tenth = step * 10 // self.iterations
            if not self.tty and tenth > st["printed"]:
                st["printed"] = tenth
                self._print(progress_line(name, st, self.iterations, now))

    def _print(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def _redraw(self) -> None:
        now = time.perf_counter()
        lines = [progress_line(n, self.state.get(n), self.iterations, now) for n in self.names]
        up = f"\x1b[{self._drawn}F" if self._drawn else ""
        self.stream.write(up + "".join(f"\x1b[2K{line}\n" for line in lines))
        self.stream.flush()
        self._drawn = len(lines)

    def _loop(self) -> None:
        while not self._stop.wait(0.5):
            self._drain()
            if self.tty:
                self._redraw()


def _train_variant(item) -> dict:
    """One variant in a worker process: train (resuming from a checkpoint of an unfinished earlier demo),
    report progress on the queue, evaluate. The result has compare.compare_variants' shape."""
    name, cfg, run, queue = item
    from .train.evaluate import evaluate
    from .train.trainer import Trainer

    trainer = Trainer(cfg, run, quiet=True)   # loads the scene: not counted as training time
    clock = {"train": 0.0, "last": time.perf_counter(), "sent": 0.0}

    def on_step(tr, rec):
        now = time.perf_counter()
        clock["train"] += now - clock["last"]
        if now - clock["sent"] > 0.25 or tr.step == tr.cfg.iterations:
            queue.put((name, tr.step, float(rec.get("loss", float("nan")))))
            clock["sent"] = now
        clock["last"] = time.perf_counter()

    trainer.fit(resume=_resumable(Path(run), cfg.iterations), on_step=on_step)
    queue.put((name, -1, None))
    return {"name": name, "metrics": evaluate(run), "curve": [], "train_seconds": clock["train"],
            "iterations": cfg.iterations, "gaussians": len(trainer.model)}


def _resumable(run: Path, iterations: int) -> bool:
    """An unfinished run of an earlier demo with the same settings: its checkpoint is continued."""
    try:
        return (run / "ckpt.pt").is_file() and json.loads((run / "config.json").read_text()).get(
            "iterations") == iterations
    except (OSError, ValueError):
        return False


def train_variants(path: Path, runs: Path, base, names: list[str], jobs: int, quiet: bool) -> dict:
    """Train `names` (of compare.VARIANTS) side by side, with progress lines; {name: result}."""
    import multiprocessing as mp
    from dataclasses import replace

    from .train.compare import VARIANTS
    from .train.jobs import run_parallel

    manager = mp.get_context("spawn").Manager()
    try:
        queue = manager.Queue()
        items = [(n, replace(base, **VARIANTS[n], **({"threads": 1} if jobs > 1 else {})), runs / n, queue)
                 for n in names]
        items.sort(key=lambda it: bool(it[1].naive))   # the most expensive first
        if quiet:
            done = run_parallel(_train_variant, items, jobs)
        else:
            with Progress(names, base.iterations, queue):
                done = run_parallel(_train_variant, items, jobs)
    finally:
        manager.shutdown()
    return {r["name"]: {k: v for k, v in r.items() if k != "name"} for r in done}


def _finished(run: Path) -> dict:
    """The result of a finished run kept from an earlier demo (its metrics.json; the training time from its
    log)."""
    metrics = json.loads((run / "metrics.json").read_text())
    seconds = 0.0
    try:
        *_, last = (run / "log.jsonl").read_text().splitlines()
        seconds = float(json.loads(last).get("seconds", 0.0))
    except (OSError, ValueError):
        pass
    return {"metrics": metrics, "curve": [], "train_seconds": seconds, "iterations": metrics.get("iterations")}


# ------------------------------------------------------------------------------------- run

def run(out: Path, scene: str = "lego", seed: int = 0, iterations: int = DEMO_ITERATIONS, quiet: bool = False,
        train: bool = True, fresh: bool = False, **overrides) -> dict:
    t0 = time.perf_counter()
    out = Path(out)
    render = {**DEMO_RENDER, **overrides}
    wanted = settings(scene, seed, iterations, render)
    mode, done, why = plan(out, wanted, fresh)
    _say(quiet, describe_plan(out, mode, done, why))
    if mode == "reuse":
        path = out / f"{load_scene(scene).name}.h5"
        write_atomic(out / "demo.json", json.dumps(wanted, indent=2).encode())   # the iterations may be new
    else:
        (out / "demo.json").unlink(missing_ok=True)       # written again once the dataset is made
        path = make_scene(out, scene, seed, quiet, **render)
        if (out / "runs").is_dir():
            import shutil

            shutil.rmtree(out / "runs")                   # runs of another dataset: made again below
        write_atomic(out / "demo.json", json.dumps(wanted, indent=2).encode())
    result = {"path": path, "events": len(schema.read(path).events), "mode": mode, "reused_runs": done}
    if train:
        from .train.compare import summary_table
        from .train.config import TrainConfig

        base = TrainConfig(scene=str(path), iterations=iterations, init_points=5000, seed=seed)
        todo = [n for n in VARIANT_ORDER if n not in done]
        results = {n: _finished(out / "runs" / n) for n in done}
        if todo:
            compile_kernels(path, seed, quiet)
            # the variants train side by side, one process with one thread each, all at once even on 2 cores
            # (same results as one after the other): with a pool of 2 the short naive run waited for a long
            # one to finish and then ran alone (2 cores: 116 + 29 s); all at once share the cores (~128 s)
            _say(quiet, f"training {', '.join(todo)}: {iterations} steps each, side by side")
            results |= train_variants(path, out / "runs", base, todo, max(default_jobs(), len(todo)), quiet)
        results = {n: results[n] for n in VARIANT_ORDER}
        result["variants"] = {k: v["metrics"] for k, v in results.items()}
        write_atomic(out / "comparison.json", json.dumps(
            {k: {"test_psnr": v["metrics"]["test"]["psnr"], "test_ssim": v["metrics"]["test"]["ssim"],
                 "train_sharp_psnr": v["metrics"]["train_sharp"]["psnr"], "train_seconds": v["train_seconds"]}
             for k, v in results.items()}, indent=2).encode())
        if not quiet:
            print(f"training {iterations} steps per variant, then PSNR/SSIM against the sharp ground truth"
                  + (f" ({', '.join(done)} kept from the earlier demo)" if done else "") + ":")
            print(summary_table(results))
    _say(quiet, f"done in {time.perf_counter() - t0:.0f} s -> {out}/ (scene, runs/*/metrics.json, eval PNGs)")
    return result


def main(argv=None) -> int:
    from .cli.common import run as run_cli

    def _main(argv):
        ap = argparse.ArgumentParser(description="The whole chain on a --quick built-in scene.")
        ap.add_argument("--out", default="demo_out")
        ap.add_argument("--scene", default="lego")
        ap.add_argument("--iterations", type=int, default=None,
                        help=f"training steps per variant (default {DEMO_ITERATIONS}; {TEST_ITERATIONS} with "
                             "--test-size)")
        ap.add_argument("--seed", type=int, default=0)
        ap.add_argument("--fresh", action="store_true",
                        help="start afresh: make the dataset and every run again (default: off, a demo folder "
                             "made with the same settings is reused: its dataset and finished runs are kept)")
        ap.add_argument("--test-size", action="store_true",
                        help="a small demo to check that the chain runs, in a few minutes (3 views at 48x36, 2 "
                             f"samples, {TEST_ITERATIONS} steps); its numbers mean nothing (default: off)")
        args = ap.parse_args(argv)
        from .claims import claim_run

        claim_run(args.out)  # a second `make demo` on the same folder refuses at once (ev3dgs.claims)
        overrides = TEST_SIZE if args.test_size else {}
        iterations = args.iterations or (TEST_ITERATIONS if args.test_size else DEMO_ITERATIONS)
        try:
            run(Path(args.out), args.scene, args.seed, iterations, fresh=args.fresh, **overrides)
        except KeyboardInterrupt:
            from .cli.common import Interrupted

            if (Path(args.out) / "demo.json").is_file():   # the dataset is made: the runs can continue
                raise Interrupted("the same command continues: it reuses the dataset and the finished runs, and "
                                  "resumes the others from their last checkpoints") from None
            raise
        return 0

    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
