"""Training on the `cuda` backend (marked ``gpu``: runs only where CUDA and gsplat's kernels are; skipped
elsewhere, run by tools/gpu_check.py).

The same scene, seed and settings on the `cpu` backend are the independent answer for the first step: both
start from the same Gaussians and draw the same view, so the first blur loss differs only by the rasterizers'
pixel differences. tests/test_gsplat_parity.py bounds those (at most 1 % of the pixels differ by more than
1e-4, none by more than 0.02), so the mean absolute pixel difference is at most 0.01 * 0.02 + 1e-4 = 3e-4;
the blur loss, (1 - 0.2) L1 + 0.2 (1 - SSIM), moves by at most that for its L1 part, and SSIM, whose local
means and variances are 7x7 averages of those pixels, by a few times it: 2e-3 bounds the sum with room."""
import math

import numpy as np
import pytest
import torch

from ev3dgs.blob_scene import blob_scene
from ev3dgs.train.config import TrainConfig
from ev3dgs.train.trainer import Trainer

pytestmark = pytest.mark.gpu


def _first_and_run(tmp_path, backend, device, steps, **kw):
    scene = tmp_path / "blobs.h5"
    if not scene.exists():
        blob_scene(scene, 64, 48, views=3, subframes=5, n=200, seed=1)
    cfg = TrainConfig(scene=str(scene), iterations=steps, init_points=2000, seed=0, device=device, backend=backend,
                      checkpoint_every=steps, **kw)
    recs = []
    trainer = Trainer(cfg, tmp_path / f"run_{backend}", quiet=True)
    trainer.fit(on_step=lambda tr, rec: recs.append(rec))
    return trainer, recs


@pytest.mark.parametrize("kw", [dict(), dict(refine_poses=True, pose_start=5, pose_warmup=5)],
                         ids=["blur+event", "blur+event+refine-poses"])
def test_cuda_training_agrees_with_cpu_at_the_first_step_and_stays_finite(tmp_path, kw):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    _, cpu = _first_and_run(tmp_path, "cpu", "cpu", 1, **kw)
    trainer, gpu = _first_and_run(tmp_path, "cuda", "cuda", 60, **kw)
    assert gpu[0]["view"] == cpu[0]["view"]
    assert abs(gpu[0]["blur"] - cpu[0]["blur"]) <= 2e-3
    for rec in gpu:  # the trainer stops on a non-finite loss or gradient; the log must say finite too
        assert all(math.isfinite(rec[k]) for k in ("loss", "blur", "event", "psnr_blurry"))
    for name, p in trainer.model.params.items():
        assert torch.isfinite(p).all(), name
    first = sum(r["blur"] for r in gpu[:5]) / 5
    last = sum(r["blur"] for r in gpu[-5:]) / 5
    assert last < first  # it fits: the blur loss falls
    if kw.get("refine_poses"):  # camera gradients reached the corrections through gsplat's view matrices
        table = trainer.term("poses").refiner.table()
        assert np.isfinite(table).all() and np.abs(table).max() > 0
