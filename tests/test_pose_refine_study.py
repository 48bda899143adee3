"""The pose-refinement study end to end on a small simulated scene (slow: simulates a scene and trains three
times). Verification on a known trajectory: every training view's poses are moved by 1 degree and 2% of the
camera distance; refinement must reduce the mid-exposure rotation error against the truth and beat training
on the perturbed poses in blur-view PSNR, and eval must report aligned and unaligned novel views."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "investigations"))


@pytest.mark.slow
def test_refinement_reduces_pose_error_and_improves_blur_views(tmp_path):
    import study_refine

    out = tmp_path / "study.json"
    assert study_refine.main(["--quick", "--size", "48x36", "--views", "6", "--iterations", "400",
                              "--pose-frame", "world", "camera",
                              "--json", str(out), "--plot", str(tmp_path / "study.png")]) == 0
    d = json.loads(out.read_text())
    before = d["pose_errors_before"]
    assert abs(before["rotation_deg_mean_unaligned"] - 1.0) < 1e-6  # the perturbation is what it says
    assert d["pose_frames"] == ["world", "camera"]
    refined = {v["pose_frame"]: v for k, v in d["runs"].items() if "refine" in k}
    assert sorted(refined) == ["camera", "world"]
    pert, true = d["runs"]["perturbed"], d["runs"]["true poses"]
    # a statistical outcome of one seeded run (the optimisation is deterministic on the CPU): the study at
    # 64x48 / 500 steps measured 1.00 -> 0.79 deg and +5.0 dB; the bounds ask for the direction and a margin.
    # Here (48x36, 400 steps) seen: 0.95 -> 0.87 (world) / 0.86 (camera) deg, +4.4 dB in both frames
    for ref in refined.values():
        assert ref["pose_errors_after"]["rotation_deg_median"] < before["rotation_deg_median"]
        assert ref["blur_view_psnr"] > pert["blur_view_psnr"] + 1.0
        assert ref["blur_view_psnr"] > pert["blur_view_psnr_training_poses"]
        assert "novel_view_psnr_unaligned" in ref and ref["pose_steps_skipped"] == 0
    assert true["blur_view_psnr"] > pert["blur_view_psnr"]
    assert (tmp_path / "study.png").stat().st_size > 0


@pytest.mark.slow
def test_pose_only_refinement_against_a_frozen_scene(tmp_path):
    """tools/investigations/refine_frozen.py: against a scene trained on the true poses and then frozen, only the cameras
    can move, so the images' disagreement must go down by moving them (the reprojection error of the scene's
    points, the quantity the loss sees), and the Gaussians must come out bit for bit as they went in."""
    import refine_frozen
    import torch

    from ev3dgs.demo import make_scene

    scene = make_scene(tmp_path / "scene", quiet=True, width=48, height=36, views=6, test_views=2)
    out = tmp_path / "frozen.json"
    assert refine_frozen.main(["--scene", str(scene), "--seeds", "0", "--scene-steps", "300", "--pose-steps", "200",
                               "--keep", str(tmp_path / "runs"), "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    row = d["per_seed"][0]
    assert d["scene_from"] == "true" and abs(row["before"]["rotation_deg_median_unaligned"] - 1.0) < 1e-6
    # seen at this size (48x36, 6 views, 300 + 200 steps): 1.35 -> 0.21 px; asked: a clear drop
    assert row["after"]["reprojection_px_median"] < 0.7 * row["before"]["reprojection_px_median"]
    known = torch.load(tmp_path / "runs" / "known" / "model.pt", weights_only=False)["model"]
    frozen = torch.load(tmp_path / "runs" / "frozen_s0" / "model.pt", weights_only=False)["model"]
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN"):
        assert torch.equal(known[name], frozen[name]), name
