"""The `cpu` backend's projection and SH colours: one numba kernel for all cameras, hand-written backward.

Same maths as ``project.project_gaussians`` followed by ``sh.eval_sh`` (see their docstrings: non-finite rows
culled with zero gradient, depth cull before any division, FOV clamp inside the Jacobian only, det clamped at
1e-12, exact-support radii, SH directions from the camera centre, colours clamped at 0), but:

* every camera of a batch in one call: Gaussians in parallel (numba prange), cameras inner, so each
  Gaussian's gradient is summed over the cameras in camera order by the thread that owns it: the result
  does not depend on the thread count (no atomics, no shared accumulators);
* computed in float64 whatever the input dtype (outputs are cast back), so the float32 trainer gets a
  slightly more accurate projection than the torch one, and float64 matches the torch autograd oracle to
  rounding (tests/test_splat_backends.py, 1e-10);
* the backward recomputes the forward's intermediates per (Gaussian, camera) instead of storing them.

Gradients go to means, quats, scales, the SH coefficients (or plain colours) and, when they require it, the
view matrices (C, 4, 4): through the camera point t = W p + tw, the EWA Jacobian T = J W (cov = T Sigma T^T)
and the SH view directions p - campos with campos = inv(viewmat)[:3, 3], differentiated as the torch path
differentiates ``torch.linalg.inv`` (see ``viewmat_grad``; all 16 entries, the bottom row included). Rows
culled as non-finite contribute nothing to the camera gradient (the rasterizer gives them none anyway: their
radius is 0). The per-camera sums over Gaussians are taken in fixed blocks (VM_BLOCK) in index order, so
they do not depend on the thread count either. K gets no gradient: a K that requires one makes
``rasterization`` use the torch path.

float32 inputs run the same two kernels written in C (``cpu_simd.project_forward`` / ``project_backward``,
in the rasterizer's optional extension, 4 Gaussians per vector): the same float64 operations in the same
order, so bitwise the same outputs and gradients; float64 inputs, ``EV3DGS_CPU_KERNEL=numba`` and installs
without the extension run the numba kernels here.
"""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from . import cpu_simd
from .project import ALPHA_MIN, RADIUS_MARGIN
from .sh import C0, C1, C2, C3

_C2 = np.array(C2)
_C3 = np.array(C3)


@njit(cache=True, nogil=True)
def _rotmat(qw, qx, qy, qz):
    return (1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
            2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
            2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))


@njit(cache=True, nogil=True)
def _sh_basis(deg, x, y, z, out):
    out[0] = C0
    if deg >= 1:
        out[1] = -C1 * y
        out[2] = C1 * z
        out[3] = -C1 * x
    if deg >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out[4] = _C2[0] * xy
        out[5] = _C2[1] * yz
        out[6] = _C2[2] * (2.0 * zz - xx - yy)
        out[7] = _C2[3] * xz
        out[8] = _C2[4] * (xx - yy)
        if deg >= 3:
            out[9] = _C3[0] * y * (3.0 * xx - yy)
            out[10] = _C3[1] * xy * z
            out[11] = _C3[2] * y * (4.0 * zz - xx - yy)
            out[12] = _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = _C3[4] * x * (4.0 * zz - xx - yy)
            out[14] = _C3[5] * z * (xx - yy)
            out[15] = _C3[6] * x * (xx - 3.0 * yy)


@njit(cache=True, nogil=True)
def _sh_basis_vjp(deg, x, y, z, gb):
    """d(sum_k gb[k] * basis_k)/d(x, y, z)."""
    gx = gy = gz = 0.0
    if deg >= 1:
        gy -= C1 * gb[1]
        gz += C1 * gb[2]
        gx -= C1 * gb[3]
    if deg >= 2:
        xx, yy, zz = x * x, y * y, z * z
        g = _C2[0] * gb[4]
        gx += g * y
        gy += g * x
        g = _C2[1] * gb[5]
        gy += g * z
        gz += g * y
        g = _C2[2] * gb[6]
        gx -= 2.0 * g * x
        gy -= 2.0 * g * y
        gz += 4.0 * g * z
        g = _C2[3] * gb[7]
        gx += g * z
        gz += g * x
        g = _C2[4] * gb[8]
        gx += 2.0 * g * x
        gy -= 2.0 * g * y
        if deg >= 3:
            g = _C3[0] * gb[9]
            gx += g * 6.0 * x * y
            gy += g * (3.0 * xx - 3.0 * yy)
            g = _C3[1] * gb[10]
            gx += g * y * z
            gy += g * x * z
            gz += g * x * y
            g = _C3[2] * gb[11]
            gx -= g * 2.0 * x * y
            gy += g * (4.0 * zz - xx - 3.0 * yy)
            gz += g * 8.0 * y * z
            g = _C3[3] * gb[12]
            gx -= g * 6.0 * x * z
            gy -= g * 6.0 * y * z
            gz += g * (6.0 * zz - 3.0 * xx - 3.0 * yy)
            g = _C3[4] * gb[13]
            gx += g * (4.0 * zz - 3.0 * xx - yy)
            gy -= g * 2.0 * x * y
            gz += g * 8.0 * x * z
            g = _C3[5] * gb[14]
            gx += g * 2.0 * x * z
            gy -= g * 2.0 * y * z
            gz += g * (xx - yy)
            g = _C3[6] * gb[15]
            gx += g * (3.0 * xx - 3.0 * yy)
            gy -= g * 6.0 * x * y
    return gx, gy, gz


@njit(cache=True, nogil=True)
def _finite_row(means, quats, scales, opac, n):
    ok = np.isfinite(opac[n])
    for i in range(3):
        ok = ok and np.isfinite(means[n, i]) and np.isfinite(scales[n, i])
    for i in range(4):
        ok = ok and np.isfinite(quats[n, i])
    return ok


@njit(cache=True, nogil=True)
def _inputs(means, quats, scales, n, finite):
    """The row's (sanitised) mean, normalised quaternion (and 1/|q|, |q|^2) and scales."""
    if finite:
        # read as float64 whatever the arrays' dtype (float32 inputs: exact), so the maths is float64
        px, py, pz = np.float64(means[n, 0]), np.float64(means[n, 1]), np.float64(means[n, 2])
        qw, qx = np.float64(quats[n, 0]), np.float64(quats[n, 1])
        qy, qz = np.float64(quats[n, 2]), np.float64(quats[n, 3])
        sx, sy, sz = np.float64(scales[n, 0]), np.float64(scales[n, 1]), np.float64(scales[n, 2])
    else:
        px = py = pz = 0.0
        qw = qx = qy = qz = 1.0
        sx = sy = sz = 1.0
    sq = qw * qw + qx * qx + qy * qy + qz * qz
    inv = 1.0 / math.sqrt(max(sq, 1e-24))
    return px, py, pz, qw, qx, qy, qz, inv, sq, sx, sy, sz


@njit(cache=True, nogil=True)
def _sigma(qw, qx, qy, qz, inv, sx, sy, sz):
    r = _rotmat(qw * inv, qx * inv, qy * inv, qz * inv)
    m = (r[0] * sx, r[1] * sy, r[2] * sz, r[3] * sx, r[4] * sy, r[5] * sz, r[6] * sx, r[7] * sy, r[8] * sz)
    s00 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    s01 = m[0] * m[3] + m[1] * m[4] + m[2] * m[5]
    s02 = m[0] * m[6] + m[1] * m[7] + m[2] * m[8]
    s11 = m[3] * m[3] + m[4] * m[4] + m[5] * m[5]
    s12 = m[3] * m[6] + m[4] * m[7] + m[5] * m[8]
    s22 = m[6] * m[6] + m[7] * m[7] + m[8] * m[8]
    return r, m, (s00, s01, s02, s01, s11, s12, s02, s12, s22)


@njit(cache=True, nogil=True)
def _camera(vm, c, px, py, pz, cam, near, far, finite):
    """Camera point, culling and the clamped point of the Jacobian. cam[c] = fx fy cx cy lxn lxp lyn lyp."""
    x = vm[c, 0, 0] * px + vm[c, 0, 1] * py + vm[c, 0, 2] * pz + vm[c, 0, 3]
    y = vm[c, 1, 0] * px + vm[c, 1, 1] * py + vm[c, 1, 2] * pz + vm[c, 1, 3]
    zr = vm[c, 2, 0] * px + vm[c, 2, 1] * py + vm[c, 2, 2] * pz + vm[c, 2, 3]
    valid = zr > near and zr < far and finite
    z = zr if valid else 1.0
    xz, yz = x / z, y / z
    cxz = min(max(xz, -cam[c, 4]), cam[c, 5])
    cyz = min(max(yz, -cam[c, 6]), cam[c, 7])
    return x, y, zr, valid, z, xz, yz, cxz, cyz


@njit(cache=True, nogil=True)
def _jw(vm, c, fx, fy, z, tx, ty):
    """T = J W (2x3) of the EWA linearisation."""
    rz = 1.0 / z
    j00, j02, j11, j12 = fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz
    t0 = (j00 * vm[c, 0, 0] + j02 * vm[c, 2, 0], j00 * vm[c, 0, 1] + j02 * vm[c, 2, 1],
          j00 * vm[c, 0, 2] + j02 * vm[c, 2, 2])
    t1 = (j11 * vm[c, 1, 0] + j12 * vm[c, 2, 0], j11 * vm[c, 1, 1] + j12 * vm[c, 2, 1],
          j11 * vm[c, 1, 2] + j12 * vm[c, 2, 2])
    return rz, t0, t1


@njit(cache=True, nogil=True)
def _cov2d(t0, t1, S, eps2d):
    # u = Sigma t0, v = Sigma t1
    u0 = S[0] * t0[0] + S[1] * t0[1] + S[2] * t0[2]
    u1 = S[3] * t0[0] + S[4] * t0[1] + S[5] * t0[2]
    u2 = S[6] * t0[0] + S[7] * t0[1] + S[8] * t0[2]
    v0 = S[0] * t1[0] + S[1] * t1[1] + S[2] * t1[2]
    v1 = S[3] * t1[0] + S[4] * t1[1] + S[5] * t1[2]
    v2 = S[6] * t1[0] + S[7] * t1[1] + S[8] * t1[2]
    c11 = t0[0] * u0 + t0[1] * u1 + t0[2] * u2 + eps2d
    c12 = t0[0] * v0 + t0[1] * v1 + t0[2] * v2
    c22 = t1[0] * v0 + t1[1] * v1 + t1[2] * v2 + eps2d
    return c11, c12, c22


@njit(cache=True, nogil=True, parallel=True)
def _project_forward(means, quats, scales, opac, sh, deg, vm, campos, cam, width, height, near, far, eps2d,
                     alpha_min, means2d, conics, depths, colors, radii):
    N, C = means.shape[0], vm.shape[0]
    K = (deg + 1) * (deg + 1)
    for n in prange(N):
        basis = np.empty(16)
        finite = _finite_row(means, quats, scales, opac, n)
        px, py, pz, qw, qx, qy, qz, inv, sq, sx, sy, sz = _inputs(means, quats, scales, n, finite)
        _, _, S = _sigma(qw, qx, qy, qz, inv, sx, sy, sz)
        o = np.float64(opac[n]) if finite else 1.0
        for c in range(C):
            fx, fy = cam[c, 0], cam[c, 1]
            x, y, zr, valid, z, xz, yz, cxz, cyz = _camera(vm, c, px, py, pz, cam, near, far, finite)
            rz, t0, t1 = _jw(vm, c, fx, fy, z, z * cxz, z * cyz)
            c11, c12, c22 = _cov2d(t0, t1, S, eps2d)
            det = max(c11 * c22 - c12 * c12, 1e-12)
            conics[c, n, 0] = c22 / det
            conics[c, n, 1] = -c12 / det
            conics[c, n, 2] = c11 / det
            mx, my = fx * xz + cam[c, 2], fy * yz + cam[c, 3]
            means2d[c, n, 0] = mx
            means2d[c, n, 1] = my
            depths[c, n] = zr
            # exact-support radius (project.compute_radii)
            r = 0.0
            if valid and finite and not (o < alpha_min):
                extent = math.sqrt(2.0 * max(math.log(255.0 * o), 0.0))
                mid = 0.5 * (c11 + c22)
                lam = mid + math.sqrt(max(mid * mid - (c11 * c22 - c12 * c12), 0.1))
                r = math.ceil(extent * math.sqrt(max(lam, 0.0)) * (1.0 + RADIUS_MARGIN))
                if not np.isfinite(r):
                    r = 0.0
                elif r < 1.0:
                    r = 1.0
                if (mx + r < -0.5 or mx - r > width - 0.5 or my + r < -0.5 or my - r > height - 0.5
                        or not np.isfinite(mx) or not np.isfinite(my)):
                    r = 0.0
            radii[c, n] = int(min(r, 2.0 ** 30))
            if deg >= 0:
                dx, dy, dz = px - campos[c, 0], py - campos[c, 1], pz - campos[c, 2]
                d2 = max(dx * dx + dy * dy + dz * dz, 1e-24)
                di = 1.0 / math.sqrt(d2)
                _sh_basis(deg, dx * di, dy * di, dz * di, basis)
                for ch in range(3):
                    acc = 0.0
                    for k in range(K):
                        acc += basis[k] * np.float64(sh[n, k, ch])
                    colors[c, n, ch] = max(acc + 0.5, 0.0)


# the C projection kernels (cpu_simd.project_forward / project_backward) are off: a training run with them
# differs in the last bits between one and two threads (tests/test_reliability_training.py::
# test_thread_environment_does_not_change_a_bit: the rasterizer's opacity and screen-space gradients after the
# first step), which the numba kernels do not; the kernels stay tested against numba on their own
# (tests/test_splat_simd_project.py) until the difference is found
C_PROJECTION = False
VM_BLOCK = 256  # Gaussians per block of the backward: the camera-gradient partial sums are per block


@njit(cache=True, nogil=True, parallel=True)
def _project_backward(means, quats, scales, opac, sh, deg, vm, campos, cam, near, far, eps2d,
                      g_m2d, g_con, g_dep, g_col, g_means, g_quats, g_scales, g_sh, want_vm, g_vm):
    """Gradients per Gaussian (summed over the cameras in camera order) and, with ``want_vm``, per camera:
    g_vm[block, c, 0:12] = dL/d(viewmat[c][:3, :4]) row-major through the camera point t = W p + tw and the
    Jacobian T = J W, g_vm[block, c, 12:15] = dL/d(camera centre) of the SH directions, each summed over the
    block's Gaussians in index order (fixed blocks of VM_BLOCK: the sums do not depend on the thread count)."""
    N, C = means.shape[0], vm.shape[0]
    K = (deg + 1) * (deg + 1)
    n_blocks = (N + VM_BLOCK - 1) // VM_BLOCK
    for blk in prange(n_blocks):
        basis = np.empty(16)
        gb = np.empty(16)
        u = np.empty(3)
        v = np.empty(3)
        gS = np.empty(9)  # dL/dSigma (as a general 3x3), summed over cameras
        for n in range(blk * VM_BLOCK, min(N, (blk + 1) * VM_BLOCK)):
            finite = _finite_row(means, quats, scales, opac, n)
            if not finite:
                continue  # torch.where in the oracle: exactly zero gradient for the whole row
            px, py, pz, qw, qx, qy, qz, inv, sq, sx, sy, sz = _inputs(means, quats, scales, n, finite)
            r, m, S = _sigma(qw, qx, qy, qz, inv, sx, sy, sz)
            gpx = gpy = gpz = 0.0
            gS[:] = 0.0
            for c in range(C):
                fx, fy = cam[c, 0], cam[c, 1]
                x, y, zr, valid, z, xz, yz, cxz, cyz = _camera(vm, c, px, py, pz, cam, near, far, finite)
                tx, ty = z * cxz, z * cyz
                rz, t0, t1 = _jw(vm, c, fx, fy, z, tx, ty)
                c11, c12, c22 = _cov2d(t0, t1, S, eps2d)
                det_raw = c11 * c22 - c12 * c12
                det = max(det_raw, 1e-12)
                ga, gbb, gc = np.float64(g_con[c, n, 0]), np.float64(g_con[c, n, 1]), np.float64(g_con[c, n, 2])
                # conic = (c22, -c12, c11) / det
                g11 = gc / det
                g12 = -gbb / det
                g22 = ga / det
                if det_raw >= 1e-12:
                    gdet = -(ga * c22 - gbb * c12 + gc * c11) / (det * det)
                    g11 += gdet * c22
                    g22 += gdet * c11
                    g12 -= 2.0 * gdet * c12
                # cov = T Sigma T^T with G = [[g11, g12/2], [g12/2, g22]] (symmetric):
                # dL/dSigma += T^T G T ; dL/dT = 2 G T Sigma
                h = 0.5 * g12
                for i in range(3):
                    for j in range(3):
                        gS[i * 3 + j] += (g11 * t0[i] * t0[j] + h * (t0[i] * t1[j] + t1[i] * t0[j])
                                          + g22 * t1[i] * t1[j])
                for i in range(3):
                    u[i] = S[i * 3] * t0[0] + S[i * 3 + 1] * t0[1] + S[i * 3 + 2] * t0[2]
                    v[i] = S[i * 3] * t1[0] + S[i * 3 + 1] * t1[1] + S[i * 3 + 2] * t1[2]
                gT0 = (2.0 * (g11 * u[0] + h * v[0]), 2.0 * (g11 * u[1] + h * v[1]),
                       2.0 * (g11 * u[2] + h * v[2]))
                gT1 = (2.0 * (h * u[0] + g22 * v[0]), 2.0 * (h * u[1] + g22 * v[1]),
                       2.0 * (h * u[2] + g22 * v[2]))
                # T = J W: dL/dJ = dL/dT W^T
                gj00 = gT0[0] * vm[c, 0, 0] + gT0[1] * vm[c, 0, 1] + gT0[2] * vm[c, 0, 2]
                gj02 = gT0[0] * vm[c, 2, 0] + gT0[1] * vm[c, 2, 1] + gT0[2] * vm[c, 2, 2]
                gj11 = gT1[0] * vm[c, 1, 0] + gT1[1] * vm[c, 1, 1] + gT1[2] * vm[c, 1, 2]
                gj12 = gT1[0] * vm[c, 2, 0] + gT1[1] * vm[c, 2, 1] + gT1[2] * vm[c, 2, 2]
                grz = fx * gj00 + fy * gj11 - 2.0 * fx * tx * rz * gj02 - 2.0 * fy * ty * rz * gj12
                gtx = -fx * rz * rz * gj02
                gty = -fy * rz * rz * gj12
                gz = -grz * rz * rz + gtx * cxz + gty * cyz
                gxz = fx * np.float64(g_m2d[c, n, 0])
                gyz = fy * np.float64(g_m2d[c, n, 1])
                if xz > -cam[c, 4] and xz < cam[c, 5]:
                    gxz += gtx * z
                if yz > -cam[c, 6] and yz < cam[c, 7]:
                    gyz += gty * z
                gx = gxz / z
                gy = gyz / z
                gz -= (gxz * x + gyz * y) / (z * z)
                gzr = np.float64(g_dep[c, n]) + (gz if valid else 0.0)
                # (gx, gy, gzr) = dL/d(camera point t); t = W p + tw
                for i in range(3):
                    g = vm[c, 0, i] * gx + vm[c, 1, i] * gy + vm[c, 2, i] * gzr
                    if i == 0:
                        gpx += g
                    elif i == 1:
                        gpy += g
                    else:
                        gpz += g
                if want_vm:
                    # dL/dW = dL/dt p^T + J^T dL/dT, J = [[j00, 0, j02], [0, j11, j12]]; dL/dtw = dL/dt
                    j00, j02, j11, j12 = fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz
                    for j in range(3):
                        pj = px if j == 0 else (py if j == 1 else pz)
                        g_vm[blk, c, j] += gx * pj + j00 * gT0[j]
                        g_vm[blk, c, 4 + j] += gy * pj + j11 * gT1[j]
                        g_vm[blk, c, 8 + j] += gzr * pj + j02 * gT0[j] + j12 * gT1[j]
                    g_vm[blk, c, 3] += gx
                    g_vm[blk, c, 7] += gy
                    g_vm[blk, c, 11] += gzr
                if deg >= 0:
                    dx, dy, dz = px - campos[c, 0], py - campos[c, 1], pz - campos[c, 2]
                    d2r = dx * dx + dy * dy + dz * dz
                    d2 = max(d2r, 1e-24)
                    di = 1.0 / math.sqrt(d2)
                    ux, uy, uz = dx * di, dy * di, dz * di
                    _sh_basis(deg, ux, uy, uz, basis)
                    for k in range(K):
                        gb[k] = 0.0
                    for ch in range(3):
                        acc = 0.0
                        for k in range(K):
                            acc += basis[k] * np.float64(sh[n, k, ch])
                        if acc + 0.5 >= 0.0:
                            gcol = np.float64(g_col[c, n, ch])
                            for k in range(K):
                                g_sh[n, k, ch] += basis[k] * gcol
                                gb[k] += np.float64(sh[n, k, ch]) * gcol
                    gux, guy, guz = _sh_basis_vjp(deg, ux, uy, uz, gb)
                    # d = p - campos: dL/dd is dL/dp's SH part and minus dL/dcampos
                    gdx, gdy, gdz = gux * di, guy * di, guz * di
                    if d2r >= 1e-24:
                        dot = (gux * dx + guy * dy + guz * dz) * di * di * di
                        gdx -= dx * dot
                        gdy -= dy * dot
                        gdz -= dz * dot
                    gpx += gdx
                    gpy += gdy
                    gpz += gdz
                    if want_vm:
                        g_vm[blk, c, 12] -= gdx
                        g_vm[blk, c, 13] -= gdy
                        g_vm[blk, c, 14] -= gdz
            g_means[n, 0], g_means[n, 1], g_means[n, 2] = gpx, gpy, gpz
            # Sigma = M M^T, M = R diag(s): dL/dM = (gS + gS^T) M
            gM = np.empty(9)
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += (gS[i * 3 + k] + gS[k * 3 + i]) * m[k * 3 + j]
                    gM[i * 3 + j] = acc
            gsx = gM[0] * r[0] + gM[3] * r[3] + gM[6] * r[6]
            gsy = gM[1] * r[1] + gM[4] * r[4] + gM[7] * r[7]
            gsz = gM[2] * r[2] + gM[5] * r[5] + gM[8] * r[8]
            g_scales[n, 0], g_scales[n, 1], g_scales[n, 2] = gsx, gsy, gsz
            G = np.empty(9)
            for i in range(3):
                G[i * 3] = gM[i * 3] * sx
                G[i * 3 + 1] = gM[i * 3 + 1] * sy
                G[i * 3 + 2] = gM[i * 3 + 2] * sz
            w, a, b, d = qw * inv, qx * inv, qy * inv, qz * inv
            gw = 2.0 * (-G[1] * d + G[2] * b + G[3] * d - G[5] * a - G[6] * b + G[7] * a)
            ga_ = 2.0 * (G[1] * b + G[2] * d + G[3] * b - 2.0 * G[4] * a - G[5] * w + G[6] * d + G[7] * w
                         - 2.0 * G[8] * a)
            gb_ = 2.0 * (-2.0 * G[0] * b + G[1] * a + G[2] * w + G[3] * a + G[5] * d - G[6] * w + G[7] * d
                         - 2.0 * G[8] * b)
            gd = 2.0 * (-2.0 * G[0] * d - G[1] * w + G[2] * a + G[3] * w - 2.0 * G[4] * d + G[5] * b
                        + G[6] * a + G[7] * b)
            # q_n = q * inv, inv = 1/sqrt(max(|q|^2, 1e-24))
            dot = 0.0
            if sq >= 1e-24:
                dot = (gw * qw + ga_ * qx + gb_ * qy + gd * qz) * inv * inv * inv
            g_quats[n, 0] = gw * inv - qw * dot
            g_quats[n, 1] = ga_ * inv - qx * dot
            g_quats[n, 2] = gb_ * inv - qy * dot
            g_quats[n, 3] = gd * inv - qz * dot


def _f64(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


def _in(t: torch.Tensor) -> np.ndarray:
    """A kernel input as a contiguous array, float32 and float64 as they are (the kernels read every element
    as float64, exactly, so the results are those of a float64 copy without making one), others as float64."""
    a = t.detach().cpu().numpy()
    return np.ascontiguousarray(a if a.dtype in (np.float32, np.float64) else a.astype(np.float64))


def _out_dtype(dtype: torch.dtype):
    """The numpy dtype the forward kernel writes its outputs in: the tensors' own for float32 (a float64
    result stored as float32 rounds to nearest, exactly as the ``.to(float32)`` of a float64 array would),
    else float64 (converted after)."""
    return np.float32 if dtype == torch.float32 else np.float64


def inv4(vm: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) float64 view matrices through torch (as the torch path's ``torch.linalg.inv``),
    not numpy: numpy's bundled OpenBLAS wakes its thread pool for even a 4x4 ``np.linalg.inv``, and the woken
    threads spin (sched_yield) between calls; called for every render, that kept a second core busy all
    through training (measured: ~1.2 s of CPU per second of wall time in the pool's thread, whatever
    --threads says). torch's LAPACK call here runs on the calling thread."""
    return torch.linalg.inv(torch.from_numpy(np.ascontiguousarray(vm, dtype=np.float64))).numpy()


def camera_table(viewmats: np.ndarray, K: np.ndarray, width: int, height: int):
    """Per camera: fx fy cx cy and the FOV clamp limits (project.py), and the camera centres."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    row = [fx, fy, cx, cy, (cx + 0.5) / fx + 0.3 * tan_x, (width - 0.5 - cx) / fx + 0.3 * tan_x,
           (cy + 0.5) / fy + 0.3 * tan_y, (height - 0.5 - cy) / fy + 0.3 * tan_y]
    cam = np.tile(np.array(row, np.float64), (len(viewmats), 1))
    campos = inv4(viewmats)[:, :3, 3] if len(viewmats) else np.zeros((0, 3))
    return cam, np.ascontiguousarray(campos)


_AMIN: dict = {}


def _alpha_min(dtype: torch.dtype) -> float:
    """ALPHA_MIN rounded to ``dtype`` (as a Python float)."""
    if dtype not in _AMIN:
        _AMIN[dtype] = float(torch.tensor(ALPHA_MIN, dtype=dtype))
    return _AMIN[dtype]


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, viewmats, K, width, height, near, far, eps2d, deg):
        from .cpu import _parallel

        dtype = means.dtype
        m, q, s = _in(means), _in(quats), _in(scales)
        o = _in(opacities)
        # the C kernels (float32), where switched on
        ctx.c = C_PROJECTION and cpu_simd.project_active(m, q, s, o, *((_in(sh),) if deg >= 0 else ()))
        shc = _in(sh) if deg >= 0 else np.zeros((len(m), 1, 3), np.float32 if ctx.c else np.float64)
        vm = _f64(viewmats)
        cam, campos = camera_table(vm, _f64(K), width, height)
        C, N = vm.shape[0], m.shape[0]
        # outputs without a gradient (depths, colours without SH) reach the backward as None, not as zero tensors
        ctx.set_materialize_grads(False)
        # opacity below 1/255 is compared in the opacities' dtype, like the rasterizer's skip test
        amin = _alpha_min(opacities.dtype)
        odt = _out_dtype(dtype)
        new = np.zeros if ctx.c else np.empty   # the numba kernel writes every entry; the C kernels are zero-filled
        means2d, conics = new((C, N, 2), odt), new((C, N, 3), odt)
        depths, colors = new((C, N), odt), new((C, N, 3), odt)
        radii = new((C, N), np.int32)
        if ctx.c:
            cpu_simd.project_forward(m, q, s, o, shc, deg, vm, campos, cam, width, height, near, far, eps2d, amin,
                                     RADIUS_MARGIN, means2d, conics, depths, colors, radii, numba.get_num_threads())
        else:
            _parallel(_project_forward, m, q, s, o, shc, deg, vm, campos, cam, width, height, near, far, eps2d, amin,
                      means2d, conics, depths, colors, radii)
        ctx.arrays = (m, q, s, o, shc, vm, campos, cam)
        # the float32 arrays above share memory with the inputs (no copies): saved through autograd so that an
        # in-place change of an input before the backward is an error, not a gradient at the changed values
        ctx.save_for_backward(means, quats, scales, opacities, sh)
        ctx.vm_dtype = viewmats.dtype
        ctx.consts = (deg, near, far, eps2d, dtype, tuple(sh.shape))
        out = [torch.from_numpy(a).to(dtype) for a in (means2d, conics, depths, colors)]
        r = torch.from_numpy(radii)
        ctx.mark_non_differentiable(r)
        return (*out, r)

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, g_col, _g_radii):
        from .cpu import _parallel

        ctx.saved_tensors  # noqa: B018  (raises if an input was changed in place since the forward)
        m, q, s, o, shc, vm, campos, cam = ctx.arrays
        deg, near, far, eps2d, dtype, sh_shape = ctx.consts
        C, N = vm.shape[0], m.shape[0]

        want_vm = bool(ctx.needs_input_grad[5])
        g_vm = np.zeros(((N + VM_BLOCK - 1) // VM_BLOCK if want_vm else 1, C, 15))
        grads = [None if g is None else _in(g) for g in (g_m2d, g_con, g_dep, g_col)]
        if ctx.c and all(g is None or g.dtype == np.float32 for g in grads):
            gm2d, gcon, gdep, gcol = (np.zeros(shape, np.float32) if g is None else g
                                      for g, shape in zip(grads, ((C, N, 2), (C, N, 3), (C, N), (C, N, 3))))
            g_means, g_quats, g_scales = (np.zeros((N, 3), np.float32), np.zeros((N, 4), np.float32),
                                          np.zeros((N, 3), np.float32))
            g_sh = np.zeros((N, shc.shape[1], 3), np.float32)
            cpu_simd.project_backward(m, q, s, o, shc, deg, vm, campos, cam, near, far, eps2d, gm2d, gcon, gdep, gcol,
                                      g_means, g_quats, g_scales, g_sh, want_vm, g_vm, numba.get_num_threads())
        else:
            gm2d, gcon, gdep, gcol = (np.zeros(shape) if g is None else g
                                      for g, shape in zip(grads, ((C, N, 2), (C, N, 3), (C, N), (C, N, 3))))
            g_means, g_quats, g_scales = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
            g_means[:] = 0.0
            g_quats[:] = 0.0
            g_scales[:] = 0.0
            g_sh = np.zeros((N, shc.shape[1], 3))
            _parallel(_project_backward, m, q, s, o, shc, deg, vm, campos, cam, near, far, eps2d,
                      gm2d, gcon, gdep, gcol, g_means, g_quats, g_scales, g_sh, want_vm, g_vm)
        grad_sh = torch.from_numpy(g_sh).to(dtype) if deg >= 0 and ctx.needs_input_grad[4] else None
        t = lambda a: torch.from_numpy(a).to(dtype)  # noqa: E731
        grad_vm = t(viewmat_grad(g_vm, vm)).to(ctx.vm_dtype) if want_vm else None
        return (t(g_means), t(g_quats), t(g_scales), None, grad_sh, grad_vm, None, None, None, None, None, None,
                None)


def viewmat_grad(g_vm: np.ndarray, vm: np.ndarray) -> np.ndarray:
    """(blocks, C, 15) per-block partial sums of the backward kernel -> dL/d(viewmats) (C, 4, 4).

    The blocks are added in block order (a fixed order: thread-count independent). Entries 0:12 are the
    gradient of the 3x4 top of each viewmat through the camera point and the EWA Jacobian. Entries 12:15 are
    dL/d(campos) of the SH view directions, with campos = inv(viewmat)[:3, 3] exactly as the torch path
    computes it (``torch.linalg.inv``), so its gradient is the inverse's: dL/dV = -V^-T G V^-T with G zero
    but for column 3, rows 0-2 = dL/dcampos. That is -(V^-1[:3, :])^T g (x) V^-1[:, 3], which also reaches
    the bottom row of V; on rotations (dR = Omega R) it equals the gradient of campos = -R^T t."""
    acc = np.zeros(g_vm.shape[1:])
    for b in range(g_vm.shape[0]):
        acc += g_vm[b]
    C = vm.shape[0]
    out = np.zeros((C, 4, 4))
    out[:, :3, :] = acc[:, :12].reshape(C, 3, 4)
    inv = inv4(vm)
    a = np.einsum("cij,ci->cj", inv[:, :3, :], acc[:, 12:15])  # (C, 4): (V^-1[:3, :])^T g
    out -= a[:, :, None] * inv[:, None, :, 3]
    return out


def project_sh_cpu(means, quats, scales, opacities, sh, viewmats, K, width: int, height: int, *,
                   sh_degree: int | None, near: float = 0.01, far: float = 1e10, eps2d: float = 0.3):
    """Project N Gaussians into C cameras (viewmats (C, 4, 4)) and, with SH coefficients sh (N, K, 3) and
    sh_degree, evaluate their colours per camera. Returns means2d (C,N,2), conics (C,N,3), depths (C,N),
    colors (C,N,3) (None without SH) and radii (C,N) int32; differentiable in means, quats, scales, sh and
    viewmats."""
    deg = -1 if sh_degree is None else int(sh_degree)
    sh_in = sh[:, :max(1, (deg + 1) ** 2)] if deg >= 0 else means.new_zeros((means.shape[0], 1, 3))
    means2d, conics, depths, colors, radii = _ProjectCPU.apply(
        means, quats, scales, opacities, sh_in, viewmats, K, int(width), int(height),
        float(near), float(far), float(eps2d), deg)
    return means2d, conics, depths, (colors if deg >= 0 else None), radii


__all__ = ["project_sh_cpu", "camera_table"]
