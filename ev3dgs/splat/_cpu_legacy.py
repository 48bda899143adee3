"""KEPT FOR COMPARISON ONLY: the `cpu` backend's scalar rasterizer kernels as they were before the vectorised
ones (cpu.py, cpu_backward.py), importable so that tools/bench/bench_raster.py and the tests can run old and new
side by side in one process. Not used by any backend; remove once the comparison is no longer needed.

The public entry is `rasterize_cpu_legacy` (same signature and semantics as cpu.rasterize_cpu: libm exp,
per-pixel branches, recorded fragments replayed in the backward). Binning and packing are shared (cpu_tiles)."""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from .cpu import _parallel, _per_camera, _threads, _work_order, set_numba_threads
from .cpu_tiles import (ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, _bin, _entry, _pack, _pixel_boxes, _row_span, _span_params,
                        _tile)


@njit(cache=True, nogil=True, inline="always")
def _tile_state(cam, x0, y0, w, h, D, t_final, last, grad_image, grad_alpha, background, first):
    """Per pixel of a tile: T (final transmittance, walked back), S (colour behind, starting with the
    background), G / GA (the image's and alpha's gradients), TF (final T), stop (one past the last entry it
    composited); and kmax, one past the last entry any pixel composited (at least ``first``)."""
    P = w * h
    T = np.empty(P, t_final.dtype)
    S = np.empty((P, D), t_final.dtype)
    G = np.empty((P, D), t_final.dtype)
    GA = np.empty(P, t_final.dtype)
    TF = np.empty(P, t_final.dtype)
    stop = np.empty(P, np.int64)
    kmax = first
    for p in range(P):
        px, py = x0 + p % w, y0 + p // w
        T[p] = t_final[cam, py, px]
        TF[p] = T[p]
        stop[p] = last[cam, py, px]
        kmax = max(kmax, stop[p])
        GA[p] = grad_alpha[cam, py, px]
        for d in range(D):
            G[p, d] = grad_image[cam, py, px, d]
            S[p, d] = T[p] * background[d]
    return T, S, G, GA, TF, stop, kmax


@njit(cache=True, nogil=True, inline="always")
def _fragment_grad(p, dx, dy, e, o, a, b, c, col, gcol, T, S, G, GA, TF, half, one, amax, acc):
    """One fragment (pixel p of a Gaussian, exp(-sigma) = e), back to front: walks T and S back past it,
    adds its colour gradient to gcol and returns the updated accumulators acc = (d mx, d my, d a, d b, d c,
    d opacity)."""
    D = col.shape[0]
    gmx, gmy, ga, gb, gc, go = acc
    raw = o * e
    alpha = min(amax, raw)
    inv = one / (one - alpha)    # 1 - alpha >= 0.01
    Ti = T[p] * inv              # transmittance in front of this Gaussian
    wgt = alpha * Ti
    cg = half - half
    sg = half - half
    for d in range(D):
        gcol[d] += wgt * G[p, d]
        cg += col[d] * G[p, d]
        sg += S[p, d] * G[p, d]
    # dL/dalpha: own colour, everything behind (S, incl. background), the alpha output
    d_alpha = Ti * cg - (sg - GA[p] * TF[p]) * inv
    for d in range(D):
        S[p, d] += col[d] * wgt
    T[p] = Ti
    if raw > amax:              # clamped: no gradient to opacity or the footprint
        return gmx, gmy, ga, gb, gc, go
    d_sigma = -d_alpha * alpha
    return (gmx - d_sigma * (a * dx + b * dy), gmy - d_sigma * (c * dy + b * dx), ga + d_sigma * half * dx * dx,
            gb + d_sigma * dx * dy, gc + d_sigma * half * dy * dy, go + d_alpha * e)


@njit(cache=True, nogil=True, inline="always")
def _store(per_pair, k, gcol, acc):
    for d in range(gcol.shape[0]):
        per_pair[k, 6 + d] = gcol[d]
    gmx, gmy, ga, gb, gc, go = acc
    per_pair[k, 0] += gmx
    per_pair[k, 1] += gmy
    per_pair[k, 2] += ga
    per_pair[k, 3] += gb
    per_pair[k, 4] += gc
    per_pair[k, 5] += go


@njit(cache=True, nogil=True, parallel=True)
def _backward(params, boxes, offsets, work, background, width, height, tiles_x, t_final, last, grad_image,
              grad_alpha, per_pair, consts, frag_start, frag_pix, frag_e, frag_n, n_threads):
    """per_pair[k] gets tile-list entry k's gradient (its Gaussian as its camera sees it; params and boxes per
    entry from cpu_tiles._pack): [dmx, dmy, da, db, dc, do, dcol...].
    When the forward recorded its fragments (frag_n has one entry per tile-list entry) they are replayed:
    no row spans, exp or tests. Otherwise each is recomputed: the pixels of the entry's spans that it
    composited (k < stop[p], sigma in range, alpha >= 1/255), which is exactly the recorded set. Either way the
    same updates (_fragment_grad) in the same order: bitwise the same per_pair."""
    D = per_pair.shape[1] - 6
    half, one, amax, amin = consts[0], consts[1], consts[2], consts[3]
    zero = half - half
    n_tiles = tiles_x * (-(-height // TILE))
    replay = frag_n.shape[0] == params.shape[0]
    for t in prange(n_threads):  # tiles dealt round robin to the threads (see cpu._work_order)
        for i in range(t, work.shape[0], n_threads):
            gt = work[i]
            cam, x0, y0, w, h, xs, ys = _tile(gt, n_tiles, tiles_x, width, height, t_final)
            T, S, G, GA, TF, stop, kmax = _tile_state(cam, x0, y0, w, h, D, t_final, last, grad_image, grad_alpha,
                                                      background, offsets[gt])
            gcol = np.empty(D, t_final.dtype)
            col = np.empty(D, t_final.dtype)
            for k in range(kmax - 1, offsets[gt] - 1, -1):
                if replay and frag_n[k] == 0:  # per_pair[k] stays 0, as recomputing leaves it
                    continue
                mx, my, a, b, c, o, smax = _entry(params, k, col)
                acc = (zero, zero, zero, zero, zero, zero)
                for d in range(D):
                    gcol[d] = zero
                if replay:
                    fs = frag_start[k]
                    for j in range(fs, fs + frag_n[k]):
                        p = np.int64(frag_pix[j])
                        acc = _fragment_grad(p, xs[p % w] - mx, ys[p // w] - my, frag_e[j], o, a, b, c, col, gcol, T,
                                             S, G, GA, TF, half, one, amax, acc)
                    _store(per_pair, k, gcol, acc)
                    continue
                bx0, bx1, by0, by1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
                ok, det, s = _span_params(a, b, c, smax, bx1 - bx0)
                for py in range(by0, by1 + 1):
                    dy = ys[py - y0] - my
                    rx0, rx1 = _row_span(ok, a, b, det, s, mx, dy, bx0, bx1)
                    for px in range(rx0, rx1 + 1):
                        p = (py - y0) * w + (px - x0)
                        if k >= stop[p]:
                            continue
                        dx = xs[px - x0] - mx
                        sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                        if sigma < 0 or sigma > smax:
                            continue
                        e = np.exp(-sigma)
                        if min(amax, o * e) < amin:
                            continue
                        acc = _fragment_grad(p, dx, dy, e, o, a, b, c, col, gcol, T, S, G, GA, TF, half, one, amax, acc)
                _store(per_pair, k, gcol, acc)


@njit(cache=True, nogil=True, parallel=True)
def _reduce(ids, per_pair, offsets, n_cameras, n):
    """Per camera (in parallel: disjoint rows), a serial sum in tile-list order, straight into the layouts
    the autograd function returns: means2d (C, N, 2), conics (C, N, 3), opacity (C, N), colours (C, N, D).
    (Splitting one camera's sum over threads by Gaussian, each thread scanning the whole list, measured no
    faster: the scan is the cost.)"""
    D = per_pair.shape[1] - 6
    g_mean = np.zeros((n_cameras, n, 2), per_pair.dtype)
    g_conic = np.zeros((n_cameras, n, 3), per_pair.dtype)
    g_op = np.zeros((n_cameras, n), per_pair.dtype)
    g_col = np.zeros((n_cameras, n, D), per_pair.dtype)
    n_tiles = (offsets.shape[0] - 1) // n_cameras
    for c in prange(n_cameras):
        for k in range(offsets[c * n_tiles], offsets[(c + 1) * n_tiles]):
            g = ids[k]
            g_mean[c, g, 0] += per_pair[k, 0]
            g_mean[c, g, 1] += per_pair[k, 1]
            g_conic[c, g, 0] += per_pair[k, 2]
            g_conic[c, g, 1] += per_pair[k, 3]
            g_conic[c, g, 2] += per_pair[k, 4]
            g_op[c, g] += per_pair[k, 5]
            for d in range(D):
                g_col[c, g, d] += per_pair[k, 6 + d]
    return g_mean, g_conic, g_op, g_col


FRAGMENT_BUDGET = 512 * 2 ** 20  # bytes of recorded fragments per call; above it the backward recomputes


@njit(cache=True, nogil=True, parallel=True)
def _forward(params, boxes, offsets, work, background, width, height, tiles_x, image, t_final, last, consts,
             frag_start, frag_pix, frag_e, frag_n, n_threads):
    """All cameras at once: params and boxes per tile-list entry (cpu_tiles._pack); global tile
    c * n_tiles + t is camera c's tile t; image (C,H,W,D), t_final and last (C,H,W).

    Fragments (when frag_n has one entry per tile-list entry; else not recorded): tile-list entry k's
    composited pixels, in the order they were composited, go to slots frag_start[k] ... (frag_n[k] of them,
    at most the entry's box area): the pixel's index in its tile (frag_pix) and exp(-sigma) (frag_e), exactly
    as computed here, so the backward replays them without recomputing or re-testing anything."""
    D = image.shape[3]
    # consts = (0.5, 1, ALPHA_MAX, ALPHA_MIN, T_MIN) in the input dtype: with float32 inputs the maths stays
    # float32 (numba would promote to float64 on any Python float literal)
    half, one, amax, amin, tmin = consts[0], consts[1], consts[2], consts[3], consts[4]
    n_tiles = tiles_x * (-(-height // TILE))
    record = frag_n.shape[0] == params.shape[0]
    for t in prange(n_threads):  # tiles dealt round robin to the threads (see cpu._work_order)
        for i in range(t, work.shape[0], n_threads):
            gt = work[i]
            cam, x0, y0, w, h, xs, ys = _tile(gt, n_tiles, tiles_x, width, height, image)
            P = w * h
            T = np.ones(P, image.dtype)
            C = np.zeros((P, D), image.dtype)
            stop = np.zeros(P, np.int64)
            done = np.zeros(P, np.bool_)
            col = np.empty(D, image.dtype)
            n_done = 0
            start, end = offsets[gt], offsets[gt + 1]
            for k in range(start, end):
                if n_done == P:  # every pixel done: no later entry is composited (nor replayed: kmax <= k)
                    break
                mx, my, a, b, c, o, smax = _entry(params, k, col)
                # only the pixels of the entry's box (radius box, ellipse bounds, tile) can have alpha >= 1/255
                bx0, bx1, by0, by1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
                ok, det, s = _span_params(a, b, c, smax, bx1 - bx0)
                nf = 0
                fs = frag_start[k] if record else 0
                for py in range(by0, by1 + 1):
                    dy = ys[py - y0] - my
                    rx0, rx1 = _row_span(ok, a, b, det, s, mx, dy, bx0, bx1)
                    for px in range(rx0, rx1 + 1):
                        p = (py - y0) * w + (px - x0)
                        if done[p]:
                            continue
                        dx = xs[px - x0] - mx
                        sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                        if sigma < 0 or sigma > smax:  # beyond smax: alpha < 1/255, no exp needed
                            continue
                        e = np.exp(-sigma)
                        alpha = min(amax, o * e)
                        if alpha < amin:
                            continue
                        nT = T[p] * (one - alpha)
                        if nT < tmin:
                            done[p] = True
                            n_done += 1
                            continue
                        wgt = alpha * T[p]
                        for d in range(D):
                            C[p, d] += col[d] * wgt
                        T[p] = nT
                        stop[p] = k + 1
                        if record:
                            frag_pix[fs + nf] = p
                            frag_e[fs + nf] = e
                            nf += 1
                if record:
                    frag_n[k] = nf
            for p in range(P):
                px, py = x0 + p % w, y0 + p // w
                for d in range(D):
                    image[cam, py, px, d] = C[p, d] + T[p] * background[d]
                t_final[cam, py, px] = T[p]
                last[cam, py, px] = stop[p]


def _fragment_buffers(boxes, dtype, record: bool) -> tuple:
    """(frag_start, frag_pix, frag_e, frag_n) for the forward to record its fragments in: slots for every
    pixel of every tile-list entry's box (an upper bound). Without ``record`` (no input needs a
    gradient) or over FRAGMENT_BUDGET bytes, nothing is recorded (frag_n empty) and a backward recomputes."""
    none = (np.zeros(1, np.int64), np.zeros(0, np.uint8), np.zeros(0, dtype), np.zeros(0, np.int32))
    if not record or len(boxes) == 0:
        return none
    b = boxes.astype(np.int64)
    areas = (b[:, 1] - b[:, 0] + 1) * (b[:, 3] - b[:, 2] + 1)  # empty boxes are stored as (0, -1, 0, -1): 0
    start = np.zeros(len(boxes) + 1, np.int64)
    np.cumsum(areas, out=start[1:])
    total = int(start[-1])
    if total * (1 + np.dtype(dtype).itemsize) > FRAGMENT_BUDGET:
        return none
    return start, np.empty(total, np.uint8), np.empty(total, dtype), np.empty(len(boxes), np.int32)


def _consts(dtype) -> np.ndarray:
    return np.array([0.5, 1.0, ALPHA_MAX, ALPHA_MIN, T_MIN], dtype)


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


class _RasterizeCPULegacy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, width, height, background):
        """Batched: means2d (C,N,2), conics (C,N,3), colors (C,N,D) or shared (N,D), depths and radii (C,N)."""
        dtype = colors.dtype
        m, q, col, o = (_np(x.to(dtype)) for x in (means2d, conics, colors, opacities))
        C = m.shape[0]
        ctx.shared_colors = col.ndim == 2
        if ctx.shared_colors:
            col = np.ascontiguousarray(np.broadcast_to(col, (C,) + col.shape))
        bg = _np(background.to(dtype))
        r = _np(radii).astype(np.int64)
        tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
        # alpha >= 1/255 needs sigma <= ln(255 o): beyond that (plus a margin, so the exact alpha test still
        # decides at the boundary) no exp is computed, and no tile or pixel outside that ellipse is visited
        with np.errstate(divide="ignore"):
            smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(col.dtype)
        gboxes = _parallel(_pixel_boxes, m, r, q, smax, width, height)
        offsets, ids = _parallel(_bin, gboxes, r, _np(depths), tiles_x, tiles_y, _per_camera(C))
        work = _work_order(offsets)
        image = np.empty((C, height, width, col.shape[2]), col.dtype)
        t_final = np.empty((C, height, width), col.dtype)
        last = np.empty((C, height, width), np.int64)
        params, boxes = _parallel(_pack, m, q, col, o, smax, offsets, ids, gboxes, width, height, tiles_x)
        frags = _fragment_buffers(boxes, col.dtype, record=any(ctx.needs_input_grad[:4]))
        _parallel(_forward, params, boxes, offsets, work, bg, width, height, tiles_x, image, t_final, last,
                  _consts(col.dtype), *frags, _threads(work))
        ctx.save_for_backward(means2d, conics, colors, opacities, background)
        ctx.arrays = (params, boxes, bg, offsets, ids, work, t_final, last, frags)
        ctx.size = (width, height, tiles_x, C, m.shape[1], col.shape[2])
        alpha = torch.from_numpy(1.0 - t_final)[..., None]
        return torch.from_numpy(image), alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        params, boxes, bg, offsets, ids, work, t_final, last, frags = ctx.arrays
        width, height, tiles_x, C, N, D = ctx.size
        dtype = t_final.dtype
        gi = (np.zeros((C, height, width, D), dtype) if grad_image is None
              else _np(grad_image).astype(dtype, copy=False))
        ga = (np.zeros_like(t_final) if grad_alpha is None
              else _np(grad_alpha).astype(dtype, copy=False)[..., 0])
        per_pair = np.zeros((len(ids), 6 + D), dtype)
        # replays the fragments when the forward recorded them (frags not empty), else recomputes them
        _parallel(_backward, params, boxes, offsets, work, bg, width, height, tiles_x, t_final, last, gi, ga,
                  per_pair, _consts(dtype), *frags, _threads(work))
        g_mean, g_conic, g_ops, g_col = _parallel(_reduce, ids, per_pair, offsets, C, N)
        means2d, conics, colors, opacities, background = ctx.saved_tensors
        grad_bg = None
        if ctx.needs_input_grad[8]:
            grad_bg = torch.from_numpy((gi * t_final[..., None]).sum(axis=(1, 2)).sum(axis=0)).to(background.dtype)
        g_op = g_ops[0].copy()
        for c in range(1, C):  # fixed camera order
            g_op += g_ops[c]
        if ctx.shared_colors:
            g_sum = g_col[0].copy()
            for c in range(1, C):
                g_sum += g_col[c]
            g_col = g_sum
        t = torch.from_numpy
        return (t(g_mean).to(means2d.dtype), t(g_conic).to(conics.dtype), t(g_col).to(colors.dtype),
                t(g_op).to(opacities.dtype), None, None, None, None, grad_bg)


def rasterize_cpu_legacy(means2d, conics, colors, opacities, depths, radii, width: int, height: int,
                  background=None, threads: int | None = None):
    """Same signature and result as reference.rasterize_reference: (image (H,W,D), alpha (H,W,1)). Batched
    over C cameras when means2d is (C,N,2) (conics (C,N,3), depths/radii (C,N), colors (C,N,D) or shared
    (N,D)): (C,H,W,D), (C,H,W,1), every camera's gradients exactly those of its own single-camera call."""
    if background is None:
        background = torch.zeros(colors.shape[-1], dtype=colors.dtype)
    if threads is not None:
        set_numba_threads(threads)
    batched = means2d.ndim == 3
    if not batched:
        means2d, conics, depths, radii = means2d[None], conics[None], depths[None], radii[None]
    image, alpha = _RasterizeCPULegacy.apply(means2d, conics, colors, opacities, depths, radii, int(width), int(height),
                                       background.to(colors.dtype))
    return (image, alpha) if batched else (image[0], alpha[0])
