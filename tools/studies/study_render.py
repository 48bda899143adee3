"""Study: Cycles samples per pixel and the denoiser against image noise and seconds per frame.

Renders one view of a built-in scene at several sample counts, without OpenImageDenoise and with it (its
albedo and normal guides prefiltered "accurate", as the default, or "fast", as --quick), and scores each
against a high-sample reference (no denoiser) by PSNR of the sRGB-encoded image. Runs Blender in a
child process (bpy state is global).

    python tools/studies/study_render.py [--quick] [--scene lego] --json tools/results/study_render.json
    python tools/studies/study_render.py --size 346x260 --spp 4 8 16 32 --json tools/results/study_render_346x260.json
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import pareto_plot, save_json


def child(args) -> None:
    from ev3dgs.geometry import intrinsics, look_at
    from ev3dgs_blender import render

    W, H = args.size
    K = intrinsics(W, H, 40.0)
    pose = look_at([3.2, -2.2, 1.6], [0, 0, 0])[None]
    out = {}
    for spp, denoise in args.configs:  # denoise: "" (off) or OIDN's guide prefilter
        render.init_scene(args.scene, {}, None, W, H, K.tolist(), samples=spp, denoise=bool(denoise),
                          background=(1.0, 1.0, 1.0), seed=0, denoise_prefilter=denoise or "accurate")
        render.render(pose)  # warm-up (kernel load, BVH)
        t0 = time.perf_counter()
        frames, _ = render.render(np.repeat(pose, 2, axis=0))
        out[f"{spp}_{denoise or 'off'}"] = ((time.perf_counter() - t0) / 2, frames[0])
    np.savez(args.out, **{k: v[1] for k, v in out.items()}, times=json.dumps({k: v[0] for k, v in out.items()}))


def psnr_srgb(a, b) -> float:
    from ev3dgs.sim.isp import linear_to_srgb

    x, y = linear_to_srgb(a), linear_to_srgb(b)
    return float(10 * np.log10(1.0 / max(np.mean((x - y) ** 2), 1e-12)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--json", default="tools/results/study_render.json")
    ap.add_argument("--plot", default="tools/results/study_render.png")
    ap.add_argument("--size", help="image size WxH (default 200x150; --quick 96x72)")
    ap.add_argument("--spp", type=int, nargs="+", help="sample counts (default 1 4 8 16 64 256; --quick up to 64)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    size = tuple(int(x) for x in args.size.split("x")) if args.size else (96, 72) if args.quick else (200, 150)
    spps = args.spp or ((1, 4, 8, 16, 64) if args.quick else (1, 4, 8, 16, 64, 256))
    ref_spp = 1024
    if args.child:
        ns = argparse.Namespace(**json.loads(args.child))
        ns.configs = [tuple(c) for c in ns.configs]
        child(ns)
        return 0
    modes = {"": "no denoiser", "accurate": "OpenImageDenoise", "fast": "OpenImageDenoise, fast prefilter"}
    configs = [(s, d) for s in spps for d in modes] + [(ref_spp, "")]
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "r.npz"
        spec = json.dumps({"scene": args.scene, "size": size, "configs": configs, "out": str(out)})
        subprocess.run([sys.executable, __file__, "--child", spec], check=True, stdout=subprocess.DEVNULL)
        z = np.load(out)
        times = json.loads(str(z["times"]))
        ref = z[f"{ref_spp}_off"]
        rows = {name: [] for name in modes.values()}
        for s, dn in configs[:-1]:
            key = f"{s}_{dn or 'off'}"
            r = {"label": s, "samples": s, "denoise": bool(dn), "prefilter": dn or None,
                 "seconds_per_frame": times[key], "psnr_vs_reference": psnr_srgb(z[key], ref)}
            rows[modes[dn]].append(r)
            print(f"{s:5d} spp {modes[dn]:33s}: {r['psnr_vs_reference']:6.2f} dB, {times[key]:.3f} s/frame")
    save_json(args.json, {"scene": args.scene, "size": list(size), "reference_spp": ref_spp,
                          "reference_seconds_per_frame": times[f"{ref_spp}_off"], "rows": rows})
    pareto_plot(args.plot, rows, "seconds_per_frame", "psnr_vs_reference", "seconds per frame (2 cores)",
                f"PSNR vs {ref_spp} spp (dB)", f"Rendering: Cycles samples and denoiser ({size[0]}x{size[1]})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
