"""A scene file made without Blender: a cloud of coloured Gaussian blobs seen from a shaky orbit.

Each training view is `subframes` sharp renders (our rasterizer) along a drifting camera path over a 100 ms
exposure; the blurry frame is their mean in linear light, the events come from the simulator fed the linear
sub-frames, the sharp frame is the middle sub-frame; two sharp test views. For tests, `tools/gpu_check.py`
and anyone who wants a scene file in seconds without the Blender extra.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def blob_scene(path, width: int, height: int, views: int = 6, subframes: int = 5, n: int = 300, seed: int = 0,
               backend: str = "cpu", name: str = "blobs", source: str = "ev3dgs.blob_scene") -> Path:
    """Write the scene to `path` (folders created) and return it."""
    import torch

    from . import schema
    from .events import Events
    from .geometry import intrinsics, look_at
    from .sim import DVSSimulator
    from .sim.isp import linear_to_srgb, srgb_to_linear
    from .splat.model import GaussianModel
    from .splat.rasterize import rasterization

    path = Path(path)
    rng = np.random.default_rng(seed)
    truth = GaussianModel.from_points(rng.uniform(-0.6, 0.6, (n, 3)), rng.integers(30, 255, (n, 3)).astype(np.uint8),
                                      sh_degree=0, init_opacity=0.8)
    K = intrinsics(width, height, 50)
    Kt = torch.as_tensor(K, dtype=torch.float32)

    def draw(c2w):
        vm = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
        with torch.no_grad():
            img, _, _ = rasterization(truth.means, truth.quats_normalised, truth.scales, truth.opacities, truth.sh,
                                      vm, Kt, width, height, sh_degree=0, background=torch.ones(3), backend=backend)
        return img.clamp(0, 1).numpy()

    sim = DVSSimulator(height, width)
    imgs, sharp, sharp_poses, poses, pose_t, exposure, parts = [], [], [], [], [], [], []
    for v in range(views):
        az = 2 * np.pi * v / views
        eye = 3.0 * np.array([np.cos(az), np.sin(az), 0.5])
        t = v * 150_000 + np.linspace(0, 100_000, subframes).astype(np.int64)
        drift = rng.normal(0, 0.3, 3)
        ps = [look_at(eye + drift * (k / (subframes - 1) - 0.5), [0, 0, 0]) for k in range(subframes)]
        frames = np.stack([draw(p) for p in ps])
        lin = srgb_to_linear(frames)
        sim.restart()
        parts.append(sim.feed(lin.astype(np.float32), t))
        imgs.append((linear_to_srgb(lin.mean(0)) * 255 + 0.5).astype(np.uint8))
        sharp.append((frames[subframes // 2] * 255 + 0.5).astype(np.uint8))
        sharp_poses.append(ps[subframes // 2])
        poses.append(np.stack(ps))
        pose_t.append(t)
        exposure.append((t[0], t[-1]))
    test_poses = [look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.4]), [0, 0, 0]) for a in (0.5, 2.5)]
    sc = schema.Scene(
        name=name, source=source, camera=schema.Camera(width, height, K=K, background=(1.0, 1.0, 1.0)),
        events=Events.concatenate(parts), sensor=schema.EventSensor(), bounds=np.array([[-0.7] * 3, [0.7] * 3]),
        train=schema.Train(images=np.stack(imgs), exposure=np.array(exposure), poses=np.stack(poses),
                           pose_t=np.stack(pose_t), sharp=np.stack(sharp), sharp_poses=np.stack(sharp_poses)),
        test=schema.Test(images=np.stack([(draw(p) * 255 + 0.5).astype(np.uint8) for p in test_poses]),
                         poses=np.stack(test_poses)))
    path.parent.mkdir(parents=True, exist_ok=True)
    schema.write(sc, path)
    return path
