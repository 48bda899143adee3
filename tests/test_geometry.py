"""Rotation maths near the hard angles (0 and pi), checked against independent forms.

Tolerances: every function here is backward stable in float64, so a result carries an absolute error of a
small multiple of the unit round-off u = 2^-53 ~ 1.1e-16 per operation on O(1) quantities. A chain of < 100
such operations cannot exceed ~1e-14; the bounds below (1e-12 for angles and matrix entries) leave a margin
of 100 on top, and are independent of the CPU, BLAS build or thread count (3x3 products are not threaded).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.geometry import (interpolate_pose, matrix_to_quat, matrix_to_rotvec, pose_errors, quat_to_matrix,
                             relative_rotation_angle, rotation_angle, rotvec_to_matrix, slerp, umeyama)

TOL = 1e-12  # see the module docstring

unit_axes = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1).map(lambda v: v / np.linalg.norm(v))
# angles that are tiny, ordinary, or within a hair of pi (the two ends arccos handles badly)
small = st.floats(0.0, 1e-3, allow_nan=False)
near_pi = st.floats(0.0, 1e-3, allow_nan=False).map(lambda e: math.pi - e)
angles = st.one_of(small, st.floats(0.0, math.pi, allow_nan=False), near_pi)


def _axis_angle_matrix(k: np.ndarray, t: float) -> np.ndarray:
    """An independent construction: R = cos t I + sin t [k]x + (1 - cos t) k k^T (k unit)."""
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return math.cos(t) * np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * np.outer(k, k)


@settings(max_examples=300, deadline=None)
@given(unit_axes, angles)
def test_rotation_angle_is_accurate_near_zero_and_pi(k, t):
    R = _axis_angle_matrix(k, t)
    assert abs(rotation_angle(R) - t) < TOL
    # arccos of the trace would give ~sqrt(u) ~ 1e-8 here for t ~ 0: the atan2 form stays at round-off
    assert abs(relative_rotation_angle(np.eye(3), R) - t) < TOL


@settings(max_examples=300, deadline=None)
@given(unit_axes, angles)
def test_rotvec_round_trip(k, t):
    R = _axis_angle_matrix(k, t)
    assert np.abs(rotvec_to_matrix(k * t) - R).max() < TOL
    v = matrix_to_rotvec(R)
    assert np.isfinite(v).all()
    # at exactly pi, k and -k are the same rotation; compare matrices, and vectors away from pi
    assert np.abs(rotvec_to_matrix(v) - R).max() < TOL
    if t < math.pi - 1e-6:
        assert np.abs(v - k * t).max() < TOL


@settings(max_examples=200, deadline=None)
@given(unit_axes, angles)
def test_quaternion_round_trip(k, t):
    R = _axis_angle_matrix(k, t)
    q = matrix_to_quat(R)
    assert abs(np.linalg.norm(q) - 1) < TOL and q[0] >= 0
    assert np.abs(quat_to_matrix(q) - R).max() < TOL


@settings(max_examples=200, deadline=None)
@given(unit_axes, st.one_of(small, st.floats(0, math.pi / 2 - 1e-3)), st.floats(0, 1))
def test_slerp_follows_the_geodesic(k, t, a):
    """slerp(q, q R(k, t), a) is the rotation by a t about k, for tiny angles too (no linear fallback)."""
    R0 = _axis_angle_matrix(np.array([0.0, 0.0, 1.0]), 0.7)
    R1 = R0 @ _axis_angle_matrix(k, t)
    q = slerp(matrix_to_quat(R0), matrix_to_quat(R1), a)
    expect = R0 @ _axis_angle_matrix(k, a * t)
    assert np.abs(quat_to_matrix(q) - expect).max() < TOL


def test_slerp_ends_and_opposite_signs():
    q0 = matrix_to_quat(_axis_angle_matrix(np.array([1.0, 0, 0]), 0.3))
    q1 = matrix_to_quat(_axis_angle_matrix(np.array([0, 1.0, 0]), 2.0))
    assert np.abs(slerp(q0, q1, 0.0) - q0).max() < TOL
    assert np.abs(slerp(q0, -q1, 1.0) - q1).max() < TOL or np.abs(slerp(q0, -q1, 1.0) + q1).max() < TOL
    assert np.abs(slerp(q0, q0, 0.5) - q0).max() < TOL  # zero angle: exact, no 0/0
    with pytest.raises(ValueError, match="norm"):
        slerp(np.zeros(4), q1, 0.5)


def test_interpolated_pose_between_nearly_equal_rotations_is_rigid():
    p0 = np.eye(4)
    p1 = np.eye(4)
    p1[:3, :3] = _axis_angle_matrix(np.array([0, 0, 1.0]), 1e-9)
    mid = interpolate_pose(np.stack([p0, p1]), np.array([0, 10]), 5)
    assert abs(rotation_angle(mid[:3, :3]) - 0.5e-9) < TOL
    assert np.abs(mid[:3, :3] @ mid[:3, :3].T - np.eye(3)).max() < TOL


def test_umeyama_degenerate_sets_never_give_nan():
    rng = np.random.default_rng(1)
    one = np.tile(rng.normal(size=3), (5, 1))  # coincident points: scale and rotation undetermined
    s, R, t = umeyama(one, one + 1.0)
    assert np.isfinite([s, *R.ravel(), *t]).all() and np.allclose(s * R @ one[0] + t, one[0] + 1.0)
    line = np.outer(np.linspace(-1, 1, 7), [1.0, 2.0, 3.0])  # collinear: rotation about the line is free
    R_true = _axis_angle_matrix(np.array([0.6, 0.0, 0.8]), 1.1)
    dst = 2.0 * line @ R_true.T + 0.5
    s, R, t = umeyama(line, dst)
    assert abs(np.linalg.det(R) - 1) < TOL and abs(s - 2.0) < 1e-12
    assert np.abs(s * line @ R.T + t - dst).max() < 1e-12  # a minimiser: the residual is zero
    with pytest.raises(ValueError):
        umeyama(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError):
        umeyama(np.full((3, 3), np.nan), np.zeros((3, 3)))


def test_pose_errors_of_identical_poses_are_round_off():
    """Identical poses in another frame: every error is round-off. The chordal-mean rotation is a polar
    factor of a matrix with equal singular values (12): its error is ~||dM|| / 12 ~ 1e-15, and atan2 keeps
    that; so < 1e-12 rad whatever the BLAS. (arccos of the trace gave 1.7e-6 deg on another CPU.)"""
    rng = np.random.default_rng(0)
    gt = np.stack([np.eye(4) for _ in range(12)])
    gt[:, :3, :3] = rotvec_to_matrix(rng.normal(size=(12, 3)))
    gt[:, :3, 3] = rng.normal(size=(12, 3))
    R = _axis_angle_matrix(np.array([0.0, 0.6, 0.8]), 2.5)
    est = gt.copy()
    est[:, :3, :3] = R @ gt[:, :3, :3]
    est[:, :3, 3] = 3.0 * gt[:, :3, 3] @ R.T - 1.0
    e = pose_errors(est, gt)
    assert math.radians(e["rotation_deg_max"]) < TOL
    assert e["centre_error_max"] < 1e-12 * 10  # coordinates O(3): a few ulp of 3, times a margin
