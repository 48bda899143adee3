"""`make demo`: the whole chain on the built-in default.

1. a --quick dataset of the lego scene (10 shaky views of 17 sub-frames over 100 ms exposures, 3 sharp test
   views, 96x72) rendered in Blender, with events and raw-domain blur;
2. three trainings on it: naive 3DGS on the blurry frames, the blur rendering loss alone, and blur + event
   rendering losses;
3. evaluation on the sharp test views and the deblurred training views, printed as a table.
Everything lands in demo_out/ (scene, runs with metrics.json and side-by-side PNGs, a strip per view).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from . import schema
from .cli.common import write_atomic
from .sim.dataset import make_dataset
from .sim.scenes import load_scene, resolve_render
from .train.jobs import default_jobs

DEMO_RENDER = dict(views=10, test_views=3)
DEMO_ITERATIONS = 1500


def event_image(ev, height, width) -> np.ndarray:
    """ON events red, OFF blue, on white (what DV shows); the majority polarity wins per pixel."""
    img = np.full((height, width, 3), 255, np.uint8)
    net = np.zeros((height, width), np.int64)
    np.add.at(net, (ev.y, ev.x), ev.p.astype(np.int64))
    img[net > 0] = (220, 40, 40)
    img[net < 0] = (40, 60, 220)
    return img


def view_strip(sc: schema.Scene, view: int) -> np.ndarray:
    """sharp | blurry | events of one training view, side by side (RGB uint8)."""
    start, end = sc.train.exposure[view]
    ev = sc.events.load().window(int(start), int(end) + 1)
    row = [np.asarray(sc.train.images[view]), event_image(ev, sc.camera.height, sc.camera.width)]
    if sc.train.sharp is not None:
        row.insert(0, np.asarray(sc.train.sharp[view]))
    return np.hstack([np.pad(im, ((2, 2), (2, 2), (0, 0)), constant_values=255) for im in row])


def make_scene(out: Path, scene: str = "lego", seed: int = 0, quiet: bool = False, **overrides) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    spec = load_scene(scene)
    render = resolve_render(spec, quick=True, **overrides)
    path = out / f"{spec.name}.h5"
    # two Blender workers overlap one view's scene set-up and denoising with another's render (Cycles already
    # uses every core): 17.3 -> 16.2 s for the demo scene on 2 cores, the same file bit for bit
    stats = make_dataset(spec, render, path, seed=seed, quiet=quiet, workers=min(2, default_jobs()))
    sc = schema.read(path)
    for v in range(len(sc.train)):
        png = cv2.imencode(".png", cv2.cvtColor(view_strip(sc, v), cv2.COLOR_RGB2BGR))[1]
        write_atomic(out / f"{spec.name}_view{v}.png", png.tobytes())
    if not quiet:
        sec = stats.seconds
        print(f"dataset: {spec.name} --quick, {render.views} views x {render.subframes} sub-frames + "
              f"{render.test_views} test views at {render.width}x{render.height}: {len(sc.events)} events; "
              f"render {sec['render']:.0f} s, simulate+ISP+write {sec['simulate'] + sec['isp'] + sec['write']:.2f} s")
    return path


def run(out: Path, scene: str = "lego", seed: int = 0, iterations: int = DEMO_ITERATIONS, quiet: bool = False,
        train: bool = True, **overrides) -> dict:
    t0 = time.perf_counter()
    path = make_scene(out, scene, seed, quiet, **{**DEMO_RENDER, **overrides})
    result = {"path": path, "events": len(schema.read(path).events)}
    if train:
        from .train.compare import compare_variants, summary_table
        from .train.config import TrainConfig

        base = TrainConfig(scene=str(path), iterations=iterations, init_points=5000, seed=seed)
        # the three variants train side by side, one process with one thread each, all three at once even on
        # 2 cores (same results as one after the other): with a pool of 2 the short naive run waited for a
        # long one to finish and then ran alone (2 cores: 116 + 29 s); all at once share the cores (~128 s)
        results = compare_variants(path, out / "runs", base, quiet=True, jobs=max(default_jobs(), 3))
        result["variants"] = {k: v["metrics"] for k, v in results.items()}
        write_atomic(out / "comparison.json", json.dumps(
            {k: {"test_psnr": v["metrics"]["test"]["psnr"], "test_ssim": v["metrics"]["test"]["ssim"],
                 "train_sharp_psnr": v["metrics"]["train_sharp"]["psnr"], "train_seconds": v["train_seconds"]}
             for k, v in results.items()}, indent=2).encode())
        if not quiet:
            print(f"training {iterations} steps per variant, then PSNR/SSIM against the sharp ground truth:")
            print(summary_table(results))
    if not quiet:
        print(f"done in {time.perf_counter() - t0:.0f} s -> {out}/ (scene, runs/*/metrics.json, eval PNGs)")
    return result


def main(argv=None) -> int:
    from .cli.common import run as run_cli

    def _main(argv):
        ap = argparse.ArgumentParser(description="The whole chain on a --quick built-in scene.")
        ap.add_argument("--out", default="demo_out")
        ap.add_argument("--scene", default="lego")
        ap.add_argument("--iterations", type=int, default=DEMO_ITERATIONS)
        ap.add_argument("--seed", type=int, default=0)
        args = ap.parse_args(argv)
        run(Path(args.out), args.scene, args.seed, args.iterations)
        return 0

    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
