"""A recording made by `ev3dgs-sim record` goes through `ev3dgs-ingest davis` with poses and `ev3dgs train`."""
import importlib.util

import numpy as np
import pytest

from ev3dgs import schema
from ev3dgs.cli import ingest
from ev3dgs.cli import main as cli
from ev3dgs.cli import sim as sim_cli

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="needs bpy")]


def test_record_ingest_with_poses_then_train(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "studies"))
    from record_chain import poses_vs_truth

    rec = tmp_path / "lego.aedat4"
    assert sim_cli.main(["record", "--scene", "lego", "--out", str(rec), "--seconds", "1.5", "--size", "173x130",
                         "--render-rate", "100", "--samples", "4", "--quiet"]) == 0
    scene = tmp_path / "lego.h5"
    assert ingest.main(["davis", str(rec), "--out", str(scene), "--calibration",
                        str(tmp_path / "lego.calibration.toml"), "--quiet"]) == 0
    sc = schema.read(scene)
    assert len(sc.train) >= 0.9 * 15 and sc.train.poses.shape[1] == 5 and sc.points is not None
    err = poses_vs_truth(scene, rec.with_suffix(".trajectory.npz"))
    assert err["rotation_deg_median"] < 2.0 and err["centre_error_rel_extent"] < 0.05, err
    assert cli.main(["train", str(scene), "--out", str(tmp_path / "run"), "--iterations", "20",
                     "--set", "init_points=500", "--quiet"]) == 0
    log = (tmp_path / "run" / "log.jsonl").read_text().splitlines()
    assert len(log) == 20 and np.isfinite([__import__("json").loads(x)["loss"] for x in log]).all()
