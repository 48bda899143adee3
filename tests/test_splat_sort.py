"""The cpu binning's depth sort (cpu._stable_argsort, an LSD radix sort) against numpy's stable sort."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ev3dgs.splat.cpu import _stable_argsort

finite32 = st.floats(allow_nan=False, width=32).filter(lambda x: x != 0.0 or str(x) == "0.0")
finite64 = st.floats(allow_nan=False).filter(lambda x: x != 0.0 or str(x) == "0.0")


@settings(max_examples=200, deadline=None)
@given(arrays(np.float32, st.integers(0, 300), elements=finite32))
def test_float32_equals_numpy_stable(v):
    assert np.array_equal(_stable_argsort(v), np.argsort(v, kind="stable"))


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, st.integers(0, 300), elements=finite64))
def test_float64_equals_numpy_stable(v):
    assert np.array_equal(_stable_argsort(v), np.argsort(v, kind="stable"))


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2 ** 31), st.integers(1, 5000), st.integers(1, 50))
def test_many_ties_keep_index_order(seed, n, levels):
    """Depths drawn from a few values (ties everywhere, as for Gaussians on one plane): ties stay in index
    order, like the merge sort this replaced."""
    rng = np.random.default_rng(seed)
    v = (0.01 + rng.integers(0, levels, n) * 0.37).astype(np.float32)
    assert np.array_equal(_stable_argsort(v), np.argsort(v, kind="stable"))


def test_non_contiguous_input():
    v = np.linspace(5.0, 1.0, 40)[::3]
    assert np.array_equal(_stable_argsort(v), np.argsort(v, kind="stable"))


def _random_boxes(rng, C, N, width, height, reach, size):
    """(C, N, 4) int32 pixel boxes [x0, x1, y0, y1]: corners from ``reach`` pixels outside the image, up to
    ``size`` pixels wide and high, clipped to the image; about 10 % empty (0, -1, 0, -1). The draws are in
    the order the tests made them before this helper, so their seeds give the same boxes."""
    x0 = rng.integers(-reach, width, (C, N))
    y0 = rng.integers(-reach, height, (C, N))
    boxes = np.stack([np.clip(x0, 0, width - 1), np.clip(x0 + rng.integers(0, size, (C, N)), 0, width - 1),
                      np.clip(y0, 0, height - 1), np.clip(y0 + rng.integers(0, size, (C, N)), 0, height - 1)],
                     axis=-1).astype(np.int32)
    boxes[rng.random((C, N)) < 0.1] = (0, -1, 0, -1)
    return boxes


def test_binning_does_not_depend_on_how_the_work_is_split():
    """_bin cut into chunks per camera (used when there are fewer cameras than threads) gives exactly the
    lists of the one-piece version, which places Gaussians in depth order, ties by index: checked against
    that order built here with numpy."""
    from ev3dgs.splat.cpu_tiles import TILE, _bin

    rng = np.random.default_rng(3)
    C, N, width, height = 2, 300, 70, 50
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    boxes = _random_boxes(rng, C, N, width, height, reach=10, size=30)
    radii = rng.integers(0, 3, (C, N)).astype(np.int64)  # 0: not visible
    depths = rng.integers(0, 20, (C, N)).astype(np.float32)  # many ties
    offsets, ids = _bin(boxes, radii, depths, tiles_x, tiles_y, 1)
    for c in range(C):  # the lists, built independently
        order = np.flatnonzero(radii[c] > 0)
        order = order[np.argsort(depths[c][order], kind="stable")]
        for t in range(tiles_x * tiles_y):
            tx, ty = t % tiles_x, t // tiles_x
            want = [g for g in order if boxes[c, g, 0] <= boxes[c, g, 1]
                    and boxes[c, g, 0] // TILE <= tx <= boxes[c, g, 1] // TILE
                    and boxes[c, g, 2] // TILE <= ty <= boxes[c, g, 3] // TILE]
            got = ids[offsets[c * tiles_x * tiles_y + t]:offsets[c * tiles_x * tiles_y + t + 1]]
            assert got.tolist() == want
    for n in (2, 3, 5, 7):
        o, i = _bin(boxes, radii, depths, tiles_x, tiles_y, n)
        assert np.array_equal(o, offsets) and np.array_equal(i, ids)


def _lists_by_numpy(boxes, radii, depths, tiles_x, tiles_y):
    """Every (camera, tile) list built independently: visible Gaussians in numpy's stable depth order, kept
    where the pixel box's tile range holds the tile."""
    from ev3dgs.splat.cpu_tiles import TILE

    C = radii.shape[0]
    out = []
    for c in range(C):
        order = np.flatnonzero(radii[c] > 0)
        order = order[np.argsort(depths[c][order], kind="stable")]
        b = boxes[c, order]
        for t in range(tiles_x * tiles_y):
            tx, ty = t % tiles_x, t // tiles_x
            keep = ((b[:, 0] <= b[:, 1]) & (b[:, 0] // TILE <= tx) & (tx <= b[:, 1] // TILE)
                    & (b[:, 2] // TILE <= ty) & (ty <= b[:, 3] // TILE))
            out.append(order[keep].tolist())
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2 ** 31), st.integers(1, 4), st.integers(0, 400), st.integers(1, 90), st.integers(1, 70),
       st.integers(1, 30))
def test_binning_equals_an_independent_construction(seed, C, N, width, height, levels):
    """_bin (which copies each camera's boxes in depth order before counting and placing) gives exactly the
    lists built with numpy from the boxes as given, for any cameras, image size, empty boxes, culled
    Gaussians and depth ties; a dropped, duplicated or misplaced entry fails this."""
    from ev3dgs.splat.cpu_tiles import TILE, _bin

    rng = np.random.default_rng(seed)
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    boxes = _random_boxes(rng, C, N, width, height, reach=20, size=60)
    radii = rng.integers(0, 3, (C, N)).astype(np.int64)
    depths = (0.5 + rng.integers(0, levels, (C, N))).astype(np.float32)
    want = _lists_by_numpy(boxes, radii, depths, tiles_x, tiles_y)
    for chunks in (1, 3):
        offsets, ids = _bin(boxes, radii, depths, tiles_x, tiles_y, chunks)
        assert [ids[offsets[i]:offsets[i + 1]].tolist() for i in range(len(offsets) - 1)] == want
