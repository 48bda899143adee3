"""The cpu rasterizer's pixel bounds are conservative: every pixel its kernels can composite (float32 sigma
in [0, sigma_max], computed as the kernels compute it) lies inside the ellipse box (cpu_tiles._ellipse_box)
and inside the row span (cpu_tiles._row_span). Checked by brute force over every pixel of a window around
the Gaussian, for conics from random covariances (thin, large, tilted) and opacities down to the 1/255 cut."""
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.splat.cpu_tiles import _ellipse_box, _row_span, _span_params


def _conic(sx, sy, angle):
    """float32 conic (a, b, c) of a 2-D covariance with standard deviations sx, sy rotated by angle."""
    r = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    cov = r @ np.diag([sx * sx, sy * sy]) @ r.T
    q = np.linalg.inv(cov)
    return np.float32(q[0, 0]), np.float32(q[0, 1]), np.float32(q[1, 1])


def _accepted(mx, my, a, b, c, smax, xs, ys):
    """Pixels (x, y) whose float32 sigma = 0.5 (a dx^2 + c dy^2) + b dx dy, in the kernels' operation order,
    lies in [0, smax]."""
    half = np.float32(0.5)
    dx = (xs.astype(np.float32) - mx)[None, :]
    dy = (ys.astype(np.float32) - my)[:, None]
    sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
    assert sigma.dtype == np.float32
    iy, ix = np.nonzero((sigma >= 0) & (sigma <= smax))
    return xs[ix], ys[iy]


@settings(max_examples=300, deadline=None)
@given(sx=st.floats(0.05, 40.0), sy=st.floats(0.05, 40.0), angle=st.floats(0.0, math.pi),
       mx=st.floats(-5.0, 70.0), my=st.floats(-5.0, 70.0), opacity=st.floats(1.0 / 255.0, 1.0))
def test_every_composited_pixel_is_inside_the_ellipse_box_and_the_row_span(sx, sy, angle, mx, my, opacity):
    a, b, c = _conic(sx, sy, angle)
    mx, my = np.float32(mx), np.float32(my)
    smax = np.float32(math.log(opacity * 255.0) + 1e-6)
    reach = int(math.ceil(4.0 * max(sx, sy))) + 2  # beyond the 3.33-sigma support of any alpha >= 1/255
    xs = np.arange(int(mx) - reach, int(mx) + reach + 1)
    ys = np.arange(int(my) - reach, int(my) + reach + 1)
    px, py = _accepted(mx, my, a, b, c, smax, xs, ys)
    box = (int(xs[0]), int(xs[-1]), int(ys[0]), int(ys[-1]))
    bx0, bx1, by0, by1 = _ellipse_box(mx, my, a, b, c, smax, *box)
    assert np.all((px >= bx0) & (px <= bx1) & (py >= by0) & (py <= by1))
    # tighter than the square box of the longest axis whenever the Gaussian is elongated enough to show it
    assert (bx1 - bx0 + 1) * (by1 - by0 + 1) <= (box[1] - box[0] + 1) * (box[3] - box[2] + 1)
    ok, det, s = _span_params(a, b, c, smax)
    for x, y in zip(px, py):
        rx0, rx1 = _row_span(ok, a, b, det, s, mx, np.float32(y) - my, bx0, bx1)
        assert rx0 <= x <= rx1


def test_ellipse_box_of_an_axis_aligned_gaussian():
    """sigma = 0.5 (x/2)^2 + 0.5 (y/1)^2 <= s: half-widths 2 sqrt(2 s) and sqrt(2 s), here s = ln 255."""
    a, b, c = np.float32(0.25), np.float32(0.0), np.float32(1.0)
    smax = np.float32(math.log(255.0))
    bx0, bx1, by0, by1 = _ellipse_box(np.float32(30.0), np.float32(20.0), a, b, c, smax, 0, 100, 0, 100)
    hx, hy = 2.0 * math.sqrt(2.0 * math.log(255.0)), math.sqrt(2.0 * math.log(255.0))  # 6.66, 3.33
    assert (bx0, bx1, by0, by1) == (math.ceil(30 - hx), math.floor(30 + hx), math.ceil(20 - hy), math.floor(20 + hy))


def test_ellipse_box_leaves_degenerate_and_empty_cases_safe():
    # not positive definite: the given box; a negative cut-off (opacity < 1/255): empty
    assert _ellipse_box(np.float32(5), np.float32(5), np.float32(1), np.float32(2), np.float32(1),
                        np.float32(3), 0, 9, 0, 9) == (0, 9, 0, 9)
    assert _ellipse_box(np.float32(5), np.float32(5), np.float32(1), np.float32(0), np.float32(1),
                        np.float32(-0.5), 0, 9, 0, 9) == (0, -1, 0, -1)
    assert _ellipse_box(np.float32(5), np.float32(5), np.float32(1), np.float32(0), np.float32(1),
                        np.float32(np.nan), 0, 9, 0, 9) == (0, 9, 0, 9)


def test_a_nearly_flat_form_keeps_its_box():
    """A huge, nearly flat Gaussian (conic ~1e-38: half-widths ~1e19 px, past int64): the ellipse bounds are
    clamped before the int conversion, so the box stays the given one instead of wrapping to empty; the same
    for the row span."""
    tiny = np.float32(1e-38)
    smax = np.float32(math.log(255.0))
    assert _ellipse_box(np.float32(5), np.float32(5), tiny, np.float32(0), tiny, smax, 0, 15, 0, 15) == (0, 15, 0, 15)
    ok, det, s = _span_params(tiny, np.float32(0), tiny, smax)
    assert ok and _row_span(ok, tiny, np.float32(0), det, s, np.float32(5), np.float32(3), 0, 15) == (0, 15)
