"""Compiled (numba) kernel of ``openxr.joint_poses``: the 26 OpenXR joint poses of a hand in one call,
from the calibration packed by ``openxr._packed_calibration``. ``openxr.joint_poses`` (numpy and
scipy) is the reference; ``tests/test_openxr_kernel.py`` checks the two against each other."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import JIT_CACHE, KERNEL_FASTMATH



@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _store(m, hp, hx, r00, r01, r02, r10, r11, r12, r20, r21, r22, positions, quats, j):
    """Joint ``j``: position ``hp + R_M m`` and the orientation ``R_M r X`` (``X`` = finger frame to
    OpenXR, ``(x, y, z)`` -> ``(-X, -Z, -Y)``), as a ``[x, y, z, w]`` quaternion with ``w >= 0``
    (scipy's ``from_matrix`` choice of the largest of the trace and the diagonal, then canonical)."""
    for a in range(3):
        positions[j, a] = hp[a] + hx[a, 0] * m[0] + hx[a, 1] * m[1] + hx[a, 2] * m[2]
    # R_M r, then times X: columns (-c0, -c2, -c1)
    t00 = hx[0, 0] * r00 + hx[0, 1] * r10 + hx[0, 2] * r20
    t01 = hx[0, 0] * r01 + hx[0, 1] * r11 + hx[0, 2] * r21
    t02 = hx[0, 0] * r02 + hx[0, 1] * r12 + hx[0, 2] * r22
    t10 = hx[1, 0] * r00 + hx[1, 1] * r10 + hx[1, 2] * r20
    t11 = hx[1, 0] * r01 + hx[1, 1] * r11 + hx[1, 2] * r21
    t12 = hx[1, 0] * r02 + hx[1, 1] * r12 + hx[1, 2] * r22
    t20 = hx[2, 0] * r00 + hx[2, 1] * r10 + hx[2, 2] * r20
    t21 = hx[2, 0] * r01 + hx[2, 1] * r11 + hx[2, 2] * r21
    t22 = hx[2, 0] * r02 + hx[2, 1] * r12 + hx[2, 2] * r22
    m00, m01, m02 = -t00, -t02, -t01
    m10, m11, m12 = -t10, -t12, -t11
    m20, m21, m22 = -t20, -t22, -t21
    trace = m00 + m11 + m22
    if m00 >= m11 and m00 >= m22 and m00 >= trace:          # argmax picks the first of equals
        qx, qy, qz, qw = 1.0 - trace + 2.0 * m00, m10 + m01, m20 + m02, m21 - m12
    elif m11 >= m22 and m11 >= trace:
        qx, qy, qz, qw = m01 + m10, 1.0 - trace + 2.0 * m11, m21 + m12, m02 - m20
    elif m22 >= trace:
        qx, qy, qz, qw = m02 + m20, m12 + m21, 1.0 - trace + 2.0 * m22, m10 - m01
    else:
        qx, qy, qz, qw = m21 - m12, m02 - m20, m10 - m01, 1.0 + trace
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    sign = 1.0
    if qw < 0.0 or (qw == 0.0 and (qx < 0.0 or (qx == 0.0 and (qy < 0.0 or (qy == 0.0 and qz < 0.0))))):
        sign = -1.0
    quats[j, 0] = sign * qx / norm
    quats[j, 1] = sign * qy / norm
    quats[j, 2] = sign * qz / norm
    quats[j, 3] = sign * qw / norm


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def joint_poses(packed, phi, hand_rotation, hand_position, positions, quats):
    """``positions`` (26, 3) and ``quats`` (26, 4) in ``openxr.JOINT_NAMES`` order, world frame, from
    the packed calibration (6, 16), joint angles ``phi`` (5, 3) (thumb first, zero-padded), the
    metacarpus rotation (3, 3) and position (3,)."""
    hx, hp = hand_rotation, hand_position
    m = np.zeros(3)
    m[1] = packed[5, 0]
    zero = np.zeros(3)
    _store(zero, hp, hx, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, positions, quats, 1)     # wrist
    _store(m, hp, hx, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, positions, quats, 0)        # palm
    j = 2
    point = m.copy()
    for f in range(5):
        n = int(packed[f, 0])
        b = packed[f, 1:10]
        b00, b01, b02, b10, b11, b12, b20, b21, b22 = b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7], b[8]
        bp0, bp1, bp2 = packed[f, 10], packed[f, 11], packed[f, 12]
        if f == 0:                               # the thumb's CMC joint, behind its MCP joint
            lm = packed[5, 1]
            point[0], point[1], point[2] = bp0 - lm * b01, bp1 - lm * b11, bp2 - lm * b21
        else:                                    # the long fingers' on the wrist line
            point[0], point[1], point[2] = bp0, 0.0, bp2
        _store(point, hp, hx, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, positions, quats, j)
        j += 1
        point[0], point[1], point[2] = bp0, bp1, bp2
        theta, c, s = 0.0, 1.0, 0.0
        bones = 3 if f == 0 else 4
        for i in range(bones):
            if i < n:
                theta += phi[f, i]
                c, s = math.cos(theta), math.sin(theta)
            # phalanx frame r = R_B R_x(θ): columns b0, c b1 + s b2, -s b1 + c b2
            r00, r01, r02 = b00, c * b01 + s * b02, -s * b01 + c * b02
            r10, r11, r12 = b10, c * b11 + s * b12, -s * b11 + c * b12
            r20, r21, r22 = b20, c * b21 + s * b22, -s * b21 + c * b22
            _store(point, hp, hx, r00, r01, r02, r10, r11, r12, r20, r21, r22, positions, quats, j)
            j += 1
            if i < n:
                length = packed[f, 13 + i]
                point[0] += length * r01
                point[1] += length * r11
                point[2] += length * r21
