"""Where a `cpu` rasterizer call's fragments go: a counting replica of the forward's visiting order.

`fragment_stats(means2d, conics, colors, opacities, depths, radii, width, height)` bins and packs exactly as
`rasterize_cpu` does (the same cpu_tiles kernels) and walks every (tile, Gaussian) entry's row spans in depth
order like the forward kernel, classifying every pixel it visits:

* ``composited``: a fragment (alpha >= 1/255 and the pixel still open): the work that makes the image;
* ``below_cut``: sigma outside [0, sigma_max] or alpha < 1/255 (inside the span's conservative bounds but
  contributing nothing);
* ``behind``: the pixel already stopped (its next T would have fallen below 1e-4);
* ``after_tile_done``: entries never visited because every pixel of their tile had stopped (the tile loop's
  early exit), counted as the span pixels they would have visited.

Per tile it also reports the fragments composited by Gaussians whose box covers the whole tile ("huge":
radius >= a tile), so a tile "dominated by huge Gaussians" is one where they composite most fragments.
Used by tools/bench/bench_raster.py (--fragments), with `schedule_efficiency` for the thread analysis."""
from __future__ import annotations

import numpy as np
from numba import njit

from ev3dgs.splat import cpu
from ev3dgs.splat.cpu_tiles import TILE, _entry, _row_span, _span_params, _tile


@njit(cache=True, nogil=True)
def _count(params, boxes, offsets, width, height, tiles_x, amax, amin, tmin, out, per_tile):
    n_tiles = tiles_x * (-(-height // TILE))
    D = params.shape[1] - 7
    col = np.empty(D, params.dtype)
    half = params.dtype.type(0.5)
    one = params.dtype.type(1.0)
    for gt in range(offsets.shape[0] - 1):
        cam, x0, y0, w, h, xs, ys = _tile(gt, n_tiles, tiles_x, width, height, params)
        P = w * h
        T = np.ones(P, params.dtype)
        done = np.zeros(P, np.bool_)
        n_done = 0
        for k in range(offsets[gt], offsets[gt + 1]):
            mx, my, a, b, c, o, smax = _entry(params, k, col)
            bx0, bx1, by0, by1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
            huge = (bx1 - bx0 + 1) == w and (by1 - by0 + 1) == h
            ok, det, s = _span_params(a, b, c, smax, bx1 - bx0)
            for py in range(by0, by1 + 1):
                dy = ys[py - y0] - my
                rx0, rx1 = _row_span(ok, a, b, det, s, mx, dy, bx0, bx1)
                if rx0 <= rx1 and n_done < P:
                    out[4] += 1
                for px in range(rx0, rx1 + 1):
                    if n_done == P:
                        out[3] += 1
                        continue
                    per_tile[gt, 3] += 1
                    p = (py - y0) * w + (px - x0)
                    if done[p]:
                        out[2] += 1
                        continue
                    dx = xs[px - x0] - mx
                    sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                    if sigma < 0 or sigma > smax:
                        out[1] += 1
                        continue
                    alpha = min(amax, o * np.exp(-sigma))
                    if alpha < amin:
                        out[1] += 1
                        continue
                    nT = T[p] * (one - alpha)
                    if nT < tmin:
                        done[p] = True
                        n_done += 1
                        out[2] += 1
                        continue
                    T[p] = nT
                    out[0] += 1
                    per_tile[gt, 0] += 1
                    if huge:
                        per_tile[gt, 1] += 1
            per_tile[gt, 2] += 1


def fragment_stats(means2d, conics, colors, opacities, depths, radii, width, height) -> dict:
    """Counts (see the module docstring) for one camera's projected Gaussians (torch or numpy, float32)."""
    m, q, col, o = (np.ascontiguousarray(np.asarray(x.detach() if hasattr(x, "detach") else x, np.float32))
                    for x in (means2d, conics, colors, opacities))
    d = np.ascontiguousarray(np.asarray(depths.detach() if hasattr(depths, "detach") else depths, np.float32))
    r = np.asarray(radii.detach() if hasattr(radii, "detach") else radii).astype(np.int64)
    m, q, col, d, r = m[None], q[None], col[None], d[None], r[None]
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    with np.errstate(divide="ignore"):
        smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(np.float32)
    gboxes = cpu._pixel_boxes(m, r, q, smax, width, height)
    offsets, ids = cpu._bin(gboxes, r, d, tiles_x, tiles_y, 1)
    params, boxes = cpu._pack(m, q, col, o, smax, offsets, ids, gboxes, width, height, tiles_x)
    out = np.zeros(5, np.int64)
    # composited, composited by huge, entries, visited pixels
    per_tile = np.zeros((len(offsets) - 1, 4), np.int64)
    _count(params, boxes, offsets, width, height, tiles_x, np.float32(cpu.ALPHA_MAX), np.float32(cpu.ALPHA_MIN),
           np.float32(cpu.T_MIN), out, per_tile)
    visited = int(out[:3].sum())
    comp = per_tile[:, 0]
    dominated = int(np.sum(per_tile[:, 1] * 2 > comp))
    return {"width": width, "height": height, "gaussians_visible": int((r > 0).sum()),
            "entries": int(len(ids)), "composited": int(out[0]), "visited": visited,
            "share_below_cut": float(out[1] / max(visited, 1)), "share_behind": float(out[2] / max(visited, 1)),
            "skipped_after_tile_done": int(out[3]),
            # row spans visited, and the share of TILE lanes they fill (a tile-row-wide SIMD layout's use)
            "row_spans": int(out[4]), "lane_fill_16": float(visited / max(16 * out[4], 1)),
            "fragments_per_pixel": float(out[0] / (width * height)),
            "fragments_per_tile": {"median": float(np.median(comp)), "max": int(comp.max()),
                                   "mean": float(comp.mean())},
            "entries_per_tile": {"median": float(np.median(per_tile[:, 2])), "max": int(per_tile[:, 2].max())},
            "tiles_dominated_by_huge": dominated, "tiles": int(len(comp)),
            "share_composited_by_huge": float(per_tile[:, 1].sum() / max(out[0], 1)),
            "per_tile": {"composited": comp.tolist(), "entries": per_tile[:, 2].tolist(),
                         "visited": per_tile[:, 3].tolist(), "list_length": np.diff(offsets).tolist()}}


def schedule_efficiency(cost, list_length, threads: int) -> dict:
    """Parallel efficiency sum(cost) / (threads * max thread load) of the kernels' schedule: tiles sorted by
    list length (pairs, most first; cpu._work_order) dealt round robin, as the kernels do; and for comparison
    the same deal ordered by ``cost`` itself (what a schedule that knew the true per-tile cost would give)."""
    cost = np.asarray(cost, np.float64)
    out = {}
    for name, order in (("by_list_length", np.argsort(-np.asarray(list_length), kind="stable")),
                        ("by_cost", np.argsort(-cost, kind="stable"))):
        loads = np.zeros(threads)
        for i, t in enumerate(order):
            loads[i % threads] += cost[t]
        out[name] = float(cost.sum() / (threads * loads.max())) if loads.max() > 0 else 1.0
    return out
