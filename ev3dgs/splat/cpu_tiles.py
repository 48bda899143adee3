"""Tiles and binning of the `cpu` backend (see cpu.py): the constants shared with `reference`, a Gaussian's
pixel box and per-row ellipse span, tile geometry, the depth sort and the (camera, tile) lists."""
from __future__ import annotations

import numpy as np
from numba import njit, prange

TILE = 16
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
# boxes narrower than this many pixels are walked whole: solving each row's span costs more than the pixels it
# skips (measured on a trained demo model, radii 2-4 px: forward ~10 % faster; same pixels composited)
SPAN_MIN_WIDTH = 10


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
    (1 + rho) / (1 - rho) times sigma for the positive-definite form (rho = |b| / sqrt(ac) < 1), which is
    (1 + rho)^2 ac / det <= 4 ac / det; so an inflation of 4e-6 ac / det (> 16 u times that bound; no square
    root) relative, plus 1e-9 absolute, covers it. Not
    positive definite (ok False): no span, the caller keeps the whole box row (the kernel skips sigma < 0).
    Nor for a box narrower than SPAN_MIN_WIDTH (``box_width`` = x1 - x0): the whole row costs less there."""
    if box_width < SPAN_MIN_WIDTH:
        return False, 0.0, 0.0
    a64, b64, c64 = np.float64(a), np.float64(b), np.float64(c)
    det = a64 * c64 - b64 * b64
    if not (a64 > 0.0 and det > 0.0):
        return False, det, 0.0
    s = np.float64(smax) * (1.0 + 4e-6 * (a64 * c64 / det)) + 1e-9
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
    lo = max(centre - root / a64 - 1e-6, bx0 - 1.0)  # clamped before the int conversion (no int64 overflow)
    hi = min(centre + root / a64 + 1e-6, bx1 + 1.0)
    return max(bx0, int(np.ceil(lo))), min(bx1, int(np.floor(hi)))


@njit(cache=True, nogil=True, inline="always")
def _tile(gt, n_tiles, tiles_x, width, height, like):
    """Global tile gt (camera cam's tile gt % n_tiles) -> (cam, origin, size, pixel-centre coordinates in
    like's dtype, so float32 maths stays float32)."""
    cam, tile = gt // n_tiles, gt % n_tiles
    x0, y0 = (tile % tiles_x) * TILE, (tile // tiles_x) * TILE
    w, h = min(TILE, width - x0), min(TILE, height - y0)
    xs = np.empty(w, like.dtype)
    ys = np.empty(h, like.dtype)
    for i in range(w):
        xs[i] = x0 + i
    for i in range(h):
        ys[i] = y0 + i
    return cam, x0, y0, w, h, xs, ys


@njit(cache=True, nogil=True, inline="always")
def _entry(params, k, col):
    """Tile-list entry k's packed data (see _pack) for a tile kernel: (mx, my, a, b, c, opacity, sigma_max);
    its colour into col."""
    for d in range(col.shape[0]):
        col[d] = params[k, 7 + d]
    return params[k, 0], params[k, 1], params[k, 2], params[k, 3], params[k, 4], params[k, 5], params[k, 6]


@njit(cache=True, nogil=True, inline="always")
def _ellipse_box(mx, my, a, b, c, smax, bx0, bx1, by0, by1):
    """The box [bx0, bx1] x [by0, by1] shrunk to the axis-aligned bounds of the Gaussian's cut-off ellipse
    sigma <= s (s: smax inflated against the kernel's rounding, as in _span_params): for sigma = 0.5 d^T Q d,
    Q = [[a, b], [b, c]], the half-widths are sqrt(2 s c / det) in x and sqrt(2 s a / det) in y, widened by
    1e-6 px against this float64 solve. The radius box is a square around the ellipse's longest axis, so for
    an elongated Gaussian this one is much smaller (on a trained demo step 57 % of the pixels the square boxes
    visited were outside the ellipse). Not positive definite, or smax not finite: the box as given; s <= 0:
    empty (a kernel only composites 0 <= sigma <= smax)."""
    ok, det, s = _span_params(a, b, c, smax)
    if not ok or not np.isfinite(s):
        return bx0, bx1, by0, by1
    if s <= 0.0:
        return 0, -1, 0, -1
    k = 2.0 * s / det
    hx = np.sqrt(k * np.float64(c)) + 1e-6
    hy = np.sqrt(k * np.float64(a)) + 1e-6
    # bounds clamped to one pixel outside the box before the int conversion: a huge (or infinite) half-width
    # of a nearly flat form must not overflow int64 (which would wrap the box to empty)
    bx0 = max(bx0, int(np.ceil(max(np.float64(mx) - hx, bx0 - 1.0))))
    bx1 = min(bx1, int(np.floor(min(np.float64(mx) + hx, bx1 + 1.0))))
    by0 = max(by0, int(np.ceil(max(np.float64(my) - hy, by0 - 1.0))))
    by1 = min(by1, int(np.floor(min(np.float64(my) + hy, by1 + 1.0))))
    if bx0 > bx1 or by0 > by1:
        return 0, -1, 0, -1
    return bx0, bx1, by0, by1


@njit(cache=True, nogil=True, parallel=True)
def _pixel_boxes(means2d, radii, conics, sigma_max, width, height):
    """(C, N, 4) int32: the pixels (x0, x1, y0, y1) Gaussian g can reach in camera c's image, its radius box
    clipped to the image and to its cut-off ellipse's bounds (_ellipse_box); (0, -1, 0, -1) when empty or
    not visible (radius 0). Gaussians in parallel, in index order (the binning then reads one small record
    per Gaussian in depth order instead of its mean, radius and conic)."""
    C, N = radii.shape
    out = np.empty((C, N, 4), np.int32)
    for g in prange(N):
        for c in range(C):
            x0, x1, y0, y1 = 0, -1, 0, -1
            if radii[c, g] > 0:
                x0, x1, y0, y1 = _box(means2d[c, g, 0], means2d[c, g, 1], radii[c, g], 0, 0, width - 1, height - 1)
                if x0 > x1 or y0 > y1:
                    x0, x1, y0, y1 = 0, -1, 0, -1
                else:
                    x0, x1, y0, y1 = _ellipse_box(means2d[c, g, 0], means2d[c, g, 1], conics[c, g, 0],
                                                  conics[c, g, 1], conics[c, g, 2], sigma_max[g], x0, x1, y0, y1)
            out[c, g, 0] = x0
            out[c, g, 1] = x1
            out[c, g, 2] = y0
            out[c, g, 3] = y1
    return out


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


@njit(cache=True, nogil=True, inline="always")
def _tile_rect(boxes, c, g):
    """Tiles (tx0, tx1, ty0, ty1) of Gaussian g's pixel box in camera c; an empty box, stored as
    (0, -1, 0, -1), gives the empty range tx0 = 0 > tx1 = -1."""
    return boxes[c, g, 0] // TILE, boxes[c, g, 1] // TILE, boxes[c, g, 2] // TILE, boxes[c, g, 3] // TILE


@njit(cache=True, nogil=True, parallel=True)
def _bin(boxes, radii, depths, tiles_x, tiles_y, n_chunks=1):
    """Counting sort of (camera, tile, Gaussian) triples, all cameras at once. Per camera the visible
    Gaussians (radius > 0) are put in depth order by a stable sort (ties by index), then counted and placed
    in every tile their pixel box (boxes (C, N, 4) from _pixel_boxes) touches, so every tile's list is in
    depth order. Returns (offsets (C * n_tiles + 1,), ids): camera c's tile t (global tile c * n_tiles + t)
    holds ids[offsets[g]:offsets[g + 1]], front to back.

    Parallel over (camera, chunk): each camera's depth order is cut into ``n_chunks`` consecutive pieces
    (more than one where there are fewer cameras than threads), each counted and placed by one thread into
    its own slots (tile by tile, the chunks' slots follow each other in depth order), so the lists are the
    same for any n_chunks and thread count."""
    C, N = radii.shape
    n_tiles = tiles_x * tiles_y
    orders = np.empty((C, N), np.int64)
    # each camera's boxes copied in depth order: the count and place passes below then read them as a stream
    # instead of gathering each box twice from a random place
    boxes_sorted = np.empty((C, N, 4), np.int32)
    n_vis = np.zeros(C, np.int64)
    for c in prange(C):
        vis = np.flatnonzero(radii[c] > 0)
        order = vis[_stable_argsort(depths[c][vis])]
        n_vis[c] = order.shape[0]
        orders[c, :order.shape[0]] = order
        for j in range(order.shape[0]):
            for q in range(4):
                boxes_sorted[c, j, q] = boxes[c, order[j], q]
    n_items = C * n_chunks
    counts = np.zeros((n_items, n_tiles), np.int64)
    for item in prange(n_items):
        c, ch = item // n_chunks, item % n_chunks
        for j in range(ch * n_vis[c] // n_chunks, (ch + 1) * n_vis[c] // n_chunks):
            tx0, tx1, ty0, ty1 = _tile_rect(boxes_sorted, c, j)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[item, ty * tiles_x + tx] += 1
    offsets = np.empty(C * n_tiles + 1, np.int64)
    starts = np.empty((n_items, n_tiles), np.int64)
    pos = 0
    for c in range(C):  # serial prefix sum over (camera, tile, chunk)
        for t in range(n_tiles):
            offsets[c * n_tiles + t] = pos
            for ch in range(n_chunks):
                starts[c * n_chunks + ch, t] = pos
                pos += counts[c * n_chunks + ch, t]
    offsets[C * n_tiles] = pos
    ids = np.empty(pos, np.int64)
    for item in prange(n_items):
        c, ch = item // n_chunks, item % n_chunks
        fill = starts[item].copy()
        for j in range(ch * n_vis[c] // n_chunks, (ch + 1) * n_vis[c] // n_chunks):
            g = orders[c, j]
            tx0, tx1, ty0, ty1 = _tile_rect(boxes_sorted, c, j)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * tiles_x + tx
                    ids[fill[t]] = g
                    fill[t] += 1
    return offsets, ids


@njit(cache=True, nogil=True, parallel=True)
def _pack(means2d, conics, colors, opacities, sigma_max, offsets, ids, gboxes, width, height, tiles_x):
    """The tile kernels' inputs per tile-list entry, in list order: entry k (Gaussian g = ids[k] as its
    camera sees it, in its tile) gets params[k] = (mx, my, a, b, c, opacity, sigma_max, colour...) in the
    colours' dtype and boxes[k] = (bx0, bx1, by0, by1), g's pixel box (_bin's gboxes: radius box and cut-off
    ellipse bounds) clipped to the tile ((0, -1, 0, -1) when empty): every pixel k can composite lies
    inside, so its area bounds the fragments k can have. The forward and backward kernels then read their
    entries as one forward stream instead of gathering each from five per-Gaussian arrays."""
    n_tiles = tiles_x * (-(-height // TILE))
    D = colors.shape[2]
    params = np.empty((ids.shape[0], 7 + D), colors.dtype)
    boxes = np.empty((ids.shape[0], 4), np.int32)
    for gt in prange(offsets.shape[0] - 1):
        cam, x0, y0, w, h, _, _ = _tile(gt, n_tiles, tiles_x, width, height, params)
        for k in range(offsets[gt], offsets[gt + 1]):
            g = ids[k]
            params[k, 0] = means2d[cam, g, 0]
            params[k, 1] = means2d[cam, g, 1]
            params[k, 2] = conics[cam, g, 0]
            params[k, 3] = conics[cam, g, 1]
            params[k, 4] = conics[cam, g, 2]
            params[k, 5] = opacities[g]
            params[k, 6] = sigma_max[g]
            for d in range(D):
                params[k, 7 + d] = colors[cam, g, d]
            bx0, bx1 = max(x0, gboxes[cam, g, 0]), min(x0 + w - 1, gboxes[cam, g, 1])
            by0, by1 = max(y0, gboxes[cam, g, 2]), min(y0 + h - 1, gboxes[cam, g, 3])
            if bx0 > bx1 or by0 > by1:
                bx0, bx1, by0, by1 = 0, -1, 0, -1
            boxes[k, 0] = bx0
            boxes[k, 1] = bx1
            boxes[k, 2] = by0
            boxes[k, 3] = by1
    return params, boxes
