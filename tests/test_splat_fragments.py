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
from fragments import fragment_stats, schedule_efficiency, subpose_coherence  # noqa: E402


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
    # per pixel: the histogram covers every pixel once and its weighted sum is the composited count
    h = np.asarray(st["composited_per_pixel"]["histogram"])
    assert h.sum() == W * H and (np.arange(len(h)) * h).sum() == st["composited"]
    assert st["composited_per_pixel"]["max"] == len(h) - 1
    # the ellipse's pixels are a part of the boxes', and hold every visited pixel that was composited
    assert st["composited"] <= st["box_pixels_in_ellipse"] <= st["box_pixels"]
    assert 0 <= st["entries_missing_tile"] < st["entries"]
    assert st["share_box_outside_ellipse"] == pytest.approx(1 - st["box_pixels_in_ellipse"] / st["box_pixels"])
    assert 0 < st["top5_share_per_tile"]["median"] <= 1


def test_box_pixels_inside_the_ellipse_match_a_brute_force_count():
    """One tilted Gaussian alone: the pixels of its box with sigma <= its (slightly inflated) cut-off,
    counted pixel by pixel in float64, are the statistics' ellipse pixels, and its box is the rest; the
    tiles its ellipse misses (box corners of a thin diagonal Gaussian) are counted as missing entries."""
    W = H = 64
    ang = math.radians(45)
    R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    cov = R @ np.diag([20.0 ** 2, 1.5 ** 2]) @ R.T
    q = np.linalg.inv(cov)
    conic = torch.tensor([[q[0, 0], q[0, 1], q[1, 1]]], dtype=torch.float32)
    m = torch.tensor([[31.3, 32.6]])
    o = torch.tensor([0.8])
    st = fragment_stats(m, conic, torch.ones(1, 3), o, torch.ones(1), torch.tensor([70]), W, H)
    qa, qb, qc = (float(v) for v in conic[0])
    # the spans' cut-off: sigma_max (float32) inflated against the kernel's rounding (cpu_tiles._span_params)
    smax = float(np.float32(math.log(float(np.float32(0.8)) * 255) + 1e-6))
    smax = smax * (1 + 4e-6 * qa * qc / (qa * qc - qb * qb)) + 1e-9
    inside = 0
    tiles_hit = set()
    for y in range(H):
        for x in range(W):
            dx, dy = x - 31.3, y - 32.6
            if 0.5 * (qa * dx * dx + qc * dy * dy) + qb * dx * dy <= smax:
                inside += 1
                tiles_hit.add((x // 16, y // 16))
    # the spans are widened by 1e-6 px against their own rounding: at most a boundary pixel or two more
    assert inside <= st["box_pixels_in_ellipse"] <= inside + 2 and inside > 100
    assert st["entries"] - st["entries_missing_tile"] == len(tiles_hit)
    assert st["entries_missing_tile"] > 0  # a diagonal needle's box holds tiles its ellipse never reaches


def test_subpose_coherence_counts_neighbours_out_of_order():
    d = np.array([[1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0], [2.0, 1.0, 3.0, 4.0], [1.0, 2.0, 4.0, 3.0]])
    r = np.ones((4, 4), np.int64)
    out = subpose_coherence(d, r)["vs_subpose_0"]
    assert out[0] == {"subpose": 1, "same_order": True, "neighbours_out_of_order": 0, "share_rank_changed": 0.0}
    assert not out[1]["same_order"] and out[1]["neighbours_out_of_order"] == 1 and out[1]["share_rank_changed"] == 0.5
    assert out[2]["neighbours_out_of_order"] == 1
    # a tie is in order only with the lower index first (the stable sort's tie rule)
    d2 = np.array([[1.0, 2.0], [2.0, 2.0]])
    assert subpose_coherence(d2, np.ones((2, 2), np.int64))["vs_subpose_0"][0]["same_order"]


def test_schedule_efficiency_of_a_round_robin_deal():
    # costs 8, 1, 1, 1 by list length order; 2 threads round robin: loads 8 + 1 = 9 and 1 + 1 = 2 -> 11 / 18
    eff = schedule_efficiency([8, 1, 1, 1], [4, 3, 2, 1], 2)
    assert eff["by_list_length"] == pytest.approx(11 / 18)
    # ordered by cost the deal is the same here; with list lengths that invert the costs it is worse
    assert schedule_efficiency([1, 1, 1, 8], [4, 3, 2, 1], 2)["by_list_length"] == pytest.approx(11 / 18)
    assert schedule_efficiency([4, 4, 4, 4], [1, 1, 1, 1], 4)["by_cost"] == 1.0
