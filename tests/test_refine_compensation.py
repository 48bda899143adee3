"""tools/investigations/refine_compensation.py: the split of a camera error into its rotation-only and centre-only image
displacement and into roll / pan-tilt, against analytic answers on a ring of cameras around the origin."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools" / "investigations"))

from ev3dgs.geometry import intrinsics, look_at, rotvec_to_matrix  # noqa: E402


def _ring(n=4, dist=4.0):
    return np.stack([look_at([dist * np.cos(a), dist * np.sin(a), 0.0], [0.0, 0.0, 0.0])
                     for a in np.arange(n) * 2 * np.pi / n])


def _turn(cams, axis, angles):
    """Each camera turned about its own (camera-frame) axis by its angle, centre kept."""
    out = cams.copy()
    for c, a in zip(out, angles):
        c[:3, :3] = c[:3, :3] @ rotvec_to_matrix(np.radians(a) * np.asarray(axis, float))
    return out


@settings(max_examples=20, deadline=None)
@given(st.floats(0.05, 3.0))
def test_roll_is_invisible_at_the_image_centre_and_pan_moves_it_f_tan(theta):
    from refine_compensation import split_errors

    true = _ring()
    K = intrinsics(64, 48, 40.0)
    centre = np.array([[-1e-6] * 3, [1e-6] * 3])  # points at the origin: the principal point of every camera
    # roll (about the optical axis z) of every camera: the four world axes cancel in the alignment's mean
    r = split_errors(_turn(true, [0, 0, 1], [theta] * 4), true, K, centre, n=50)
    assert np.allclose(r["roll_deg"], theta, atol=1e-9) and np.allclose(r["pan_tilt_deg"], 0, atol=1e-9)
    assert np.allclose(r["centre_only"], 0, atol=1e-6)
    # a point on the optical axis stays at the principal point under roll: 0 up to the 1e-6 box size
    assert np.allclose(r["full"], 0, atol=1e-4) and np.allclose(r["rotation_only"], 0, atol=1e-4)
    # pan (about camera y, a common world axis here) with alternating signs, so the alignment keeps it:
    # the origin moves by f tan(theta) (pinhole projection of a ray turned by theta)
    p = split_errors(_turn(true, [0, 1, 0], [theta, -theta] * 2), true, K, centre, n=50)
    f_tan = K[0, 0] * np.tan(np.radians(theta))
    assert np.allclose(p["pan_tilt_deg"], theta, atol=1e-9) and np.allclose(p["roll_deg"], 0, atol=1e-9)
    # box of 1e-6 around the origin: displacement differs from f tan(theta) by O(f * 1e-6 / dist)
    assert np.allclose(p["rotation_only"], f_tan, rtol=1e-6, atol=1e-4)
    assert np.allclose(p["full"], f_tan, rtol=1e-6, atol=1e-4)


def test_a_shift_alone_is_centre_only():
    from refine_compensation import split_errors

    true = _ring()
    K = intrinsics(64, 48, 40.0)
    moved = true.copy()
    moved[:, :3, 3] += np.array([[0, 0, 0.1], [0, 0, -0.1], [0, 0, 0.1], [0, 0, -0.1]])  # alternating: no
    r = split_errors(moved, true, K, np.array([[-1e-6] * 3, [1e-6] * 3]), n=50)  # similarity absorbs it
    assert np.allclose(r["rotation_only"], 0, atol=1e-9)
    assert np.allclose(r["roll_deg"], 0, atol=1e-9) and np.allclose(r["pan_tilt_deg"], 0, atol=1e-9)
    # a 0.1 sideways (image-vertical) shift at distance 4 moves the origin by f * 0.1 / 4 pixels
    assert np.allclose(r["centre_only"], K[1, 1] * 0.1 / 4, rtol=1e-4)
    assert np.allclose(r["full"], r["centre_only"])
