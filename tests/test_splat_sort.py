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
