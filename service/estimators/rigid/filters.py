"""The rigid-IMU cores as filters of their own: one sensor (or a stack), gyro + accelerometer and
optionally a second reference vector known in the world frame with its sensor-frame counterpart.
The finger estimators use the same step functions (``madgwick.madgwick_step`` and ``ekf``'s
process/measurement models); these classes only hold the state, so the cores can run on rigid-body
recordings.

Quaternions in and out are ``[x, y, z, w]`` (sensor to world). The accelerometer reference is the
world "up" direction (specific force at rest): ``[0, 1, 0]`` in the OpenXR stage frame, ``[0, 0, 1]``
in an east-north-up frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import quaternion as quat
from .ekf import BatchedKalman, FilterpyKalman, inject, measurement_model, process_model
from .madgwick import madgwick_step


class _RigidFilter:
    """State holder shared by the rigid filters: the quaternion in ``[x, y, z, w]`` and a batch loop."""

    q: np.ndarray

    @property
    def quaternion(self) -> np.ndarray:
        return quat.to_xyzw(self.q)

    @quaternion.setter
    def quaternion(self, q_xyzw: np.ndarray) -> None:
        self.q = quat.normalize(quat.from_xyzw(q_xyzw))

    def update(self, gyr, acc, dt, ref_world=None, ref_sensor=None) -> np.ndarray:
        raise NotImplementedError

    def run(self, gyr: np.ndarray, acc: np.ndarray, dt: float,
            ref_world: np.ndarray | None = None, ref_sensor: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) samples at a fixed ``dt`` (optionally (N, 3) second references); returns (N, 4)."""
        out = np.empty(np.shape(gyr)[:-1] + (4,))
        for k in range(len(gyr)):
            out[k] = self.update(gyr[k], acc[k], dt, None if ref_world is None else ref_world[k],
                                 None if ref_sensor is None else ref_sensor[k])
        return out


def tilt_from_accelerometer(acc: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``[w,x,y,z]`` quaternions (..., 4) of the smallest rotation taking the measured specific force
    direction (sensor frame) onto ``up`` (world): an initial attitude with an arbitrary heading."""
    a = np.asarray(acc, dtype=float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    u = np.broadcast_to(np.asarray(up, dtype=float), a.shape)
    c = np.sum(a * u, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + c, np.cross(a, u)], axis=-1)
    # opposite vectors: any axis perpendicular to a
    flip = (1.0 + c[..., 0]) < 1e-9
    if np.any(flip):
        perp = np.cross(a, np.eye(3)[np.argmin(np.abs(a), axis=-1)])
        q = np.where(flip[..., None], np.concatenate([np.zeros_like(c), perp], axis=-1), q)
    return quat.normalize(q)


_XYZW = [1, 2, 3, 0]


@dataclass
class MadgwickImu(_RigidFilter):
    """Madgwick filter (paper eqs. 9-19) on one rigid IMU, or a stack of them (``batch_shape``).
    ``beta`` rad/s. ``engine``: ``"numba"`` runs the compiled kernels (``madgwick_kernel``), ``"numpy"``
    the reference implementation (``madgwick.madgwick_step``); they agree to 1e-12."""

    beta: float = 0.041
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    batch_shape: tuple[int, ...] = ()
    engine: str = "numba"

    def __post_init__(self) -> None:
        if self.engine not in ("numba", "numpy"):
            raise ValueError(f"engine must be 'numba' or 'numpy', got {self.engine!r}")
        self.q = np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), self.batch_shape + (4,)).copy()
        self._up = np.asarray(self.up, dtype=float)

    def _flat(self, v, n=None):
        """``v`` as a C-contiguous float (B, 3) (or (N, B, 3)) array, without a copy when it already is one."""
        want = (self.batch_shape + (3,)) if n is None else ((n,) + self.batch_shape + (3,))
        v = np.asarray(v, dtype=float)
        if v.shape != want:
            v = np.broadcast_to(v, want)
        return np.ascontiguousarray(v.reshape((-1, 3) if n is None else (n, -1, 3)))

    def update(self, gyr: np.ndarray, acc: np.ndarray, dt: float,
               ref_world: np.ndarray | None = None, ref_sensor: np.ndarray | None = None) -> np.ndarray:
        if self.engine == "numba":
            from .madgwick_kernel import madgwick_sample
            q = self.q.reshape(-1, 4)
            use = ref_world is not None
            rw = self._flat(ref_world) if use else self._up.reshape(1, 3)
            rs = self._flat(ref_sensor) if use else rw
            madgwick_sample(q, self._flat(gyr), self._flat(acc), float(dt), float(self.beta), self._up, rw, rs, use)
            self.q = q.reshape(self.q.shape)
            return self.q[..., _XYZW]
        refs_w, refs_s = [np.asarray(self.up, dtype=float)], [np.asarray(acc, dtype=float)]
        if ref_world is not None:
            refs_w.append(np.asarray(ref_world, dtype=float))
            refs_s.append(np.asarray(ref_sensor, dtype=float))
        self.q = madgwick_step(self.q, np.asarray(gyr, dtype=float), dt, self.beta, refs_w, refs_s)
        return self.quaternion

    def run(self, gyr: np.ndarray, acc: np.ndarray, dt: float,
            ref_world: np.ndarray | None = None, ref_sensor: np.ndarray | None = None) -> np.ndarray:
        if self.engine != "numba":
            return super().run(gyr, acc, dt, ref_world, ref_sensor)
        from .madgwick_kernel import madgwick_batch
        n = len(gyr)
        q = np.ascontiguousarray(self.q.reshape(-1, 4))
        use = ref_world is not None
        rw = self._flat(ref_world, n) if use else np.zeros((n, q.shape[0], 3))
        rs = self._flat(ref_sensor, n) if use else rw
        out = madgwick_batch(q, self._flat(gyr, n), self._flat(acc, n), float(dt), float(self.beta),
                             np.asarray(self.up, dtype=float), rw, rs, use)
        self.q = q.reshape(self.q.shape)
        return quat.to_xyzw(out.reshape((n,) + self.batch_shape + (4,)))


@dataclass
class EkfImu(_RigidFilter):
    """Error-state EKF (quaternion + gyro bias, ``ekf`` module) on one rigid IMU. Noise figures: gyro
    density rad/s/√Hz, bias walk rad/s/√s, accelerometer std m/s², second reference std."""

    gyro_noise_density: float = 0.01 * np.pi / 180.0
    bias_walk: float = 1e-5
    acc_noise: float = 0.5
    ref_noise: float = 0.05
    initial_angle_std: float = 0.5
    initial_bias_std: float = 0.05
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    gravity: float = 9.81
    use_filterpy: bool = True
    batch_shape: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        b = self.batch_shape
        self.q = np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), b + (4,)).copy()
        self.bias = np.zeros(b + (3,))
        self.P = np.broadcast_to(np.diag([self.initial_angle_std**2] * 3 + [self.initial_bias_std**2] * 3), b + (6, 6)).copy()
        self._kalman = FilterpyKalman() if self.use_filterpy else BatchedKalman()

    def update(self, gyr: np.ndarray, acc: np.ndarray, dt: float,
               ref_world: np.ndarray | None = None, ref_sensor: np.ndarray | None = None) -> np.ndarray:
        q, F, Q = process_model(self.q, self.bias, np.asarray(gyr, dtype=float), dt, self.gyro_noise_density, self.bias_walk)
        P = self._kalman.predict(self.P, F, Q)
        refs_w = [self.gravity * np.asarray(self.up, dtype=float)]
        refs_s = [np.asarray(acc, dtype=float)]
        sig = [np.full(self.batch_shape, self.acc_noise)]
        if ref_world is not None:
            refs_w.append(np.asarray(ref_world, dtype=float))
            refs_s.append(np.asarray(ref_sensor, dtype=float))
            sig.append(np.full(self.batch_shape, self.ref_noise))
        y, H, R = measurement_model(q, refs_w, refs_s, sig)
        dx, self.P = self._kalman.update(P, H, R, y)
        self.q, self.bias = inject(q, self.bias, dx)
        return self.quaternion
