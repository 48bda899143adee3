"""tools/investigations: floor_tail's summary of the noise norm's excess residual against hand-computed
values and its spy on a resumed run with every floor option, exact_thresholds' pattern against the
simulator's own draw."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "investigations"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from exact_thresholds import drawn_multipliers  # noqa: E402
from floor_tail import measure, tail_summary  # noqa: E402
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


@pytest.mark.parametrize("opts", [dict(event_floor="mean", event_huber=0.0, densify_from="all"), {}])
def test_floor_tail_measures_a_resumed_run_with_any_floor_option(scene_path, tmp_path, opts):
    """floor_tail.measure resumes a run for two steps with the trainer's event loss wrapped, whatever the
    run's floor statistic and penalty (the wrapper passes them on), and summarises each step's excess; the
    run folder itself is left as it was."""
    from ev3dgs.train.trainer import Trainer

    run = tmp_path / "run"
    Trainer(cfg(scene_path, iterations=20, **opts), run, quiet=True).fit()
    before = (run / "log.jsonl").read_text()
    got = measure(run, 2)
    assert got["steps"] == 2 and set(got) == {"mean", "median", "top1", "top5", "steps"}
    assert np.isfinite([got[k] for k in ("mean", "median", "top1", "top5")]).all()
    assert 0 <= got["top1"] <= got["top5"] <= 1
    assert (run / "log.jsonl").read_text() == before
