"""The optional IMU on the back of the hand (sensor id ``metacarpus``): the hand's rotation and
acceleration between optical samples and through occlusions.

The optics give the metacarpus orientation well but its derivatives late: the angular velocity and
acceleration come from a derivative fit over a window of poses (``OpticalTrack``), which lags in a
fast reach by about half the window. An IMU fixed to the metacarpus measures both directly. Here:

* the sensor's axes are not exactly the metacarpus frame's (a mounting misalignment of a few degrees,
  scale and cross-axis errors of a few per cent): a rotation-proportional error the optics can reveal.
  Every ``CALIBRATION_INCREMENT_S`` of tracking, the optical rotation increment (body frame, the
  rotation vector of ``R(t₀)ᵀ R(t₁)``: orientations, which do not lag) is regressed on the gyro's
  integral over the same interval and the interval's length: ``Δθ = A ∫g dt + c Δt``, recursive least
  squares with exponential forgetting (``CALIBRATION_MEMORY_S``) and a prior ``A = R_S``, ``c = 0``.
  The hand's angular velocity is then ``ω = R_M (A g + c)``;
* while the optics track: the orientation, position and acceleration stay the optics'; the angular
  velocity is the gyro's and the angular acceleration its change (``α = R_M dω_body/dt``; differencing
  the world-frame rate would carry the optical orientation's jitter). The accelerometer's map and
  offset are fitted meanwhile, ``f_opt = A_f f + c_f`` by recursive least squares against the optics'
  specific force at the sensor (``R_Mᵀ(a_opt + α×r + ω×(ω×r) - g_world)``, ``r = R_M p``), so that
  they are known when the optics are lost. The accelerometer's own acceleration is not used while
  the optics track: on tuning trials (``bench accuracy`` seeds 500-503, 8 s, ``chain`` with the
  reference pose and its linear-map states on, as they were then; pooled RMS over every scored joint
  sample) it made a rotating hand's fingers worse
  (4.07 deg against 3.76 with the optics' acceleration and 3.81 without the IMU) and fast reaches no
  better (3.47 against 3.46 and 3.60): its scale and cross-axis errors (a few per cent of g, changing
  with the hand's orientation) cost more than the optical fit's lag;
* while the optics are lost: the orientation is carried on by the gyro (``R ← R Exp(ω_body dt)``), the
  acceleration of the metacarpus origin is the accelerometer's,
  ``a_M = R_M (A_f f + c_f) + g_world - α×r - ω×(ω×r)``, the calibration is held; the position is held.

What it leaves: the accelerometer's own scale and cross-axis errors (a few per cent of the force) and
an orientation that drifts with the residual gyro error while the optics are lost.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..model.hand import MetacarpusImu
from ..model.kinematics import BaseMotion

CALIBRATION_INCREMENT_S = 0.1
"""Length of the optical rotation increments the gyro's linear map is fitted to, s."""
CALIBRATION_MEMORY_S = 30.0
"""Forgetting time constant of that fit, s."""
OPTICAL_INCREMENT_STD_RAD = 0.005
"""Assumed noise of one optical rotation increment per axis (two poses' jitter of about 0.2 deg), rad."""
PRIOR_MAP_STD = 0.05
"""Prior std of each entry of the gyro's linear map around the nominal mounting (5 deg, a few per cent)."""
PRIOR_OFFSET_STD_RAD_S = 0.1
"""Prior std of the gyro offset (MPU-9250: ±5 deg/s), rad/s."""
OPTICAL_FORCE_STD_M_S2 = 1.0
"""Assumed error of the optics' specific force at one tick (their acceleration lags in fast motion), m/s²."""
PRIOR_ACC_OFFSET_STD_M_S2 = 0.5
"""Prior std of the accelerometer offset (MPU-9250: ±60-80 mg), m/s²."""


class LinearMapFit:
    """Recursive least squares of ``y = M x + c`` (3-vectors) with exponential forgetting and a prior
    ``M = prior_map``, ``c = 0`` (regressor ``z = [x, scale]``, ``Θ = [Mᵀ; cᵀ]``): each prior std is
    expressed against the measurement's noise ``noise_std`` as a pseudo-observation weight."""

    def __init__(self, prior_map: np.ndarray, noise_std: float, map_std: float, offset_std: float):
        w_map, w_off = (noise_std / map_std) ** 2, (noise_std / offset_std) ** 2
        self._prior_info = np.diag([w_map, w_map, w_map, w_off])
        self._prior_cross = self._prior_info @ np.vstack([prior_map.T, np.zeros((1, 3))])
        self._info = np.zeros((4, 4))
        self._cross = np.zeros((4, 3))
        self.map = prior_map.copy()
        self.offset = np.zeros(3)

    def update(self, x: np.ndarray, scale: float, y: np.ndarray, forget: float) -> None:
        """One observation ``y ≈ M x + c · scale``; older ones weigh ``forget`` times less."""
        z = np.append(x, scale)
        self._info = forget * self._info + np.outer(z, z)
        self._cross = forget * self._cross + np.outer(z, y)
        theta = np.linalg.solve(self._info + self._prior_info, self._cross + self._prior_cross)
        self.map, self.offset = theta[:3].T, theta[3]


class HandImu:
    """One hand's back-of-hand IMU (module docstring). ``add`` its samples, ``aid`` the hand's
    kinematics at each tick. Deterministic: the same samples and poses give the same numbers."""

    def __init__(self, placement: MetacarpusImu, gravity_world: np.ndarray, timeout_s: float):
        self.placement = placement
        self.mount = placement.mounting_matrix()                 # sensor -> metacarpus
        self.lever = np.asarray(placement.position_m, dtype=float)
        self.gravity_world = np.asarray(gravity_world, dtype=float)
        self.timeout_s = timeout_s
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None
        self._prev_t: float | None = None
        self._prev_omega: np.ndarray | None = None
        # Δθ = A ∫g dt + c Δt against the optical rotation increments; f_opt = A_f f + c_f against the
        # optics' specific force
        self.gyr_fit = LinearMapFit(self.mount, OPTICAL_INCREMENT_STD_RAD, PRIOR_MAP_STD, PRIOR_OFFSET_STD_RAD_S)
        self.acc_fit = LinearMapFit(self.mount, OPTICAL_FORCE_STD_M_S2, PRIOR_MAP_STD, PRIOR_ACC_OFFSET_STD_M_S2)
        self._increment: tuple[np.ndarray, np.ndarray, float] | None = None   # (R at start, ∫g dt, Δt)

    def add(self, t: float, gyr: np.ndarray, acc: np.ndarray) -> None:
        self._last = (t, np.asarray(gyr, dtype=float), np.asarray(acc, dtype=float))

    def live(self, t: float) -> bool:
        """True while the latest sample is younger than ``timeout_s``."""
        return self._last is not None and t - self._last[0] <= self.timeout_s

    def aid(self, t: float, hand: BaseMotion, tracking: bool) -> BaseMotion:
        """The hand's kinematics at ``t``: ``hand`` is the optics' (``tracking``) or the previous tick's
        aided kinematics (optics lost)."""
        assert self._last is not None
        _, gyr, acc = self._last
        dt = 0.0 if self._prev_t is None else max(0.0, t - self._prev_t)
        rot = hand.rotation
        if tracking:
            self._calibrate(rot, gyr, dt)
        else:
            self._increment = None
        w_body = self.gyr_fit.map @ gyr + self.gyr_fit.offset      # metacarpus frame
        if tracking:
            # the optics' view of the force, to fit the accelerometer's map and offset to
            r_opt = rot @ self.lever
            a_opt = hand.acceleration + np.cross(hand.angular_acceleration, r_opt) + \
                np.cross(hand.angular_velocity, np.cross(hand.angular_velocity, r_opt))
            self.acc_fit.update(acc, 1.0, rot.T @ (a_opt - self.gravity_world), np.exp(-dt / CALIBRATION_MEMORY_S))
        else:
            rot = rot @ Rotation.from_rotvec(w_body * dt).as_matrix()
        f_body = self.acc_fit.map @ acc + self.acc_fit.offset
        omega = rot @ w_body
        # α = R dω_body/dt (the body-frame derivative; differencing the world-frame ω would carry
        # the optical orientation's jitter)
        alpha = rot @ (w_body - self._prev_omega) / dt if (self._prev_omega is not None and dt > 0) else \
            (hand.angular_acceleration if tracking else np.zeros(3))
        r = rot @ self.lever
        if tracking:
            acc_m = hand.acceleration          # the optics' fit: measured better here (module docstring)
        else:
            acc_m = rot @ f_body + self.gravity_world - np.cross(alpha, r) - np.cross(omega, np.cross(omega, r))
        self._prev_t, self._prev_omega = t, w_body
        velocity = hand.velocity if tracking else np.zeros(3)
        return BaseMotion(rot, hand.position.copy(), velocity, acc_m, omega, alpha)

    def _calibrate(self, rot: np.ndarray, gyr: np.ndarray, dt: float) -> None:
        """Accumulate the gyro over the current increment; at its end, one recursive least-squares
        step of the linear map (module docstring)."""
        if self._increment is None:
            self._increment = (rot.copy(), np.zeros(3), 0.0)
            return
        start, integral, elapsed = self._increment
        integral, elapsed = integral + gyr * dt, elapsed + dt
        if elapsed < CALIBRATION_INCREMENT_S:
            self._increment = (start, integral, elapsed)
            return
        turned = Rotation.from_matrix(start.T @ rot).as_rotvec()
        self.gyr_fit.update(integral, elapsed, turned, np.exp(-elapsed / CALIBRATION_MEMORY_S))
        self._increment = (rot.copy(), np.zeros(3), 0.0)
