"""Compiled (numba) kernel of the inertial-frame core. ``inertial.py`` explains the method and holds
the numpy reference (matrix form); the tests check the two against each other.

One sensor's whole state is one row of a float array laid out by the offsets below, so a stack of
sensors is a (B, STATE_SIZE) array that both implementations read and write the same way. The
kernel works on scalars and explicit offsets (no array views per sample), which is what makes it
cost about as much per sample as a C++ filter.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

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
TMP_SIZE = 128

# scratch offsets
T_X, T_OUT, T_H, T_HX, T_E, T_W, T_PHT, T_S, T_SI, T_K, T_Q, T_REF = 0, 3, 6, 24, 26, 29, 32, 50, 59, 68, 86, 90


@njit(cache=True, inline="always", error_model="numpy")
def _lowpass(s, off, x, xo, n, b0, b1, b2, a1, a2, tau, dt, out, oo):
    """Second-order low-pass of ``x[xo:xo+n]`` into ``out[oo:oo+n]``. State ``s[off]`` = sample count
    during the start-up (NaN after), ``s[off+1 : off+1+2n]`` = direct-form-II-transposed state. For
    the first ``tau`` seconds the output is the running mean, which then seeds the steady state."""
    z = off + 1
    if not math.isnan(s[off]):
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
        return
    for i in range(n):
        xi = x[xo + i]
        y = b0 * xi + s[z + i]
        s[z + i] = b1 * xi - a1 * y + s[z + n + i]
        s[z + n + i] = b2 * xi - a2 * y
        out[oo + i] = y


@njit(cache=True, inline="always", error_model="numpy")
def _rotate(q, qo, vx, vy, vz, out, oo):
    """``out[oo:oo+3] = R(q[qo:qo+4]) v``."""
    w, x, y, z = q[qo], q[qo + 1], q[qo + 2], q[qo + 3]
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    out[oo] = vx + w * tx + y * tz - z * ty
    out[oo + 1] = vy + w * ty + z * tx - x * tz
    out[oo + 2] = vz + w * tz + x * ty - y * tx


@njit(cache=True, inline="always", error_model="numpy")
def _left_multiply(pw, px, py, pz, s, off):
    """``s[off:off+4] = p ⊗ s[off:off+4]``, normalised."""
    _compose(pw, px, py, pz, s[off], s[off + 1], s[off + 2], s[off + 3], s, off)


@njit(cache=True, inline="always", error_model="numpy")
def _compose(pw, px, py, pz, qw, qx, qy, qz, s, off):
    """``s[off:off+4] = p ⊗ q``, normalised."""
    w = pw * qw - px * qx - py * qy - pz * qz
    x = pw * qx + px * qw + py * qz - pz * qy
    y = pw * qy - px * qz + py * qw + pz * qx
    z = pw * qz + px * qy - py * qx + pz * qw
    n = math.sqrt(w * w + x * x + y * y + z * z)
    s[off], s[off + 1], s[off + 2], s[off + 3] = w / n, x / n, y / n, z / n


@njit(cache=True, inline="always", error_model="numpy")
def output_quaternion(s, out, oo):
    """``out[oo:oo+4] = QC ⊗ QG`` [w,x,y,z]: sensor -> world (z up)."""
    pw, px, py, pz = s[QC], s[QC + 1], s[QC + 2], s[QC + 3]
    qw, qx, qy, qz = s[QG], s[QG + 1], s[QG + 2], s[QG + 3]
    out[oo] = pw * qw - px * qx - py * qy - pz * qz
    out[oo + 1] = pw * qx + px * qw + py * qz - pz * qy
    out[oo + 2] = pw * qy - px * qz + py * qw + pz * qx
    out[oo + 3] = pw * qz + px * qy - py * qx + pz * qw


@njit(cache=True, error_model="numpy")
def step(s, g0, g1, g2, a0, a1, a2, c, r0, r1, r2, m0, m1, m2, use_ref, t):
    """One sample of one sensor, in place: gyro ``g`` rad/s, accelerometer ``a`` m/s², optional
    second reference ``r`` (world, z up) with its sensor-frame counterpart ``m``. ``t``: scratch
    of TMP_SIZE floats. Non-finite gyro or accelerometer samples skip their part of the step."""
    dt = c[C_DT]
    clip = c[C_CLIP_BIAS]
    gyr_ok = math.isfinite(g0) and math.isfinite(g1) and math.isfinite(g2)
    acc_ok = math.isfinite(a0) and math.isfinite(a1) and math.isfinite(a2) and (a0 != 0.0 or a1 != 0.0 or a2 != 0.0)
    if gyr_ok:
        # ---- rest detection, gyro part
        t[T_X], t[T_X + 1], t[T_X + 2] = g0, g1, g2
        _lowpass(s, LP_REST_G, t, T_X, 3, c[C_RB0], c[C_RB1], c[C_RB2], c[C_RA1], c[C_RA2], c[C_TAU_REST], dt,
                 s, REST_GYR)
        d0, d1, d2 = g0 - s[REST_GYR], g1 - s[REST_GYR + 1], g2 - s[REST_GYR + 2]
        big = abs(s[REST_GYR]) > clip or abs(s[REST_GYR + 1]) > clip or abs(s[REST_GYR + 2]) > clip
        if d0 * d0 + d1 * d1 + d2 * d2 >= c[C_REST_TH_GYR] ** 2 or big:
            s[REST_T] = 0.0
            s[REST] = 0.0
        # ---- strapdown integration of the corrected rate: ω̂ = g - b̂ - diag(g) ŝ
        wx = g0 - s[X] - g0 * s[X + 3]
        wy = g1 - s[X + 1] - g1 * s[X + 4]
        wz = g2 - s[X + 2] - g2 * s[X + 5]
        wn = math.sqrt(wx * wx + wy * wy + wz * wz)
        if wn > 1e-15:
            half = 0.5 * wn * dt
            k = math.sin(half) / wn
            _compose(s[QG], s[QG + 1], s[QG + 2], s[QG + 3], math.cos(half), k * wx, k * wy, k * wz, s, QG)
    if not acc_ok:
        return
    # ---- rest detection, accelerometer part
    t[T_X], t[T_X + 1], t[T_X + 2] = a0, a1, a2
    _lowpass(s, LP_REST_A, t, T_X, 3, c[C_RB0], c[C_RB1], c[C_RB2], c[C_RA1], c[C_RA2], c[C_TAU_REST], dt, t, T_OUT)
    d0, d1, d2 = a0 - t[T_OUT], a1 - t[T_OUT + 1], a2 - t[T_OUT + 2]
    if d0 * d0 + d1 * d1 + d2 * d2 >= c[C_REST_TH_ACC] ** 2:
        s[REST_T] = 0.0
        s[REST] = 0.0
    else:
        s[REST_T] += dt
        if s[REST_T] >= c[C_REST_MIN_T]:
            s[REST] = 1.0
    # ---- accelerometer low-passed in the almost-inertial frame I
    _rotate(s, QG, a0, a1, a2, t, T_X)
    _lowpass(s, LP_ACC, t, T_X, 3, c[C_AB0], c[C_AB1], c[C_AB2], c[C_AA1], c[C_AA2], c[C_TAU_ACC], dt, s, ACC_I)
    # ---- in the world frame, normalised; full inclination correction
    _rotate(s, QC, s[ACC_I], s[ACC_I + 1], s[ACC_I + 2], t, T_OUT)
    ex, ey, ez = t[T_OUT], t[T_OUT + 1], t[T_OUT + 2]
    en = math.sqrt(ex * ex + ey * ey + ez * ez)
    ex, ey, ez = ex / en, ey / en, ez / en
    cw = math.sqrt(max(0.5 * (ez + 1.0), 0.0))
    if cw > 1e-6:
        _left_multiply(cw, 0.5 * ey / cw, -0.5 * ex / cw, 0.0, s, QC)
    else:
        _left_multiply(0.0, 1.0, 0.0, 0.0, s, QC)
    # ---- second reference: heading correction about the vertical
    if use_ref and math.isfinite(r0 + r1 + r2 + m0 + m1 + m2):
        output_quaternion(s, t, T_Q)
        _rotate(t, T_Q, m0, m1, m2, t, T_OUT)
        hx, hy = t[T_OUT], t[T_OUT + 1]
        hn = math.sqrt(hx * hx + hy * hy)
        rn = math.sqrt(r0 * r0 + r1 * r1)
        mn = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        rfull = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        if hn > c[C_REF_MIN] * mn and rn > c[C_REF_MIN] * rfull:
            ang = math.atan2(hx * r1 - hy * r0, hx * r0 + hy * r1)
            half = 0.5 * c[C_K_REF] * ang
            _left_multiply(math.cos(half), 0.0, 0.0, math.sin(half), s, QC)
    # ---- gyro error states: Kalman update from the inclination correction (motion) or the rest mean
    output_quaternion(s, t, T_Q)
    qw, qx, qy, qz = t[T_Q], t[T_Q + 1], t[T_Q + 2], t[T_Q + 3]
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
    t[h], t[h + 1], t[h + 2], t[h + 3], t[h + 4], t[h + 5] = R00, R01, R02, R00 * g0, R01 * g1, R02 * g2
    t[h + 6], t[h + 7], t[h + 8], t[h + 9], t[h + 10], t[h + 11] = R10, R11, R12, R10 * g0, R11 * g1, R12 * g2
    t[h + 12], t[h + 13], t[h + 14], t[h + 15], t[h + 16], t[h + 17] = R20, R21, R22, R20 * g0, R21 * g1, R22 * g2
    for i in range(2):
        v = 0.0
        for k in range(N_X):
            v += t[h + 6 * i + k] * s[X + k]
        t[T_HX + i] = v
    _lowpass(s, LP_H, t, T_H, 18, c[C_AB0], c[C_AB1], c[C_AB2], c[C_AA1], c[C_AA2], c[C_TAU_ACC], dt, t, T_H)
    _lowpass(s, LP_HX, t, T_HX, 2, c[C_AB0], c[C_AB1], c[C_AB2], c[C_AA1], c[C_AA2], c[C_TAU_ACC], dt, t, T_HX)
    e, w = T_E, T_W
    if s[REST] > 0.5:
        for i in range(18):
            t[h + i] = 0.0
        for i in range(3):
            t[h + 7 * i] = 1.0
            t[e + i] = s[REST_GYR + i] - s[X + i]
            t[w + i] = c[C_W_REST]
    else:
        for i in range(3):
            v = 0.0
            for k in range(N_X):
                v += t[h + 6 * i + k] * s[X + k]
            t[e + i] = -v
        t[e] += -ey / dt + t[T_HX]
        t[e + 1] += ex / dt + t[T_HX + 1]
        t[w], t[w + 1], t[w + 2] = c[C_W_MOTION], c[C_W_MOTION], c[C_W_VERTICAL]
    for i in range(3):
        if s[P + 7 * i] < c[C_P0_BIAS]:
            s[P + 7 * i] += c[C_V_BIAS]
        if s[P + 7 * (i + 3)] < c[C_P0_SCALE]:
            s[P + 7 * (i + 3)] += c[C_V_SCALE]
        t[e + i] = min(max(t[e + i], -clip), clip)
    # PHᵀ (6x3), S = H P Hᵀ + W (3x3), K = PHᵀ S⁻¹, x += K e, P -= K (PHᵀ)ᵀ
    pht = T_PHT
    for i in range(N_X):
        for j in range(3):
            v = 0.0
            for k in range(N_X):
                v += s[P + N_X * i + k] * t[h + N_X * j + k]
            t[pht + 3 * i + j] = v
    S = T_S
    for i in range(3):
        for j in range(i, 3):
            v = t[w + i] if i == j else 0.0
            for k in range(N_X):
                v += t[h + N_X * i + k] * t[pht + 3 * k + j]
            t[S + 3 * i + j] = v
            t[S + 3 * j + i] = v
    a_, b_, c_, d_, e_, f_ = t[S], t[S + 1], t[S + 2], t[S + 4], t[S + 5], t[S + 8]
    A_ = d_ * f_ - e_ * e_
    B_ = c_ * e_ - b_ * f_
    C_ = b_ * e_ - c_ * d_
    inv_det = 1.0 / (a_ * A_ + b_ * B_ + c_ * C_)
    si = T_SI
    t[si], t[si + 1], t[si + 2] = A_ * inv_det, B_ * inv_det, C_ * inv_det
    t[si + 3], t[si + 4], t[si + 5] = B_ * inv_det, (a_ * f_ - c_ * c_) * inv_det, (b_ * c_ - a_ * e_) * inv_det
    t[si + 6], t[si + 7], t[si + 8] = C_ * inv_det, (b_ * c_ - a_ * e_) * inv_det, (a_ * d_ - b_ * b_) * inv_det
    kk = T_K
    for i in range(N_X):
        for j in range(3):
            t[kk + 3 * i + j] = t[pht + 3 * i] * t[si + j] + t[pht + 3 * i + 1] * t[si + 3 + j] + \
                t[pht + 3 * i + 2] * t[si + 6 + j]
        s[X + i] += t[kk + 3 * i] * t[e] + t[kk + 3 * i + 1] * t[e + 1] + t[kk + 3 * i + 2] * t[e + 2]
    for i in range(N_X):
        for j in range(i, N_X):
            v = s[P + N_X * i + j] - (t[kk + 3 * i] * t[pht + 3 * j] + t[kk + 3 * i + 1] * t[pht + 3 * j + 1]
                                      + t[kk + 3 * i + 2] * t[pht + 3 * j + 2])
            s[P + N_X * i + j] = v
            s[P + N_X * j + i] = v
    for i in range(3):
        s[X + i] = min(max(s[X + i], -clip), clip)
        s[X + 3 + i] = min(max(s[X + 3 + i], -c[C_CLIP_SCALE]), c[C_CLIP_SCALE])


@njit(cache=True, error_model="numpy")
def run_sample(state, gyr, acc, c, ref_w, ref_s, use_ref, to_world, out):
    """One sample of every sensor: ``state`` (B, STATE_SIZE), inputs (B, 3), ``ref_w`` in the caller's frame;
    ``out`` (B, 4) receives ``to_world ⊗ q`` as ``[x,y,z,w]`` (the public convention), so a
    streaming call needs no numpy work around it."""
    t = np.zeros(TMP_SIZE)
    rw, rx, ry, rz = to_world[0], to_world[1], to_world[2], to_world[3]
    for j in range(state.shape[0]):
        s = state[j]
        if use_ref:
            t[T_Q], t[T_Q + 1], t[T_Q + 2], t[T_Q + 3] = rw, -rx, -ry, -rz
            _rotate(t, T_Q, ref_w[j, 0], ref_w[j, 1], ref_w[j, 2], t, T_REF)
            step(s, gyr[j, 0], gyr[j, 1], gyr[j, 2], acc[j, 0], acc[j, 1], acc[j, 2], c,
                 t[T_REF], t[T_REF + 1], t[T_REF + 2], ref_s[j, 0], ref_s[j, 1], ref_s[j, 2], True, t)
        else:
            step(s, gyr[j, 0], gyr[j, 1], gyr[j, 2], acc[j, 0], acc[j, 1], acc[j, 2], c,
                 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, t)
        output_quaternion(s, t, T_Q)
        qw, qx, qy, qz = t[T_Q], t[T_Q + 1], t[T_Q + 2], t[T_Q + 3]
        out[j, 3] = rw * qw - rx * qx - ry * qy - rz * qz
        out[j, 0] = rw * qx + rx * qw + ry * qz - rz * qy
        out[j, 1] = rw * qy - rx * qz + ry * qw + rz * qx
        out[j, 2] = rw * qz + rx * qy - ry * qx + rz * qw


@njit(cache=True, error_model="numpy")
def run_batch(state, gyr, acc, c, ref_w, ref_s, use_ref, to_world):
    """All samples: ``state`` (B, STATE_SIZE) in place; ``gyr``/``acc``/refs (N, B, 3) (refs ignored
    unless ``use_ref``; ``ref_w`` in the caller's world frame, which ``to_world`` [w,x,y,z] maps the
    core's z-up frame into); returns ``to_world ⊗ q`` (N, B, 4) as ``[x,y,z,w]``, sensor -> caller's world."""
    n, nb = gyr.shape[0], gyr.shape[1]
    out = np.empty((n, nb, 4))
    for k in range(n):
        run_sample(state, gyr[k], acc[k], c, ref_w[k], ref_s[k], use_ref, to_world, out[k])
    return out
