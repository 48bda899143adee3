"""The `cpu` backend's SIMD tile kernels (`_raster.c`, a C extension called through ctypes), float32 only.

Same tiles, entries, rules and work list as the numba kernels in cpu.py / cpu_backward.py, but per tile-list
entry and row of its (tile-clipped) pixel box, the pixels run 8 at a time in SIMD lanes (columns x0 ... x0 + 7
from the box's first column x0, then x0 + 8 ...; no per-row span solve: the lanes' sigma test decides),
with per-lane masks instead of branches (inside the box, pixel not done, 0 <= sigma <= sigma_max,
alpha >= 1/255, T (1 - alpha) >= 1e-4; one branch skips a group whose mask is empty before its exp: 74 %
of the groups on a dense 346x260 scene), on structure-of-arrays tile state (T, each colour channel, stop,
done). The forward records exp(-sigma) densely per (box row, lane group) slot, 0 where it composited
nothing, so the backward replays the same lanes with masks (no exp, no tests); over the fragment budget
it recomputes them with the same exp and tests (bitwise the same gradients). Gradients are accumulated per
lane and summed over the 8 lanes in a fixed order at the end of each entry.

Vehicle, by measurement: numba's LLVM did not vectorise an 8-lane rewrite of the numba kernel (it ran
0.41-0.63x as fast as the scalar one), so the lanes are written explicitly with GCC/clang vector extensions.
The extension holds two builds of the same code, AVX2 (ymm registers: the packed vmulps / vaddps / vdivps /
vcmpps / vblendvps / vpslld ymm instructions can be seen with ``objdump -d`` on the built module) and the
compiler's baseline (SSE2 on x86_64: each operation on two xmm halves), chosen at run time by
``__builtin_cpu_supports("avx2")``: the wheel is built without -march and runs on any CPU. Compiled with
-ffp-contract=off (no FMA), both builds do the same float32 operations in the same order: bitwise the
same results (tested).

Exactness. sigma, alpha, the transmittance and the compositing are the numba kernel's float32 operations
in its order, so only three things differ from it:

* exp(-sigma) comes from a polynomial (`EXP_REL_ERROR`): x = -sigma = n ln2 + f, n = round(x / ln2),
  f = (x - n C1) - n C2 with Cody-Waite's split ln2 = C1 + C2 (C1 = 0.693359375 has 9 significant bits, so
  n C1 is exact for |n| <= 126; the first subtraction is exact by Sterbenz's lemma where n != 0, |f| <=
  ln2 / 2 + a rounding), then exp(f) = 1 + f + f^2 P(f) with Cephes' degree-5 expf minimax P, and 2^n
  put in the exponent bits (exact; inputs are clamped to sigma <= 87, no subnormals). With u = 2^-24 the
  relative error is at most: reduction, f's one rounding (|f| u <= 0.35 u) and C1 + C2 - ln2 (|n| 2.3e-11
  <= 3e-9 over the whole range, 2e-10 for sigma <= 5.6); P's approximation error (max |1 + f + f^2 P(f) -
  e^f| / e^f over |f| <= 0.35 in exact arithmetic: < 0.22 u, computed in tests/test_splat_simd.py); the
  rounding of f^2 P (P by Estrin's scheme, for a shorter dependency chain: <= 9 roundings of a term <= 0.07
  of the result: <= 0.7 u) and the two final additions (f + f^2 P, |.| <= 0.41, then + 1, against a result
  >= 0.7: <= 0.6 u + u); the product by 2^n is exact. In all <= 2.9 u + 3e-9 < 3 u, stated with a margin as
  EXP_REL_ERROR = 2^-22 (4 u = 2.4e-7), which the tests check, not assume: every float32 sigma in
  [0, ln(255 * 0.99) + 1e-6] (a slow test; measured maximum 1.31 u = 7.8e-8 at sigma = 5.286) and a
  strided sample of it (default) against float64 exp, and property-wise over [0, 87] (measured 1.38 u on a
  2e7-point sweep). libm's float32 exp (the numba kernels') is within about 1 u, so the two kernels'
  alphas differ by at most ~5 u relative.
* the order of a Gaussian's gradient sum: per lane, then the 8 lanes (numba: fragment by fragment).
* the backward keeps the dot product of the colour behind a fragment with the pixel's image gradient as one
  running sum (it grows by (colour . G) * weight per fragment) instead of the colour behind per channel:
  D - 1 fewer loads, stores and products per lane group, a different rounding.

Both are tolerances in tests/test_splat_simd.py, derived there. Fragments whose sigma or alpha lie within
a few u of a cut-off may be composited by one kernel and not the other (as between the numba kernel and
`reference`); the tests allow for that as the existing float32 tests do.

Threads: C pthreads (the GIL released by ctypes) over the cost-sorted work list (cpu._work_order, the
numba kernels' list), each thread taking the next tile when it is free (a shared atomic counter; the numba
kernels deal the list round robin instead: tools/bench/schedule.py compares the two on measured per-tile
times). Tiles own disjoint pixels and per-pair rows, so every result is bitwise the same for any thread
count and whichever thread ran a tile (tested).

The stages around the kernels (same extension, scalar C: they move data or do float64 arithmetic in the
numba stages' order, so their results are bitwise those of the numba stages, tested): ``records`` (one
64-byte record per camera and Gaussian: kernel inputs and pixel box) and ``pack`` (cpu_tiles._pack from
the records, one gather per entry, and the fragment slots per entry), the backward's ``write_rows`` (every
per-pair row written, no zeroed buffer), ``reduce`` (cpu_backward._reduce), and ``project_forward`` /
``project_backward`` (project_cpu's kernels, float32 inputs, 4 Gaussians per vector of float64 lanes).

Used when the extension was built and imported, the colours are float32 with at most DMAX channels and
KERNEL is "simd" (the default; the environment variable EV3DGS_CPU_KERNEL=numba, or setting KERNEL, selects
the numba kernels, which serve float64 and are the fallback without a C compiler).
"""
from __future__ import annotations

import ctypes
import os

import numpy as np

try:
    from . import _raster as _ext
except ImportError:  # built without a C compiler: the numba kernels run
    _ext = None

KERNEL = os.environ.get("EV3DGS_CPU_KERNEL", "simd")  # "simd" or "numba" (tests and benchmarks compare them)
ISA = -1  # -1: best build for this CPU, 0: the portable build, 1: AVX2 (where the CPU has it)
DMAX = 8  # colour channels the C kernels serve (as in _raster.c)
LANES = 8
# benchmarks: a list to which every call appends ("forward" or "backward", per-tile thread CPU time in ns)
TILE = 16   # the C kernels' tile side, as cpu_tiles.TILE
TILE_TIMES: list | None = None
# exp(-sigma)'s relative error bound (derivation above), and the unit roundoff of float32
U32 = 2.0 ** -24
EXP_REL_ERROR = 2.0 ** -22

_P = ctypes.c_void_p
_I = ctypes.c_int64


class Job(ctypes.Structure):
    """_raster.c's job_t."""
    _fields_ = [("params", _P), ("boxes", _P), ("offsets", _P), ("work", _P), ("n_work", _I),
                ("background", _P), ("D", _I), ("width", _I), ("height", _I), ("tiles_x", _I), ("n_tiles", _I),
                ("image", _P), ("t_final", _P), ("last", _P), ("frag_start", _P), ("frag_e", _P),
                ("frag_n", _P), ("record", _I), ("grad_image", _P), ("grad_alpha", _P), ("per_pair", _P),
                ("n_threads", _I), ("isa", _I), ("tile_ns", _P), ("write_rows", _I)]


_D = ctypes.c_double


class Proj(ctypes.Structure):
    """_raster.c's proj_t."""
    _fields_ = [("means", _P), ("quats", _P), ("scales", _P), ("opac", _P), ("sh", _P), ("N", _I), ("C", _I),
                ("KS", _I), ("deg", _I), ("width", _I), ("height", _I), ("vm", _P), ("campos", _P), ("cam", _P),
                ("near", _D), ("far", _D), ("eps2d", _D), ("alpha_min", _D), ("radius_margin", _D),
                ("means2d", _P), ("conics", _P), ("depths", _P), ("colors", _P), ("radii", _P),
                ("g_m2d", _P), ("g_con", _P), ("g_dep", _P), ("g_col", _P),
                ("g_means", _P), ("g_quats", _P), ("g_scales", _P), ("g_sh", _P), ("want_vm", _I), ("g_vm", _P),
                ("n_threads", _I), ("isa", _I)]


_lib = None


def _load():
    """The extension's shared object as a ctypes library (ctypes.CDLL releases the GIL during calls)."""
    global _lib
    if _lib is None and _ext is not None:
        lib = ctypes.CDLL(_ext.__file__)
        for name in ("ev3dgs_raster_forward", "ev3dgs_raster_backward"):
            getattr(lib, name).argtypes = [ctypes.POINTER(Job)]
            getattr(lib, name).restype = ctypes.c_int
        lib.ev3dgs_raster_isa.argtypes = [_I]
        lib.ev3dgs_raster_isa.restype = ctypes.c_int
        lib.ev3dgs_exp_neg.argtypes = [_P, _P, _I, _I]
        lib.ev3dgs_exp_neg.restype = None
        lib.ev3dgs_raster_records.argtypes = [_P, _I, _I, _I, _I, _P, _P, _P, _I, _P, _P, _P]
        lib.ev3dgs_raster_records.restype = ctypes.c_int64
        lib.ev3dgs_raster_pack.argtypes = [_P, _P, _P, _I, _I, _I, _I, _I, _I, _I, _P, _P, _P, _I]
        lib.ev3dgs_raster_pack.restype = ctypes.c_int64
        lib.ev3dgs_raster_reduce.argtypes = [_P, _P, _P, _I, _I, _I, _I, _P, _P, _P, _P, _P, _I]
        lib.ev3dgs_raster_reduce.restype = ctypes.c_int
        lib.ev3dgs_raster_bin_count.argtypes = [_P, _P, _P, _I, _I, _I, _I, _P, _P, _P, _P]
        lib.ev3dgs_raster_bin_count.restype = ctypes.c_int64
        lib.ev3dgs_raster_bin_place.argtypes = [_P, _P, _P, _I, _I, _I, _I, _P, _P]
        lib.ev3dgs_raster_bin_place.restype = ctypes.c_int
        for name in ("ev3dgs_project_forward", "ev3dgs_project_backward"):
            getattr(lib, name).argtypes = [ctypes.POINTER(Proj)]
            getattr(lib, name).restype = None
        _lib = lib
    return _lib


def available() -> bool:
    """Whether the C kernels were built (and load)."""
    return _ext is not None and _load() is not None


def active(dtype, channels: int) -> bool:
    """Whether a call with these colours runs the C kernels."""
    return KERNEL == "simd" and np.dtype(dtype) == np.float32 and 1 <= channels <= DMAX and available()


def isa() -> str:
    """Which build runs: "avx2" or "portable"."""
    return "avx2" if _load().ev3dgs_raster_isa(ISA) == 1 else "portable"


def exp_neg(sigma: np.ndarray) -> np.ndarray:
    """The kernels' exp(-sigma) for float32 sigma >= 0 (for tests)."""
    s = np.ascontiguousarray(sigma, np.float32)
    out = np.empty_like(s)
    _load().ev3dgs_exp_neg(s.ctypes.data, out.ctypes.data, s.size, ISA)
    return out


def fragment_slots(boxes: np.ndarray) -> np.ndarray:
    """Slots each tile-list entry's recorded fragments take: 8 per row of its box and group of 8 columns
    (x0 ... x0 + 7, x0 + 8 ..., from the box's first column x0)."""
    b = boxes.astype(np.int64)
    rows = np.maximum(b[:, 3] - b[:, 2] + 1, 0)
    groups = -(-np.maximum(b[:, 1] - b[:, 0] + 1, 0) // LANES)
    return rows * groups * LANES


def _ptr(a: np.ndarray | None):
    return None if a is None else a.ctypes.data


_pending = {}


def _tile_ns(offsets):
    if TILE_TIMES is None:
        return None
    a = np.zeros(len(offsets) - 1, np.int64)
    _pending["tile_ns"] = a
    return a.ctypes.data


def _keep_tile_ns(kind, job):
    if TILE_TIMES is not None and job.tile_ns:
        TILE_TIMES.append((kind, _pending.pop("tile_ns")))


def _aligned(shape, dtype, align=64) -> np.ndarray:
    """An uninitialised C-contiguous array whose data starts on an ``align``-byte boundary."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape))
    raw = np.empty(n * dtype.itemsize + align, np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off:off + n * dtype.itemsize].view(dtype).reshape(shape)


def record_stride(channels: int) -> int:
    """float32 words per Gaussian record: 7 + D values and 4 box ints, padded to 16 (one 64-byte cache line,
    D <= 5) or 32."""
    return 16 if 11 + channels <= 16 else 32


def records(means2d, conics, colors, opacities, sigma_max, gboxes) -> tuple:
    """(recs, slots): recs (C * N, record_stride(D)) float32, 64-byte aligned, per camera and Gaussian its kernel
    inputs and pixel box (see _raster.c's ev3dgs_raster_records; colours (C, N, D) or shared (N, D)); slots:
    the fragment slots all the tile-list entries take (as ``prep`` counts them per entry)."""
    C, N = gboxes.shape[:2]
    D = colors.shape[-1]
    S = record_stride(D)
    recs = _aligned((C * N, S), np.float32)
    slots = _load().ev3dgs_raster_records(_ptr(recs), S, C, N, D, _ptr(means2d), _ptr(conics), _ptr(colors),
                                          0 if colors.ndim == 2 else N * D, _ptr(opacities), _ptr(sigma_max),
                                          _ptr(gboxes))
    return recs, int(slots)


def pack(recs, ids, offsets, C, N, D, width, height, slots: bool, n_threads: int):
    """cpu_tiles._pack's (params, boxes), bitwise, from the records; with ``slots`` also frag_start (K + 1,):
    entry k's fragment slots are frag_start[k] ... frag_start[k + 1] - 1 (as fragment_slots counts them),
    else None. See _raster.c's ev3dgs_raster_pack."""
    K = len(ids)
    params, boxes = np.empty((K, 7 + D), np.float32), np.empty((K, 4), np.int32)
    start = np.empty(K + 1, np.int64) if slots else None
    _load().ev3dgs_raster_pack(_ptr(ids), _ptr(offsets), _ptr(recs), recs.shape[1], D, C, N, width, height,
                               -(-width // TILE), _ptr(params), _ptr(boxes), _ptr(start), n_threads)
    return params, boxes, start


def bin_active(depths) -> bool:
    """Whether the binning runs in C: the C kernels selected and built, float32 depths (the numba binning
    serves float64)."""
    return KERNEL == "simd" and depths.dtype == np.float32 and available()


def bin(boxes, radii, depths, tiles_x, tiles_y):
    """cpu_tiles._bin's (offsets, ids), bitwise, serially in C (the call uses it on one thread; numba's _bin,
    parallel over cameras, on more): boxes (C, N, 4) int32, radii (C, N) int64, depths (C, N) float32, all
    C-contiguous. Measured on one thread: about 0.8-0.9x the time of _bin (a 10k cloud at 200x200, 23 k entries;
    a 50k scene at 346x260 with 5 cameras, 1.22 M entries)."""
    C, N = radii.shape
    orders, n_vis = np.empty((C, N), np.int64), np.empty(C, np.int64)
    offsets, sorted_boxes = np.empty(C * tiles_x * tiles_y + 1, np.int64), np.empty((C, N, 4), np.int32)
    lib = _load()
    total = lib.ev3dgs_raster_bin_count(_ptr(boxes), _ptr(radii), _ptr(depths), C, N, tiles_x, tiles_y,
                                        _ptr(orders), _ptr(n_vis), _ptr(offsets), _ptr(sorted_boxes))
    if total < 0:
        raise MemoryError("C rasterizer: binning")
    ids = np.empty(total, np.int64)
    if lib.ev3dgs_raster_bin_place(_ptr(sorted_boxes), _ptr(orders), _ptr(n_vis), C, N, tiles_x, tiles_y, _ptr(offsets),
                                   _ptr(ids)) != 0:
        raise MemoryError("C rasterizer: binning")
    return offsets, ids


def reduce(per_pair, ids, offsets, C, N, n_threads):
    """cpu_backward._reduce's result (bitwise: the same float32 sums in the same order), cameras in parallel."""
    D = per_pair.shape[1] - 6
    acc = np.empty((C, N, 6 + D), np.float32)
    g_mean, g_conic = np.empty((C, N, 2), np.float32), np.empty((C, N, 3), np.float32)
    g_op, g_col = np.empty((C, N), np.float32), np.empty((C, N, D), np.float32)
    if _load().ev3dgs_raster_reduce(_ptr(per_pair), _ptr(ids), _ptr(offsets), C, (len(offsets) - 1) // C, N, D,
                                    _ptr(acc), _ptr(g_mean), _ptr(g_conic), _ptr(g_op), _ptr(g_col),
                                    n_threads) != 0:
        raise ValueError("C rasterizer: unsupported channel count")
    return g_mean, g_conic, g_op, g_col


def forward(params, boxes, offsets, work, background, width, height, tiles_x, image, t_final, last, frags,
            n_threads):
    """cpu._forward's contract (float32); frags = (frag_start, frag_e, frag_n), frag_n empty: not recorded."""
    start, fe, fn = frags
    record = len(fn) == len(params) and len(params) > 0
    n_tiles = tiles_x * (-(-height // TILE))
    job = Job(_ptr(params), _ptr(boxes), _ptr(offsets), _ptr(work), len(work), _ptr(background),
              image.shape[3], width, height, tiles_x, n_tiles, _ptr(image), _ptr(t_final), _ptr(last),
              _ptr(start), _ptr(fe), _ptr(fn), int(record), None, None, None, n_threads, ISA, _tile_ns(offsets), 0)
    if _load().ev3dgs_raster_forward(ctypes.byref(job)) != 0:
        raise ValueError("C rasterizer: unsupported channel count")
    _keep_tile_ns("forward", job)


def backward(params, boxes, offsets, work, background, width, height, tiles_x, t_final, last, grad_image,
             grad_alpha, per_pair, frags, n_threads, write_rows=False):
    """cpu_backward._backward's contract (float32): per_pair[k] gets entry k's gradient, added to it, or with
    ``write_rows`` written (every row, 0 for an entry without fragments: per_pair need not be zeroed)."""
    start, fe, fn = frags
    record = len(fn) == len(params) and len(params) > 0
    n_tiles = tiles_x * (-(-height // TILE))
    job = Job(_ptr(params), _ptr(boxes), _ptr(offsets), _ptr(work), len(work), _ptr(background),
              per_pair.shape[1] - 6, width, height, tiles_x, n_tiles, None, _ptr(t_final), _ptr(last),
              _ptr(start), _ptr(fe), _ptr(fn), int(record), _ptr(grad_image), _ptr(grad_alpha), _ptr(per_pair),
              n_threads, ISA, _tile_ns(offsets), int(write_rows))
    if _load().ev3dgs_raster_backward(ctypes.byref(job)) != 0:
        raise ValueError("C rasterizer: unsupported channel count")
    _keep_tile_ns("backward", job)


def project_active(*arrays) -> bool:
    """Whether the projection + SH kernels run in C: the C kernels selected and built, every input float32."""
    return KERNEL == "simd" and all(a.dtype == np.float32 for a in arrays) and available()


def _proj(m, q, s, o, sh, deg, vm, campos, cam, near, far, eps2d, n_threads, **fields) -> Proj:
    """The proj_t both projection passes share (the Gaussians, cameras and settings) plus ``fields``."""
    return Proj(means=_ptr(m), quats=_ptr(q), scales=_ptr(s), opac=_ptr(o), sh=_ptr(sh), N=len(m), C=len(vm),
                KS=sh.shape[1], deg=deg, vm=_ptr(vm), campos=_ptr(campos), cam=_ptr(cam), near=near, far=far,
                eps2d=eps2d, n_threads=n_threads, isa=ISA, **fields)


def project_forward(m, q, s, o, sh, deg, vm, campos, cam, width, height, near, far, eps2d, alpha_min, radius_margin,
                    means2d, conics, depths, colors, radii, n_threads):
    """project_cpu._project_forward's contract, float32 inputs and outputs (bitwise its results)."""
    p = _proj(m, q, s, o, sh, deg, vm, campos, cam, near, far, eps2d, n_threads, width=width, height=height,
              alpha_min=alpha_min, radius_margin=radius_margin, means2d=_ptr(means2d), conics=_ptr(conics),
              depths=_ptr(depths), colors=_ptr(colors), radii=_ptr(radii))
    _load().ev3dgs_project_forward(ctypes.byref(p))


def project_backward(m, q, s, o, sh, deg, vm, campos, cam, near, far, eps2d, g_m2d, g_con, g_dep, g_col,
                     g_means, g_quats, g_scales, g_sh, want_vm, g_vm, n_threads):
    """project_cpu._project_backward's contract, float32 inputs and gradients (rounded from its float64 ones:
    bitwise the numba kernel's after .to(float32)); g_vm (blocks, C, 15) float64, zeroed."""
    p = _proj(m, q, s, o, sh, deg, vm, campos, cam, near, far, eps2d, n_threads, g_m2d=_ptr(g_m2d),
              g_con=_ptr(g_con), g_dep=_ptr(g_dep), g_col=_ptr(g_col), g_means=_ptr(g_means), g_quats=_ptr(g_quats),
              g_scales=_ptr(g_scales), g_sh=_ptr(g_sh), want_vm=int(want_vm), g_vm=_ptr(g_vm))
    _load().ev3dgs_project_backward(ctypes.byref(p))
