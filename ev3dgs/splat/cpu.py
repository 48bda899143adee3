"""The `cpu` backend: exact tile rasterization with hand-written forward and backward kernels (numba).

Same semantics and constants as `reference` (front-to-back, alpha = min(0.99, o*exp(-sigma)), skip
sigma < 0 or alpha < 1/255, stop before a Gaussian that would take T below 1e-4), but:

* binning (one numba call, cameras in parallel, and chunks of a camera when there are fewer cameras than
  threads): per camera the Gaussians are depth-sorted once, then counted and placed per 16x16 tile (a
  counting sort), so every tile's list is already in depth order.
  Nothing is dropped: a Gaussian goes to every tile its pixel box touches (its opacity-aware, exact radius
  box cut to the bounds of its cut-off ellipse, cpu_tiles._pixel_boxes), so the per-tile lists hold every
  Gaussian that can reach a pixel.
* packing (cpu_tiles._pack): each tile-list entry's Gaussian data (mean, conic, opacity, cut-off, colour)
  copied in list order, so the tile kernels stream it instead of gathering it from per-Gaussian arrays, and
  its pixel box: the radius box clipped to the tile and to the axis-aligned bounds of the cut-off ellipse
  (the radius box is a square around the longest axis; on a trained demo step 57 % of its pixels lay
  outside the ellipse).
* forward: per tile, Gaussians outer and the tile's pixels inner; per pixel it keeps T and the index after
  the last Gaussian it composited. Per row of a Gaussian's box (at least SPAN_MIN_WIDTH wide) only the
  pixels inside its cut-off ellipse (sigma <= ln(255 o), solved per row, conservatively) are visited: about
  half of the box. Tiles run in parallel when threads > 1: sorted most expensive first and dealt out round
  robin to the threads (a prange over threads; numba's own split of a prange into contiguous blocks gave one
  thread all the expensive tiles of a cost-sorted list, so 2 threads ran no faster than one). When a
  gradient will be needed it records every fragment it composites (the pixel's index in its tile and
  exp(-sigma), in slots bounded by each entry's clipped box area; FRAGMENT_BUDGET caps the memory).
* backward: per tile, Gaussians in reverse depth order; T is recovered by dividing by (1 - alpha) >= 0.01,
  the colour behind each Gaussian is accumulated, and gradients go to a per-(tile, Gaussian) buffer that a
  serial pass sums per Gaussian. No atomics, and the result does not depend on the thread count. It
  replays the recorded fragments (no spans, exp or tests: ~2.4x faster than recomputing them); over the
  budget it recomputes them (the same updates in the same order: bitwise the same gradients, tested).

float32 calls (the training dtype) run the same tile kernels written in C with 8-lane SIMD when the
optional extension is built (cpu_simd.py: the same rules and schedule, exp(-sigma) from a polynomial with a
stated error bound), and the stages around them in C too: the packing from one record per (camera, Gaussian)
(cpu_simd.records / pack, bitwise _pack, the fragment slots counted in the same pass), the backward writing
every per-pair row (no zeroed buffer) and the per-Gaussian sum (cpu_simd.reduce, bitwise _reduce); float64
calls, and every call without the extension, run the numba kernels here.

Batched: C cameras share one call. Their tile lists are concatenated (camera c's tile t is global tile
c * n_tiles + t), so forward and backward are one parallel loop over (camera, tile), and the per-pair
gradients are summed per camera in the same order as a single-camera call: bitwise the same result.

Determinism: forward and backward are bitwise the same for any numba thread count (tiles own disjoint
pixels and disjoint per-pair gradient slots; the per-Gaussian sum is serial, in tile-list order). One side
effect had to be contained: numba's "omp" threading layer shares the OpenMP runtime with torch, and
launching its thread pool sets OpenMP's thread count, i.e. torch's intra-op thread count, to numba's. The
kernels are therefore called through `_parallel`, which puts torch's thread count back, and numba's thread
count is set through `set_numba_threads`: the first ``numba.set_num_threads`` of a process is what launches
the pool (with NUMBA_NUM_THREADS threads), before any kernel runs.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

# the kernels live in cpu_tiles.py (constants, boxes, spans, depth sort, binning) and cpu_backward.py; the
# names tests and tools reach through this module are imported here
from .. import numba_cache
from . import cpu_simd
from .cpu_backward import _backward, _reduce
from .cpu_tiles import ALPHA_MAX, ALPHA_MIN, SPAN_MIN_WIDTH, T_MIN, TILE  # noqa: F401
from .cpu_tiles import _bin, _box, _ellipse_box, _entry, _pack, _pixel_boxes, _row_span, _span_params, _stable_argsort, _tile  # noqa: F401

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


def announce_compile() -> None:
    """A one-line notice on stderr before the first process on a machine compiles the CPU kernels."""
    if "splat-cpu" in numba_cache._NOTIFIED:  # told (or not needed) already: every later call returns here
        return
    import sys

    from ..numba_cache import notify_first_compile
    from . import cpu_backward, cpu_tiles, project_cpu

    notify_first_compile("splat-cpu", [sys.modules[__name__], cpu_tiles, cpu_backward, project_cpu],
                         "CPU rasterizer kernels", "about a minute on 2 cores")


def _parallel(kernel, *args):
    """Run a parallel kernel (or anything that may start numba's pool) without letting numba change torch's
    intra-op thread count (see above)."""
    threads = torch.get_num_threads()
    try:
        return kernel(*args)
    finally:
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def set_numba_threads(threads: int) -> None:
    """numba's thread count for the kernels that follow (at most NUMBA_NUM_THREADS), torch's left as it was
    (a process's first call starts numba's pool: see above)."""
    _parallel(numba.set_num_threads, max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


def _work_order(offsets: np.ndarray) -> np.ndarray:
    """Global tiles, most (tile, Gaussian) pairs first (ties by tile index). The tile kernels deal them out
    round robin (thread t takes work[t], work[t + T], ...), so each thread gets a near-equal share of the
    expensive and the cheap tiles; which thread ran a tile does not change any result."""
    cost = np.diff(offsets)
    return np.argsort(-cost, kind="stable").astype(np.int64)


def _threads(work: np.ndarray) -> int:
    """How many threads the tile kernels deal the work list to: numba's thread count (thread-local, as
    rasterize_cpu set it), at most one per tile, at least one."""
    return max(1, min(numba.get_num_threads(), len(work)))


def _per_camera(n_cameras: int) -> int:
    """Work items per camera for the binning, which is parallel over cameras: enough that fewer cameras
    than threads still keep every thread busy; 1 when there are at least as many cameras as threads."""
    return max(1, -(-numba.get_num_threads() // max(1, n_cameras)))


def _simd_frags(frags: tuple) -> tuple:
    """The C kernels' fragment buffers: (frag_start, frag_e, frag_n), without frag_pix (the numba kernels')."""
    return frags[::2] + frags[3:]


def _fragment_buffers(boxes, dtype, simd=False, *, record: bool, start=None) -> tuple:
    """(frag_start, frag_pix, frag_e, frag_n) for the forward to record its fragments in: slots for every
    pixel of every tile-list entry's box (an upper bound); for the C kernels (``simd``) 8 slots per box row
    and group of 8 tile columns, exp(-sigma) only (frag_pix empty), counted per entry by cpu_simd.pack
    (``start``; None: over the budget). Without ``record`` (no input needs a gradient) or over
    FRAGMENT_BUDGET bytes, nothing is recorded (frag_n empty) and a backward recomputes."""
    none = (np.zeros(1, np.int64), np.zeros(0, np.uint8), np.zeros(0, dtype), np.zeros(0, np.int32))
    if not record or len(boxes) == 0 or (simd and start is None):
        return none
    if simd:
        per_slot = np.dtype(dtype).itemsize
    else:
        b = boxes.astype(np.int64)
        slots = (b[:, 1] - b[:, 0] + 1) * (b[:, 3] - b[:, 2] + 1)  # empty boxes are stored as (0, -1, 0, -1): 0
        per_slot = 1 + np.dtype(dtype).itemsize
        start = np.zeros(len(boxes) + 1, np.int64)
        np.cumsum(slots, out=start[1:])
    total = int(start[-1])
    if total * per_slot > FRAGMENT_BUDGET:
        return none
    pix = np.empty(0 if simd else total, np.uint8)
    return start, pix, np.empty(total, dtype), np.empty(len(boxes), np.int32)


def _consts(dtype) -> np.ndarray:
    return np.array([0.5, 1.0, ALPHA_MAX, ALPHA_MIN, T_MIN], dtype)


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, width, height, background):
        """Batched: means2d (C,N,2), conics (C,N,3), colors (C,N,D) or shared (N,D), depths and radii (C,N)."""
        # an output without a gradient reaches the backward as None, not as a zero tensor autograd would fill
        ctx.set_materialize_grads(False)
        dtype = colors.dtype
        m, q, col, o = (_np(x.to(dtype)) for x in (means2d, conics, colors, opacities))
        C, N, D = m.shape[0], m.shape[1], col.shape[-1]
        ctx.shared_colors = col.ndim == 2
        bg = _np(background.to(dtype))
        r = _np(radii).astype(np.int64)
        tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
        # alpha >= 1/255 needs sigma <= ln(255 o): beyond that (plus a margin, so the exact alpha test still
        # decides at the boundary) no exp is computed, and no tile or pixel outside that ellipse is visited
        with np.errstate(divide="ignore"):
            smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(col.dtype)
        ctx.simd = cpu_simd.active(col.dtype, D)  # the C kernels (float32), else numba's
        gboxes = _parallel(_pixel_boxes, m, r, q, smax, width, height)  # (numba's: faster than a plain C loop)
        d = _np(depths)
        # bitwise _bin's lists in C on one thread (serial: with more threads numba's, parallel over cameras)
        if cpu_simd.bin_active(d) and numba.get_num_threads() == 1:
            offsets, ids = cpu_simd.bin(gboxes, r, d, tiles_x, tiles_y)
        else:
            offsets, ids = _parallel(_bin, gboxes, r, d, tiles_x, tiles_y, _per_camera(C))
        work = _work_order(offsets)
        image = np.empty((C, height, width, D), col.dtype)
        t_final = np.empty((C, height, width), col.dtype)
        last = np.empty((C, height, width), np.int64)
        record = any(ctx.needs_input_grad[:4])
        if ctx.simd:
            # the entries packed in C from one record per Gaussian (cpu_simd.records: no broadcast copy of
            # shared colours, one gather per entry instead of six), bitwise _pack's result
            recs, slots = cpu_simd.records(m, q, col, o, smax, gboxes)
            fits = slots * np.dtype(col.dtype).itemsize <= FRAGMENT_BUDGET  # else not counted per entry
            params, boxes, fstart = cpu_simd.pack(recs, ids, offsets, C, N, D, width, height, record and fits,
                                                  _threads(work))
            frags = _fragment_buffers(boxes, col.dtype, True, record=record, start=fstart)
            cpu_simd.forward(params, boxes, offsets, work, bg, width, height, tiles_x, image, t_final, last,
                             _simd_frags(frags), _threads(work))
        else:
            if ctx.shared_colors:
                col = np.ascontiguousarray(np.broadcast_to(col, (C,) + col.shape))
            params, boxes = _parallel(_pack, m, q, col, o, smax, offsets, ids, gboxes, width, height, tiles_x)
            frags = _fragment_buffers(boxes, col.dtype, record=record)
            _parallel(_forward, params, boxes, offsets, work, bg, width, height, tiles_x, image, t_final, last,
                      _consts(col.dtype), *frags, _threads(work))
        ctx.arrays = (params, boxes, bg, offsets, ids, work, t_final, last, frags)
        ctx.save_for_backward(means2d, conics, colors, opacities, background)
        ctx.size = (width, height, tiles_x, C, N, D)
        alpha = torch.from_numpy(1.0 - t_final)[..., None]
        return torch.from_numpy(image), alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        width, height, tiles_x, C, N, D = ctx.size
        params, boxes, bg, offsets, ids, work, t_final, last, frags = ctx.arrays
        dtype = t_final.dtype
        gi = (np.zeros((C, height, width, D), dtype) if grad_image is None
              else _np(grad_image).astype(dtype, copy=False))
        ga = (np.zeros_like(t_final) if grad_alpha is None
              else _np(grad_alpha).astype(dtype, copy=False)[..., 0])
        # replays the fragments when the forward recorded them (frags not empty), else recomputes them
        if ctx.simd:
            per_pair = np.empty((len(ids), 6 + D), dtype)  # every row written by the C backward
            cpu_simd.backward(params, boxes, offsets, work, bg, width, height, tiles_x, t_final, last,
                              np.ascontiguousarray(gi), np.ascontiguousarray(ga), per_pair, _simd_frags(frags),
                              _threads(work), write_rows=True)
            g_mean, g_conic, g_ops, g_col = cpu_simd.reduce(per_pair, ids, offsets, C, N, _threads(work))
        else:
            per_pair = np.zeros((len(ids), 6 + D), dtype)
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


def rasterize_cpu(means2d, conics, colors, opacities, depths, radii, width: int, height: int,
                  background=None, threads: int | None = None):
    """Same signature and result as reference.rasterize_reference: (image (H,W,D), alpha (H,W,1)). Batched
    over C cameras when means2d is (C,N,2) (conics (C,N,3), depths/radii (C,N), colors (C,N,D) or shared
    (N,D)): (C,H,W,D), (C,H,W,1), every camera's gradients exactly those of its own single-camera call."""
    if background is None:
        background = torch.zeros(colors.shape[-1], dtype=colors.dtype)
    if threads is not None:
        set_numba_threads(threads)
    batched = means2d.ndim == 3
    if not batched:  # views in and out (unsqueeze / squeeze: their backward is a view too, no copy)
        means2d, conics, depths, radii = (t.unsqueeze(0) for t in (means2d, conics, depths, radii))
    image, alpha = _RasterizeCPU.apply(means2d, conics, colors, opacities, depths, radii, int(width), int(height),
                                       background.to(colors.dtype))
    return (image, alpha) if batched else (image.squeeze(0), alpha.squeeze(0))
