"""Metacarpus kinematics at IMU times from the optical pose stream.

Offline (whole recordings): each position axis and each quaternion component (signs made continuous)
is fitted with a cubic smoothing spline (``scipy.interpolate.make_smoothing_spline``, smoothing
chosen by generalised cross-validation), so the derivatives are smooth instead of a double difference
of jittery samples. With ``q(t)`` the unit quaternion (metacarpus to world):

* angular velocity (world frame): ``ω = 2 q̇ ⊗ q*`` (vector part);
* angular acceleration: ``α = 2 q̈ ⊗ q*`` (vector part; ``q̇ ⊗ q̇*`` is a scalar for unit ``q``);
* acceleration: the second derivative of the position splines.

Poses marked ``valid: false`` are left out; the splines bridge the gaps.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import make_smoothing_spline

from ..estimators.rigid import quaternion as quat
from ..model.kinematics import BaseMotion

MIN_POSES = 5


def _continuous_signs(q: np.ndarray) -> np.ndarray:
    q = q.copy()
    flips = np.cumsum(np.sum(q[1:] * q[:-1], axis=1) < 0) % 2
    q[1:][flips == 1] *= -1.0
    return q


def hand_kinematics_offline(pose_t: np.ndarray, position: np.ndarray, orientation_xyzw: np.ndarray,
                            valid: np.ndarray, query_t: np.ndarray) -> BaseMotion:
    """Metacarpus kinematics at ``query_t`` from the valid poses (module docstring)."""
    pose_t = np.asarray(pose_t, dtype=float)
    keep = np.asarray(valid, dtype=bool)
    if keep.sum() < MIN_POSES:
        raise ValueError(f"need at least {MIN_POSES} valid optical poses to derive the hand's motion, got {int(keep.sum())}")
    t = pose_t[keep]
    pos = np.asarray(position, dtype=float)[keep]
    q = _continuous_signs(quat.from_xyzw(np.asarray(orientation_xyzw, dtype=float)[keep]))
    n = len(query_t)
    p, v, a = (np.empty((n, 3)) for _ in range(3))
    for j in range(3):
        spl = make_smoothing_spline(t, pos[:, j])
        p[:, j], v[:, j], a[:, j] = spl(query_t), spl(query_t, 1), spl(query_t, 2)
    qs, dq, ddq = (np.empty((n, 4)) for _ in range(3))
    for j in range(4):
        spl = make_smoothing_spline(t, q[:, j])
        qs[:, j], dq[:, j], ddq[:, j] = spl(query_t), spl(query_t, 1), spl(query_t, 2)
    norm = np.linalg.norm(qs, axis=1, keepdims=True)
    qs, dq, ddq = qs / norm, dq / norm, ddq / norm
    conj = qs * np.array([1.0, -1.0, -1.0, -1.0])
    omega = 2.0 * quat.multiply(dq, conj)[:, 1:]
    alpha = 2.0 * quat.multiply(ddq, conj)[:, 1:]
    return BaseMotion(quat.to_matrix(qs), p, v, a, omega, alpha)
