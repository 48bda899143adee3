"""The `cpu` backend's backward kernel (see cpu.py), which replays the forward's recorded fragments or
recomputes them, and the per-camera, per-Gaussian sum of its per-(tile, Gaussian) gradients. Both ways run the
same per-tile set-up (_tile_state) and the same per-fragment update (_fragment_grad), so they give bitwise
the same gradients."""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .cpu_tiles import TILE, _entry, _row_span, _span_params, _tile


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
