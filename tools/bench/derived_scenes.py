"""Scene files derived from a scene's render cache (its sharp linear sub-frames and their poses), for the
bounds the fidelity studies measure against:

* "info": every sharp sub-frame of every exposure as a training image at its own pose, the most any
  deblurring could recover from these exposures (the information oracle);
* "ideal": each blurry frame as the trainer's blur model makes it from the sharp sub-frames (sRGB decoded,
  averaged in linear light, encoded);
* for a scene with frame noise, "clean" (the ISP's blurry frames without the noise) and "noisy" (the sharp
  frames with it).

Each is checked against the scene file first: the cached mid sub-frame must be its sharp frame and the cached
sub-frames must make its blurry frame, so a cache of other frames is refused.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

SUBFRAMES = 17   # the rendered sub-frames per exposure of the studies' and the benchmark's scenes
# Cycles on the CPU renders a scene again the same to float precision, not always to the bit (multithreaded
# sums): an 8-bit value within a float error (~1e-6 of full scale, a quarter of a thousandth of a level) of a
# rounding boundary lands one level apart, so about 5e-4 of the values may (a glossy built-in scene: 2e-5 to
# 2e-4). Frames that differ by more than one level, or at more than RENDER_FLIP_SHARE of their values, are
# other frames.
RENDER_FLIP_SHARE = 1e-3


def same_frames(a, b) -> bool:
    """Whether two uint8 frame stacks are the same render: equal shape, no value more than one level apart,
    at most RENDER_FLIP_SHARE of them (one, in a stack too small for that) one level apart."""
    a, b = np.asarray(a).astype(np.int16), np.asarray(b).astype(np.int16)
    if a.shape != b.shape:
        return False
    d = np.abs(a - b)
    return int(d.max(initial=0)) <= 1 and np.count_nonzero(d) <= max(1.0, RENDER_FLIP_SHARE * d.size)


def render_cache(scene_file: Path) -> Path:
    """The render cache make_dataset kept beside ``scene_file`` (``.STEM.cache-KEY/view_NNNN.npz``: the linear
    sub-frames of each view and their poses), as study_event_term's cells and bench_fidelity's scenes keep it."""
    found = _find_cache(scene_file)
    if found is None:
        raise SystemExit(f"no render cache beside {scene_file}: make the scene with its render cache kept")
    return found


def _find_cache(scene_file: Path) -> Path | None:
    found = sorted(p for p in scene_file.parent.glob(f".{scene_file.stem}.cache-*") if p.is_dir())
    return found[0] if found else None


def derived_scenes(spec_path: str, cell: Path, out_dir: Path) -> dict[str, Path]:
    """Write (once) the scene files made from ``cell`` and its render cache: "info" (every sharp sub-frame a
    view), "ideal" (blurry frames as the trainer's blur model makes them) and, for a scene with frame noise,
    "clean" (the ISP's blurry frames without the noise) and "noisy" (sharp frames with it)."""
    import torch

    from ev3dgs import schema
    from ev3dgs.sim.blur import blur_frames
    from ev3dgs.sim.dataset import _to_srgb
    from ev3dgs.sim.scenes import load_scene
    from ev3dgs.train.losses import linear_to_srgb_torch, srgb_to_linear_torch

    spec = load_scene(spec_path)
    isp, noise = spec.sensor.isp, spec.sensor.sensor_noise
    kinds = ("info", "ideal") + (("clean", "noisy") if noise is not None else ())
    names = {"info": "info_oracle.h5", "ideal": "blur_ideal.h5", "clean": "blur_clean.h5",
             "noisy": "sharp_noisy.h5"}
    paths = {k: out_dir / names[k] for k in kinds}
    if all(p.exists() for p in paths.values()):
        return paths
    sc = schema.read(cell)
    tr = sc.train
    cache = render_cache(cell)
    subs, sub_poses, ideal, clean, noisy = [], [], [], [], []
    for v in range(len(tr)):
        r = np.load(cache / f"view_{v:04d}.npz")
        frames, poses = r["frames"][:SUBFRAMES], r["poses"][:SUBFRAMES]
        mid = SUBFRAMES // 2
        if not np.allclose(poses[mid], tr.sharp_poses[v], atol=1e-9):
            raise SystemExit(f"{cache}: view {v}'s cached poses are not the scene's")
        srgb = np.stack([_to_srgb(f, spec) for f in frames])          # (17, H, W, 3) uint8, as /train/sharp
        if not same_frames(srgb[mid], tr.sharp[v]):
            raise SystemExit(f"{cache}: view {v}'s mid sub-frame is not the scene's sharp frame")
        # make_dataset's blurry frame (dataset seed 0: noise seed = view index): the cache is this scene's
        if not same_frames(blur_frames(frames, isp, noise, seed=v), tr.images[v]):
            raise SystemExit(f"{cache}: view {v}'s blurry frame does not come from these sub-frames")
        subs.append(srgb)
        sub_poses.append(poses)
        lin = srgb_to_linear_torch(torch.from_numpy(srgb).double() / 255.0).mean(dim=0)
        ideal.append(np.clip(np.rint(linear_to_srgb_torch(lin).numpy() * 255.0), 0, 255).astype(np.uint8))
        if noise is not None:
            clean.append(blur_frames(frames, isp, None))
            # the mid sub-frame through the same raw-domain noise (another stream than the blurry frame's)
            noisy.append(blur_frames(frames[mid:mid + 1], isp, noise, seed=1_000_003 + v))
    out_dir.mkdir(parents=True, exist_ok=True)
    rep = lambda a: np.repeat(np.asarray(a), SUBFRAMES, axis=0)  # noqa: E731
    made = {"info": replace(tr, images=np.concatenate(subs), exposure=rep(tr.exposure), poses=rep(tr.poses),
                            pose_t=rep(tr.pose_t), sharp=np.concatenate(subs),
                            sharp_poses=np.concatenate(sub_poses)),
            "ideal": replace(tr, images=np.stack(ideal))}
    if noise is not None:
        made |= {"clean": replace(tr, images=np.stack(clean)), "noisy": replace(tr, sharp=np.stack(noisy))}
    for kind, train in made.items():
        if not paths[kind].exists():
            schema.write(replace(sc, train=train), paths[kind])
    return paths


def ensure_render_cache(scene_file: Path, make, quiet: bool = True) -> Path:
    """The render cache beside ``scene_file``; where there is none (the file was made without keeping it),
    render the scene again into a temporary folder with ``make(out)`` (make_dataset with keep_cache, the same
    spec, render settings and dataset seed), check that the new file holds the same frames as ``scene_file``
    (same_frames: to within the rounding of a float render), and move its cache beside
    ``scene_file``. ``scene_file`` itself is never replaced."""
    import shutil

    from ev3dgs import schema

    found = _find_cache(scene_file)
    if found is not None:
        return found
    tmp = scene_file.parent / f".{scene_file.stem}.rerender"
    tmp.mkdir(exist_ok=True)
    # an interrupted earlier attempt: its render cache resumes the render (make_dataset), its file goes
    (tmp / scene_file.name).unlink(missing_ok=True)
    if not quiet:
        print(f"  {scene_file.name}: rendering again to keep its render cache", flush=True)
    make(tmp / scene_file.name)
    new, old = schema.read(tmp / scene_file.name), schema.read(scene_file)
    for part in ("train", "test"):
        a, b = getattr(new, part), getattr(old, part)
        for field in ("images", "sharp"):
            x, y = getattr(a, field, None), getattr(b, field, None)
            if (x is None) != (y is None) or (x is not None and not same_frames(x, y)):
                shutil.rmtree(tmp, ignore_errors=True)
                raise SystemExit(f"{scene_file}: rendering it again gives other {part} {field}; the file was made "
                                 "with other settings or another renderer: move it away to make it afresh")
    cache = render_cache(tmp / scene_file.name)
    target = scene_file.parent / cache.name
    cache.rename(target)
    shutil.rmtree(tmp, ignore_errors=True)
    return target
