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

from ...model import quaternion as quat
from ...model.units import MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ
from . import inertial
from .ekf import BatchedKalman, FilterpyKalman, inject, measurement_model, process_model
from .inertial_kernel import N_X, P, X, run_batch, run_sample
from .madgwick import madgwick_step
from .madgwick_kernel import madgwick_batch, madgwick_sample


class _RigidFilter:
    """State holder shared by the rigid filters: the quaternion in ``[x, y, z, w]`` and a batch loop."""

    q: np.ndarray
    batch_shape: tuple[int, ...] = ()

    @property
    def quaternion(self) -> np.ndarray:
        return quat.to_xyzw(self.q)

    @quaternion.setter
    def quaternion(self, q_xyzw: np.ndarray) -> None:
        self.q = quat.normalize(quat.from_xyzw(q_xyzw))

    def update(self, gyr, acc, dt, ref_world=None, ref_sensor=None) -> np.ndarray:
        raise NotImplementedError

    def _flat(self, v, n=None):
        """``v`` as a C-contiguous float (B, 3) (or (N, B, 3)) array, without a copy when it already is one."""
        want = (self.batch_shape + (3,)) if n is None else ((n,) + self.batch_shape + (3,))
        v = np.asarray(v, dtype=float)
        if v.shape != want:
            v = np.broadcast_to(v, want)
        return np.ascontiguousarray(v.reshape((-1, 3) if n is None else (n, -1, 3)))

    def run(self, gyr: np.ndarray, acc: np.ndarray, dt: float,
            ref_world: np.ndarray | None = None, ref_sensor: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) samples at a fixed ``dt`` (optionally (N, 3) second references); returns (N, 4)."""
        out = np.empty(np.shape(gyr)[:-1] + (4,))
        for k in range(len(gyr)):
            out[k] = self.update(gyr[k], acc[k], dt, None if ref_world is None else ref_world[k],
                                 None if ref_sensor is None else ref_sensor[k])
        return out


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

    def update(self, gyr: np.ndarray, acc: np.ndarray, dt: float,
               ref_world: np.ndarray | None = None, ref_sensor: np.ndarray | None = None) -> np.ndarray:
        if self.engine == "numba":
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

    gyro_noise_density: float = MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ
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


class InertialImu(_RigidFilter):
    """The inertial-frame core (``inertial``: accelerometer low-passed in an almost-inertial frame,
    gyro bias and scale-factor estimation) on one rigid IMU or a stack (``batch_shape``).
    ``engine``: ``"numba"`` (``inertial_kernel``) or ``"numpy"`` (``inertial.reference_step``).
    The sampling interval is fixed at construction (the low-pass coefficients depend on it); the
    filter starts by itself (the first ``tau_acc`` seconds average the accelerometer)."""

    def __init__(self, dt: float, settings=None, up=(0.0, 1.0, 0.0), batch_shape: tuple[int, ...] = (),
                 engine: str = "numba") -> None:
        if engine not in ("numba", "numpy"):
            raise ValueError(f"engine must be 'numba' or 'numpy', got {engine!r}")
        self.settings = settings if settings is not None else inertial.InertialSettings()
        self.dt = float(dt)
        self.c = inertial.coefficients(self.settings, self.dt)
        self.batch_shape = tuple(batch_shape)
        self.engine = engine
        self.up = np.asarray(up, dtype=float)
        self._to_world = inertial.world_rotation(self.up)
        self.state = inertial.initial_state(self.settings, int(np.prod(self.batch_shape, dtype=int)))

    # the world frame of the public API is the caller's (``up``); the core's is z up
    @property
    def q(self) -> np.ndarray:
        return quat.multiply(self._to_world, inertial.output(self.state)).reshape(self.batch_shape + (4,))

    @q.setter
    def q(self, q_wxyz: np.ndarray) -> None:
        """Sets the attitude (``[w,x,y,z]`` sensor -> world): the strapdown part takes it, the
        correction is reset, the low-passes restart; the gyro error estimates are kept."""
        q = np.broadcast_to(np.asarray(q_wxyz, dtype=float), self.batch_shape + (4,)).reshape(-1, 4)
        fresh = inertial.initial_state(self.settings, self.state.shape[0], q, self._to_world)
        keep = slice(X, P + N_X * N_X)
        fresh[:, keep] = self.state[:, keep]
        self.state = fresh

    @property
    def gyro_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """(bias rad/s, scale-factor error) estimates, each (*batch, 3)."""
        return (self.state[:, X:X + 3].reshape(self.batch_shape + (3,)),
                self.state[:, X + 3:X + 6].reshape(self.batch_shape + (3,)))

    def _world_to_core(self, v: np.ndarray) -> np.ndarray:
        """Vectors from the caller's world frame into the core's (z up)."""
        return np.ascontiguousarray(quat.rotate_into_sensor(self._to_world, v))

    def update(self, gyr, acc, dt=None, ref_world=None, ref_sensor=None) -> np.ndarray:
        """One sample of every sensor; returns ``[x,y,z,w]`` (*batch, 4)."""
        self._check_dt(dt)
        use = ref_world is not None
        g, a = self._flat(gyr), self._flat(acc)
        rw = self._flat(ref_world) if use else g
        rs = self._flat(ref_sensor) if use else g
        out = np.empty((self.state.shape[0], 4))
        if self.engine == "numba":
            run_sample(self.state, g, a, self.c, rw, rs, use, self._to_world, out)
            return out.reshape(self.batch_shape + (4,))
        for j in range(self.state.shape[0]):
            inertial.reference_step(self.state[j], g[j], a[j], self.c, self._world_to_core(rw[j]) if use else None,
                           rs[j] if use else None)
        return self.quaternion

    def run(self, gyr, acc, dt=None, ref_world=None, ref_sensor=None) -> np.ndarray:
        """(N, *batch, 3) samples; returns (N, *batch, 4) ``[x,y,z,w]``."""
        if self.engine != "numba":
            return super().run(gyr, acc, dt, ref_world, ref_sensor)
        self._check_dt(dt)
        n = len(gyr)
        use = ref_world is not None
        g, a = self._flat(gyr, n), self._flat(acc, n)
        rw = self._flat(ref_world, n) if use else g
        rs = self._flat(ref_sensor, n) if use else g
        out = run_batch(self.state, g, a, self.c, rw, rs, use, self._to_world)
        return out.reshape((n,) + self.batch_shape + (4,))

    def _check_dt(self, dt) -> None:
        if dt is not None and abs(float(dt) - self.dt) > 1e-9 * self.dt:
            raise ValueError(f"InertialImu was built for dt = {self.dt} s, got dt = {dt} s; build one per rate")
