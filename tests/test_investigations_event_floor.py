"""tools/investigations: floor_tail's summary of the noise norm's excess residual against hand-computed
values, exact_thresholds' pattern against the simulator's own draw, event_weighting's penalty against its
formula and its wrappers against the unwrapped trainer."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "investigations"))

sys.path.insert(0, str(Path(__file__).resolve().parent))

from exact_thresholds import drawn_multipliers  # noqa: E402
from floor_tail import tail_summary  # noqa: E402
from test_train import cfg, scene_path  # noqa: E402,F401  (the small blob scene and its settings)


def test_tail_summary_of_1_to_100_with_negatives():
    """1..100 plus 100 values of -1 (negative excess counts in the mean and median, not in the shares):
    mean (5050 - 100) / 200, lower median -1 (the 100th of 200 sorted values), top 1 % = the 2 largest of
    the positive part (200 // 100), top 5 % = the 10 largest."""
    x = torch.cat([torch.arange(1, 101, dtype=torch.float64), -torch.ones(100, dtype=torch.float64)])
    s = tail_summary(x[torch.randperm(200, generator=torch.Generator().manual_seed(0))])
    assert s["mean"] == pytest.approx(4950 / 200, rel=1e-15)
    assert s["median"] == -1.0
    assert s["top1"] == pytest.approx((100 + 99) / 5050, rel=1e-15)
    assert s["top5"] == pytest.approx(sum(range(91, 101)) / 5050, rel=1e-15)
    assert tail_summary(-torch.ones(10))["top1"] == 0.0      # no positive excess: no share, no division by 0


def test_drawn_multipliers_are_the_scene_files_mismatch():
    """ficus is simulated with thresholds 0.2 and a mismatch sigma of 0.03: the drawn multipliers have mean 1
    and spread 0.15 to within sampling error (6912 pixels per polarity: 4 standard errors), ON and OFF
    drawn independently; a second draw is the same (seeded)."""
    m = drawn_multipliers("ficus", 72, 96)
    assert m.shape == (2, 72, 96)
    n = m[0].size
    for pol in m:
        assert abs(pol.mean() - 1) < 4 * 0.15 / np.sqrt(n)
        assert abs(pol.std() - 0.15) < 4 * 0.15 / np.sqrt(2 * n)
    assert abs(np.corrcoef(m[0].ravel(), m[1].ravel())[0, 1]) < 4 / np.sqrt(n)
    assert np.array_equal(m, drawn_multipliers("ficus", 72, 96))


def test_huber_is_the_square_within_c_and_linear_in_the_residual_beyond():
    """x <= c^2: x; beyond, 2 c sqrt(x) - c^2, which meets x at c^2 with the same slope (1) and at x = 4 c^2
    is 3 c^2; c = 0 leaves x as it is."""
    from event_weighting import huber

    c = 3.0
    x = torch.tensor([0.0, 4.0, 9.0, 36.0, 1e6], dtype=torch.float64)
    assert huber(x, c).tolist() == pytest.approx([0.0, 4.0, 9.0, 27.0, 6e3 - 9.0], rel=1e-15)
    t = torch.tensor([9.0 - 1e-6, 9.0 + 1e-6], dtype=torch.float64)
    slopes = (huber(t + 1e-7, c) - huber(t, c)) / 1e-7
    assert slopes.tolist() == pytest.approx([1.0, 1.0], abs=1e-6)
    assert torch.equal(huber(x, 0.0), x)


def test_event_weighting_with_its_defaults_is_the_trainer_bit_for_bit(scene_path, tmp_path, monkeypatch):
    """The probe's wrappers (event loss, blur loss, densification hooks) with the default floor, no penalty
    and all-loss densification change nothing: the same parameters to the bit after 25 steps. With all three
    changes the run differs and stays finite."""
    import ev3dgs.splat.strategy as strategy
    import ev3dgs.train.trainer as trainer
    from event_weighting import _patch

    from ev3dgs.train.trainer import Trainer

    for owner, name in ((trainer, "noise_event_loss"), (trainer, "average_loss"),
                        (strategy.DefaultStrategy, "step_pre_backward"),
                        (strategy.DefaultStrategy, "step_post_backward")):
        monkeypatch.setattr(owner, name, getattr(owner, name))   # restored after the test
    params = {}
    for name, patch in (("plain", None), ("defaults", ("mean", 0.0, False)), ("all", ("median", 3.0, True))):
        if patch:
            _patch(*patch)
        tr = Trainer(cfg(scene_path, iterations=25), tmp_path / name, quiet=True)
        tr.fit()
        params[name] = {k: p.detach().clone() for k, p in tr.model.params.items()}
    assert params["plain"].keys() == params["defaults"].keys()
    for k in params["plain"]:
        assert torch.equal(params["plain"][k], params["defaults"][k]), k
    assert any(params["all"][k].shape != params["plain"][k].shape or not torch.equal(params["all"][k],
                                                                                       params["plain"][k])
               for k in params["plain"])
    assert all(torch.isfinite(p).all() for p in params["all"].values())
