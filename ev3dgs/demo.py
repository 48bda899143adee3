"""`make demo`: the toolkit's main job on the built-in default, a --quick dataset of the lego scene.

Renders 4 shaky views (17 sub-frames over a 100 ms exposure each) and 2 sharp test views in Blender,
simulates events and raw-domain blur, writes demo_out/lego.h5 (validated against the schema) and a
sharp | blurry | events PNG per view, and prints where the time went. The trainer joins the chain later.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from . import schema
from .cli.common import write_atomic
from .sim.dataset import make_dataset
from .sim.scenes import load_scene, resolve_render


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


def run(out: Path, scene: str = "lego", seed: int = 0, quiet: bool = False, **overrides) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    spec = load_scene(scene)
    render = resolve_render(spec, quick=True, **overrides)
    path = out / f"{spec.name}.h5"
    stats = make_dataset(spec, render, path, seed=seed, quiet=quiet)
    sc = schema.read(path)
    for v in range(len(sc.train)):
        png = cv2.imencode(".png", cv2.cvtColor(view_strip(sc, v), cv2.COLOR_RGB2BGR))[1]
        write_atomic(out / f"{spec.name}_view{v}.png", png.tobytes())
    if not quiet:
        sec = stats.seconds
        print(f"ev3dgs demo: scene {spec.name!r} --quick: {render.views} views x {render.subframes} sub-frames "
              f"+ {render.test_views} test views at {render.width}x{render.height}, {render.samples} spp")
        print(f"  {len(sc.events)} events; render {sec['render']:.1f} s, simulate {sec['simulate']:.2f} s, "
              f"ISP {sec['isp']:.2f} s, write {sec['write']:.2f} s")
        psnr = [_psnr(np.asarray(sc.train.images[v]), np.asarray(sc.train.sharp[v])) for v in range(len(sc.train))]
        print("  blurry vs sharp PSNR per view: " + ", ".join(f"{p:.1f} dB" for p in psnr))
        print(f"  wrote {path} (valid) and {spec.name}_view*.png (sharp | blurry | events)")
    return {"path": path, "events": len(sc.events), "stats": stats}


def _psnr(a, b) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def main(argv=None) -> int:
    from .cli.common import run as run_cli

    def _main(argv):
        ap = argparse.ArgumentParser(description="Make a --quick dataset of a built-in scene.")
        ap.add_argument("--out", default="demo_out")
        ap.add_argument("--scene", default="lego")
        ap.add_argument("--seed", type=int, default=0)
        args = ap.parse_args(argv)
        run(Path(args.out), args.scene, args.seed)
        return 0

    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
