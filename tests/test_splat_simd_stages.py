"""The C stages around the `cpu` backend's SIMD tile kernels (ev3dgs/splat/_raster.c through cpu_simd):
the per-Gaussian records, the packing of the tile-list entries, the fragment slot count, the backward's
written (not added) gradient rows and the per-Gaussian gradient sum.

They move data and add float32 numbers in the numba stages' order, no new arithmetic, so each is held
bitwise to the numba stage it replaces (cpu_tiles._pack, cpu_simd.fragment_slots on _pack's boxes,
cpu_backward._reduce), for any thread count, and the whole call bitwise to the C kernels fed by the numba
stages."""
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import ev3dgs.splat.cpu as cpu
import ev3dgs.splat.cpu_simd as cpu_simd
from ev3dgs.splat.cpu_backward import _reduce
from ev3dgs.splat.cpu_tiles import TILE, _bin, _pack, _pixel_boxes

from test_splat_simd import inputs, rasterize

needs_c = pytest.mark.skipif(not cpu_simd.available(), reason="the C rasterizer extension is not built")


def binned(n, W, H, C, seed, shared):
    """The numba stages' inputs and outputs up to the packing: (m, q, col, o, smax, gboxes, offsets, ids)."""
    m, q, col, o, d, r = (t.numpy() for t in inputs(n, W, H, C=C, seed=seed))
    if shared:
        col = np.ascontiguousarray(col[0])
    r = r.astype(np.int64)
    smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(np.float32)
    gboxes = _pixel_boxes(m, r, q, smax, W, H)
    offsets, ids = _bin(gboxes, r, d, -(-W // TILE), -(-H // TILE), 1)
    return m, q, col, o, smax, gboxes, offsets, ids


@needs_c
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 150), W=st.integers(1, 50), H=st.integers(1, 50),
       C=st.integers(1, 3), shared=st.booleans(), threads=st.integers(1, 3))
def test_c_pack_is_numba_pack_bitwise(seed, n, W, H, C, shared, threads):
    m, q, col, o, smax, gboxes, offsets, ids = binned(n, W, H, C, seed, shared)
    recs, slots = cpu_simd.records(m, q, col, o, smax, gboxes)
    assert recs.size == 0 or recs.ctypes.data % 64 == 0
    params, boxes, start = cpu_simd.pack(recs, ids, offsets, C, n, 3, W, H, True, threads)
    cols = np.ascontiguousarray(np.broadcast_to(col, (C,) + col.shape)) if shared else col
    want_params, want_boxes = _pack(m, q, cols, o, smax, offsets, ids, gboxes, W, H, -(-W // TILE))
    assert np.array_equal(params.view(np.uint32), want_params.view(np.uint32))
    assert np.array_equal(boxes, want_boxes)
    # the kernels' fragment slots: per entry as fragment_slots counts them, in all as records' count
    want_start = np.concatenate([[0], np.cumsum(cpu_simd.fragment_slots(want_boxes))])
    assert np.array_equal(start, want_start)
    assert slots == int(want_start[-1])
    _, _, none = cpu_simd.pack(recs, ids, offsets, C, n, 3, W, H, False, threads)
    assert none is None


@needs_c
def test_c_pack_threads_split_a_large_list_bitwise():
    """More than the 65536 entries under which the packing stays on one thread."""
    W, H = 160, 120
    m, q, col, o, smax, gboxes, offsets, ids = binned(6000, W, H, 4, 3, False)
    assert len(ids) > 65536
    recs, slots = cpu_simd.records(m, q, col, o, smax, gboxes)
    one = cpu_simd.pack(recs, ids, offsets, 4, 6000, 3, W, H, True, 1)
    for t in (2, 3):
        assert all(np.array_equal(a, b) for a, b in zip(one, cpu_simd.pack(recs, ids, offsets, 4, 6000, 3, W, H,
                                                                              True, t)))
    assert np.array_equal(one[0], _pack(m, q, col, o, smax, offsets, ids, gboxes, W, H, -(-W // TILE))[0])


@needs_c
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 200), K=st.integers(0, 3000), C=st.integers(1, 4),
       D=st.integers(1, cpu_simd.DMAX), threads=st.integers(1, 3))
def test_c_reduce_is_numba_reduce_bitwise(seed, n, K, C, D, threads):
    """Random entries and rows (values of mixed sign and magnitude, so that the order of the sums shows)."""
    rng = np.random.default_rng(seed)
    n_tiles = 7
    cuts = np.sort(rng.integers(0, K + 1, C * n_tiles - 1))
    offsets = np.concatenate([[0], cuts, [K]]).astype(np.int64)
    ids = rng.integers(0, n, K).astype(np.int64)
    per_pair = (rng.standard_normal((K, 6 + D)) * 10.0 ** rng.integers(-3, 4, (K, 6 + D))).astype(np.float32)
    got = cpu_simd.reduce(per_pair, ids, offsets, C, n, threads)
    want = _reduce(ids, per_pair, offsets, C, n)
    for a, b in zip(got, want):
        assert a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


@needs_c
@pytest.mark.parametrize("budget", [cpu.FRAGMENT_BUDGET, 0])  # replayed, recomputed
def test_backward_writes_every_row(budget, monkeypatch):
    """write_rows: every row written (0 without fragments), bitwise the rows added to a zeroed buffer; a row
    left unwritten keeps the NaN the buffer starts with."""
    monkeypatch.setattr(cpu, "FRAGMENT_BUDGET", budget)
    W, H, C, n = 64, 48, 2, 400
    m, q, col, o, smax, gboxes, offsets, ids = binned(n, W, H, C, 21, False)
    tiles_x = -(-W // TILE)
    recs, slots = cpu_simd.records(m, q, col, o, smax, gboxes)
    params, boxes, start = cpu_simd.pack(recs, ids, offsets, C, n, 3, W, H, budget > 0, 1)
    frags = cpu._fragment_buffers(boxes, np.float32, True, record=True, start=start)
    frags = frags[::2] + frags[3:]
    work = cpu._work_order(offsets)
    bg = np.array([0.2, 0.4, 0.6], np.float32)
    image, t_final = np.empty((C, H, W, 3), np.float32), np.empty((C, H, W), np.float32)
    last = np.empty((C, H, W), np.int64)
    cpu_simd.forward(params, boxes, offsets, work, bg, W, H, tiles_x, image, t_final, last, frags, 1)
    rng = np.random.default_rng(0)
    gi = rng.standard_normal((C, H, W, 3)).astype(np.float32)
    ga = rng.standard_normal((C, H, W)).astype(np.float32)
    added = np.zeros((len(ids), 9), np.float32)
    written = np.full((len(ids), 9), np.nan, np.float32)
    cpu_simd.backward(params, boxes, offsets, work, bg, W, H, tiles_x, t_final, last, gi, ga, added, frags, 1)
    cpu_simd.backward(params, boxes, offsets, work, bg, W, H, tiles_x, t_final, last, gi, ga, written, frags, 1,
                      write_rows=True)
    assert np.array_equal(added.view(np.uint32), written.view(np.uint32))
    assert (added == 0).all(axis=1).any() and (added != 0).any()  # rows of both kinds


@needs_c
@pytest.mark.parametrize("C", [1, 3])
def test_whole_call_bitwise_the_c_kernels_fed_by_the_numba_stages(C, monkeypatch):
    """The C binning, records, packing and gradient sum in the call change no bit of its images and gradients:
    the same call with the numba binning, packing and sum around the same C kernels gives the same result."""
    W, H = 72, 56
    x = inputs(700, W, H, C=C, seed=31 + C)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float32)
    binned_in_c = []
    real_bin = cpu_simd.bin
    monkeypatch.setattr(cpu_simd, "bin", lambda *a: binned_in_c.append(1) or real_bin(*a))
    got = rasterize("simd", x, W, H, bg)
    assert binned_in_c  # the C binning ran

    def numba_pack(recs, ids, offsets, C, N, D, width, height, slots, n_threads):
        m, q, col = (recs[:, i:j].reshape(C, N, j - i).copy() for i, j in ((0, 2), (2, 5), (7, 7 + D)))
        o, smax = recs[:N, 5].copy(), recs[:N, 6].copy()
        gboxes = recs[:, 7 + D:11 + D].copy().view(np.int32).reshape(C, N, 4)
        params, boxes = _pack(m, q, col, o, smax, offsets, ids, gboxes, width, height, -(-width // TILE))
        start = np.concatenate([[0], np.cumsum(cpu_simd.fragment_slots(boxes))]) if slots else None
        return params, boxes, start

    real_backward = cpu_simd.backward

    def zeroed_backward(*a, write_rows=False):
        a = list(a)
        a[12][:] = 0.0
        return real_backward(*a)

    monkeypatch.setattr(cpu_simd, "bin_active", lambda depths: False)  # numba's _bin
    monkeypatch.setattr(cpu_simd, "pack", numba_pack)
    monkeypatch.setattr(cpu_simd, "backward", zeroed_backward)
    monkeypatch.setattr(cpu_simd, "reduce", lambda per_pair, ids, offsets, C, N, t: _reduce(ids, per_pair, offsets,
                                                                                           C, N))
    want = rasterize("simd", x, W, H, bg)
    assert all(torch.equal(a, b) for a, b in zip(got, want))


def numba_bin(boxes, radii, depths, tiles_x, tiles_y, chunks=1):
    return _bin(boxes, radii, depths, tiles_x, tiles_y, chunks)


@needs_c
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 150), W=st.integers(1, 70), H=st.integers(1, 70),
       C=st.integers(1, 3), levels=st.sampled_from([0, 3, 1 << 20]), signs=st.booleans())
def test_c_bin_is_numba_bin_bitwise(seed, n, W, H, C, levels, signs):
    """cpu_simd.bin gives cpu_tiles._bin's offsets and ids exactly: the projected boxes of a random scene, its
    radii (0: not visible), depths with ties (quantised to ``levels`` values, 0: all equal) and, with
    ``signs``, negative, -0.0 and +0.0 depths (the sort keys' sign handling)."""
    m, q, col, o, d, r = (t.numpy() for t in inputs(n, W, H, C=C, seed=seed))
    r = r.astype(np.int64)
    rng = np.random.default_rng(seed)
    if levels:
        d = (np.floor(d * levels / max(1.0, float(d.max(initial=1.0)))) + 1).astype(np.float32)
    else:
        d = np.full_like(d, 2.5)
    if signs and n:
        d = np.where(rng.random(d.shape) < 0.3, -d, d).astype(np.float32)
        d.flat[rng.integers(0, d.size, 3)] = rng.choice(np.array([0.0, -0.0], np.float32), 3)
    d = np.ascontiguousarray(d)
    smax = (np.log(np.maximum(o.astype(np.float64), 0.0) * 255.0) + 1e-6).astype(np.float32)
    gboxes = _pixel_boxes(m, r, q, smax, W, H)
    tx, ty = -(-W // TILE), -(-H // TILE)
    want_offsets, want_ids = numba_bin(gboxes, r, d, tx, ty)
    offsets, ids = cpu_simd.bin(gboxes, r, d, tx, ty)
    assert np.array_equal(offsets, want_offsets)
    assert np.array_equal(ids, want_ids)


@needs_c
def test_c_bin_sorts_every_byte_and_odd_boxes():
    """Depths that differ in each of the four key bytes (no radix pass skipped), and boxes that are empty in
    one axis or both, some with a negative end (numba's // floors, -1 // 16 = -1: no tile; C's / truncates
    to 0, which would put the box in the first tile column or row)."""
    rng = np.random.default_rng(3)
    N, W = 3000, 160
    d = rng.uniform(0.01, 1e6, (1, N)).astype(np.float32)
    r = rng.integers(0, 3, (1, N)).astype(np.int64)
    keys = d.view(np.uint32)
    assert all(len(np.unique((keys >> (8 * b)) & 0xFF)) > 1 for b in range(4))
    x0, y0 = rng.integers(0, W, N), rng.integers(0, W, N)
    x1 = np.minimum(x0 + rng.integers(-20, 40, N), W - 1)
    y1 = np.minimum(y0 + rng.integers(-20, 40, N), W - 1)
    boxes = np.ascontiguousarray(np.stack([x0, x1, y0, y1], 1).astype(np.int32)[None])
    boxes[0, :5] = (0, -1, 0, -1)
    boxes[0, 5:10] = (0, -3, 2, 30)
    boxes[0, 10:15] = (4, 20, 0, -1)
    r[0, :15] = 1
    assert (boxes[0, :, 1] < 0).sum() >= 5 and (boxes[0, :, 0] > boxes[0, :, 1]).sum() > 20
    want = numba_bin(boxes, r, d, W // TILE, W // TILE)
    got = cpu_simd.bin(boxes, r, d, W // TILE, W // TILE)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert len(got[1]) > N


def test_binning_falls_back_to_numba(monkeypatch):
    """Without the C kernels (KERNEL "numba", as without a compiler) or with float64 depths the binning is
    numba's _bin, and the call runs."""
    monkeypatch.setattr(cpu_simd, "KERNEL", "numba")
    assert not cpu_simd.bin_active(np.zeros(3, np.float32))
    monkeypatch.setattr(cpu_simd, "KERNEL", "simd")
    assert not cpu_simd.bin_active(np.zeros(3, np.float64))
    calls = []
    real = cpu._bin
    monkeypatch.setattr(cpu, "_bin", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(cpu_simd, "bin", lambda *a: pytest.fail("the C binning ran"))
    monkeypatch.setattr(cpu_simd, "_ext", None)  # as built without a compiler
    W, H = 40, 30
    x = inputs(200, W, H, seed=2)
    bg = torch.zeros(3, dtype=torch.float32)
    image = rasterize("simd", x, W, H, bg)[0]
    assert calls and float(image.abs().sum()) > 0


def test_single_camera_call_has_no_select_in_its_graph():
    """A single-camera cpu call reaches the batched kernels through views (unsqueeze / squeeze), not selects:
    a select's backward allocates a zero tensor of the whole batch and copies the gradient into it."""
    from ev3dgs.splat.rasterize import rasterization

    g = torch.Generator().manual_seed(0)
    n = 50
    means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 3 + torch.rand(n, 1, generator=g)], 1)
    leaves = [t.requires_grad_(True) for t in (means, torch.randn(n, 4, generator=g), 0.05 + 0.05 * torch.rand(
        n, 3, generator=g), 0.5 * torch.ones(n), torch.rand(n, 3, generator=g))]
    K = torch.tensor([[40.0, 0, 20], [0, 40.0, 15], [0, 0, 1]])
    image, alpha, meta = rasterization(*leaves, torch.eye(4), K, 40, 30, backend="cpu")
    seen, stack = set(), [image.grad_fn, alpha.grad_fn]
    while stack:
        fn = stack.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        stack.extend(f for f, _ in fn.next_functions)
    names = {type(fn).__name__ for fn in seen}
    assert "_RasterizeCPUBackward" in names and "_ProjectCPUBackward" in names
    assert not any(name.startswith("SelectBackward") for name in names), names
    (image.sum() + alpha.sum()).backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves[:3])
