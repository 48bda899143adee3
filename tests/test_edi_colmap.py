"""EDI latent frames (ev3dgs.io.edi) and pycolmap poses (ev3dgs.io.colmap) on synthetic data."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.errors import Ev3dgsError, InputError
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.io.colmap import PoseEstimationError, estimate_poses
from ev3dgs.io.edi import edi_latent_frames, edi_to_uint8, linear_to_srgb, srgb_to_linear
from ev3dgs.sim.config import DVSConfig
from ev3dgs.sim.dvs import simulate_events


def psnr(a, b, peak=1.0):
    return float(10 * np.log10(peak**2 / np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


# ------------------------------------------------------------------------------------------------ EDI
def moving_texture(n=24, h=48, w=64, shift=4.0, seed=0):
    """n sub-frames of a smooth random texture (linear 0.05..1) translated by up to `shift` px."""
    rng = np.random.default_rng(seed)
    pad = 8
    tex = cv2.GaussianBlur(rng.random((h + 2 * pad, w + 2 * pad)), (0, 0), 2.0)
    tex = 0.05 + 0.95 * (tex - tex.min()) / (tex.max() - tex.min())
    subs = []
    for d in np.linspace(0.0, shift, n):
        m = np.float32([[1, 0, d], [0, 1, 0.5 * d]])
        subs.append(cv2.warpAffine(tex, m, tex.shape[::-1], flags=cv2.INTER_CUBIC)[pad:pad + h, pad:pad + w])
    return np.clip(np.array(subs), 0.05, 1.0)


def test_edi_recovers_sharp_subframes():
    subs = moving_texture()
    t_us = np.linspace(0, 23_000, len(subs)).astype(np.int64)
    blurry = subs.mean(0)
    ev = simulate_events(subs, t_us, DVSConfig(pos_threshold=0.2, neg_threshold=0.2), seed=0)
    assert len(ev) > 500
    idx = [0, 6, 12, 17, 23]
    latent = edi_latent_frames(blurry, ev.t, ev.x, ev.y, ev.p, (0, 23_000), t_us[idx], 0.2, 0.2)
    assert latent.shape == (5, 48, 64) and np.all(np.isfinite(latent))
    gain = [psnr(latent[j], subs[k]) - psnr(blurry, subs[k]) for j, k in enumerate(idx)]
    gain_log = [psnr(np.log(latent[j]), np.log(subs[k]), 3.0) - psnr(np.log(blurry), np.log(subs[k]), 3.0)
                for j, k in enumerate(idx)]
    assert np.mean(gain) >= 3.0, gain          # measured +5.5 dB linear (8.7, 5.3, 0.2, 5.8, 7.4)
    assert np.mean(gain_log) >= 3.0, gain_log  # measured +6.9 dB in log
    # the ends of the exposure are the most blurred, so they gain the most
    assert gain[0] > 5 and gain[-1] > 5


def test_edi_static_scene_is_exact():
    rng = np.random.default_rng(1)
    blurry = rng.random((6, 7)) + 0.01
    empty = np.zeros(0)
    out = edi_latent_frames(blurry, empty, empty, empty, empty, (100, 900), [100, 500, 900])
    assert out.shape == (3, 6, 7)
    np.testing.assert_array_equal(out, np.broadcast_to(blurry, out.shape))
    # events outside the exposure are ignored
    out2 = edi_latent_frames(blurry, [0, 50, 950], [1, 2, 3], [1, 2, 3], [1, -1, 1], (100, 900), [500])
    np.testing.assert_array_equal(out2[0], blurry)


def test_edi_single_event_analytic():
    # one ON event half-way: B = L0 (0.5 + 0.5 e^0.2)
    blurry = np.full((1, 1), 0.5)
    out = edi_latent_frames(blurry, [500], [0], [0], [1], (0, 1000), [0, 499, 500, 1000], 0.2, 0.3)
    l0 = 0.5 / (0.5 + 0.5 * np.exp(0.2))
    np.testing.assert_allclose(out[:, 0, 0], [l0, l0, l0 * np.exp(0.2), l0 * np.exp(0.2)], rtol=1e-12)
    # OFF uses the negative threshold; p in {0, 1} is accepted (0 = OFF)
    out = edi_latent_frames(blurry, [250], [0], [0], [0], (0, 1000), [0, 1000], 0.2, 0.3)
    l0 = 0.5 / (0.25 + 0.75 * np.exp(-0.3))
    np.testing.assert_allclose(out[:, 0, 0], [l0, l0 * np.exp(-0.3)], rtol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n_events=st.integers(0, 200), thr=st.floats(0.05, 1.0))
def test_edi_mean_of_latent_is_blurry(seed, n_events, thr):
    """The defining identity: the exposure mean of L(t) reproduces B (exact integral, integer us stamps)."""
    rng = np.random.default_rng(seed)
    h, w, s, e = 3, 4, 1000, 1400
    blurry = rng.random((h, w)) * 2
    t = np.sort(rng.integers(s - 50, e + 50, n_events))
    x, y = rng.integers(0, w, n_events), rng.integers(0, h, n_events)
    p = rng.choice([-1, 1], n_events)
    times = np.arange(s, e)                     # E is right-continuous and constant on [t, t+1)
    latent = edi_latent_frames(blurry, t, x, y, p, (s, e), times, thr, thr * 1.3)
    np.testing.assert_allclose(latent.mean(0), blurry, rtol=1e-9, atol=1e-12)


def test_edi_finite_for_zero_pixels_and_huge_counts():
    blurry = np.zeros((4, 5))
    blurry[1:, :] = 0.3
    n = 200_000
    rng = np.random.default_rng(2)
    t = np.sort(rng.integers(0, 10_000, n))
    x = np.zeros(n, np.int64)
    y = np.zeros(n, np.int64)
    y[n // 2:] = 1                               # pixel (0, 0): zero intensity; pixel (1, 0): 0.3
    p = np.ones(n)
    p[rng.random(n) < 0.05] = -1                 # mostly ON: E climbs to thousands of thresholds
    t[:1000] = 5000                              # and a burst of events sharing one timestamp
    t = np.sort(t)
    times = np.array([0, 4999, 5000, 5001, 10_000])
    out = edi_latent_frames(blurry, t, x, y, p, (0, 10_000), times, 0.2, 0.2)
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    assert np.all(out[:, 0, 0] == 0)                          # zero stays zero
    np.testing.assert_array_equal(out[:, 2:, :], 0.3)         # untouched pixels keep B
    # float32 input, a single time as a scalar
    out32 = edi_latent_frames(blurry.astype(np.float32), t, x, y, p, (0, 10_000), 7000)
    assert out32.shape == (1, 4, 5) and np.all(np.isfinite(out32))


def test_edi_input_errors():
    b = np.ones((2, 2))
    z = np.zeros(0)
    with pytest.raises(InputError):
        edi_latent_frames(b, z, z, z, z, (0, 100), [200])                  # time outside exposure
    with pytest.raises(InputError):
        edi_latent_frames(np.ones((2, 2), np.uint8), z, z, z, z, (0, 100), [50])   # not linear float
    with pytest.raises(InputError):
        edi_latent_frames(b, [1], [5], [0], [1], (0, 100), [50])          # x outside the frame
    with pytest.raises(InputError):
        edi_latent_frames(b, z, z, z, z, (100, 100), [100])               # empty exposure
    assert issubclass(InputError, Ev3dgsError)


def test_edi_to_uint8_and_srgb():
    rng = np.random.default_rng(3)
    lat = rng.random((3, 8, 9)) * 5
    lat[0, 0, 0] = np.inf
    lat[1, 0, 0] = 1e9                                    # outlier: clipped, does not darken the rest
    u = edi_to_uint8(lat)
    assert u.dtype == np.uint8 and u.shape == lat.shape
    assert u.max() == 255 and np.median(u) > 100
    assert edi_to_uint8(np.zeros((4, 4))).max() == 0
    v = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(v)), v, atol=1e-12)
    assert abs(srgb_to_linear(np.array([128], np.uint8))[0] - 0.2158605) < 1e-6


# --------------------------------------------------------------------------------------------- COLMAP
W, H = 320, 240
N_VIEWS = 16


def _texture(rng, size=256):
    t = np.zeros((size, size, 3))
    for sigma, amp in ((16, 0.5), (5, 0.35), (1.5, 0.25)):
        n = cv2.GaussianBlur(rng.random((size, size, 3)), (0, 0), sigma)
        t += amp * (n - n.mean()) / (n.std() + 1e-9)
    t = 0.5 + 0.18 * t
    for _ in range(60):                                   # discs and squares: blobs and corners for SIFT
        c, (x, y), r = rng.random(3).tolist(), rng.integers(0, size, 2).tolist(), int(rng.integers(3, 14))
        if rng.random() < 0.5:
            cv2.circle(t, (x, y), r, c, -1)
        else:
            cv2.rectangle(t, (x, y), (x + r, y + r), c, -1)
    return np.clip(t, 0, 1).astype(np.float32)


def _scene(seed=0):
    """A textured room (floor + 3 walls) with a textured box in the middle: (origin, u, v, texture)."""
    rng = np.random.default_rng(seed)
    planes = [((-4, -4, 0), (8, 0, 0), (0, 8, 0)), ((-4, 4, 0), (8, 0, 0), (0, 0, 3)),
              ((-4, -4, 0), (0, 8, 0), (0, 0, 3)), ((4, -4, 0), (0, 8, 0), (0, 0, 3)),
              ((-0.5, -0.5, 1), (1, 0, 0), (0, 1, 0)), ((-0.5, -0.5, 0), (1, 0, 0), (0, 0, 1)),
              ((-0.5, -0.5, 0), (0, 1, 0), (0, 0, 1)), ((0.5, -0.5, 0), (0, 1, 0), (0, 0, 1))]
    return [tuple(np.array(v, float) for v in pl) + (_texture(rng),) for pl in planes]


def _render(scene, K, c2w, ss=2):
    """Ray-cast the planes at ss x ss supersampling (OpenCV pixel convention), box-filter down. RGB uint8."""
    Ks = K.copy()
    Ks[:2, :2] *= ss
    Ks[:2, 2] = (K[:2, 2] + 0.5) * ss - 0.5
    u, v = np.meshgrid(np.arange(W * ss), np.arange(H * ss))
    d = np.stack([(u - Ks[0, 2]) / Ks[0, 0], (v - Ks[1, 2]) / Ks[1, 1], np.ones(u.shape)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    best = np.full(u.shape, np.inf)
    img = np.zeros(u.shape + (3,), np.float32)
    for po, pu, pv, tex in scene:
        n = np.cross(pu, pv)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((po - o) @ n) / (d @ n)
        q = o + t[..., None] * d - po
        a, b = q @ pu / (pu @ pu), q @ pv / (pv @ pv)
        hit = (t > 1e-6) & (t < best) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        s = tex.shape[0] - 1
        col = cv2.remap(tex, (a * s).astype(np.float32), (b * s).astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT)
        img[hit], best[hit] = col[hit], t[hit]
    img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


@pytest.fixture(scope="module")
def orbit_views():
    K = intrinsics(W, H, 70.0)
    angles = np.deg2rad(np.linspace(-40, 40, N_VIEWS)) - np.pi / 2
    poses = [look_at((2.8 * np.cos(a), 2.8 * np.sin(a), 1.6), (0, 0.8, 0.6)) for a in angles]
    scene = _scene(0)
    return K, np.array(poses), [_render(scene, K, c2w) for c2w in poses]


def umeyama(src, dst):
    """Similarity (s, R, t) minimising |s R src + t - dst|^2."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (xs**2).sum(1).mean()
    return s, R, mu_d - s * R @ mu_s


def pose_errors(est, gt):
    """Max rotation error (deg) and max centre error (world units) after aligning the centres."""
    reg = [i for i, p in enumerate(est) if p is not None]
    e = np.array([est[i] for i in reg])
    g = gt[reg]
    s, R, t = umeyama(e[:, :3, 3], g[:, :3, 3])
    centre = np.linalg.norm(s * e[:, :3, 3] @ R.T + t - g[:, :3, 3], axis=1)
    rot = [np.degrees(np.arccos(np.clip((np.trace(gi[:3, :3].T @ R @ ei[:3, :3]) - 1) / 2, -1, 1)))
           for ei, gi in zip(e, g)]
    return float(max(rot)), float(centre.max())


def test_estimate_poses_known_K(orbit_views, tmp_path):
    K, gt, images = orbit_views
    res = estimate_poses(images, K, tmp_path / "sfm")
    assert res.num_registered >= 0.9 * N_VIEWS
    assert res.registered.sum() == res.num_registered == sum(p is not None for p in res.poses)
    assert res.camera_model == "PINHOLE"
    np.testing.assert_allclose(res.K, K, atol=1e-6)           # fixed intrinsics, convention round-trips
    rot, centre = pose_errors(res.poses, gt)
    orbit_size = np.linalg.norm(gt[0, :3, 3] - gt[-1, :3, 3])
    assert rot < 2.0, rot                                       # measured 0.35 deg
    assert centre < 0.02 * orbit_size, (centre, orbit_size)    # measured ~0.004 of a 3.6 chord
    for p in res.poses:
        if p is not None:
            np.testing.assert_allclose(p[:3, :3] @ p[:3, :3].T, np.eye(3), atol=1e-9)
            np.testing.assert_array_equal(p[3], [0, 0, 0, 1])
    assert res.points_xyz.dtype == np.float32 and res.points_xyz.shape[1] == 3 and len(res.points_xyz) > 100
    assert res.points_rgb.dtype == np.uint8 and res.points_rgb.shape == res.points_xyz.shape
    assert res.mean_reprojection_error < 1.0
    assert (tmp_path / "sfm" / "images" / res.image_names[0]).is_file()
    # sparse points project into a registered view (poses and points share the world frame, K convention)
    i = next(i for i, p in enumerate(res.poses) if p is not None)
    w2c = np.linalg.inv(res.poses[i])
    pc = res.points_xyz.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    front = pc[:, 2] > 0
    uv = pc[front] @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    inside = (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
    assert inside.mean() > 0.3


def test_estimate_poses_unknown_K(orbit_views, tmp_path):
    K, gt, images = orbit_views
    gray = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in images]     # (H, W) input too
    res = estimate_poses(gray, None, tmp_path / "sfm", min_registered=0.9)
    assert res.num_registered >= 0.9 * N_VIEWS
    assert res.camera_model == "SIMPLE_RADIAL"
    assert abs(res.K[0, 0] / K[0, 0] - 1) < 0.05, res.K
    np.testing.assert_allclose(res.K[:2, 2], K[:2, 2], atol=1e-6)     # centre, back in OpenCV convention
    rot, centre = pose_errors(res.poses, gt)
    assert rot < 2.0 and centre < 0.02 * np.linalg.norm(gt[0, :3, 3] - gt[-1, :3, 3])


def test_estimate_poses_failures(orbit_views, tmp_path):
    K, _, images = orbit_views
    flat = [np.full((H, W), 128, np.uint8)] * 6
    with pytest.raises(PoseEstimationError, match=r"^only 0 of 6 views registered") as info:
        estimate_poses(flat, K, tmp_path / "flat")
    assert "\n" not in str(info.value) and isinstance(info.value, Ev3dgsError)
    with pytest.raises(PoseEstimationError, match=r"^only 0 of 1 views registered"):
        estimate_poses(images[:1], K, tmp_path / "one")
    # 3 textured views + 9 featureless ones: at most 3 of 12 can register, min_registered=0.5 needs 6
    with pytest.raises(PoseEstimationError, match=r"^only [0-3] of 12 views registered \(need 6"):
        estimate_poses(images[:3] + [np.full((H, W, 3), 90, np.uint8)] * 9, K, tmp_path / "mixed")
    with pytest.raises(InputError):
        estimate_poses([images[0], images[1][:100]], K, tmp_path / "sizes")
    with pytest.raises(InputError):
        estimate_poses([im.astype(np.float32) for im in images[:2]], K, tmp_path / "dtype")
