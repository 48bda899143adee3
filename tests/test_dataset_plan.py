"""make-dataset pieces that need no Blender: camera shake, axes, view planning, scene files."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.errors import ConfigError
from ev3dgs.geometry import (blender_to_opencv, interpolate_pose, intrinsics, look_at, matrix_to_quat,
                             opencv_to_blender, project, quat_to_matrix, rotvec_to_matrix)
from ev3dgs.sim.scenes import Render, ShakeSpec, builtin_scenes, load_scene, resolve_render
from ev3dgs.sim.views import novel_view_poses, plan_views
from ev3dgs_blender.shake import Shake, apply_offsets, shake_offsets


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.floats(0.01, 5.0), st.floats(0.0, 0.2), st.floats(0.02, 0.5))
def test_shake_is_bounded_zero_mean_and_seeded(seed, rot_deg, trans, exposure_s):
    sh = Shake(rotation_deg=rot_deg, translation=trans)
    t = np.linspace(0, exposure_s, 4001)
    off = shake_offsets(sh, t, exposure_s, seed)
    amp = np.array([math.radians(rot_deg)] * 3 + [trans] * 3)
    assert (np.abs(off) <= amp * (1 + 1e-4) + 1e-15).all()
    assert np.abs(off).max(axis=0) == pytest.approx(amp, rel=1e-2, abs=1e-12)  # the bound is reached
    assert np.abs(off.mean(axis=0)).max() <= 1e-3 * max(amp.max(), 1e-12)    # zero mean over the exposure
    assert np.array_equal(off, shake_offsets(sh, t, exposure_s, seed))


def test_shake_is_smooth():
    sh = Shake(rotation_deg=1.0, max_hz=8.0)
    t = np.linspace(0, 0.1, 1001)
    rot = shake_offsets(sh, t, 0.1, 3)[:, 0]
    # band-limited to 8 Hz: |x''| <= (2 pi f)^2 * amplitude-ish; a jittery signal would be far above
    second = np.diff(rot, 2) / (t[1] - t[0]) ** 2
    assert np.abs(second).max() <= (2 * math.pi * 8.0) ** 2 * math.radians(1.0) * 3
    assert not np.array_equal(rot, shake_offsets(sh, t, 0.1, 4)[:, 0])


def test_blender_axes_on_a_known_camera():
    # a Blender camera at (0,-4,0) rotated 90 deg about x looks along +y at the origin, image up = +z
    R = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, (0, -4, 0)
    cv = blender_to_opencv(m)
    assert np.allclose(cv, look_at([0, -4, 0], [0, 0, 0]))
    assert np.allclose(opencv_to_blender(cv), m)
    K = intrinsics(100, 80, 60)
    uv, depth = project(K, cv, np.array([[0, 0, 0], [0.5, 0, 0], [0, 0, 0.5]], float))
    assert np.allclose(uv[0], [49.5, 39.5]) and np.allclose(depth, 4)
    assert uv[1, 0] > 49.5 and uv[2, 1] < 39.5  # +x to the right, +z (up) is up in the image


def test_rotations_round_trip_and_interpolation_hits_samples():
    rng = np.random.default_rng(0)
    for v in rng.normal(size=(20, 3)):
        R = rotvec_to_matrix(v)
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
        assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R)
    poses = apply_offsets(look_at([3, 1, 2], [0, 0, 0]), shake_offsets(Shake(rotation_deg=5, translation=0.3),
                                                                      np.linspace(0, 0.1, 5), 0.1, 1))
    t = np.array([0, 25_000, 50_000, 75_000, 100_000])
    for p, tt in zip(poses, t):
        assert np.allclose(interpolate_pose(poses, t, tt), p, atol=1e-12)
    half = interpolate_pose(poses, t, 12_500)
    assert np.allclose(half[:3, 3], (poses[0, :3, 3] + poses[1, :3, 3]) / 2)


def test_view_plan():
    r = Render(width=64, height=48, views=5, test_views=3, subframes=17, exposure_ms=100, gap_ms=50)
    plans = plan_views(r, ShakeSpec(rotation_deg=1.0), seed=0)
    assert len(plans) == 5
    for i, p in enumerate(plans):
        assert p.exposure == (i * 150_000, i * 150_000 + 100_000)
        assert p.t_us[0] == p.exposure[0] and p.t_us[-1] == p.exposure[1] and len(p.t_us) == 17
        assert (np.diff(p.t_us) > 0).all()
        assert not np.allclose(p.poses[0], p.poses[-1])          # sub-frame poses differ inside an exposure
        assert np.allclose(p.poses[8], p.mid_pose)                # 17 sub-frames: #8 is the midpoint
        centre = p.poses[8][:3, 3]
        assert np.linalg.norm(centre) == pytest.approx(4.0, rel=0.01)
    tp = novel_view_poses(r, 0)
    assert tp.shape == (3, 4, 4)
    assert min(np.linalg.norm(a[:3, 3] - b.mid_pose[:3, 3]) for a in tp for b in plans) > 0.05  # novel


def test_builtin_scene_files_load():
    names = builtin_scenes()
    assert {"lego", "ficus", "materials", "lowlight"} <= set(names)
    for n in names:
        spec = load_scene(n)
        assert spec.builder and spec.description
        q = resolve_render(spec, quick=True)
        assert q.width <= 128 and q.views <= 4
        assert spec.render.denoise_prefilter == "accurate" and q.denoise_prefilter == "fast"
    assert load_scene("lowlight").sensor.sensor_noise is not None  # only the dim scene asks for noise
    assert load_scene("lego").sensor.dvs.effects == ()


@pytest.mark.parametrize("text,match", [
    ('name = "x"\nbuilder = "lego"\n[render]\nwidht = 3\n', "unknown config key render.widht"),
    ('name = "x"\n[render]\nwidth = 2\n', "render size"),
    ('name = "x"\n[render]\nsubframes = 1\n', "subframes"),
    ('name = "x"\n[shake]\nmin_hz = 9\nmax_hz = 2\n', "min_hz"),
    ('name = "x"\n[sensor.dvs.leek]\n', "unknown config key sensor.dvs.leek"),
    ('name = "x"\n[quick]\nsamplez = 2\n', "quick"),
    ('name = "x"\n[render]\ndenoise_prefilter = "FAST"\n', "denoise_prefilter must be one of accurate, fast, none"),
    ('name = "x"\n[quick]\ndenoise_prefilter = "slow"\n', "quick: .*denoise_prefilter"),
    ('builder = "lego"\n', "name"),
    ('name = "x"\n[render\n', "invalid TOML"),
])
def test_bad_scene_files(tmp_path, text, match):
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_scene(str(p))


def test_overrides_are_validated():
    spec = load_scene("lego")
    with pytest.raises(ConfigError, match="render size"):
        resolve_render(spec, width=100000)
    assert resolve_render(spec, quick=True, views=2).views == 2


def test_pose_errors_after_similarity_alignment():
    from ev3dgs.geometry import pose_errors, umeyama

    rng = np.random.default_rng(0)
    gt = np.stack([look_at(rng.normal(size=3) * 3 + [0, 0, 4], [0, 0, 0]) for _ in range(12)])
    s, R = 0.37, rotvec_to_matrix(np.array([0.3, -0.2, 0.9]))
    t = np.array([1.0, -2.0, 0.5])
    est = gt.copy()  # the same cameras seen in another frame: x_est = s R x_gt + t
    est[:, :3, 3] = (s * (R @ gt[:, :3, 3].T)).T + t
    est[:, :3, :3] = R @ gt[:, :3, :3]
    s2, R2, t2 = umeyama(est[:, :3, 3], gt[:, :3, 3])
    assert s2 == pytest.approx(1 / s) and np.allclose(R2, R.T, atol=1e-9)
    e = pose_errors(est, gt)
    # exact data: the errors are round-off. The rotation angle comes from atan2 (a few ulp, any CPU/BLAS):
    # < 1e-12 rad = 5.7e-11 deg, bounded here by 1e-9 deg. The centres, O(5) with s = 0.37, are recovered
    # to ~1e-14 from a well-conditioned 12-point covariance: 1e-9 leaves a margin of 1e5.
    assert e["rotation_deg_max"] < 1e-9 and e["centre_error_max"] < 1e-9
    est[3, :3, :3] = rotvec_to_matrix(np.array([0, 0, math.radians(2.0)])) @ est[3, :3, :3]
    e = pose_errors(est, gt)  # one camera off by 2 deg: it dominates; the others are off by its share
    assert 1.6 < e["rotation_deg_max"] <= 2.0 and e["rotation_deg_median"] < 0.3
