"""tools/bench/fragments.py, the fragment statistics of the `cpu` rasterizer, against a brute-force compositor
of the reference rules (an independent count), and its schedule model against hand-computed loads."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ev3dgs.splat.project import project_gaussians

from test_splat_backends import scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "bench"))
from fragments import fragment_stats, schedule_efficiency  # noqa: E402


def brute_force(m, q, o, r, d, W, H):
    """Per pixel, the reference rules in float64: (composited, below the cut, behind a stopped pixel) over
    every visible Gaussian whose sigma lies in [0, ln(255 o)] (the kernels' cut-off ellipse)."""
    order = [g for g in np.argsort(d, kind="stable") if r[g] > 0]
    comp = 0
    for y in range(H):
        for x in range(W):
            T = 1.0
            for g in order:
                dx, dy = x - m[g, 0], y - m[g, 1]
                s = 0.5 * (q[g, 0] * dx * dx + q[g, 2] * dy * dy) + q[g, 1] * dx * dy
                if s < 0:
                    continue
                a = min(0.99, o[g] * math.exp(-s))
                if a < 1 / 255:
                    continue
                if T * (1 - a) < 1e-4:
                    break
                T *= 1 - a
                comp += 1
    return comp


@pytest.mark.parametrize("seed,opaque", [(3, False), (4, True)])
def test_composited_fragments_match_a_brute_force_count(seed, opaque):
    params, vm, K = scene(80, 24, seed=seed, dtype=torch.float32)
    if opaque:  # nearly opaque front layers: pixels stop, tiles finish early
        params[0][:8, 2] = 1.0 + 0.01 * torch.arange(8, dtype=torch.float32)
        params[2][:8] = 5.0
        params[3][:8] = 0.999
    W, H = 24, 20
    with torch.no_grad():
        pr = project_gaussians(params[0], params[1], params[2], params[3], vm, K, W, H)
    st = fragment_stats(pr.means2d, pr.conics, params[4], params[3], pr.depths, pr.radii, W, H)
    n = brute_force(pr.means2d.double().numpy(), pr.conics.double().numpy(), params[3].double().numpy(),
                    pr.radii.numpy(), pr.depths.double().numpy(), W, H)
    # the kernel's float32 sigma and alpha against float64 here: a fragment within rounding of a cut-off may
    # fall on the other side (none did when written; 2 of several hundred allowed)
    assert abs(st["composited"] - n) <= 2 and st["composited"] > 50
    assert st["fragments_per_pixel"] == pytest.approx(st["composited"] / (W * H))
    assert sum(st["per_tile"]["composited"]) == st["composited"]
    assert 0 <= st["share_below_cut"] < 1 and 0 <= st["share_behind"] < 1
    # every visited pixel lies in a visited row span of at most 16 pixels
    assert st["visited"] <= 16 * st["row_spans"] and 0 < st["lane_fill_16"] <= 1
    if opaque:  # pixels stopped, and whole tiles: their later entries were never visited
        assert st["share_behind"] > 0 and st["skipped_after_tile_done"] > 0


def test_schedule_efficiency_of_a_round_robin_deal():
    # costs 8, 1, 1, 1 by list length order; 2 threads round robin: loads 8 + 1 = 9 and 1 + 1 = 2 -> 11 / 18
    eff = schedule_efficiency([8, 1, 1, 1], [4, 3, 2, 1], 2)
    assert eff["by_list_length"] == pytest.approx(11 / 18)
    # ordered by cost the deal is the same here; with list lengths that invert the costs it is worse
    assert schedule_efficiency([1, 1, 1, 8], [4, 3, 2, 1], 2)["by_list_length"] == pytest.approx(11 / 18)
    assert schedule_efficiency([4, 4, 4, 4], [1, 1, 1, 1], 4)["by_cost"] == 1.0
