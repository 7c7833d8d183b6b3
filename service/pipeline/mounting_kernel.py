"""Compiled (numba) kernels of the flexion-axis fit (``mounting.py``) for every finger sensor of a hand at
once: one call turns a tick's raw readings by the current corrections, one call adds the tick's gyro
samples to the fits. ``HingeAxisFit`` (closed forms in Python, one sensor and sample at a time) is the
reference; ``tests/test_mounting.py`` checks the two against each other to 1e-9 on random inputs and
through the pipeline on a recording with a saturated and a missing sample.

Each sensor is one row of ``state`` (S, ``WIDTH``) float64:

* ``M`` (9, row-major) its calibrated sensor-to-phalanx mounting, ``B`` (9) its finger's base frame in
  the metacarpus frame, ``C`` (9) the correction applied to raw readings (``Mᵀ R(ε) M``);
* the normal equations' sums ``a00, a01, a11, by0, by1, bz0, bz1`` (``HingeAxisFit.add``);
* the tilt ``(ε_y, ε_z)``, the number of samples used, and whether ``M`` is the identity;
* the cross-axis fit of the hinge-axis reading (``HingeAxisFit._add_quiet``): its normal equations
  ``q00 .. q22, qb0 .. qb2``, the sensitivities ``(k_y, k_z)`` and the number of samples it used;
* per raw gyro axis, the record of a clipped run (``HingeAxisFit.reconstruct``).

``meta`` (S, 3) int64 holds each sensor's finger (its index among the hand's fingers), phalanx and the
offset of its finger's joint angles in the flat ``phi`` the fit reads. A tick's samples come as
``raw`` (k, 2, 3) (gyro, accelerometer) with their rows ``idx`` (k,) in ``state`` (-1: a sensor
without a fit, e.g. the back-of-hand IMU, passed through unchanged).
"""
from __future__ import annotations

import math

from numba import njit

from .. import JIT_CACHE, KERNEL_FASTMATH


M0, B0, C0 = 0, 9, 18
"""Offsets of the mounting, the finger base and the correction (3 x 3 row-major each) in a row."""
A00, A01, A11, BY0, BY1, BZ0, BZ1 = range(27, 34)
TILT_Y, TILT_Z, SAMPLES, STRAIGHT = 34, 35, 36, 37
Q00, Q01, Q02, Q11, Q12, Q22, QB0, QB1, QB2 = range(38, 47)
"""The cross-axis fit's normal equations (symmetric 3 x 3, regressors ``[1, f_y, f_z]``) and right-hand side."""
LEAK_Y, LEAK_Z, QUIET_SAMPLES = 47, 48, 49
CLIP_N, CLIP_RISE, LAST1, LAST2, HISTORY, CLIP_ADDED = 50, 53, 56, 59, 62, 65
"""The clipped-sample reconstruction (``HingeAxisFit.reconstruct``), three columns each (one per raw gyro
axis): the number of clipped samples in the current run, the rise of the reading over the two samples
before it, the last two readings, how many of them there are (up to 2) and the rate added to the
current run's samples so far."""
O00, O01, O11, OY0, OY1, OZ0, OZ1 = range(68, 75)
"""The offsets' normal equations (``cross_offsets``): ``a00 .. bz1`` with the still samples added."""
WIDTH = 75
(ST_MIN_RATE, ST_MAX_TILT, ST_QUIET_RATE, ST_CLIP_RANGE, ST_CLIP_MAX, ST_FIT_RANGE, ST_RESIDUAL_VAR, ST_STILL,
 ST_STILL_GYRO, ST_STILL_ON) = range(10)
"""The settings vector: ``min_rate_rad_s``, ``max_tilt_rad``, ``quiet_rate_rad_s`` (0: no cross-axis fit),
``clip_range_rad_s`` (0: no reconstruction), ``clip_max_samples`` and the full scale at which a sample is
left out of the fits (0: none, ``fit_clipped``), ``residual_std_rad_s²``, ``still_rate_rad_s``, the bound on
the gyro's own cross-axis rate of a still sample (``still_rate_rad_s + still_gyro_margin_rad_s``; 0: no such
check) and whether still samples are admitted now (1: the optics' fit window is full; the pipeline sets it,
``HandMountings.admit_still``)."""


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _reconstruct(state, j, k, g, clip_range, clip_max):
    """The raw reading ``g`` of gyro axis ``k`` of sensor row ``j``, with the angle its clipped run
    missed added at the run's end (``HingeAxisFit.reconstruct``, the same arithmetic); the axis's record
    updated."""
    if abs(g) >= clip_range * (1.0 - 1e-3):
        if state[j, CLIP_N + k] == 0.0:
            sign = 1.0 if g > 0.0 else -1.0
            state[j, CLIP_RISE + k] = sign * (state[j, LAST1 + k] - state[j, LAST2 + k]) \
                if state[j, HISTORY + k] >= 2.0 else 0.0
            state[j, CLIP_ADDED + k] = 0.0
        state[j, CLIP_N + k] += 1.0
        n = state[j, CLIP_N + k]
        rise = state[j, CLIP_RISE + k]
        guess = min(0.5 * rise * n, clip_range) if rise > 0.0 and n <= clip_max else 0.0
        state[j, CLIP_ADDED + k] += guess
        state[j, LAST1 + k] = g
        state[j, HISTORY + k] = 0.0
        return g + guess if g > 0.0 else g - guess
    out = g
    n = state[j, CLIP_N + k]
    if n > 0.0:
        rise = state[j, CLIP_RISE + k]
        total = 0.0
        if rise > 0.0 and n <= clip_max:
            height = min(0.25 * rise * n, clip_range)
            total = (2.0 / 3.0) * height * n
        extra = total - state[j, CLIP_ADDED + k]
        out = g + extra if state[j, LAST1 + k] > 0.0 else g - extra
        state[j, CLIP_N + k] = 0.0
        state[j, CLIP_ADDED + k] = 0.0
    state[j, LAST2 + k] = state[j, LAST1 + k]
    state[j, LAST1 + k] = g
    state[j, HISTORY + k] = min(state[j, HISTORY + k] + 1.0, 2.0)
    return out


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def correct(state, idx, raw, out, st):
    """``out[r] = C raw[r]`` (both vectors of sample ``r``) with the correction of its sensor; the raw
    reading itself where the sensor has no fit or its fit no sample yet (``HingeAxisFit.correct``); the
    gyro's then without its cross-axis leak into the hinge-axis reading (``HingeAxisFit.correct_gyro``).
    First, a gyro axis whose clipped run has just ended gets the angle the run missed
    (``HingeAxisFit.reconstruct``; ``st[ST_CLIP_RANGE]`` 0: none)."""
    clip_range, clip_max = st[ST_CLIP_RANGE], st[ST_CLIP_MAX]
    for r in range(idx.shape[0]):
        j = idx[r]
        g0, g1, g2 = raw[r, 0, 0], raw[r, 0, 1], raw[r, 0, 2]
        if j >= 0 and clip_range > 0.0:
            g0 = _reconstruct(state, j, 0, g0, clip_range, clip_max)
            g1 = _reconstruct(state, j, 1, g1, clip_range, clip_max)
            g2 = _reconstruct(state, j, 2, g2, clip_range, clip_max)
        if j < 0 or state[j, SAMPLES] == 0.0:
            out[r, 0, 0], out[r, 0, 1], out[r, 0, 2] = g0, g1, g2
            for i in range(3):
                out[r, 1, i] = raw[r, 1, i]
        else:
            for v in range(2):
                if v == 0:
                    x, y, z = g0, g1, g2
                else:
                    x, y, z = raw[r, 1, 0], raw[r, 1, 1], raw[r, 1, 2]
                for i in range(3):
                    o = C0 + 3 * i
                    out[r, v, i] = state[j, o] * x + state[j, o + 1] * y + state[j, o + 2] * z
        if j >= 0 and state[j, QUIET_SAMPLES] != 0.0:
            x, y, z = out[r, 0, 0], out[r, 0, 1], out[r, 0, 2]
            f1 = state[j, M0 + 3] * x + state[j, M0 + 4] * y + state[j, M0 + 5] * z
            f2 = state[j, M0 + 6] * x + state[j, M0 + 7] * y + state[j, M0 + 8] * z
            leak = state[j, LEAK_Y] * f1 + state[j, LEAK_Z] * f2
            for i in range(3):
                out[r, 0, i] = out[r, 0, i] - state[j, M0 + i] * leak


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def cross_offsets(state, idx, out, st):
    """``out[r] = (b_y, b_z)`` of the sensor in row ``idx[r]`` (0 where -1): the tilt fit's normal equations
    solved for their constant terms, the cross axes' offsets (``HingeAxisFit.cross_offsets``); with a third
    column, their variance ``σ² a00 / det`` (``HingeAxisFit.cross_offsets_var``)."""
    var = out.shape[1] > 2
    for r in range(idx.shape[0]):
        j = idx[r]
        if j < 0:
            out[r, 0] = out[r, 1] = 0.0
            if var:
                out[r, 2] = 0.0
            continue
        a00, a01 = state[j, O00], state[j, O01]
        det = a00 * state[j, O11] - a01 * a01
        out[r, 0] = (a00 * state[j, OY1] - a01 * state[j, OY0]) / det
        out[r, 1] = (a00 * state[j, OZ1] - a01 * state[j, OZ0]) / det
        if var:
            out[r, 2] = st[ST_RESIDUAL_VAR] * a00 / det


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _add_quiet(state, j, gx, gy, gz, w0, quiet_rate):
    """A sample of a finger still on its hand into its sensor's cross-axis fit (``HingeAxisFit._add_quiet``):
    the raw gyro ``g`` turned by the current correction into the phalanx frame, ``f = M C g``, and the
    hand's rate about the hinge axis ``w0``; the 3 x 3 normal equations solved by Cramer's rule."""
    if state[j, SAMPLES] != 0.0:
        x = state[j, C0] * gx + state[j, C0 + 1] * gy + state[j, C0 + 2] * gz
        y = state[j, C0 + 3] * gx + state[j, C0 + 4] * gy + state[j, C0 + 5] * gz
        z = state[j, C0 + 6] * gx + state[j, C0 + 7] * gy + state[j, C0 + 8] * gz
    else:
        x, y, z = gx, gy, gz
    f0 = state[j, M0] * x + state[j, M0 + 1] * y + state[j, M0 + 2] * z
    f1 = state[j, M0 + 3] * x + state[j, M0 + 4] * y + state[j, M0 + 5] * z
    f2 = state[j, M0 + 6] * x + state[j, M0 + 7] * y + state[j, M0 + 8] * z
    r = f0 - w0
    if not abs(r) < quiet_rate:
        return
    state[j, Q00] += 1.0
    state[j, Q01] += f1
    state[j, Q02] += f2
    state[j, Q11] += f1 * f1
    state[j, Q12] += f1 * f2
    state[j, Q22] += f2 * f2
    state[j, QB0] += r
    state[j, QB1] += f1 * r
    state[j, QB2] += f2 * r
    a00, a01, a02 = state[j, Q00], state[j, Q01], state[j, Q02]
    a11, a12, a22 = state[j, Q11], state[j, Q12], state[j, Q22]
    b0, b1, b2 = state[j, QB0], state[j, QB1], state[j, QB2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    # the second and third unknowns (Cramer's rule with the symmetric matrix's cofactors)
    state[j, LEAK_Y] = (c01 * b0 + (a00 * a22 - a02 * a02) * b1 + (a01 * a02 - a00 * a12) * b2) / det
    state[j, LEAK_Z] = (c02 * b0 + (a01 * a02 - a00 * a12) * b1 + (a00 * a11 - a01 * a01) * b2) / det
    state[j, QUIET_SAMPLES] += 1.0


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def fit(state, meta, idx, raw, hand, phi, started, st):
    """Every sample of a tick whose finger's estimator has started and whose gyro has no axis at full scale
    into its sensor's fit: one whose flexion rate reaches ``min_rate_rad_s`` into the tilt's and the offsets'
    sums, a slower one while the hand turns across the hinge slower than ``still_rate_rad_s`` (and its gyro's
    cross axes slower than ``ST_STILL_GYRO``, the optics' window full: ``ST_STILL_ON``) into the
    offsets' only (``HingeAxisFit.add`` with the hand's rate in the finger
    base frame ``Bᵀ Rᵀ ω`` from ``hand`` = ``BaseMotion.flat`` (18) and the phalanx angle as the sum of
    the finger's joint angles up to it). Returns how many samples were used."""
    min_rate, max_tilt, quiet_rate = st[ST_MIN_RATE], st[ST_MAX_TILT], st[ST_QUIET_RATE]
    clipped = st[ST_FIT_RANGE] * (1.0 - 1e-3)
    still = st[ST_STILL] if st[ST_STILL_ON] > 0.5 else 0.0
    still_gyro = st[ST_STILL_GYRO]
    # the hand's angular velocity in the metacarpus frame, Rᵀ ω
    wm0 = hand[0] * hand[12] + hand[3] * hand[13] + hand[6] * hand[14]
    wm1 = hand[1] * hand[12] + hand[4] * hand[13] + hand[7] * hand[14]
    wm2 = hand[2] * hand[12] + hand[5] * hand[13] + hand[8] * hand[14]
    used = 0
    for r in range(idx.shape[0]):
        j = idx[r]
        if j < 0 or not started[meta[j, 0]]:
            continue
        gx, gy, gz = raw[r, 0, 0], raw[r, 0, 1], raw[r, 0, 2]
        if clipped > 0.0 and max(abs(gx), abs(gy), abs(gz)) >= clipped:
            continue                    # an axis at full scale: not the rates the sensor turned at
        wx = state[j, M0] * gx + state[j, M0 + 1] * gy + state[j, M0 + 2] * gz     # f = M gyr, phalanx frame
        # the hand's rate in the finger base frame, Bᵀ (Rᵀ ω): its y and z components
        w1 = state[j, B0 + 1] * wm0 + state[j, B0 + 4] * wm1 + state[j, B0 + 7] * wm2
        w2 = state[j, B0 + 2] * wm0 + state[j, B0 + 5] * wm1 + state[j, B0 + 8] * wm2
        f1 = state[j, M0 + 3] * gx + state[j, M0 + 4] * gy + state[j, M0 + 5] * gz
        f2 = state[j, M0 + 6] * gx + state[j, M0 + 7] * gy + state[j, M0 + 8] * gz
        if not abs(wx) >= min_rate:
            if quiet_rate > 0.0:
                # the hand's rate about the hinge axis, (Bᵀ Rᵀ ω)_x
                w0 = state[j, B0] * wm0 + state[j, B0 + 3] * wm1 + state[j, B0 + 6] * wm2
                _add_quiet(state, j, gx, gy, gz, w0, quiet_rate)
            if not w1 * w1 + w2 * w2 < still * still:
                continue                # slow, and the hand turns: the angle's error is in the residual
            if still_gyro > 0.0 and not f1 * f1 + f2 * f2 < still_gyro * still_gyro:
                continue                # the gyro's own cross axes see the hand turn: the optics' rate lags
            slow = True
        else:
            slow = False
        theta = 0.0
        o = meta[j, 2]
        for q in range(meta[j, 1] + 1):
            theta += phi[o + q]
        c, s = math.cos(theta), math.sin(theta)
        ry = f1 - (c * w1 + s * w2)
        rz = f2 - (-s * w1 + c * w2)
        if not (wx == wx and ry == ry and rz == rz):
            continue                    # a NaN would stay in the sums for the session
        _add_sums(state, j, O00, wx, ry, rz)
        if slow:
            continue                    # a still sample: the offsets' sums only
        _add_sums(state, j, A00, wx, ry, rz)
        a00, a01, a11 = state[j, A00], state[j, A01], state[j, A11]
        det = a00 * a11 - a01 * a01
        ey = (a11 * state[j, BZ0] - a01 * state[j, BZ1]) / det
        ez = -(a11 * state[j, BY0] - a01 * state[j, BY1]) / det
        norm = math.hypot(ey, ez)
        if norm > max_tilt:
            scale = max_tilt / norm
            ey, ez = ey * scale, ez * scale
            norm = math.hypot(ey, ez)
        state[j, TILT_Y], state[j, TILT_Z] = ey, ez
        state[j, SAMPLES] += 1.0
        _set_correction(state, j, ey, ez, norm)
        used += 1
    return used


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _add_sums(state, j, first, wx, ry, rz):
    """One sample into the normal equations of the regressors ``[ω_x, 1]`` of row ``j`` whose seven sums
    ``a00, a01, a11, by0, by1, bz0, bz1`` start at column ``first`` (``A00``: the tilt's, ``O00``: the
    offsets')."""
    state[j, first] += wx * wx
    state[j, first + 1] += wx
    state[j, first + 2] += 1.0
    state[j, first + 3] += wx * ry
    state[j, first + 4] += ry
    state[j, first + 5] += wx * rz
    state[j, first + 6] += rz


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _set_correction(state, j, ey, ez, angle):
    """``C = Mᵀ R M`` (``R`` itself when ``M`` is the identity) with ``R`` the rotation of the rotation
    vector ``(0, ey, ez)`` of length ``angle`` (``mounting._rotation_about_yz``)."""
    if angle == 0.0:
        k1 = k2 = 0.0
    else:
        k1 = math.sin(angle) / angle
        half = math.sin(0.5 * angle)
        k2 = 2.0 * half * half / (angle * angle)
    r00, r01, r02 = 1.0 - k2 * (ey * ey + ez * ez), -k1 * ez, k1 * ey
    r10, r11, r12 = k1 * ez, 1.0 - k2 * ez * ez, k2 * ey * ez
    r20, r21, r22 = -k1 * ey, k2 * ey * ez, 1.0 - k2 * ey * ey
    if state[j, STRAIGHT] != 0.0:
        state[j, C0], state[j, C0 + 1], state[j, C0 + 2] = r00, r01, r02
        state[j, C0 + 3], state[j, C0 + 4], state[j, C0 + 5] = r10, r11, r12
        state[j, C0 + 6], state[j, C0 + 7], state[j, C0 + 8] = r20, r21, r22
        return
    for i in range(3):
        # row i of Mᵀ R (column i of M against R's columns), then that row times M
        mi0, mi1, mi2 = state[j, M0 + i], state[j, M0 + 3 + i], state[j, M0 + 6 + i]
        t0 = mi0 * r00 + mi1 * r10 + mi2 * r20
        t1 = mi0 * r01 + mi1 * r11 + mi2 * r21
        t2 = mi0 * r02 + mi1 * r12 + mi2 * r22
        for k in range(3):
            state[j, C0 + 3 * i + k] = t0 * state[j, M0 + k] + t1 * state[j, M0 + 3 + k] + t2 * state[j, M0 + 6 + k]
