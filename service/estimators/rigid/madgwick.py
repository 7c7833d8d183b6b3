"""The Madgwick gradient-descent orientation filter for one rigid IMU, with any number of reference
vector pairs (paper 2.3, eqs. 9-19; Madgwick et al. 2011, ref. [20]).

One step, for each sensor (vectorised over leading dimensions):

* eq. 9/10: ``q̇_ω = ½ q ⊗ ω``;
* eq. 11: objective ``F = [q* ⊗ d_j ⊗ q - s_j]_j`` over the reference pairs: ``d_j`` known in the
  world frame, ``s_j`` measured in the sensor frame (both normalised). For the finger filter
  ``d_1 = (g_k - g)/|.|`` with the kinematic acceleration ``g_k`` of eq. 2 (specific-force sign of
  DESIGN.md) and ``s_1`` the accelerometer; ``d_2`` the flexion-plane normal from the optical pose and
  ``s_2`` the hinge axis in sensor coordinates, replacing the magnetometer;
* eq. 12: gradient ``∇F = Jᵀ F`` (Jacobian of Madgwick's report, eq. 20, for a general ``d``);
* eq. 18: ``q̇ = q̇_ω - β ∇F/|∇F|``; eq. 15: ``q_+ = q + q̇ Δt``; eq. 19: normalise.

With one pair and ``d = [0, 0, 1]`` this is the IMU-only Madgwick filter of the ``ahrs`` package
(tested to 1e-9). A zero-length or non-finite reference pair contributes no gradient (the others
still correct); with no usable pair, or a vanishing gradient, the correction is skipped, as ahrs
does, so no NaN enters the state.
"""
from __future__ import annotations

import numpy as np

from ...model.quaternion import multiply_vector, normalize


def objective_and_jacobian(q: np.ndarray, d: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``F`` (..., 3) and ``J`` (..., 3, 4) of eq. 11 for one reference pair (Madgwick 2011, eqs. 19-20)."""
    q1, q2, q3, q4 = np.moveaxis(q, -1, 0)
    dx, dy, dz = np.moveaxis(d, -1, 0)
    sx, sy, sz = np.moveaxis(s, -1, 0)
    f = np.stack([
        2 * dx * (0.5 - q3 * q3 - q4 * q4) + 2 * dy * (q1 * q4 + q2 * q3) + 2 * dz * (q2 * q4 - q1 * q3) - sx,
        2 * dx * (q2 * q3 - q1 * q4) + 2 * dy * (0.5 - q2 * q2 - q4 * q4) + 2 * dz * (q1 * q2 + q3 * q4) - sy,
        2 * dx * (q1 * q3 + q2 * q4) + 2 * dy * (q3 * q4 - q1 * q2) + 2 * dz * (0.5 - q2 * q2 - q3 * q3) - sz,
    ], axis=-1)
    j = np.stack([
        np.stack([2 * dy * q4 - 2 * dz * q3, 2 * dy * q3 + 2 * dz * q4,
                  -4 * dx * q3 + 2 * dy * q2 - 2 * dz * q1, -4 * dx * q4 + 2 * dy * q1 + 2 * dz * q2], axis=-1),
        np.stack([-2 * dx * q4 + 2 * dz * q2, 2 * dx * q3 - 4 * dy * q2 + 2 * dz * q1,
                  2 * dx * q2 + 2 * dz * q4, -2 * dx * q1 - 4 * dy * q4 + 2 * dz * q3], axis=-1),
        np.stack([2 * dx * q3 - 2 * dy * q2, 2 * dx * q4 - 2 * dy * q1 - 4 * dz * q2,
                  2 * dx * q1 + 2 * dy * q4 - 4 * dz * q3, 2 * dx * q2 + 2 * dy * q3], axis=-1),
    ], axis=-2)
    return f, j


def _jacobian_tensor() -> np.ndarray:
    """``T[m, i, j, k]`` with ``J_ij = 2 Σ_mk d_m T_mijk q_k``: the Jacobian of eq. 20 is bilinear in
    ``d`` and ``q``, so it is read off the explicit formula on basis vectors once."""
    t = np.zeros((3, 3, 4, 4))
    for m in range(3):
        for k in range(4):
            _, j = objective_and_jacobian(np.eye(4)[k], np.eye(3)[m], np.zeros(3))
            t[m, :, :, k] = 0.5 * j
    return t


_T = _jacobian_tensor()
_T_FLAT = _T.reshape(3, 48)


def objective_and_jacobian_fast(q: np.ndarray, d: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same ``F`` and ``J`` as ``objective_and_jacobian`` with two tensor contractions instead of
    sixty elementwise operations: ``J = 2 T(d) q`` and, since ``F`` is ``d`` plus a quadratic form in
    ``q`` whose gradient is ``J``, ``F = d + ½ J q - s``."""
    td = (d @ _T_FLAT).reshape(d.shape[:-1] + (3, 4, 4))                    # Σ_m d_m T_m
    j = 2.0 * (td @ q[..., None, :, None])[..., 0]
    f = d + 0.5 * (j @ q[..., :, None])[..., 0] - s
    return f, j


def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = np.isfinite(n) & (n > 0)
    return np.where(ok, v / np.where(ok, n, 1.0), 0.0), ok[..., 0]


def madgwick_step(q: np.ndarray, gyr: np.ndarray, dt: float | np.ndarray, beta: float | np.ndarray,
                  refs_world: list[np.ndarray], refs_sensor: list[np.ndarray]) -> np.ndarray:
    """One filter step (module docstring). ``q`` (..., 4) ``[w,x,y,z]``; ``gyr`` (..., 3) rad/s;
    ``refs_world``/``refs_sensor``: lists of (..., 3) vectors (normalised here); ``beta`` rad/s."""
    qdot = 0.5 * multiply_vector(q, gyr)                                      # eq. 9
    grad = np.zeros_like(q)
    valid = np.zeros(q.shape[:-1], dtype=bool)
    for d, s in zip(refs_world, refs_sensor):
        d_unit, d_ok = _unit(d)
        s_unit, s_ok = _unit(s)
        ok = d_ok & s_ok                      # a missing reference (zero or NaN) contributes nothing
        f, j = objective_and_jacobian_fast(q, np.where(ok[..., None], d_unit, 0.0), np.where(ok[..., None], s_unit, 0.0))  # eq. 11
        grad = grad + np.where(ok[..., None], np.einsum("...ji,...j->...i", j, f), 0.0)   # eq. 12: Jᵀ F
        valid |= ok
    gnorm = np.linalg.norm(grad, axis=-1, keepdims=True)
    use = valid[..., None] & (gnorm > 0)
    correction = np.where(use, grad / np.where(use, gnorm, 1.0), 0.0)
    beta = np.asarray(beta, dtype=float)
    qdot = qdot - (beta[..., None] if beta.ndim else beta) * correction        # eq. 18
    dt = np.asarray(dt, dtype=float)
    return normalize(q + qdot * (dt[..., None] if dt.ndim else dt))           # eqs. 15, 19
