"""Compiled (numba) kernels of the rigid Madgwick core: the same equations as ``madgwick.py``
(eqs. 9-19, Madgwick 2011 eqs. 19-20 for a general reference), one loop over samples and sensors
in machine code. ``madgwick.madgwick_step`` stays the reference implementation; the tests check
the two against each other to 1e-12.

Measured reason (``fingertrack bench peers``): the numpy step costs ~36 µs per sample for one IMU
because every operation pays numpy's per-call overhead on 4-element arrays.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ... import JIT_CACHE


@njit(cache=JIT_CACHE)
def _pair_gradient(q, d, s):
    """``(usable, Jᵀ F)`` of one normalised reference pair, as scalars (no allocation per sample)."""
    dn = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    sn = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    if not (dn > 0.0 and sn > 0.0 and math.isfinite(dn) and math.isfinite(sn)):
        return False, 0.0, 0.0, 0.0, 0.0
    dx, dy, dz = d[0] / dn, d[1] / dn, d[2] / dn
    sx, sy, sz = s[0] / sn, s[1] / sn, s[2] / sn
    q1, q2, q3, q4 = q[0], q[1], q[2], q[3]
    f0 = 2 * dx * (0.5 - q3 * q3 - q4 * q4) + 2 * dy * (q1 * q4 + q2 * q3) + 2 * dz * (q2 * q4 - q1 * q3) - sx
    f1 = 2 * dx * (q2 * q3 - q1 * q4) + 2 * dy * (0.5 - q2 * q2 - q4 * q4) + 2 * dz * (q1 * q2 + q3 * q4) - sy
    f2 = 2 * dx * (q1 * q3 + q2 * q4) + 2 * dy * (q3 * q4 - q1 * q2) + 2 * dz * (0.5 - q2 * q2 - q3 * q3) - sz
    g0 = (2 * dy * q4 - 2 * dz * q3) * f0 + (-2 * dx * q4 + 2 * dz * q2) * f1 + (2 * dx * q3 - 2 * dy * q2) * f2
    g1 = (2 * dy * q3 + 2 * dz * q4) * f0 + (2 * dx * q3 - 4 * dy * q2 + 2 * dz * q1) * f1 \
        + (2 * dx * q4 - 2 * dy * q1 - 4 * dz * q2) * f2
    g2 = (-4 * dx * q3 + 2 * dy * q2 - 2 * dz * q1) * f0 + (2 * dx * q2 + 2 * dz * q4) * f1 \
        + (2 * dx * q1 + 2 * dy * q4 - 4 * dz * q3) * f2
    g3 = (-4 * dx * q4 + 2 * dy * q1 + 2 * dz * q2) * f0 + (-2 * dx * q1 - 4 * dy * q4 + 2 * dz * q3) * f1 \
        + (2 * dx * q2 + 2 * dy * q3) * f2
    return True, g0, g1, g2, g3


@njit(cache=JIT_CACHE)
def _step_one(q, w, acc, dt, beta, up, ref_w, ref_s, use_ref):
    """One sensor, one sample, in place: eqs. 9, 11, 12, 18, 15, 19."""
    qd0 = 0.5 * (-q[1] * w[0] - q[2] * w[1] - q[3] * w[2])
    qd1 = 0.5 * (q[0] * w[0] + q[2] * w[2] - q[3] * w[1])
    qd2 = 0.5 * (q[0] * w[1] - q[1] * w[2] + q[3] * w[0])
    qd3 = 0.5 * (q[0] * w[2] + q[1] * w[1] - q[2] * w[0])
    ok, g0, g1, g2, g3 = _pair_gradient(q, up, acc)
    if use_ref:
        ok2, h0, h1, h2, h3 = _pair_gradient(q, ref_w, ref_s)
        ok = ok or ok2
        g0, g1, g2, g3 = g0 + h0, g1 + h1, g2 + h2, g3 + h3
    gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2 + g3 * g3)
    if ok and gn > 0.0:
        qd0 -= beta * g0 / gn
        qd1 -= beta * g1 / gn
        qd2 -= beta * g2 / gn
        qd3 -= beta * g3 / gn
    q0, q1, q2, q3 = q[0] + qd0 * dt, q[1] + qd1 * dt, q[2] + qd2 * dt, q[3] + qd3 * dt
    n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    q[0], q[1], q[2], q[3] = q0 / n, q1 / n, q2 / n, q3 / n


@njit(cache=JIT_CACHE)
def madgwick_batch(q, gyr, acc, dt, beta, up, ref_w, ref_s, use_ref):
    """All samples: ``q`` (B, 4) ``[w,x,y,z]`` updated in place; ``gyr``/``acc``/refs (N, B, 3);
    returns (N, B, 4)."""
    n, b = gyr.shape[0], gyr.shape[1]
    out = np.empty((n, b, 4))
    for k in range(n):
        for j in range(b):
            _step_one(q[j], gyr[k, j], acc[k, j], dt, beta, up, ref_w[k, j] if use_ref else up,
                      ref_s[k, j] if use_ref else up, use_ref)
            out[k, j] = q[j]
    return out


@njit(cache=JIT_CACHE)
def madgwick_sample(q, gyr, acc, dt, beta, up, ref_w, ref_s, use_ref):
    """One sample of every sensor of a stack: ``q`` (B, 4) in place, ``gyr``/``acc``/refs (B, 3)."""
    for j in range(q.shape[0]):
        _step_one(q[j], gyr[j], acc[j], dt, beta, up, ref_w[j] if use_ref else up,
                  ref_s[j] if use_ref else up, use_ref)
    return None
