"""tools/investigations/refine_observability.py: the ratios and per-size statistics it reports, on hand-made study JSON whose
answers are known (single-seed and --seeds layouts of tools/investigations/study_refine.py)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "investigations"))


def _study(size, its, seed, rot, rep, cen):
    err = lambda r, p, c: {"rotation_deg_median": r, "reprojection_px_median": p, "centre_error_median": c}  # noqa
    return {"size": size, "iterations": its, "seed": seed, "fov_deg": 40.0, "views": 8,
            "pose_errors_before": err(*rot[:1], *rep[:1], *cen[:1]),
            "runs": {"perturbed": {}, "perturbed + refine (lr 0.003)": {"pose_errors_after": err(rot[1], rep[1],
                                                                                                   cen[1])}}}


def test_ratios_and_seed_statistics(tmp_path):
    import refine_observability as ro

    one = tmp_path / "one.json"
    one.write_text(json.dumps(_study("64x48", 1500, 0, (1.0, 0.64), (2.0, 0.5), (0.08, 0.04))))
    many = tmp_path / "many.json"
    many.write_text(json.dumps({"per_seed": [_study("96x72", 500, 0, (1.0, 0.8), (4.0, 1.0), (0.1, 0.1)),
                                             _study("96x72", 500, 1, (0.5, 0.5), (2.0, 1.0), (0.1, 0.05))]}))
    out = tmp_path / "obs.json"
    assert ro.main([str(one), str(many), "--json", str(out), "--plot", str(tmp_path / "obs.png")]) == 0
    d = json.loads(out.read_text())
    g = {(s["size"], s["iterations"]): s for s in d["summary"]}
    assert g["64x48", 1500]["rotation_ratio"]["mean"] == pytest.approx(0.64)
    assert g["64x48", 1500]["reprojection_ratio"]["mean"] == pytest.approx(0.25)
    # two seeds: ratios 0.8 and 1.0 -> mean 0.9, sample std |0.8 - 1.0| / sqrt(2)
    assert g["96x72", 500]["rotation_ratio"]["mean"] == pytest.approx(0.9)
    assert g["96x72", 500]["rotation_ratio"]["std"] == pytest.approx(0.2 / 2 ** 0.5)
    assert g["96x72", 500]["centre_ratio"]["values"] == pytest.approx([1.0, 0.5])
    assert (tmp_path / "obs.png").stat().st_size > 0


def test_missing_learning_rate_is_a_clear_error(tmp_path):
    import refine_observability as ro

    one = tmp_path / "one.json"
    one.write_text(json.dumps(_study("64x48", 500, 0, (1.0, 0.5), (1.0, 0.5), (1.0, 0.5))))
    with pytest.raises(SystemExit, match="no refined run"):
        ro.main([str(one), "--pose-lr", "1e-2", "--json", str(tmp_path / "o.json"),
                 "--plot", str(tmp_path / "o.png")])
