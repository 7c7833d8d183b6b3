"""Error-state extended Kalman filter for one rigid IMU: orientation quaternion plus gyro bias, as
the EKF of the comparison paper (section II.C.1: state = rotation quaternion and tri-axial gyro bias;
process model = gyro integration; measurement model = stacked reference-vector measurements; after
each update the error states are set to zero and the covariance is propagated with the discretised
process model).

Nominal state: ``q`` (sensor to world, ``[w,x,y,z]``) and gyro bias ``b`` (rad/s, sensor frame).
Error state ``δx = [δθ, δb]`` (6), with ``q_true = q ⊗ Exp(δθ)`` (attitude error in the sensor frame).

* Process (dt): ``q ← q ⊗ Exp((ω - b) dt)``, ``b ← b``;
  ``F = [[Exp(-(ω - b) dt), -I dt], [0, I]]``, ``Q = diag(σ_ω² dt I, σ_b² dt I)`` with ``σ_ω`` the
  gyro noise density (rad/s/√Hz) and ``σ_b`` the bias random walk (rad/s/√s).
* Measurements: each reference pair ``(d_world, s_sensor)`` predicts ``h = R(q)ᵀ d`` with Jacobian
  ``∂h/∂δθ = [h]×`` (since ``R_trueᵀ d ≈ (I - [δθ]×) Rᵀ d``), ``∂h/∂δb = 0``.
* Injection: ``q ← q ⊗ Exp(δθ)``, ``b ← b + δb``, ``δx ← 0``.

``FilterpyKalman`` runs the predict/update of every filter through ``filterpy``'s
``ExtendedKalmanFilter`` (used by the streaming mode); ``BatchedKalman`` runs the same equations
vectorised (``estimators.kalman``, used by the batch mode). Both give the same numbers.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .. import kalman
from ...model import quaternion as quat
from ...model.frames import skew

if TYPE_CHECKING:                                   # imported where first used: it takes a second (scipy.stats)
    from filterpy.kalman import ExtendedKalmanFilter


class BatchedKalman:
    """Vectorised predict/update over stacks of filters."""

    predict = staticmethod(kalman.predict)
    update = staticmethod(kalman.update)


class FilterpyKalman:
    """Predict/update through one ``filterpy.kalman.ExtendedKalmanFilter`` per filter of the stack.

    The filterpy objects are engines, not state: the covariance lives in the estimator's state and
    is loaded into the engine for each call, so states can be read, restored and shared with the
    batch mode."""

    def __init__(self) -> None:
        self._engines: dict[tuple[int, int, int], ExtendedKalmanFilter] = {}

    def _engine(self, index: int, n: int, m: int) -> ExtendedKalmanFilter:
        key = (index, n, m)
        eng = self._engines.get(key)
        if eng is None:
            from filterpy.kalman import ExtendedKalmanFilter
            eng = self._engines[key] = ExtendedKalmanFilter(dim_x=n, dim_z=m)
        return eng

    def predict(self, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> np.ndarray:
        n = P.shape[-1]
        flat_p, flat_f, flat_q = P.reshape(-1, n, n), F.reshape(-1, n, n), Q.reshape(-1, n, n)
        out = np.empty_like(flat_p)
        for i in range(flat_p.shape[0]):
            eng = self._engine(i, n, 1)
            eng.x = np.zeros((n, 1))
            eng.P, eng.F, eng.Q = flat_p[i].copy(), flat_f[i], flat_q[i]
            eng.predict()
            out[i] = eng.P
        return out.reshape(P.shape)

    def update(self, P: np.ndarray, H: np.ndarray, R: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n, m = P.shape[-1], H.shape[-2]
        flat_p, flat_h = P.reshape(-1, n, n), H.reshape(-1, m, n)
        flat_r, flat_y = R.reshape(-1, m, m), y.reshape(-1, m)
        dx = np.empty((flat_p.shape[0], n))
        out = np.empty_like(flat_p)
        for i in range(flat_p.shape[0]):
            eng = self._engine(i, n, m)
            eng.x = np.zeros((n, 1))
            eng.P = flat_p[i].copy()
            h = flat_h[i]
            # error state is zero before the update, so h(x) = H x = 0 and the residual is y
            eng.update(flat_y[i].reshape(m, 1), HJacobian=lambda x, h=h: h, Hx=lambda x, h=h: h @ x, R=flat_r[i])
            dx[i], out[i] = eng.x[:, 0], eng.P
        return dx.reshape(y.shape[:-1] + (n,)), out.reshape(P.shape)


def process_model(q: np.ndarray, b: np.ndarray, gyr: np.ndarray, dt: float,
                  gyro_noise_density: float, bias_walk: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nominal propagation and ``(q, F, Q)`` of the error state (module docstring)."""
    step = (gyr - b) * dt
    dq = quat.exp_rotvec(step)
    q = quat.normalize(quat.multiply(q, dq))
    shape = q.shape[:-1]
    F = np.zeros(shape + (6, 6))
    F[..., :3, :3] = np.swapaxes(quat.to_matrix(dq), -1, -2)                 # Exp(-ω dt)
    F[..., :3, 3:] = -dt * np.eye(3)
    F[..., 3:, 3:] = np.eye(3)
    Q = np.zeros(shape + (6, 6))
    Q[..., :3, :3] = gyro_noise_density**2 * dt * np.eye(3)
    Q[..., 3:, 3:] = bias_walk**2 * dt * np.eye(3)
    return q, F, Q


def measurement_model(q: np.ndarray, refs_world: list[np.ndarray], refs_sensor: list[np.ndarray],
                      sigmas: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Innovation ``y``, Jacobian ``H`` and noise ``R`` of the stacked reference measurements.
    ``sigmas``: per-pair measurement standard deviations (...,) in the vectors' units."""
    rot = quat.to_matrix(q)
    ys, hs, rs = [], [], []
    for d, s, sig in zip(refs_world, refs_sensor, sigmas):
        # a missing pair (non-finite) is kept as a row of zeros with a huge variance: no information
        ok = np.all(np.isfinite(d), axis=-1) & np.all(np.isfinite(s), axis=-1)
        d = np.where(ok[..., None], d, 0.0)
        h = np.einsum("...ji,...j->...i", rot, d)                            # R(q)ᵀ d
        ys.append(np.where(ok[..., None], np.where(ok[..., None], s, 0.0) - h, 0.0))
        block = np.zeros(h.shape[:-1] + (3, 6))
        block[..., :3] = skew(h)
        hs.append(block)
        sig = np.where(ok, np.asarray(sig, dtype=float), 1e6)
        rs.append(sig[..., None] ** 2 * np.ones(3))
    y = np.concatenate(ys, axis=-1)
    H = np.concatenate(hs, axis=-2)
    diag = np.concatenate([np.broadcast_to(r, y.shape[:-1] + (3,)) for r in rs], axis=-1)
    R = diag[..., :, None] * np.eye(diag.shape[-1])
    return y, H, R


def inject(q: np.ndarray, b: np.ndarray, dx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply an error-state correction to the nominal state."""
    return quat.normalize(quat.multiply(q, quat.exp_rotvec(dx[..., :3]))), b + dx[..., 3:]
