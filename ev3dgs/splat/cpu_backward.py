"""The `cpu` backend's backward kernel (see cpu.py) and the per-camera, per-Gaussian sum of its per-(tile,
Gaussian) gradients. The backward recomputes the forward's fragments with the forward's own row function
(cpu_tiles._row_exp: bitwise the same exp(-sigma)) and its tests (alpha >= 1/255, k < stop[p]), lane-parallel
over the TILE pixels of a tile row, branch-free: a lane that is not a fragment carries alpha 0 and adds nothing."""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .cpu_tiles import _U8, LANES, SIGMA_POLY_MAX, TILE, _entry, _lanes, _row_exp, _row_span, _span_params, _tile


# per-tile state of the backward, one float array per thread (one base pointer, unsigned indices: see cpu.py's
# forward), planes of TILE x TILE: T (walked back), TF (final T), GA (alpha's gradient), stop (tile-local, one
# past the last entry composited), then S[d] (colour behind) and G[d] (the image's gradient); then lane scratch
# of TILE each: alpha, 1 / (1 - alpha), T in front, weight, cg, sg, the 6 per-lane gradient sums, D colour sums.
_B = TILE * TILE
_U16, _UB = np.uint64(TILE), np.uint64(_B)
_B_T, _B_TF, _B_GA, _B_STOP, _B_S = (np.uint64(i * _B) for i in range(5))


@njit(cache=True, nogil=True, inline="always")
def _tile_state(cam, x0, y0, w, h, D, t_final, last, grad_image, grad_alpha, background, first, X):
    """Fills the planes of X (see above) for one tile; lanes outside the image stay zero (no span reaches them).
    Returns kmax, one past the last entry any pixel composited (at least ``first``)."""
    zero = X.dtype.type(0)
    X[:(4 + 2 * D) * _B] = zero
    kmax = first
    for py in range(h):
        for px in range(w):
            q = py * TILE + px
            tf = t_final[cam, y0 + py, x0 + px]
            X[q] = tf
            X[_B + q] = tf
            X[2 * _B + q] = grad_alpha[cam, y0 + py, x0 + px]
            st = last[cam, y0 + py, x0 + px]
            X[3 * _B + q] = st - first if st > 0 else 0
            kmax = max(kmax, st)
            for d in range(D):
                X[(4 + d) * _B + q] = tf * background[d]
                X[(4 + D + d) * _B + q] = grad_image[cam, y0 + py, x0 + px, d]
    return kmax


@njit(cache=True, nogil=True, inline="always")
def _lane_sum(X, o):
    """Sum of the TILE = 16 lanes X[o:o + 16] in a fixed pairwise order (deterministic, the same every call)."""
    s0 = (X[o + 0] + X[o + 8]) + (X[o + 4] + X[o + 12])
    s1 = (X[o + 2] + X[o + 10]) + (X[o + 6] + X[o + 14])
    s2 = (X[o + 1] + X[o + 9]) + (X[o + 5] + X[o + 13])
    s3 = (X[o + 3] + X[o + 11]) + (X[o + 7] + X[o + 15])
    return (s0 + s1) + (s2 + s3)


@njit(cache=True, nogil=True, parallel=True)
def _backward(params, boxes, offsets, work, background, width, height, tiles_x, t_final, last, grad_image,
              grad_alpha, per_pair, consts, n_threads):
    """per_pair[k] gets tile-list entry k's gradient (its Gaussian as its camera sees it; params and boxes per
    entry from cpu_tiles._pack): [dmx, dmy, da, db, dc, do, dcol...]. Per tile, entries back to front; per
    entry and row, the TILE lanes at once: the lane's fragment test (alpha >= 1/255 on the forward's exp, and
    k < stop[p], which is exactly "composited at k"), then, masked (alpha 0 elsewhere, which changes nothing):
    T walked back by dividing by (1 - alpha) >= 0.01, the colour behind S, dL/dalpha, and the entry's gradient
    terms summed per lane over its rows; the lanes are summed in a fixed order at the end (_lane_sum). No
    atomics, no reassociation left to the compiler: the result does not depend on the thread count."""
    D = per_pair.shape[1] - 6
    half, one, amax, amin = consts[0], consts[1], consts[2], consts[3]
    libm_all = consts[5] != 0
    zero = half - half
    n_tiles = tiles_x * (-(-height // TILE))
    dt = t_final.dtype
    L = (4 + 2 * D) * _B  # lane scratch after the planes
    uAL, uINV, uTI, uWG = np.uint64(L), np.uint64(L + TILE), np.uint64(L + 2 * TILE), np.uint64(L + 3 * TILE)
    uCG, uSG, uA = np.uint64(L + 4 * TILE), np.uint64(L + 5 * TILE), np.uint64(L + 6 * TILE)
    uGC = np.uint64(L + 12 * TILE)
    uG = np.uint64((4 + D) * _B)
    for t in prange(n_threads):  # tiles dealt round robin to the threads (see cpu._work_order)
        X = np.empty(L + (12 + D) * TILE, dt)
        e = np.empty(TILE, dt)
        col = np.empty(D, dt)
        for i in range(t, work.shape[0], n_threads):
            gt = work[i]
            cam, x0, y0, w, h, _, ys = _tile(gt, n_tiles, tiles_x, width, height, t_final)
            xs, jf = _lanes(x0, y0, t_final)
            first = offsets[gt]
            kmax = _tile_state(cam, x0, y0, w, h, D, t_final, last, grad_image, grad_alpha, background, first, X)
            for k in range(kmax - 1, first - 1, -1):
                mx, my, a, b, c, o, smax = _entry(params, k, col)
                libm = libm_all or not (smax <= SIGMA_POLY_MAX)
                kf = dt.type(k - first + 1)
                X[L + 6 * TILE:] = zero  # per-lane gradient sums
                bx0, bx1, by0, by1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
                ok, det, s = _span_params(a, b, c, smax, bx1 - bx0)
                for py in range(by0, by1 + 1):
                    dy = ys[py - y0] - my
                    rx0, rx1 = _row_span(ok, a, b, det, s, mx, dy, bx0, bx1)
                    if rx0 > rx1:
                        continue
                    base = np.uint64(py - y0) * _U16
                    for blk in range((rx0 - x0) // LANES, (rx1 - x0) // LANES + 1):
                        j0 = np.uint64(blk * LANES)
                        _row_exp(e, xs, jf, j0, mx, dy, a, b, c, smax, dt.type(rx0 - x0), dt.type(rx1 - x0), half,
                                 zero, libm)
                        b0 = base + j0
                        for j in range(_U8):
                            p = b0 + j
                            ej = e[j]
                            frag = (min(amax, o * ej) >= amin) & (kf <= X[_B_STOP + p])
                            ej = ej if frag else zero
                            e[j] = ej
                            alpha = min(amax, o * ej)
                            iv = one / (one - alpha)  # 1 - alpha >= 0.01
                            ti = X[_B_T + p] * iv     # transmittance in front of this Gaussian
                            X[uAL + j] = alpha
                            X[uINV + j] = iv
                            X[uTI + j] = ti
                            X[uWG + j] = alpha * ti
                            X[uCG + j] = zero
                            X[uSG + j] = zero
                            X[_B_T + p] = ti
                        for d in range(D):
                            cd = col[d]
                            oS = _B_S + np.uint64(d) * _UB + b0
                            oG = uG + np.uint64(d) * _UB + b0
                            oC = uGC + np.uint64(d) * _U16 + j0
                            for j in range(_U8):
                                gd = X[oG + j]
                                wj = X[uWG + j]
                                X[oC + j] += wj * gd
                                X[uCG + j] += cd * gd
                                X[uSG + j] += X[oS + j] * gd
                                X[oS + j] += cd * wj
                        for j in range(_U8):
                            p = b0 + j
                            ej = e[j]
                            # dL/dalpha: own colour, everything behind (S, incl. background), the alpha output
                            behind = X[uSG + j] - X[_B_GA + p] * X[_B_TF + p]
                            d_alpha = X[uTI + j] * X[uCG + j] - behind * X[uINV + j]
                            # clamped alpha (o e > 0.99) or no fragment: no gradient to opacity or the footprint
                            live = (ej != zero) & (o * ej <= amax)
                            d_sigma = -d_alpha * X[uAL + j] if live else zero
                            d_op = d_alpha * ej if live else zero
                            dx = xs[j0 + j] - mx
                            X[uA + j0 + j] -= d_sigma * (a * dx + b * dy)
                            X[uA + _U16 + j0 + j] -= d_sigma * (c * dy + b * dx)
                            X[uA + 2 * _U16 + j0 + j] += d_sigma * half * dx * dx
                            X[uA + 3 * _U16 + j0 + j] += d_sigma * dx * dy
                            X[uA + 4 * _U16 + j0 + j] += d_sigma * half * dy * dy
                            X[uA + 5 * _U16 + j0 + j] += d_op
                for q in range(6):
                    per_pair[k, q] = _lane_sum(X, L + (6 + q) * TILE)
                for d in range(D):
                    per_pair[k, 6 + d] = _lane_sum(X, L + (12 + d) * TILE)


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
