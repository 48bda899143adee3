"""The docs pictures (docs/scenes.png): for each built-in scene, one view's sharp frame | blurry frame | events (ON red, OFF
blue), from a small real make-dataset run.

    python tools/studies/scene_gallery.py --out docs/scenes.png
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from ev3dgs import schema
from ev3dgs.demo import view_strip
from ev3dgs.sim.dataset import make_dataset
from ev3dgs.sim.scenes import builtin_scenes, load_scene, resolve_render


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/scenes.png")
    ap.add_argument("--size", default="192x144")
    ap.add_argument("--samples", type=int, default=32)
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for name in builtin_scenes():
            spec = load_scene(name)
            render = resolve_render(spec, quick=True, width=w, height=h, views=1, test_views=0,
                                    samples=args.samples)
            make_dataset(spec, render, Path(d) / f"{name}.h5", quiet=True)
            img = view_strip(schema.read(Path(d) / f"{name}.h5"), 0)
            label = np.full((18, img.shape[1], 3), 255, np.uint8)
            cv2.putText(label, f"{name}: sharp | blurry (100 ms, shake) | events", (4, 13),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
            rows.append(np.vstack([label, img]))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(np.vstack(rows), cv2.COLOR_RGB2BGR))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
