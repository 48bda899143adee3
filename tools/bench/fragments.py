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
radius >= a tile), so a tile "dominated by huge Gaussians" is one where they composite most fragments, and
the share composited by each tile's 5 busiest Gaussians. What a tighter binning could still remove: the
pixels of the entries' boxes outside their cut-off ellipse (row spans solved for every entry, whatever its
width), and the entries whose ellipse reaches no pixel of their tile (listed because the box touches it).
`subpose_coherence` says whether the depth order of a blur exposure's sub-poses is the same (a shared sort).

Used by tools/bench/bench_raster.py (--fragments), with `schedule_efficiency` for the thread analysis, and
as a script for a training step's model (the one bench_train_scaling.make_step builds):

    python tools/bench/fragments.py --size 346x260 --gaussians 50000 \
        --json tools/results/fragments_346x260.json --plot tools/results/fragments_346x260.png"""
from __future__ import annotations

import numpy as np
from numba import njit

from ev3dgs.splat import cpu
from ev3dgs.splat.cpu_tiles import TILE, _entry, _row_span, _span_params, _tile


@njit(cache=True, nogil=True)
def _count(params, boxes, offsets, width, height, tiles_x, amax, amin, tmin, out, per_tile, per_pixel, per_entry):
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
            # the exact spans (solved whatever the box width): box pixels inside the cut-off ellipse
            ok_e, det_e, s_e = _span_params(a, b, c, smax)
            inside = 0
            for py in range(by0, by1 + 1):
                ex0, ex1 = _row_span(ok_e, a, b, det_e, s_e, mx, ys[py - y0] - my, bx0, bx1)
                inside += max(0, ex1 - ex0 + 1)
            if bx0 <= bx1 and by0 <= by1:
                out[5] += (bx1 - bx0 + 1) * (by1 - by0 + 1)
            out[6] += inside
            if inside == 0:
                out[7] += 1
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
                    per_pixel[cam, py, px] += 1
                    per_entry[k] += 1
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
    # composited, below the cut, behind, after the tile was done, row spans, box pixels, pixels in the
    # ellipse, entries whose ellipse misses their tile
    out = np.zeros(8, np.int64)
    # composited, composited by huge, entries, visited pixels
    per_tile = np.zeros((len(offsets) - 1, 4), np.int64)
    per_pixel = np.zeros((1, height, width), np.int64)
    per_entry = np.zeros(len(ids), np.int64)
    _count(params, boxes, offsets, width, height, tiles_x, np.float32(cpu.ALPHA_MAX), np.float32(cpu.ALPHA_MIN),
           np.float32(cpu.T_MIN), out, per_tile, per_pixel, per_entry)
    top5 = np.zeros(len(offsets) - 1)
    for t in range(len(offsets) - 1):
        e = np.sort(per_entry[offsets[t]:offsets[t + 1]])[::-1]
        top5[t] = e[:5].sum() / max(e.sum(), 1)
    pp = per_pixel[0].ravel()
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
            "tiles_top5_composite_half": int(np.sum(top5 > 0.5)),
            "top5_share_per_tile": {"median": float(np.median(top5)), "max": float(top5.max())},
            "composited_per_pixel": {"mean": float(pp.mean()), "median": float(np.median(pp)),
                                     "p90": float(np.percentile(pp, 90)), "max": int(pp.max()),
                                     "histogram": np.bincount(pp).tolist()},
            "box_pixels": int(out[5]), "box_pixels_in_ellipse": int(out[6]),
            "share_box_outside_ellipse": float(1.0 - out[6] / max(out[5], 1)),
            "entries_missing_tile": int(out[7]), "share_entries_missing_tile": float(out[7] / max(len(ids), 1)),
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


def subpose_coherence(depths, radii) -> dict:
    """For a stack of sub-poses (C, N): whether each sub-pose's depth order (stable, visible Gaussians) is
    sub-pose 0's, and how many neighbours of sub-pose 0's order are out of order under its depths (0: the
    sort could be shared exactly)."""
    d = np.asarray(depths.detach() if hasattr(depths, "detach") else depths)
    r = np.asarray(radii.detach() if hasattr(radii, "detach") else radii)
    orders = [np.flatnonzero(r[c] > 0)[np.argsort(d[c][r[c] > 0], kind="stable")] for c in range(d.shape[0])]
    rows = []
    for c in range(1, d.shape[0]):
        same = orders[c].shape == orders[0].shape and bool(np.array_equal(orders[c], orders[0]))
        o = orders[0][np.isin(orders[0], orders[c])]
        dc = d[c][o]
        desc = int(np.sum((dc[1:] < dc[:-1]) | ((dc[1:] == dc[:-1]) & (o[1:] < o[:-1]))))
        rows.append({"subpose": c, "same_order": same, "neighbours_out_of_order": desc,
                     "share_rank_changed": float(np.mean(orders[c] != orders[0])) if orders[c].shape == orders[0].shape
                     else 1.0})
    return {"subposes": int(d.shape[0]), "visible": int((r[0] > 0).sum()), "vs_subpose_0": rows}


def _sort_share(depths, radii, gboxes, tiles_x, tiles_y, repeats=5) -> dict:
    """Median process-time ms of the depth sorts of all sub-poses against the whole binning (which includes
    them): what sharing the sort could save at most."""
    import time

    sort_ms, bin_ms = [], []
    for _ in range(repeats + 1):
        t0 = time.process_time()
        for c in range(depths.shape[0]):
            vis = np.flatnonzero(radii[c] > 0)
            cpu._stable_argsort(depths[c][vis])
        t1 = time.process_time()
        cpu._bin(gboxes, radii, depths, tiles_x, tiles_y, 1)
        t2 = time.process_time()
        sort_ms.append(1e3 * (t1 - t0))
        bin_ms.append(1e3 * (t2 - t1))
    return {"sort_ms": float(np.median(sort_ms[1:])), "bin_ms": float(np.median(bin_ms[1:]))}


def main(argv=None) -> int:
    import argparse
    import sys
    from pathlib import Path

    import torch

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench_train_scaling import SUBPOSES, _viewmats
    from pareto import save_json

    from ev3dgs.splat.model import GaussianModel
    from ev3dgs.splat.project_cpu import project_sh_cpu

    ap = argparse.ArgumentParser(description="Where the cpu rasterizer's fragments go, for the model of "
                                 "bench_train_scaling.make_step (its middle sub-pose).")
    ap.add_argument("--size", default="346x260", help="WIDTHxHEIGHT (default 346x260)")
    ap.add_argument("--gaussians", type=int, default=50000)
    ap.add_argument("--json", default="tools/results/fragments_346x260.json")
    ap.add_argument("--plot", default="tools/results/fragments_346x260.png")
    args = ap.parse_args(argv)
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
        if not (0 < width <= 16384 and 0 < height <= 16384) or args.gaussians < 1:
            raise ValueError
    except ValueError:
        print(f"error: --size must be WIDTHxHEIGHT and --gaussians positive, got {args.size} {args.gaussians}",
              file=sys.stderr)
        return 2
    cpu.set_numba_threads(1)
    model = GaussianModel.random_in_bounds([[-0.6] * 3, [0.6] * 3], args.gaussians, seed=0, sh_degree=3,
                                           init_opacity=0.3)
    model.active_sh_degree = 3
    f = 1.2 * width
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    with torch.no_grad():
        m2d, conics, depths, cols, radii = project_sh_cpu(model.means, model.quats_normalised, model.scales,
                                                          model.opacities, model.sh, _viewmats(SUBPOSES), K,
                                                          width, height, sh_degree=3)
    mid = SUBPOSES // 2
    st = fragment_stats(m2d[mid], conics[mid], cols[mid], model.opacities, depths[mid], radii[mid], width, height)
    st["gaussians"] = args.gaussians
    st["subposes"] = subpose_coherence(depths, radii)
    o = model.opacities.detach().numpy().astype(np.float32)
    with np.errstate(divide="ignore"):
        smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(np.float32)
    r = radii.numpy().astype(np.int64)
    gboxes = cpu._pixel_boxes(m2d.numpy(), r, conics.numpy(), smax, width, height)
    st["sort_vs_binning"] = _sort_share(depths.numpy(), r, gboxes, -(-width // TILE), -(-height // TILE))
    save_json(args.json, st, f", {args.gaussians} Gaussians at {width}x{height}")
    plot(st, args.plot)
    keys = ("entries", "composited", "visited", "share_below_cut", "share_behind", "skipped_after_tile_done",
            "share_box_outside_ellipse", "share_entries_missing_tile", "tiles_dominated_by_huge",
            "tiles_top5_composite_half")
    for k in keys:
        print(f"{k}: {st[k]}")
    print("composited per pixel:", {k: v for k, v in st["composited_per_pixel"].items() if k != "histogram"})
    print("sub-poses:", st["subposes"]["vs_subpose_0"])
    print("sort vs binning (ms):", st["sort_vs_binning"])
    return 0


def plot(st: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    visited = st["visited"]
    parts = [("composited", st["composited"]), ("below 1/255", round(st["share_below_cut"] * visited)),
             ("behind T<1e-4", round(st["share_behind"] * visited)),
             ("after tile done (not visited)", st["skipped_after_tile_done"]),
             ("rest of the boxes (outside the spans)",
              max(0, st["box_pixels"] - visited - st["skipped_after_tile_done"]))]
    left = 0
    for (name, v), colour in zip(parts, ("tab:green", "tab:orange", "tab:red", "tab:gray", "lightgray")):
        ax[0].barh([0], [v / 1e6], left=left / 1e6, color=colour, label=f"{name}: {v / 1e6:.2f} M")
        left += v
    ax[0].set_yticks([])
    ax[0].set_xlabel("pixels of the tile-list entries (millions)")
    ax[0].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.25))
    h = np.asarray(st["composited_per_pixel"]["histogram"])
    ax[1].bar(np.arange(len(h)), h, width=1.0)
    ax[1].set_xlabel("Gaussians composited per pixel")
    ax[1].set_ylabel("pixels")
    fig.suptitle(f"{st['gaussians']} Gaussians at {st['width']}x{st['height']}, one sub-pose, "
                 f"{st['entries']} tile entries", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
