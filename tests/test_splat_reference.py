"""Projection (ev3dgs.splat.project) and the reference rasterizer oracle (ev3dgs.splat.reference)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs.splat.project import project_gaussians, quat_to_rotmat
from ev3dgs.splat.reference import rasterize_reference

A_MIN = 1.0 / 255.0


# ----------------------------------------------------------------------------------------------- helpers
def hamilton(p, q):
    w1, x1, y1, z1 = p
    w2, x2, y2, z2 = q
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def np_rotmat(q):
    """Rotation matrix by rotating the basis vectors with q v q* (independent of quat_to_rotmat)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q)
    qc = q * np.array([1, -1, -1, -1])
    cols = [hamilton(hamilton(q, np.r_[0.0, e]), qc)[1:] for e in np.eye(3)]
    return np.stack(cols, axis=1)


def make_K(W, H, f=None, fy=None, cx=None, cy=None):
    f = f if f is not None else 1.1 * W
    fy = fy if fy is not None else f
    cx = cx if cx is not None else (W - 1) / 2
    cy = cy if cy is not None else (H - 1) / 2
    return np.array([[f, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def random_camera(rng):
    R = np_rotmat(rng.normal(size=4))
    t = rng.normal(size=3)
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = t
    return V


def onscreen_gaussians(rng, V, K, W, H, n, zlo=2.0, zhi=6.0, margin=0.0):
    """World means whose centres project inside the image (shrunk by `margin` px)."""
    z = rng.uniform(zlo, zhi, n)
    u = rng.uniform(margin, W - 1 - margin, n)
    v = rng.uniform(margin, H - 1 - margin, n)
    pc = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    R, t = V[:3, :3], V[:3, 3]
    return (pc - t) @ R  # R^T (pc - t)


def T(x, dtype=torch.float64):
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def loop_reference(means2d, conics, colors, opac, depths, radii, W, H, bg, stats=None):
    """Literal per-pixel loop of the compositing rules (pure Python floats)."""
    means2d, conics, colors = means2d.tolist(), conics.tolist(), colors.tolist()
    opac, depths, radii, bg = opac.tolist(), depths.tolist(), radii.tolist(), bg.tolist()
    order = sorted([i for i in range(len(radii)) if radii[i] > 0], key=lambda i: depths[i])  # stable
    D = len(bg)
    img = np.zeros((H, W, D))
    alp = np.zeros((H, W, 1))
    for y in range(H):
        for x in range(W):
            Tr = 1.0
            C = [0.0] * D
            for i in order:
                dx = x - means2d[i][0]
                dy = y - means2d[i][1]
                a, b, c = conics[i]
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0:
                    if stats is not None:
                        stats["neg"] += 1
                    continue
                alpha = min(0.99, opac[i] * math.exp(-sigma))
                if alpha < 1.0 / 255.0:
                    if stats is not None:
                        stats["skip"] += 1
                    continue
                next_T = Tr * (1 - alpha)
                if next_T < 1e-4:
                    if stats is not None:
                        stats["stop"] += 1
                    break
                for k in range(D):
                    C[k] += colors[i][k] * alpha * Tr
                Tr = next_T
            for k in range(D):
                img[y, x, k] = C[k] + Tr * bg[k]
            alp[y, x, 0] = 1 - Tr
    return img, alp


def random_2d_scene(rng, n, W, H, cov_lo=0.3, cov_hi=4.0):
    means2d = np.stack([rng.uniform(-1.5, W + 0.5, n), rng.uniform(-1.5, H + 0.5, n)], axis=1)
    conics = []
    for _ in range(n):
        th = rng.uniform(0, np.pi)
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        C = R @ np.diag(rng.uniform(cov_lo, cov_hi, 2)) @ R.T
        Ci = np.linalg.inv(C)
        conics.append([Ci[0, 0], Ci[0, 1], Ci[1, 1]])
    return means2d, np.array(conics)


# ------------------------------------------------------------------------------------------- projection
def test_quat_to_rotmat_matches_hamilton_product():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(16, 4)) * rng.uniform(0.1, 10, (16, 1))
    R = quat_to_rotmat(T(q)).numpy()
    for i in range(16):
        np.testing.assert_allclose(R[i], np_rotmat(q[i]), atol=1e-12)
        np.testing.assert_allclose(R[i] @ R[i].T, np.eye(3), atol=1e-12)
    # zero quaternion -> identity, finite gradient
    qz = torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)
    Rz = quat_to_rotmat(qz)
    np.testing.assert_allclose(Rz[0].detach().numpy(), np.eye(3))
    Rz.sum().backward()
    assert torch.isfinite(qz.grad).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projection_means_and_depths_match_numpy(seed):
    rng = np.random.default_rng(seed)
    W, H = 40, 30
    V = random_camera(rng)
    K = make_K(W, H, f=37.0, fy=41.0, cx=18.2, cy=15.7)
    n = 25
    means = onscreen_gaussians(rng, V, K, W, H, n)
    means += rng.normal(size=means.shape) * 0.5  # some go off-screen: means2d is never clamped
    quats = rng.normal(size=(n, 4))
    scales = rng.uniform(0.01, 0.3, (n, 3))
    opac = rng.uniform(0.1, 1.0, n)
    p = project_gaussians(T(means), T(quats), T(scales), T(opac), T(V), T(K), W, H)
    pc = means @ V[:3, :3].T + V[:3, 3]
    uvw = pc @ K.T
    np.testing.assert_allclose(p.means2d.numpy(), uvw[:, :2] / uvw[:, 2:], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(p.depths.numpy(), pc[:, 2], atol=1e-12)
    assert p.radii.dtype == torch.int32
    assert p.means2d.shape == (n, 2) and p.conics.shape == (n, 3) and p.cov2d.shape == (n, 3)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_cov2d_matches_numerical_linearisation(seed):
    rng = np.random.default_rng(seed)
    W, H = 48, 36
    V = random_camera(rng)
    K = make_K(W, H, f=50.0, fy=45.0, cx=22.0, cy=18.5)
    n = 10
    means = onscreen_gaussians(rng, V, K, W, H, n, margin=2.0)
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(-4, 0, (n, 3)))
    opac = np.full(n, 0.8)
    eps2d = 0.3
    p = project_gaussians(T(means), T(quats), T(scales), T(opac), T(V), T(K), W, H, eps2d=eps2d)
    Vt, Kt = T(V), T(K)

    def proj(x):
        c = Vt[:3, :3] @ x + Vt[:3, 3]
        return torch.stack([Kt[0, 0] * c[0] / c[2] + Kt[0, 2], Kt[1, 1] * c[1] / c[2] + Kt[1, 2]])

    for i in range(n):
        Jw = torch.autograd.functional.jacobian(proj, T(means[i])).numpy()  # (2, 3)
        R = np_rotmat(quats[i])
        Sigma = R @ np.diag(scales[i] ** 2) @ R.T
        cov = Jw @ Sigma @ Jw.T + eps2d * np.eye(2)
        got = p.cov2d[i].numpy()
        np.testing.assert_allclose(got, [cov[0, 0], cov[0, 1], cov[1, 1]], rtol=1e-10, atol=1e-12)
        a, b, c = p.conics[i].numpy()
        np.testing.assert_allclose(np.array([[a, b], [b, c]]) @ cov, np.eye(2), atol=1e-10)
        assert p.radii[i] > 0


def test_fov_clamp_uses_clamped_point_in_jacobian():
    W, H = 20, 16
    K = make_K(W, H, f=10.0)  # tan(fov_x/2) = 1.0, centred -> limit 1.3
    V = np.eye(4)
    z = 2.0
    means = np.array([[5.0 * z, 0.3, z], [-4.0 * z, -3.0 * z, z], [0.5 * z, 0.2 * z, z]])
    quats = np.array([[1.0, 0.2, -0.3, 0.1]] * 3)
    scales = np.array([[0.3, 0.1, 0.2]] * 3)
    p = project_gaussians(T(means), T(quats), T(scales), T(np.ones(3)), T(V), T(K), W, H)
    lim_x = 1.3 * 0.5 * W / K[0, 0]
    lim_y = 1.3 * 0.5 * H / K[1, 1]
    R = np_rotmat(quats[0])
    Sigma = R @ np.diag(scales[0] ** 2) @ R.T
    for i in range(3):
        x, y, _ = means[i]
        tx = z * np.clip(x / z, -lim_x, lim_x)
        ty = z * np.clip(y / z, -lim_y, lim_y)
        J = np.array([[K[0, 0] / z, 0, -K[0, 0] * tx / z**2], [0, K[1, 1] / z, -K[1, 1] * ty / z**2]])
        cov = J @ Sigma @ J.T + 0.3 * np.eye(2)
        np.testing.assert_allclose(p.cov2d[i].numpy(), [cov[0, 0], cov[0, 1], cov[1, 1]], rtol=1e-12)
        # means2d uses the unclamped point
        np.testing.assert_allclose(p.means2d[i].numpy(), [K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]])


def test_projection_gradcheck():
    rng = np.random.default_rng(5)
    W, H = 24, 20
    V = random_camera(rng)
    K = make_K(W, H)
    n = 3
    means = T(onscreen_gaussians(rng, V, K, W, H, n, margin=3.0)).requires_grad_()
    quats = T(rng.normal(size=(n, 4))).requires_grad_()
    scales = T(rng.uniform(0.05, 0.3, (n, 3))).requires_grad_()
    opac = T(np.full(n, 0.7))

    def f(m, q, s):
        p = project_gaussians(m, q, s, opac, T(V), T(K), W, H)
        return p.means2d, p.conics, p.cov2d, p.depths

    assert torch.autograd.gradcheck(f, (means, quats, scales))


def test_culling_rules():
    W, H = 20, 16
    K = make_K(W, H, f=20.0)
    V = np.eye(4)
    near, far = 0.1, 100.0
    means = np.array(
        [
            [0, 0, 5.0],  # 0 visible
            [0, 0, -5.0],  # 1 behind
            [0, 0, near],  # 2 exactly at near
            [0, 0, 0.05],  # 3 between 0 and near
            [0, 0, 0.0],  # 4 at the camera centre
            [0, 0, far],  # 5 at far
            [1e6, 0, 1.0],  # 6 far off-screen
            [0, 0, 5.0],  # 7 opacity below 1/255
            [0, 0, 5.0],  # 8 opacity exactly 0
            [np.nan, 0, 5.0],  # 9 non-finite mean
            [0, 0, 5.0],  # 10 inf scale
        ]
    )
    n = len(means)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    scales = np.full((n, 3), 0.1)
    scales[10, 0] = np.inf
    opac = np.full(n, 0.5)
    opac[7] = 0.5 / 255
    opac[8] = 0.0
    p = project_gaussians(T(means), T(quats), T(scales), T(opac), T(V), T(K), W, H, near=near, far=far)
    assert p.radii[0] > 0
    assert (p.radii[1:] == 0).all(), p.radii
    for t in (p.means2d, p.conics, p.depths, p.cov2d):
        assert torch.isfinite(t).all()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1])
def test_radius_is_exact_support(dtype, seed):
    """Every pixel outside [mx±r]x[my±r] has alpha < 1/255 (brute force over the image, rasterizer's rule)."""
    rng = np.random.default_rng(seed)
    W, H = 64, 48
    V = random_camera(rng)
    K = make_K(W, H, f=40.0)
    n = 120
    means = onscreen_gaussians(rng, V, K, W, H, n, zlo=1.0, zhi=8.0)
    means += rng.normal(size=means.shape) * 1.0  # some partly or fully off-screen
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(-6, -0.5, (n, 3)))
    scales[::3, 0] *= 30  # elongated ones
    scales[::4, 1] = 1e-9  # flat ones
    opac = np.exp(rng.uniform(np.log(1 / 255), 0, n))
    opac[::7] = 1.0
    opac[::11] = 1 / 255 * (1 + 1e-6)
    opac[::13] = 0.99 / 255
    p = project_gaussians(T(means, dtype), T(quats, dtype), T(scales, dtype), T(opac, dtype), T(V, dtype), T(K, dtype), W, H)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    o = T(opac, dtype)
    checked = 0
    for i in range(n):
        if not (torch.isfinite(p.means2d[i]).all() and p.depths[i] > 0.01):
            assert p.radii[i] == 0
            continue
        mx, my = p.means2d[i]
        a, b, c = p.conics[i]
        dx, dy = xs - mx, ys - my
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp_max(o[i] * torch.exp(-sigma.clamp_min(0)), 0.99)
        matters = (sigma >= 0) & (alpha >= A_MIN)
        r = float(p.radii[i])
        inside = ((xs - mx).abs() <= r) & ((ys - my).abs() <= r) if r > 0 else torch.zeros_like(matters)
        assert not (matters & ~inside).any(), (i, r)
        checked += 1
    assert checked > n // 2
    assert (p.radii > 0).sum() > n // 3


# ------------------------------------------------------------------------------------------- rasterizer
@pytest.mark.parametrize("seed", list(range(6)))
def test_reference_matches_per_pixel_loop(seed):
    rng = np.random.default_rng(seed)
    W, H, n = 7, 5, 12
    means2d, conics = random_2d_scene(rng, n, W, H)
    colors = rng.uniform(0, 1, (n, 3))
    opac = rng.uniform(0.05, 1.0, n)
    opac[:4] = [1.0, 0.995, 0.98, 0.97]  # opaque ones: alpha clamps to 0.99, the 1e-4 stop triggers
    m_big, c_big = random_2d_scene(rng, 4, W, H, cov_lo=8.0, cov_hi=30.0)  # broad, overlapping
    means2d[:4] = m_big * 0.4 + np.array([W, H]) * 0.3
    conics[:4] = c_big
    opac[4] = 0.01  # mostly below 1/255
    depths = rng.uniform(1, 3, n)
    depths[5] = depths[6]  # a tie (stable order by index)
    radii = np.full(n, 5, dtype=np.int32)
    radii[7] = 0  # culled: must be ignored
    conics[8] = [0.3, 0.6, 0.2]  # indefinite (not a valid conic): exercises the sigma < 0 skip
    bg = rng.uniform(0, 1, 3)
    stats = {"skip": 0, "stop": 0, "neg": 0}
    want_img, want_a = loop_reference(T(means2d), T(conics), T(colors), T(opac), T(depths), T(radii), W, H, T(bg), stats)
    img, a = rasterize_reference(T(means2d), T(conics), T(colors), T(opac), T(depths), torch.as_tensor(radii), W, H, T(bg))
    assert img.shape == (H, W, 3) and a.shape == (H, W, 1)
    assert img.dtype == torch.float64
    np.testing.assert_allclose(img.numpy(), want_img, atol=1e-12, rtol=0)
    np.testing.assert_allclose(a.numpy(), want_a, atol=1e-12, rtol=0)
    assert stats["skip"] > 0 and stats["stop"] > 0 and stats["neg"] > 0, stats


def test_reference_small_chunks_and_no_background():
    rng = np.random.default_rng(11)
    W, H, n = 9, 6, 8
    means2d, conics = random_2d_scene(rng, n, W, H)
    args = (T(means2d), T(conics), T(rng.uniform(0, 1, (n, 2))), T(rng.uniform(0.1, 1, n)), T(rng.uniform(1, 2, n)), torch.full((n,), 100, dtype=torch.int32), W, H)
    i1, a1 = rasterize_reference(*args)
    i2, a2 = rasterize_reference(*args, background=torch.zeros(2, dtype=torch.float64), block=3)
    assert torch.equal(i1, i2) and torch.equal(a1, a2)


def test_reference_empty_scene_returns_background():
    bg = torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64)
    for n in (0, 3):
        z = torch.zeros(n, dtype=torch.float64)
        img, a = rasterize_reference(
            torch.zeros(n, 2, dtype=torch.float64), torch.ones(n, 3, dtype=torch.float64),
            torch.ones(n, 3, dtype=torch.float64), z + 1, z + 1, torch.zeros(n, dtype=torch.int32), 4, 3, bg,
        )
        assert torch.equal(img, bg.expand(3, 4, 3)) and torch.equal(a, torch.zeros(3, 4, 1, dtype=torch.float64))


@pytest.mark.parametrize("opaque", [False, True])
def test_reference_gradcheck(opaque):
    W, H = 3, 2
    means2d = T([[0.3, 0.4], [1.6, 0.8], [1.1, 0.2]]).requires_grad_()
    # broad footprints: every alpha is far from 1/255 (and from 0.99 in the non-opaque case)
    conics = T([[0.10, 0.02, 0.12], [0.08, -0.01, 0.09], [0.11, 0.0, 0.07]]).requires_grad_()
    colors = T([[0.9, 0.1], [0.2, 0.8], [0.5, 0.5]]).requires_grad_()
    opac = T([0.985, 0.975, 0.98] if opaque else [0.6, 0.5, 0.7]).requires_grad_()
    bg = T([0.3, 0.6]).requires_grad_()
    depths = T([1.0, 2.0, 3.0])
    radii = torch.full((3,), 4, dtype=torch.int32)
    if opaque:  # the 1e-4 stop really happens here, away from its threshold
        stats = {"skip": 0, "stop": 0, "neg": 0}
        loop_reference(means2d.detach(), conics.detach(), colors.detach(), opac.detach(), depths, radii, W, H, bg.detach(), stats)
        assert stats["stop"] > 0

    def f(m, cn, col, o, b):
        return rasterize_reference(m, cn, col, o, depths, radii, W, H, b)

    assert torch.autograd.gradcheck(f, (means2d, conics, colors, opac, bg))


# --------------------------------------------------------------------------------- end-to-end hard cases
def hard_scene(dtype):
    W, H = 16, 12
    K = make_K(W, H, f=14.0)
    V = np.eye(4)
    V[:3, 3] = [0.1, -0.2, 0.0]
    near = 0.01
    rows = [
        # mean, quat, scales, opacity
        ([0.0, 0.0, 3.0], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.8),  # normal
        ([0.2, 0.1, -2.0], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.8),  # behind the camera
        ([-0.1, 0.2, near], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.8),  # z exactly near (camera t has z=0)
        ([-0.1, 0.2, 0.004], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.8),  # 0 < z < near
        ([0.1, 0.1, 4.0], [0.3, 0.1, 0.4, 0.2], [1e4, 1e4, 1e4], 0.5),  # huge scale
        ([0.3, -0.2, 2.0], [0.3, 0.1, 0.4, 0.2], [1e-8, 1e-8, 1e-8], 0.9),  # tiny scale
        ([-0.3, 0.1, 2.5], [0.5, 0.5, -0.5, 0.1], [0.5, 1e-12, 0.3], 0.9),  # flat
        ([0.2, 0.3, 2.5], [0.5, 0.5, -0.5, 0.1], [0.0, 1e-12, 0.4], 0.9),  # needle (two scales ~0)
        ([0.0, 0.0, 2.0], [1, 0, 0, 0], [0.2, 0.2, 0.2], 0.0),  # opacity 0
        ([0.1, 0.0, 2.0], [1, 0, 0, 0], [0.2, 0.2, 0.2], 1e-6),  # opacity 1e-6
        ([0.0, 0.1, 2.2], [1, 0, 0, 0], [0.2, 0.2, 0.2], 1 - 1e-7),  # opacity ~1
        ([0.05, 0.1, 2.3], [1, 0, 0, 0], [0.2, 0.2, 0.2], 1.0),  # opacity 1
        ([-0.1, 0.2, 0.0], [1, 0, 0, 0], [5.0, 5.0, 5.0], 0.7),  # mean at the camera centre, big scale
        ([-0.1, 0.2, 0.03], [0.2, 0.9, 0.1, 0.3], [5.0, 2.0, 5.0], 0.7),  # camera inside, just in front
        ([1e5, 3.0, 1.0], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.8),  # far off-screen
        ([-50.0, 40.0, 1.0], [1, 0, 0, 0], [20.0, 0.3, 30.0], 0.8),  # off-screen centre, footprint on-screen
        ([0.1, -0.1, 3.0], [0, 0, 0, 0], [0.2, 0.4, 0.1], 0.6),  # zero quaternion
        ([0.0, 0.0, 1e12], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.6),  # beyond far
    ]
    means = T([r[0] for r in rows], dtype)
    quats = T([r[1] for r in rows], dtype)
    scales = T([r[2] for r in rows], dtype)
    opac = T([r[3] for r in rows], dtype)
    return W, H, T(V, dtype), T(K, dtype), near, means, quats, scales, opac


def render_and_grads(W, H, V, K, near, means, quats, scales, opac, colors, bg):
    leaves = [t.detach().clone().requires_grad_() for t in (means, quats, scales, opac, colors, bg)]
    m, q, s, o, c, b = leaves
    p = project_gaussians(m, q, s, o, V, K, W, H, near=near)
    img, a = rasterize_reference(p.means2d, p.conics, c, o, p.depths, p.radii, W, H, b)
    (img.sum() + a.sum()).backward()
    grads = [torch.zeros_like(t) if t.grad is None else t.grad for t in leaves]
    return p, img, a, grads


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hard_cases_stay_finite(dtype):
    W, H, V, K, near, means, quats, scales, opac = hard_scene(dtype)
    n = means.shape[0]
    colors = torch.linspace(0, 1, n * 3, dtype=dtype).reshape(n, 3)
    bg = T([0.1, 0.2, 0.3], dtype)
    p, img, a, grads = render_and_grads(W, H, V, K, near, means, quats, scales, opac, colors, bg)
    for t in (p.means2d, p.conics, p.depths, p.cov2d, img, a, *grads):
        assert torch.isfinite(t).all()
    r = p.radii
    assert r[0] > 0 and r[4] > 0 and r[15] > 0 and r[16] > 0
    assert (r[[1, 2, 3, 8, 9, 12, 14, 17]] == 0).all(), r
    assert (a >= 0).all() and (a <= 1).all()
    assert grads[0].abs().sum() > 0 and grads[4].abs().sum() > 0

    # each Gaussian alone, and the empty / all-culled scenes
    for i in range(n):
        sel = slice(i, i + 1)
        _, img, a, grads = render_and_grads(W, H, V, K, near, means[sel], quats[sel], scales[sel], opac[sel], colors[sel], bg)
        for t in (img, a, *grads):
            assert torch.isfinite(t).all(), i
    e = torch.zeros(0, 3, dtype=dtype)
    _, img, a, grads = render_and_grads(W, H, V, K, near, e, torch.zeros(0, 4, dtype=dtype), e, torch.zeros(0, dtype=dtype), e, bg)
    assert torch.equal(img, bg.expand(H, W, 3)) and (a == 0).all()
    culled = [1, 2, 3, 12, 14]
    _, img, a, grads = render_and_grads(W, H, V, K, near, means[culled], quats[culled], scales[culled], opac[culled], colors[culled], bg)
    assert torch.equal(img, bg.expand(H, W, 3)) and (a == 0).all()
    assert all(torch.isfinite(g).all() for g in grads)


def test_nonfinite_inputs_are_culled_with_zero_grad():
    W, H, V, K, near, means, quats, scales, opac = hard_scene(torch.float64)
    means, quats, scales, opac = means[:2].clone(), quats[:2].clone(), scales[:2].clone(), opac[:2].clone()
    means = torch.cat([means, T([[0.0, 0.0, 3.0]] * 3)])
    quats = torch.cat([quats, T([[1.0, 0, 0, 0], [np.nan, 0, 0, 0], [1.0, 0, 0, 0]])])
    scales = torch.cat([scales, T([[0.2, 0.2, np.inf], [0.2] * 3, [0.2] * 3])])
    opac = torch.cat([opac, T([0.5, 0.5, np.nan])])
    means[1, 0] = np.nan
    colors = torch.full((5, 3), 0.5, dtype=torch.float64)
    p, img, a, grads = render_and_grads(W, H, V, K, near, means, quats, scales, opac, colors, T([0.0, 0.0, 0.0]))
    assert p.radii[0] > 0 and (p.radii[1:] == 0).all()
    for t in (p.means2d, p.conics, p.depths, p.cov2d, img, a, grads[0], grads[4]):
        assert torch.isfinite(t).all()


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(0, 8),
    log_scale=st.floats(-9.0, 3.0),
    z_center=st.floats(-1.0, 8.0),
    opacity_mode=st.sampled_from(["random", "opaque", "faint", "extreme"]),
    use_f32=st.booleans(),
)
def test_property_finite_and_in_range(seed, n, log_scale, z_center, opacity_mode, use_f32):
    dtype = torch.float32 if use_f32 else torch.float64
    rng = np.random.default_rng(seed)
    W, H = 10, 8
    V = random_camera(rng)
    K = make_K(W, H, f=rng.uniform(5, 30))
    pc = np.stack([rng.normal(0, 2, n), rng.normal(0, 2, n), z_center + rng.normal(0, 2, n)], 1)
    means = (pc - V[:3, 3]) @ V[:3, :3]
    quats = rng.normal(size=(n, 4))
    scales = np.exp(log_scale + rng.normal(0, 1.5, (n, 3)))
    opac = {
        "random": rng.uniform(0, 1, n),
        "opaque": 1 - rng.uniform(0, 0.05, n),
        "faint": rng.uniform(0, 0.02, n),
        "extreme": rng.choice([0.0, 1e-6, 1 - 1e-7, 1.0], n),
    }[opacity_mode]
    colors = rng.uniform(0, 1, (n, 3))
    bg = rng.uniform(0, 1, 3)
    p, img, a, grads = render_and_grads(W, H, T(V, dtype), T(K, dtype), 0.01, *(T(x, dtype) for x in (means, quats, scales, opac, colors, bg)))
    for t in (p.means2d, p.conics, p.depths, img, a, *grads):
        assert torch.isfinite(t).all()
    allc = np.concatenate([colors.reshape(-1, 3), bg[None]], 0)
    tol = 1e-5 if use_f32 else 1e-12
    assert (img.detach().numpy() >= allc.min() - tol).all() and (img.detach().numpy() <= allc.max() + tol).all()
    assert (a >= -tol).all() and (a <= 1 + tol).all()
