"""The `cpu` backend: exact tile rasterization with hand-written forward and backward kernels (numba).

Same semantics and constants as `reference` (front-to-back, alpha = min(0.99, o*exp(-sigma)), skip
sigma < 0 or alpha < 1/255, stop before a Gaussian that would take T below 1e-4), but:

* binning (one numba call, cameras in parallel): per camera the Gaussians are depth-sorted once, then
  counted and placed per 16x16 tile (a counting sort), so every tile's list is already in depth order.
  Nothing is dropped: a Gaussian goes to every tile its (opacity-aware, exact) radius touches, so the
  per-tile lists hold every Gaussian that can reach a pixel.
* forward: per tile, Gaussians outer and the tile's pixels inner; per pixel it keeps T and the index after
  the last Gaussian it composited. Per row of a Gaussian's box (at least SPAN_MIN_WIDTH wide) only the
  pixels inside its cut-off ellipse (sigma <= ln(255 o), solved per row, conservatively) are visited: about
  half of the box. Tiles run in parallel (numba prange, handed out one at a time, most expensive first)
  when threads > 1. When a gradient will be needed it records every fragment it composites (the pixel's
  index in its tile and exp(-sigma), in slots bounded by each entry's clipped box area; FRAGMENT_BUDGET caps
  the memory).
* backward: per tile, Gaussians in reverse depth order; T is recovered by dividing by (1 - alpha) >= 0.01,
  the colour behind each Gaussian is accumulated, and gradients go to a per-(tile, Gaussian) buffer that a
  serial pass sums per Gaussian. No atomics, and the result does not depend on the thread count. It
  replays the recorded fragments (no spans, exp or tests: ~2.4x faster than recomputing them); over the
  budget it recomputes them (the same updates in the same order: bitwise the same gradients, tested).

Batched: C cameras share one call. Their tile lists are concatenated (camera c's tile t is global tile
c * n_tiles + t), so forward and backward are one parallel loop over (camera, tile), and the per-pair
gradients are summed per camera in the same order as a single-camera call: bitwise the same result.

Determinism: forward and backward are bitwise the same for any numba thread count (tiles own disjoint
pixels and disjoint per-pair gradient slots; the per-Gaussian sum is serial, in tile-list order). One side
effect had to be contained: numba's "omp" threading layer shares the OpenMP runtime with torch, and
launching its thread pool sets OpenMP's thread count, i.e. torch's intra-op thread count, to numba's. The
kernels are therefore called through `_parallel`, which puts torch's thread count back.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

TILE = 16
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
# boxes narrower than this many pixels are walked whole: solving each row's span costs more than the pixels it
# skips (measured on a trained demo model, radii 2-4 px: forward ~10 % faster; same pixels composited)
SPAN_MIN_WIDTH = 10
FRAGMENT_BUDGET = 512 * 2 ** 20  # bytes of recorded fragments per call; above it the backward recomputes


@njit(cache=True, nogil=True, inline="always")
def _box(mx, my, r, xmin, ymin, xmax, ymax):
    """Pixel rectangle [x0, x1] x [y0, y1] of a Gaussian's radius box, clipped to [xmin, xmax] x [ymin, ymax]."""
    return (max(xmin, int(np.ceil(mx - r))), min(xmax, int(np.floor(mx + r))),
            max(ymin, int(np.ceil(my - r))), min(ymax, int(np.floor(my + r))))


@njit(cache=True, nogil=True, inline="always")
def _span_params(a, b, c, smax, box_width=1 << 30):
    """Per Gaussian, for _row_span: (ok, det, s) in float64. ``s`` is the kernel's cut-off sigma ``smax``
    raised by more than the rounding error of the kernel's sigma (so every pixel the kernel's exact test can
    accept lies inside the span): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy is evaluated in 4 roundings of
    relative size u <= 2^-24 (float32), each relative to a term, and the terms' absolute sum is at most
    (1 + rho) / (1 - rho) times sigma for the positive-definite form (rho = |b| / sqrt(ac) < 1), so an
    inflation of 1e-6 * (1 + rho) / (1 - rho) (> 16 u) relative, plus 1e-9 absolute, covers it. Not
    positive definite (ok False): no span, the caller keeps the whole box row (the kernel skips sigma < 0).
    Nor for a box narrower than SPAN_MIN_WIDTH (``box_width`` = x1 - x0): the whole row costs less there."""
    if box_width < SPAN_MIN_WIDTH:
        return False, 0.0, 0.0
    a64, b64, c64 = np.float64(a), np.float64(b), np.float64(c)
    det = a64 * c64 - b64 * b64
    if not (a64 > 0.0 and det > 0.0):
        return False, det, 0.0
    rho = min(abs(b64) / np.sqrt(a64 * c64), 1.0 - 1e-12)
    s = np.float64(smax) * (1.0 + 1e-6 * (1.0 + rho) / (1.0 - rho)) + 1e-9
    return True, det, s


@njit(cache=True, nogil=True, inline="always")
def _row_span(ok, a, b, det, s, mx, dy, bx0, bx1):
    """The pixels [x0, x1] of one row (offset dy = y - my) where sigma <= s, clipped to the box [bx0, bx1]:
    sigma is a convex quadratic in dx, 0.5 a dx^2 + b dy dx + 0.5 c dy^2 <= s solves to
    dx in (-b dy -+ sqrt(2 a s - det dy^2)) / a. The span is widened by 1e-6 px against the float64
    rounding of this solve (relative 1e-15 of coordinates < 2^24), so it never loses a pixel the exact
    test accepts; it only skips pixels whose sigma exceeds the cut-off (the ellipse is ~pi/4 of its box,
    far less for thin Gaussians)."""
    if not ok:
        return bx0, bx1
    dy64 = np.float64(dy)
    disc = 2.0 * np.float64(a) * s - det * dy64 * dy64
    if disc < 0.0:
        return 1, 0
    root = np.sqrt(disc)
    a64 = np.float64(a)
    centre = np.float64(mx) - np.float64(b) * dy64 / a64
    lo = centre - root / a64 - 1e-6
    hi = centre + root / a64 + 1e-6
    return max(bx0, int(np.ceil(lo))), min(bx1, int(np.floor(hi)))


@njit(cache=True, nogil=True, inline="always")
def _tile(tile, tiles_x, width, height, like):
    """Origin, size and pixel-centre coordinates (in like's dtype, so float32 maths stays float32) of a tile."""
    x0, y0 = (tile % tiles_x) * TILE, (tile // tiles_x) * TILE
    w, h = min(TILE, width - x0), min(TILE, height - y0)
    xs = np.empty(w, like.dtype)
    ys = np.empty(h, like.dtype)
    for i in range(w):
        xs[i] = x0 + i
    for i in range(h):
        ys[i] = y0 + i
    return x0, y0, w, h, xs, ys


@njit(cache=True, nogil=True, inline="always")
def _tile_rect(mx, my, r, width, height):
    """Tile rectangle (tx0, tx1, ty0, ty1) a Gaussian's radius box touches; tx0 > tx1 when off-image."""
    x0, x1, y0, y1 = _box(mx, my, r, 0, 0, width - 1, height - 1)
    if x0 > x1 or y0 > y1:
        return 1, 0, 0, 0
    return x0 // TILE, x1 // TILE, y0 // TILE, y1 // TILE


@njit(cache=True, nogil=True)
def _sort_keys(values):
    """uint64 keys that order like the floats ``values`` (IEEE 754: set the sign bit of a non-negative value,
    flip every bit of a negative one; -0.0 sorts before +0.0, NaN after +inf)."""
    n = values.shape[0]
    out = np.empty(n, np.uint64)
    if values.itemsize == 4:
        bits32 = values.view(np.uint32)
        sign32, all32 = np.uint64(0x80000000), np.uint64(0xFFFFFFFF)
        for i in range(n):
            b = np.uint64(bits32[i])
            out[i] = (b ^ all32) if (b & sign32) != 0 else (b | sign32)
    else:
        bits64 = values.view(np.uint64)
        sign64 = np.uint64(0x8000000000000000)
        for i in range(n):
            b = bits64[i]
            out[i] = ~b if (b & sign64) != 0 else (b | sign64)
    return out


@njit(cache=True, nogil=True)
def _stable_argsort(values):
    """np.argsort(values, kind="stable") of a float32/float64 vector without NaN or -0.0 (visible depths:
    finite, >= the near plane): an LSD radix sort on the keys' bytes, 8 bits a pass, skipping a pass whose
    byte is the same in every key. Stable like the merge sort it replaced; ~4x faster on 14k depths."""
    n = values.shape[0]
    keys = _sort_keys(np.ascontiguousarray(values))
    order = np.arange(n)
    tmp = np.empty(n, np.int64)
    count = np.empty(257, np.int64)
    mask = np.uint64(0xFF)
    for p in range(values.itemsize):
        shift = np.uint64(8 * p)
        count[:] = 0
        for i in range(n):
            count[np.int64((keys[i] >> shift) & mask) + 1] += 1
        if count.max() == n:  # every key has this byte: the pass would not move anything
            continue
        for b in range(256):
            count[b + 1] += count[b]
        for i in range(n):
            j = order[i]
            byte = np.int64((keys[j] >> shift) & mask)
            tmp[count[byte]] = j
            count[byte] += 1
        order, tmp = tmp, order
    return order


@njit(cache=True, nogil=True, parallel=True)
def _bin(means2d, radii, depths, width, height, tiles_x, tiles_y):
    """Counting sort of (camera, tile, Gaussian) triples, all cameras at once (cameras in parallel: each
    writes its own rows and its own slice of ids). Per camera the visible Gaussians (radius > 0) are put
    in depth order by a stable sort (ties by index), then counted and placed per tile, so every tile's
    list is in depth order. Returns (offsets (C * n_tiles + 1,), ids): camera c's tile t (global tile
    c * n_tiles + t) holds ids[offsets[g]:offsets[g + 1]], front to back."""
    C, N = radii.shape
    n_tiles = tiles_x * tiles_y
    counts = np.zeros((C, n_tiles + 1), np.int64)
    orders = np.empty((C, N), np.int64)
    n_vis = np.zeros(C, np.int64)
    for c in prange(C):
        vis = np.flatnonzero(radii[c] > 0)
        order = vis[_stable_argsort(depths[c][vis])]
        n_vis[c] = order.shape[0]
        for j in range(order.shape[0]):
            g = order[j]
            orders[c, j] = g
            tx0, tx1, ty0, ty1 = _tile_rect(means2d[c, g, 0], means2d[c, g, 1], radii[c, g], width, height)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[c, ty * tiles_x + tx + 1] += 1
    offsets = np.empty(C * n_tiles + 1, np.int64)
    offsets[0] = 0
    for c in range(C):  # serial prefix sum over (camera, tile)
        for t in range(n_tiles):
            offsets[c * n_tiles + t + 1] = offsets[c * n_tiles + t] + counts[c, t + 1]
    ids = np.empty(offsets[C * n_tiles], np.int64)
    for c in prange(C):
        fill = offsets[c * n_tiles:(c + 1) * n_tiles].copy()
        for j in range(n_vis[c]):
            g = orders[c, j]
            tx0, tx1, ty0, ty1 = _tile_rect(means2d[c, g, 0], means2d[c, g, 1], radii[c, g], width, height)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    ids[fill[t]] = g
                    fill[t] += 1
    return offsets, ids


@njit(cache=True, nogil=True, parallel=True)
def _forward(means2d, conics, colors, opacities, radii, sigma_max, offsets, ids, work, background, width, height,
             tiles_x, image, t_final, last, consts, frag_start, frag_pix, frag_e, frag_n):
    """All cameras at once: means2d (C,N,2), conics (C,N,3), colors (C,N,D), radii (C,N); global tile
    c * n_tiles + t is camera c's tile t; image (C,H,W,D), t_final and last (C,H,W).

    Fragments (when frag_n has one entry per tile-list entry; else not recorded): tile-list entry k's
    composited pixels, in the order they were composited, go to slots frag_start[k] ... (frag_n[k] of them,
    at most the entry's box area): the pixel's index in its tile (frag_pix) and exp(-sigma) (frag_e), exactly
    as computed here, so the backward replays them without recomputing or re-testing anything."""
    D = colors.shape[2]
    # consts = (0.5, 1, ALPHA_MAX, ALPHA_MIN, T_MIN) in the input dtype: with float32 inputs the maths stays
    # float32 (numba would promote to float64 on any Python float literal)
    half, one, amax, amin, tmin = consts[0], consts[1], consts[2], consts[3], consts[4]
    n_tiles = tiles_x * (-(-height // TILE))
    record = frag_n.shape[0] == ids.shape[0]
    for i in prange(work.shape[0]):
        gt = work[i]
        cam, tile = gt // n_tiles, gt % n_tiles
        x0, y0, w, h, xs, ys = _tile(tile, tiles_x, width, height, image)
        P = w * h
        T = np.ones(P, image.dtype)
        C = np.zeros((P, D), image.dtype)
        stop = np.zeros(P, np.int64)
        done = np.zeros(P, np.bool_)
        col = np.empty(D, image.dtype)
        n_done = 0
        start, end = offsets[gt], offsets[gt + 1]
        for k in range(start, end):
            if n_done == P:
                if record:  # the rest of the list composites nothing
                    for kk in range(k, end):
                        frag_n[kk] = 0
                break
            g = ids[k]
            mx, my = means2d[cam, g, 0], means2d[cam, g, 1]
            a, b, c = conics[cam, g, 0], conics[cam, g, 1], conics[cam, g, 2]
            o = opacities[g]
            smax = sigma_max[g]
            for d in range(D):
                col[d] = colors[cam, g, d]
            # only the pixels of the Gaussian's (exact) radius box can have alpha >= 1/255
            bx0, bx1, by0, by1 = _box(mx, my, radii[cam, g], x0, y0, x0 + w - 1, y0 + h - 1)
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


@njit(cache=True, nogil=True, parallel=True)
def _backward(means2d, conics, colors, opacities, radii, sigma_max, offsets, ids, work, background, width, height,
              tiles_x, t_final, last, grad_image, grad_alpha, per_pair, consts):
    """per_pair[k] gets Gaussian ids[k]'s gradient from tile-list entry k: [dmx, dmy, da, db, dc, do, dcol...]."""
    D = colors.shape[2]
    half, one, amax, amin = consts[0], consts[1], consts[2], consts[3]
    zero = half - half
    n_tiles = tiles_x * (-(-height // TILE))
    for i in prange(work.shape[0]):
        gt = work[i]
        cam, tile = gt // n_tiles, gt % n_tiles
        x0, y0, w, h, xs, ys = _tile(tile, tiles_x, width, height, t_final)
        P = w * h
        T = np.empty(P, t_final.dtype)
        S = np.empty((P, D), t_final.dtype)
        G = np.empty((P, D), t_final.dtype)
        GA = np.empty(P, t_final.dtype)
        TF = np.empty(P, t_final.dtype)
        stop = np.empty(P, np.int64)
        gcol = np.empty(D, t_final.dtype)
        col = np.empty(D, t_final.dtype)
        kmax = offsets[gt]
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
        for k in range(kmax - 1, offsets[gt] - 1, -1):
            g = ids[k]
            mx, my = means2d[cam, g, 0], means2d[cam, g, 1]
            a, b, c = conics[cam, g, 0], conics[cam, g, 1], conics[cam, g, 2]
            o = opacities[g]
            gmx = gmy = ga = gb = gc = go = zero
            for d in range(D):
                gcol[d] = zero
                col[d] = colors[cam, g, d]
            smax = sigma_max[g]
            bx0, bx1, by0, by1 = _box(mx, my, radii[cam, g], x0, y0, x0 + w - 1, y0 + h - 1)
            ok, det, s = _span_params(a, b, c, smax)
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
                    raw = o * e
                    alpha = min(amax, raw)
                    if alpha < amin:
                        continue
                    inv = one / (one - alpha)    # 1 - alpha >= 0.01
                    Ti = T[p] * inv              # transmittance in front of this Gaussian
                    wgt = alpha * Ti
                    cg = zero
                    sg = zero
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
                        continue
                    go += d_alpha * e
                    d_sigma = -d_alpha * alpha
                    gmx -= d_sigma * (a * dx + b * dy)
                    gmy -= d_sigma * (c * dy + b * dx)
                    ga += d_sigma * half * dx * dx
                    gb += d_sigma * dx * dy
                    gc += d_sigma * half * dy * dy
            for d in range(D):
                per_pair[k, 6 + d] = gcol[d]
            per_pair[k, 0] += gmx
            per_pair[k, 1] += gmy
            per_pair[k, 2] += ga
            per_pair[k, 3] += gb
            per_pair[k, 4] += gc
            per_pair[k, 5] += go


@njit(cache=True, nogil=True, parallel=True)
def _backward_replay(means2d, conics, colors, opacities, offsets, ids, work, background, width, height, tiles_x,
                     t_final, last, grad_image, grad_alpha, per_pair, consts, frag_start, frag_pix, frag_e, frag_n):
    """_backward over the fragments the forward recorded: the same updates in the same order (so bitwise the
    same per_pair), without the row spans, the exp and the tests (a recorded fragment is exactly a pixel that
    _backward would process: k < stop[p], sigma in range, alpha >= 1/255)."""
    D = colors.shape[2]
    half, one, amax = consts[0], consts[1], consts[2]
    zero = half - half
    n_tiles = tiles_x * (-(-height // TILE))
    for i in prange(work.shape[0]):
        gt = work[i]
        cam, tile = gt // n_tiles, gt % n_tiles
        x0, y0, w, h, xs, ys = _tile(tile, tiles_x, width, height, t_final)
        P = w * h
        T = np.empty(P, t_final.dtype)
        S = np.empty((P, D), t_final.dtype)
        G = np.empty((P, D), t_final.dtype)
        GA = np.empty(P, t_final.dtype)
        TF = np.empty(P, t_final.dtype)
        gcol = np.empty(D, t_final.dtype)
        col = np.empty(D, t_final.dtype)
        kmax = offsets[gt]
        for p in range(P):
            px, py = x0 + p % w, y0 + p // w
            T[p] = t_final[cam, py, px]
            TF[p] = T[p]
            kmax = max(kmax, last[cam, py, px])
            GA[p] = grad_alpha[cam, py, px]
            for d in range(D):
                G[p, d] = grad_image[cam, py, px, d]
                S[p, d] = T[p] * background[d]
        for k in range(kmax - 1, offsets[gt] - 1, -1):
            nf = frag_n[k]
            if nf == 0:  # per_pair[k] stays 0, as _backward leaves it
                continue
            g = ids[k]
            mx, my = means2d[cam, g, 0], means2d[cam, g, 1]
            a, b, c = conics[cam, g, 0], conics[cam, g, 1], conics[cam, g, 2]
            o = opacities[g]
            gmx = gmy = ga = gb = gc = go = zero
            for d in range(D):
                gcol[d] = zero
                col[d] = colors[cam, g, d]
            fs = frag_start[k]
            for j in range(fs, fs + nf):
                p = np.int64(frag_pix[j])
                dx = xs[p % w] - mx
                dy = ys[p // w] - my
                e = frag_e[j]
                raw = o * e
                alpha = min(amax, raw)
                inv = one / (one - alpha)    # 1 - alpha >= 0.01
                Ti = T[p] * inv              # transmittance in front of this Gaussian
                wgt = alpha * Ti
                cg = zero
                sg = zero
                for d in range(D):
                    gcol[d] += wgt * G[p, d]
                    cg += col[d] * G[p, d]
                    sg += S[p, d] * G[p, d]
                d_alpha = Ti * cg - (sg - GA[p] * TF[p]) * inv
                for d in range(D):
                    S[p, d] += col[d] * wgt
                T[p] = Ti
                if raw > amax:              # clamped: no gradient to opacity or the footprint
                    continue
                go += d_alpha * e
                d_sigma = -d_alpha * alpha
                gmx -= d_sigma * (a * dx + b * dy)
                gmy -= d_sigma * (c * dy + b * dx)
                ga += d_sigma * half * dx * dx
                gb += d_sigma * dx * dy
                gc += d_sigma * half * dy * dy
            for d in range(D):
                per_pair[k, 6 + d] = gcol[d]
            per_pair[k, 0] += gmx
            per_pair[k, 1] += gmy
            per_pair[k, 2] += ga
            per_pair[k, 3] += gb
            per_pair[k, 4] += gc
            per_pair[k, 5] += go


@njit(cache=True, nogil=True, parallel=True)
def _box_areas(means2d, radii, offsets, ids, width, height, tiles_x):
    """Per tile-list entry, the pixel count of its Gaussian's radius box clipped to the tile: an upper bound
    of the fragments the forward can record for it."""
    n_tiles = tiles_x * (-(-height // TILE))
    out = np.empty(ids.shape[0], np.int64)
    for gt in prange(offsets.shape[0] - 1):
        cam, tile = gt // n_tiles, gt % n_tiles
        x0, y0 = (tile % tiles_x) * TILE, (tile // tiles_x) * TILE
        w, h = min(TILE, width - x0), min(TILE, height - y0)
        for k in range(offsets[gt], offsets[gt + 1]):
            g = ids[k]
            bx0, bx1, by0, by1 = _box(means2d[cam, g, 0], means2d[cam, g, 1], radii[cam, g], x0, y0,
                                      x0 + w - 1, y0 + h - 1)
            out[k] = max(0, bx1 - bx0 + 1) * max(0, by1 - by0 + 1)
    return out


@njit(cache=True, nogil=True, parallel=True)
def _reduce(ids, per_pair, offsets, n_cameras, n):
    """Per camera (in parallel: disjoint rows), a serial sum in tile-list order: (C, N, 6 + D)."""
    out = np.zeros((n_cameras, n, per_pair.shape[1]), per_pair.dtype)
    n_tiles = (offsets.shape[0] - 1) // n_cameras
    for c in prange(n_cameras):
        for k in range(offsets[c * n_tiles], offsets[(c + 1) * n_tiles]):
            g = ids[k]
            for j in range(per_pair.shape[1]):
                out[c, g, j] += per_pair[k, j]
    return out


def _parallel(kernel, *args, chunk: int = 0):
    """Run a parallel kernel without letting numba change torch's intra-op thread count (see above).
    ``chunk=1`` (the tile kernels): the prange is handed out one iteration at a time, so a free thread takes
    the next tile of the work list and one expensive tile does not hold a whole static block back (the
    results do not depend on which thread ran a tile). Not for kernels with whole-array operations outside
    their prange (np.zeros, slices): numba turns those into parallel loops too, and chunk 1 hands those out
    element by element (measured: _reduce 80x slower)."""
    threads = torch.get_num_threads()
    old = numba.set_parallel_chunksize(chunk)
    try:
        return kernel(*args)
    finally:
        numba.set_parallel_chunksize(old)
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def _work_order(offsets: np.ndarray) -> np.ndarray:
    """Global tiles, most (tile, Gaussian) pairs first (ties by tile index): with dynamic hand-out the long
    tiles start first and the short ones fill the gaps at the end (longest-processing-time-first)."""
    cost = np.diff(offsets)
    return np.argsort(-cost, kind="stable").astype(np.int64)


def _fragment_buffers(m, r, offsets, ids, width, height, tiles_x, dtype, record: bool) -> tuple:
    """(frag_start, frag_pix, frag_e, frag_n) for the forward to record its fragments in: slots for every
    pixel of every tile-list entry's clipped radius box (an upper bound). Without ``record`` (no input needs a
    gradient) or over FRAGMENT_BUDGET bytes, nothing is recorded (frag_n empty) and a backward recomputes."""
    none = (np.zeros(1, np.int64), np.zeros(0, np.uint8), np.zeros(0, dtype), np.zeros(0, np.int32))
    if not record or len(ids) == 0:
        return none
    areas = _parallel(_box_areas, m, r, offsets, ids, width, height, tiles_x)
    start = np.zeros(len(ids) + 1, np.int64)
    np.cumsum(areas, out=start[1:])
    total = int(start[-1])
    if total * (1 + np.dtype(dtype).itemsize) > FRAGMENT_BUDGET:
        return none
    return start, np.empty(total, np.uint8), np.empty(total, dtype), np.empty(len(ids), np.int32)


def _consts(dtype) -> np.ndarray:
    return np.array([0.5, 1.0, ALPHA_MAX, ALPHA_MIN, T_MIN], dtype)


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


class _RasterizeCPU(torch.autograd.Function):
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
        offsets, ids = _parallel(_bin, m, r, _np(depths), width, height, tiles_x, tiles_y)
        work = _work_order(offsets)
        # alpha >= 1/255 needs sigma <= ln(255 o): beyond that (plus a margin, so the exact alpha test still
        # decides at the boundary) no exp is computed
        with np.errstate(divide="ignore"):
            smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(col.dtype)
        image = np.empty((C, height, width, col.shape[2]), col.dtype)
        t_final = np.empty((C, height, width), col.dtype)
        last = np.empty((C, height, width), np.int64)
        frags = _fragment_buffers(m, r, offsets, ids, width, height, tiles_x, col.dtype,
                                  record=any(ctx.needs_input_grad[:4]))
        _parallel(_forward, m, q, col, o, r, smax, offsets, ids, work, bg, width, height, tiles_x, image, t_final, last,
                  _consts(col.dtype), *frags, chunk=1)
        ctx.save_for_backward(means2d, conics, colors, opacities, background)
        ctx.arrays = (m, q, col, o, r, smax, bg, offsets, ids, work, t_final, last, frags)
        ctx.size = (width, height, tiles_x)
        alpha = torch.from_numpy(1.0 - t_final)[..., None]
        return torch.from_numpy(image), alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        m, q, col, o, r, smax, bg, offsets, ids, work, t_final, last, frags = ctx.arrays
        width, height, tiles_x = ctx.size
        C, N, D = col.shape
        gi = (np.zeros((C, height, width, D), col.dtype) if grad_image is None
              else _np(grad_image).astype(col.dtype, copy=False))
        ga = (np.zeros_like(t_final) if grad_alpha is None
              else _np(grad_alpha).astype(col.dtype, copy=False)[..., 0])
        per_pair = np.zeros((len(ids), 6 + D), col.dtype)
        if frags[3].shape[0] == len(ids):  # the forward recorded its fragments: replay them
            _parallel(_backward_replay, m, q, col, o, offsets, ids, work, bg, width, height, tiles_x, t_final, last,
                      gi, ga, per_pair, _consts(col.dtype), *frags, chunk=1)
        else:
            _parallel(_backward, m, q, col, o, r, smax, offsets, ids, work, bg, width, height, tiles_x, t_final, last,
                      gi, ga, per_pair, _consts(col.dtype), chunk=1)
        g = _parallel(_reduce, ids, per_pair, offsets, C, N)
        means2d, conics, colors, opacities, background = ctx.saved_tensors
        grad_bg = None
        if ctx.needs_input_grad[8]:
            grad_bg = torch.from_numpy((gi * t_final[..., None]).sum(axis=(1, 2)).sum(axis=0)).to(background.dtype)
        g_op = g[0, :, 5].copy()
        for c in range(1, C):  # fixed camera order
            g_op += g[c, :, 5]
        g_col = g[:, :, 6:]
        if ctx.shared_colors:
            g_sum = g_col[0].copy()
            for c in range(1, C):
                g_sum += g_col[c]
            g_col = g_sum
        t = torch.from_numpy
        return (t(np.ascontiguousarray(g[..., 0:2])).to(means2d.dtype),
                t(np.ascontiguousarray(g[..., 2:5])).to(conics.dtype), t(np.ascontiguousarray(g_col)).to(colors.dtype),
                t(g_op).to(opacities.dtype), None, None, None, None, grad_bg)


def rasterize_cpu(means2d, conics, colors, opacities, depths, radii, width: int, height: int,
                  background=None, threads: int | None = None):
    """Same signature and result as reference.rasterize_reference: (image (H,W,D), alpha (H,W,1)). Batched
    over C cameras when means2d is (C,N,2) (conics (C,N,3), depths/radii (C,N), colors (C,N,D) or shared
    (N,D)): (C,H,W,D), (C,H,W,1), every camera's gradients exactly those of its own single-camera call."""
    if background is None:
        background = torch.zeros(colors.shape[-1], dtype=colors.dtype)
    if threads is not None:
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    batched = means2d.ndim == 3
    if not batched:
        means2d, conics, depths, radii = means2d[None], conics[None], depths[None], radii[None]
    image, alpha = _RasterizeCPU.apply(means2d, conics, colors, opacities, depths, radii, int(width), int(height),
                                       background.to(colors.dtype))
    return (image, alpha) if batched else (image[0], alpha[0])
