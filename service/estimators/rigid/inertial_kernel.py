"""Compiled (numba) kernel of the inertial-frame core. ``inertial.py`` explains the method and holds
the numpy reference (matrix form); the tests check the two against each other.

One sensor's whole state is one row of a float array laid out by the offsets below, so a stack of
sensors is a (B, STATE_SIZE) array that both implementations read and write the same way. The
kernel works on scalars, tuples and (row, offset) indexing: no array views and no array arguments
to helpers on the per-sample path, because numba reference-counts those with atomic calls (that
alone was half the cost); the Kalman update keeps the symmetric 6x6 covariance as a 21-tuple of
scalars. No fast-math licence (``service.KERNEL_FASTMATH``).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ... import JIT_CACHE, KERNEL_FASTMATH

# --- state layout (one row per sensor) -------------------------------------------------------
QG = 0            # gyro strapdown quaternion [w,x,y,z], sensor -> almost-inertial frame I
QC = 4            # inclination (and heading) correction [w,x,y,z], I -> world (z up)
X = 8             # gyro error states: bias (3, rad/s), then scale-factor error (3, dimensionless)
P = 14            # their covariance, 6x6 row-major
LP_ACC = 50       # low-pass of the accelerometer in frame I: count, 2x3 filter state
ACC_I = 57        # last output of that low-pass (frame I)
LP_H = 60         # low-pass of H = [R, R diag(ω)] (3x6, row-major): count, 2x18
LP_HX = 97        # low-pass of (H x̂)_xy at the current estimate: count, 2x2
LP_REST_G = 102   # rest detection: gyro low-pass, count, 2x3
LP_REST_A = 109   # rest detection: accelerometer low-pass, count, 2x3
REST_GYR = 116    # last rest low-pass of the gyro (the bias measured at rest)
REST_T = 119      # time the sensor has been still, s
REST = 120        # 1.0 while a rest is detected
STATE_SIZE = 121
N_X = 6

# --- coefficient vector (``inertial.coefficients``) -------------------------------------------
C_DT = 0
C_AB0, C_AB1, C_AB2, C_AA1, C_AA2, C_TAU_ACC = 1, 2, 3, 4, 5, 6
C_RB0, C_RB1, C_RB2, C_RA1, C_RA2, C_TAU_REST = 7, 8, 9, 10, 11, 12
C_P0_BIAS, C_V_BIAS, C_P0_SCALE, C_V_SCALE = 13, 14, 15, 16
C_W_MOTION, C_W_VERTICAL, C_W_REST = 17, 18, 19
C_CLIP_BIAS, C_CLIP_SCALE, C_REST_MIN_T, C_REST_TH_GYR, C_REST_TH_ACC = 20, 21, 22, 23, 24
C_K_REF, C_REF_MIN = 25, 26
C_SIZE = 27
TMP_SIZE = 26
# strict IEEE arithmetic (``service.KERNEL_FASTMATH``): NaN/inf keep their meaning, which the missing-sample
# checks rely on

# scratch offsets: a 3-vector in and out of the low-passes' start-up phase, H (3x6), (H x̂)_xy
T_X, T_OUT, T_H, T_HX = 0, 3, 6, 24


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _cos_sin(x):
    """``(cos x, sin x)``. Below 0.1 rad (a strapdown half-angle: 0.04 at 286 Hz and 1350 °/s) by
    their Taylor series to the x⁸ and x⁹ terms (truncation below 3e-17 relative, and no library call
    on the filter's critical path); above it by ``math``."""
    if abs(x) > 0.1:
        return math.cos(x), math.sin(x)
    x2 = x * x
    return (1.0 - x2 / 2.0 * (1.0 - x2 / 12.0 * (1.0 - x2 / 30.0 * (1.0 - x2 / 56.0))),
            x * (1.0 - x2 / 6.0 * (1.0 - x2 / 20.0 * (1.0 - x2 / 42.0 * (1.0 - x2 / 72.0)))))


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _finite3(x, y, z):
    """Each of three values finite (a sum would not do: finite values can overflow it)."""
    return math.isfinite(x) and math.isfinite(y) and math.isfinite(z)


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _lp(x, z0, z1, f):
    """One channel of the second-order low-pass in steady state (direct form II transposed), ``f`` =
    ``(b0, b1, b2, a1, a2)``: returns ``(y, z0', z1')``."""
    b0, b1, b2, a1, a2 = f
    y = b0 * x + z0
    return y, b1 * x - a1 * y + z1, b2 * x - a2 * y


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _lowpass_start(s, off, x, xo, n, b0, b2, a2, tau, dt, out, oo):
    """Start-up phase of the low-pass at ``s[off]`` (state: sample count, NaN once running, then
    the 2n direct-form-II-transposed values): ``out[oo:oo+n]`` = running mean of ``x[xo:xo+n]``;
    after ``tau`` seconds the mean seeds the steady state. Only called while ``s[off]`` is a count,
    so the hot path passes no arrays (numba reference-counts array arguments)."""
    z = off + 1
    cnt = s[off] + 1.0
    s[off] = cnt
    for i in range(n):
        s[z + i] += x[xo + i]
        out[oo + i] = s[z + i] / cnt
    if cnt * dt >= tau:
        for i in range(n):
            m = out[oo + i]
            s[z + i] = m * (1.0 - b0)
            s[z + n + i] = m * (b2 - a2)
        s[off] = np.nan


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _rot(q, vx, vy, vz):
    """``R(q) v`` for ``q = (w, x, y, z)``."""
    w, x, y, z = q
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _qmul(p, q):
    """``p ⊗ q`` of (w, x, y, z) tuples."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw)


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _unit(q):
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _unit_product(p, q):
    """``p ⊗ q``, normalised."""
    return _unit(_qmul(p, q))


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _dot6(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] + a[4] * b[4] + a[5] * b[5]


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _comb6(a, b, c, x, y, z):
    """``x a + y b + z c`` of three 6-tuples."""
    return (x * a[0] + y * b[0] + z * c[0], x * a[1] + y * b[1] + z * c[1], x * a[2] + y * b[2] + z * c[2],
            x * a[3] + y * b[3] + z * c[3], x * a[4] + y * b[4] + z * c[4], x * a[5] + y * b[5] + z * c[5])


# A symmetric 6x6 matrix as its upper triangle, row by row: (0,0) (0,1) .. (0,5) (1,1) .. (5,5).
# _U[i][k] is the position of element (i, k) in that 21-tuple.
_U = ((0, 1, 2, 3, 4, 5), (1, 6, 7, 8, 9, 10), (2, 7, 11, 12, 13, 14),
      (3, 8, 12, 15, 16, 17), (4, 9, 13, 16, 18, 19), (5, 10, 14, 17, 19, 20))


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _symv6(u, v):
    """``P v`` for the symmetric ``P`` given as its 21-tuple ``u``."""
    return (u[0] * v[0] + u[1] * v[1] + u[2] * v[2] + u[3] * v[3] + u[4] * v[4] + u[5] * v[5],
            u[1] * v[0] + u[6] * v[1] + u[7] * v[2] + u[8] * v[3] + u[9] * v[4] + u[10] * v[5],
            u[2] * v[0] + u[7] * v[1] + u[11] * v[2] + u[12] * v[3] + u[13] * v[4] + u[14] * v[5],
            u[3] * v[0] + u[8] * v[1] + u[12] * v[2] + u[15] * v[3] + u[16] * v[4] + u[17] * v[5],
            u[4] * v[0] + u[9] * v[1] + u[13] * v[2] + u[16] * v[3] + u[18] * v[4] + u[19] * v[5],
            u[5] * v[0] + u[10] * v[1] + u[14] * v[2] + u[17] * v[3] + u[19] * v[4] + u[20] * v[5])


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _sym6_minus_outer3(u, a, b, c, d, e, f):
    """``P - (a bᵀ + c dᵀ + e fᵀ)`` as a 21-tuple (the sum is symmetric in a Kalman update, only its
    upper triangle is formed)."""
    def o(i, k):
        return a[i] * b[k] + c[i] * d[k] + e[i] * f[k]
    return (u[0] - o(0, 0), u[1] - o(0, 1), u[2] - o(0, 2), u[3] - o(0, 3), u[4] - o(0, 4), u[5] - o(0, 5),
            u[6] - o(1, 1), u[7] - o(1, 2), u[8] - o(1, 3), u[9] - o(1, 4), u[10] - o(1, 5),
            u[11] - o(2, 2), u[12] - o(2, 3), u[13] - o(2, 4), u[14] - o(2, 5),
            u[15] - o(3, 3), u[16] - o(3, 4), u[17] - o(3, 5), u[18] - o(4, 4), u[19] - o(4, 5), u[20] - o(5, 5))


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _run(s, gyr, acc, c, ref_w, ref_s, use_ref, to_world, out, t):
    """Every sample ``k`` of every sensor ``j`` (row ``j`` of ``s``), in place: gyro ``gyr[k, j]``
    rad/s, accelerometer ``acc[k, j]`` m/s², optional second reference ``ref_w[k, j]`` (the caller's
    world frame) with its sensor-frame counterpart ``ref_s[k, j]``; ``out[k, j]`` receives
    ``to_world ⊗ q`` as ``[x,y,z,w]``. ``t``: scratch of TMP_SIZE floats. Non-finite gyro or
    accelerometer samples skip their part of the step. One flat loop with scalar helpers: numba
    reference-counts every array passed to a function (even an inlined one), with atomic calls."""
    dt = c[C_DT]
    clip = c[C_CLIP_BIAS]
    fr = (c[C_RB0], c[C_RB1], c[C_RB2], c[C_RA1], c[C_RA2])      # rest detection low-pass
    fa = (c[C_AB0], c[C_AB1], c[C_AB2], c[C_AA1], c[C_AA2])      # accelerometer (and H) low-pass
    ow, ox, oy, oz = to_world[0], to_world[1], to_world[2], to_world[3]
    for kk in range(gyr.shape[0]):
        for j in range(s.shape[0]):
            g0, g1, g2 = gyr[kk, j, 0], gyr[kk, j, 1], gyr[kk, j, 2]
            a0, a1, a2 = acc[kk, j, 0], acc[kk, j, 1], acc[kk, j, 2]
            r0 = r1 = r2 = m0 = m1 = m2 = 0.0
            if use_ref:                               # the reference into the core's frame (z up)
                r0, r1, r2 = _rot((ow, -ox, -oy, -oz), ref_w[kk, j, 0], ref_w[kk, j, 1], ref_w[kk, j, 2])
                m0, m1, m2 = ref_s[kk, j, 0], ref_s[kk, j, 1], ref_s[kk, j, 2]
            gyr_ok = _finite3(g0, g1, g2)
            acc_ok = _finite3(a0, a1, a2) and (a0 != 0.0 or a1 != 0.0 or a2 != 0.0)
            if gyr_ok:
                # ---- rest detection, gyro part (its low-pass output is the bias measured at rest)
                z = LP_REST_G + 1
                if math.isnan(s[j, LP_REST_G]):
                    s[j, REST_GYR], s[j, z], s[j, z + 3] = _lp(g0, s[j, z], s[j, z + 3], fr)
                    s[j, REST_GYR + 1], s[j, z + 1], s[j, z + 4] = _lp(g1, s[j, z + 1], s[j, z + 4], fr)
                    s[j, REST_GYR + 2], s[j, z + 2], s[j, z + 5] = _lp(g2, s[j, z + 2], s[j, z + 5], fr)
                else:
                    t[T_X], t[T_X + 1], t[T_X + 2] = g0, g1, g2
                    _lowpass_start(s[j], LP_REST_G, t, T_X, 3, fr[0], fr[2], fr[4], c[C_TAU_REST], dt, s[j], REST_GYR)
                l0, l1, l2 = s[j, REST_GYR], s[j, REST_GYR + 1], s[j, REST_GYR + 2]
                d0, d1, d2 = g0 - l0, g1 - l1, g2 - l2
                th = c[C_REST_TH_GYR]
                if d0 * d0 + d1 * d1 + d2 * d2 >= th * th or abs(l0) > clip or abs(l1) > clip or abs(l2) > clip:
                    s[j, REST_T] = 0.0
                    s[j, REST] = 0.0
                # ---- strapdown integration of the corrected rate: ω̂ = g - b̂ - diag(g) ŝ
                wx = g0 - s[j, X] - g0 * s[j, X + 3]
                wy = g1 - s[j, X + 1] - g1 * s[j, X + 4]
                wz = g2 - s[j, X + 2] - g2 * s[j, X + 5]
                wn = math.sqrt(wx * wx + wy * wy + wz * wz)
                if wn > 1e-15:
                    half = 0.5 * wn * dt
                    co, si = _cos_sin(half)
                    k = si / wn
                    qg = (s[j, QG], s[j, QG + 1], s[j, QG + 2], s[j, QG + 3])
                    s[j, QG], s[j, QG + 1], s[j, QG + 2], s[j, QG + 3] = _unit_product(qg, (co, k * wx, k * wy, k * wz))
            if acc_ok:
                # ---- rest detection, accelerometer part
                z = LP_REST_A + 1
                if math.isnan(s[j, LP_REST_A]):
                    l0, s[j, z], s[j, z + 3] = _lp(a0, s[j, z], s[j, z + 3], fr)
                    l1, s[j, z + 1], s[j, z + 4] = _lp(a1, s[j, z + 1], s[j, z + 4], fr)
                    l2, s[j, z + 2], s[j, z + 5] = _lp(a2, s[j, z + 2], s[j, z + 5], fr)
                else:
                    t[T_X], t[T_X + 1], t[T_X + 2] = a0, a1, a2
                    _lowpass_start(s[j], LP_REST_A, t, T_X, 3, fr[0], fr[2], fr[4], c[C_TAU_REST], dt, t, T_OUT)
                    l0, l1, l2 = t[T_OUT], t[T_OUT + 1], t[T_OUT + 2]
                d0, d1, d2 = a0 - l0, a1 - l1, a2 - l2
                th = c[C_REST_TH_ACC]
                if d0 * d0 + d1 * d1 + d2 * d2 >= th * th:
                    s[j, REST_T] = 0.0
                    s[j, REST] = 0.0
                else:
                    s[j, REST_T] += dt
                    if s[j, REST_T] >= c[C_REST_MIN_T]:
                        s[j, REST] = 1.0
                # ---- accelerometer low-passed in the almost-inertial frame I
                qg = (s[j, QG], s[j, QG + 1], s[j, QG + 2], s[j, QG + 3])
                v0, v1, v2 = _rot(qg, a0, a1, a2)
                z = LP_ACC + 1
                if math.isnan(s[j, LP_ACC]):
                    s[j, ACC_I], s[j, z], s[j, z + 3] = _lp(v0, s[j, z], s[j, z + 3], fa)
                    s[j, ACC_I + 1], s[j, z + 1], s[j, z + 4] = _lp(v1, s[j, z + 1], s[j, z + 4], fa)
                    s[j, ACC_I + 2], s[j, z + 2], s[j, z + 5] = _lp(v2, s[j, z + 2], s[j, z + 5], fa)
                else:
                    t[T_X], t[T_X + 1], t[T_X + 2] = v0, v1, v2
                    _lowpass_start(s[j], LP_ACC, t, T_X, 3, fa[0], fa[2], fa[4], c[C_TAU_ACC], dt, s[j], ACC_I)
                # ---- in the world frame, normalised; full inclination correction
                qc = (s[j, QC], s[j, QC + 1], s[j, QC + 2], s[j, QC + 3])
                ex, ey, ez = _rot(qc, s[j, ACC_I], s[j, ACC_I + 1], s[j, ACC_I + 2])
                en = math.sqrt(ex * ex + ey * ey + ez * ez)
                ex, ey, ez = ex / en, ey / en, ez / en
                cw = math.sqrt(max(0.5 * (ez + 1.0), 0.0))
                corr = (cw, 0.5 * ey / cw, -0.5 * ex / cw, 0.0) if cw > 1e-6 else (0.0, 1.0, 0.0, 0.0)
                qc = _unit_product(corr, qc)
                # ---- second reference: heading correction about the vertical
                if use_ref and _finite3(r0, r1, r2) and _finite3(m0, m1, m2):
                    hx, hy, _ = _rot(_qmul(qc, qg), m0, m1, m2)
                    hn = math.sqrt(hx * hx + hy * hy)
                    rn = math.sqrt(r0 * r0 + r1 * r1)
                    mn = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
                    rfull = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                    if hn > c[C_REF_MIN] * mn and rn > c[C_REF_MIN] * rfull:
                        ang = math.atan2(hx * r1 - hy * r0, hx * r0 + hy * r1)
                        half = 0.5 * c[C_K_REF] * ang
                        qc = _unit_product((math.cos(half), 0.0, 0.0, math.sin(half)), qc)
                s[j, QC], s[j, QC + 1], s[j, QC + 2], s[j, QC + 3] = qc
                # ---- gyro error states: Kalman update from the inclination correction (motion) or the rest mean
                qw, qx, qy, qz = _qmul(qc, qg)
                R00 = 1 - 2 * qy * qy - 2 * qz * qz
                R01 = 2 * (qy * qx - qw * qz)
                R02 = 2 * (qw * qy + qz * qx)
                R10 = 2 * (qw * qz + qy * qx)
                R11 = 1 - 2 * qx * qx - 2 * qz * qz
                R12 = 2 * (qy * qz - qx * qw)
                R20 = 2 * (qz * qx - qw * qy)
                R21 = 2 * (qw * qx + qz * qy)
                R22 = 1 - 2 * qx * qx - 2 * qy * qy
                # H = [R, R diag(g)], 3x6 row-major in t[T_H:] (a missing gyro sample counts as no rotation)
                if not gyr_ok:
                    g0 = g1 = g2 = 0.0
                h = T_H
                t[h], t[h + 1], t[h + 2], t[h + 3], t[h + 4], t[h + 5] = \
                    R00, R01, R02, R00 * g0, R01 * g1, R02 * g2
                t[h + 6], t[h + 7], t[h + 8], t[h + 9], t[h + 10], t[h + 11] = \
                    R10, R11, R12, R10 * g0, R11 * g1, R12 * g2
                t[h + 12], t[h + 13], t[h + 14], t[h + 15], t[h + 16], t[h + 17] = \
                    R20, R21, R22, R20 * g0, R21 * g1, R22 * g2
                for i in range(2):
                    v = 0.0
                    for k in range(N_X):
                        v += t[h + 6 * i + k] * s[j, X + k]
                    t[T_HX + i] = v
                if math.isnan(s[j, LP_H]):
                    z = LP_H + 1
                    for i in range(18):
                        t[h + i], s[j, z + i], s[j, z + 18 + i] = _lp(t[h + i], s[j, z + i], s[j, z + 18 + i], fa)
                    z = LP_HX + 1
                    for i in range(2):
                        t[T_HX + i], s[j, z + i], s[j, z + 2 + i] = _lp(t[T_HX + i], s[j, z + i], s[j, z + 2 + i], fa)
                else:
                    _lowpass_start(s[j], LP_H, t, T_H, 18, fa[0], fa[2], fa[4], c[C_TAU_ACC], dt, t, T_H)
                    _lowpass_start(s[j], LP_HX, t, T_HX, 2, fa[0], fa[2], fa[4], c[C_TAU_ACC], dt, t, T_HX)
                x6 = (s[j, X], s[j, X + 1], s[j, X + 2], s[j, X + 3], s[j, X + 4], s[j, X + 5])
                if s[j, REST] > 0.5:                              # step 4b: H = [I, 0], the rest mean measures the bias
                    h0 = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                    h1 = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0)
                    h2 = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
                    e0, e1, e2 = s[j, REST_GYR] - x6[0], s[j, REST_GYR + 1] - x6[1], s[j, REST_GYR + 2] - x6[2]
                    w0 = w1 = w2 = c[C_W_REST]
                else:                                             # step 4a: the low-passed correction rate
                    h0 = (t[h], t[h + 1], t[h + 2], t[h + 3], t[h + 4], t[h + 5])
                    h1 = (t[h + 6], t[h + 7], t[h + 8], t[h + 9], t[h + 10], t[h + 11])
                    h2 = (t[h + 12], t[h + 13], t[h + 14], t[h + 15], t[h + 16], t[h + 17])
                    e0 = -ey / dt + t[T_HX] - _dot6(h0, x6)
                    e1 = ex / dt + t[T_HX + 1] - _dot6(h1, x6)
                    e2 = -_dot6(h2, x6)
                    w0 = w1 = c[C_W_MOTION]
                    w2 = c[C_W_VERTICAL]
                for i in range(3):                                # the covariance regains variance up to its prior
                    if s[j, P + 7 * i] < c[C_P0_BIAS]:
                        s[j, P + 7 * i] += c[C_V_BIAS]
                    if s[j, P + 7 * (i + 3)] < c[C_P0_SCALE]:
                        s[j, P + 7 * (i + 3)] += c[C_V_SCALE]
                e0, e1, e2 = min(max(e0, -clip), clip), min(max(e1, -clip), clip), min(max(e2, -clip), clip)
                # M = P Hᵀ (columns m0..m2), S = H M + W, K = M S⁻¹ (columns k0..k2), x += K e, P -= K Mᵀ
                pu = (s[j, P], s[j, P + 1], s[j, P + 2], s[j, P + 3], s[j, P + 4], s[j, P + 5],
                      s[j, P + 7], s[j, P + 8], s[j, P + 9], s[j, P + 10], s[j, P + 11],
                      s[j, P + 14], s[j, P + 15], s[j, P + 16], s[j, P + 17],
                      s[j, P + 21], s[j, P + 22], s[j, P + 23], s[j, P + 28], s[j, P + 29], s[j, P + 35])
                m0, m1, m2 = _symv6(pu, h0), _symv6(pu, h1), _symv6(pu, h2)
                a_, b_, c_ = _dot6(h0, m0) + w0, _dot6(h0, m1), _dot6(h0, m2)
                d_, e_, f_ = _dot6(h1, m1) + w1, _dot6(h1, m2), _dot6(h2, m2) + w2
                A_ = d_ * f_ - e_ * e_
                B_ = c_ * e_ - b_ * f_
                C_ = b_ * e_ - c_ * d_
                inv_det = 1.0 / (a_ * A_ + b_ * B_ + c_ * C_)
                s00, s01, s02 = A_ * inv_det, B_ * inv_det, C_ * inv_det
                s11, s12 = (a_ * f_ - c_ * c_) * inv_det, (b_ * c_ - a_ * e_) * inv_det
                s22 = (a_ * d_ - b_ * b_) * inv_det
                k0 = _comb6(m0, m1, m2, s00, s01, s02)
                k1 = _comb6(m0, m1, m2, s01, s11, s12)
                k2 = _comb6(m0, m1, m2, s02, s12, s22)
                dx = _comb6(k0, k1, k2, e0, e1, e2)
                pu = _sym6_minus_outer3(pu, k0, m0, k1, m1, k2, m2)
                for i in range(6):
                    for k in range(6):
                        s[j, P + 6 * i + k] = pu[_U[i][k]]
                cs = c[C_CLIP_SCALE]
                for i in range(3):
                    s[j, X + i] = min(max(x6[i] + dx[i], -clip), clip)
                    s[j, X + 3 + i] = min(max(x6[3 + i] + dx[3 + i], -cs), cs)
            q = _qmul((ow, ox, oy, oz), _qmul((s[j, QC], s[j, QC + 1], s[j, QC + 2], s[j, QC + 3]),
                                              (s[j, QG], s[j, QG + 1], s[j, QG + 2], s[j, QG + 3])))
            qw, qx, qy, qz = q
            out[kk, j, 0], out[kk, j, 1], out[kk, j, 2], out[kk, j, 3] = qx, qy, qz, qw


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def run_sample(state, gyr, acc, c, ref_w, ref_s, use_ref, to_world, out):
    """One sample of every sensor: ``state`` (B, STATE_SIZE), inputs (B, 3), ``ref_w`` in the
    caller's frame; ``out`` (B, 4) receives ``to_world ⊗ q`` as ``[x,y,z,w]`` (the public
    convention), so a streaming call needs no numpy work around it. The inputs and ``out`` must be
    C-contiguous (numba reshapes only those; others fail to compile, nothing is computed)."""
    nb = state.shape[0]
    _run(state, gyr.reshape(1, nb, 3), acc.reshape(1, nb, 3), c, ref_w.reshape(1, nb, 3),
         ref_s.reshape(1, nb, 3), use_ref, to_world, out.reshape(1, nb, 4), np.zeros(TMP_SIZE))


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def run_batch(state, gyr, acc, c, ref_w, ref_s, use_ref, to_world):
    """All samples: ``state`` (B, STATE_SIZE) in place; ``gyr``/``acc``/refs (N, B, 3) (refs ignored
    unless ``use_ref``; ``ref_w`` in the caller's world frame, which ``to_world`` [w,x,y,z] maps the
    core's z-up frame into); returns ``to_world ⊗ q`` (N, B, 4) as ``[x,y,z,w]``, sensor -> caller's world."""
    out = np.empty((gyr.shape[0], gyr.shape[1], 4))
    _run(state, gyr, acc, c, ref_w, ref_s, use_ref, to_world, out, np.zeros(TMP_SIZE))
    return out
