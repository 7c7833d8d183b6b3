"""Sensor-to-segment calibration from motion: where each finger sensor's flexion axis lies in its own
frame, learned online from its gyro while the finger flexes, and the sensor's readings turned onto it.

A sensor sits on its phalanx turned by a small rotation ``ε`` that the glove's calibration does not
know (hand-placed sensors: a few degrees about a random axis; Picerno 2017, Gait & Posture 51:
239-246). Its gyro reads ``f = ω_p - ε × ω_p`` (first order) with ``ω_p`` the phalanx's angular
velocity in the phalanx frame, ``ω_p = R_x(θ)ᵀ w_B + θ̇ x``: the hand's rate ``w_B`` (optics, in the
finger base frame) seen from a phalanx flexed by ``θ``, and the flexion about the hinge axis ``x``.
Across the hinge axis this leaves

    ``f_y - (R_x(θ)ᵀ w_B)_y = -ε_z ω_x + b_y``,  ``f_z - (R_x(θ)ᵀ w_B)_z = ε_y ω_x + b_z``,

with ``ω_x ≈ f_x`` and ``b`` the gyro's offsets: a tilted sensor shows part of every fast flexion on
its cross axes. This is the hinge-axis identification of Seel, Raisch and Schauer ("IMU-based joint
angle measurement for gait analysis", Sensors 14 (2014) 6891-6909, section 2.1: the joint axis in
each sensor frame from the gyros of the two segments, here with the proximal segment's rate from the
optics), linearised for small angles and solved as a ridge regression (prior ``ε ~ 0 ± prior_std``,
offsets ``0 ± offset_std``) over the samples whose flexion rate exceeds ``min_rate_rad_s``. The turn
about the hinge axis itself (``ε_x``) does not show here (it looks like a change of ``θ`` to the gyro
and the accelerometer alike); a known configuration calibrates it (``chain``, item 5).

The fit turns both the gyro's and the accelerometer's readings by the estimated ``ε`` (the mounting is
one rotation for both), so every estimator reads them as if the sensor sat straight. It uses the
pipeline's current angle ``θ`` (the accelerometer's, which includes ``ε_x`` as the cross axes do) and
nothing the glove cannot give.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model.units import DEG, MPU9250_GYRO_OFFSET_STD_RAD_S


@dataclass(frozen=True)
class MountingFitSettings:
    """Attributes (SI units):
        prior_std_rad: prior std of each of the two tilt angles ``ε_y``, ``ε_z`` (a misalignment of up to
            5 deg about a random axis: about 1.7 deg per axis), rad.
        offset_std_rad_s: prior std of the gyro's cross-axis offsets (MPU-9250), rad/s.
        residual_std_rad_s: std of what else is in the cross-axis residual (the optical hand rate's
            lag and jitter, the angle's error, gyro cross-axis sensitivity), rad/s.
        min_rate_rad_s: samples whose flexion rate ``|f_x|`` is below this are not used, rad/s.
        max_tilt_rad: the correction is clipped to this angle (a sensor turned further is not a
            mounting error but a wrong calibration), rad.
    """

    prior_std_rad: float = 1.7 * DEG
    offset_std_rad_s: float = MPU9250_GYRO_OFFSET_STD_RAD_S
    residual_std_rad_s: float = 0.3
    min_rate_rad_s: float = 2.0
    max_tilt_rad: float = 10.0 * DEG


class HingeAxisFit:
    """One sensor's tilt ``(ε_y, ε_z)`` (module docstring). ``mount`` is the calibrated sensor-to-phalanx
    rotation (3, 3); the fit lives in the calibrated phalanx frame and the correction it returns turns
    raw sensor readings: ``s' = Mᵀ R(ε) M s``."""

    def __init__(self, mount: np.ndarray, settings: MountingFitSettings = MountingFitSettings()):
        self.settings = settings
        self.mount = np.asarray(mount, dtype=float)
        self._hinge = [float(v) for v in self.mount[0]]
        self._mount_rows = self.mount.tolist()
        s = settings
        lam_e = (s.residual_std_rad_s / s.prior_std_rad) ** 2
        lam_b = (s.residual_std_rad_s / s.offset_std_rad_s) ** 2
        # normal equations of the two rows (the same regressors [ω_x, 1]); ridge from the priors:
        # the symmetric 2 x 2 matrix (a00, a01, a11) and the right-hand sides of the y and z rows
        self._a00, self._a01, self._a11 = lam_e, 0.0, lam_b
        self._by0 = self._by1 = self._bz0 = self._bz1 = 0.0
        self.samples = 0
        self.tilt_rad = np.zeros(2)                  # (ε_y, ε_z)
        self._correction, self._rows = np.eye(3), None          # None: readings pass unchanged
        self._straight = bool(np.array_equal(self.mount, np.eye(3)))

    @property
    def correction(self) -> np.ndarray:
        """The rotation applied to raw readings (3, 3)."""
        return self._correction

    @correction.setter
    def correction(self, m: np.ndarray) -> None:
        self._correction, self._rows = m, m.tolist()

    def flexing(self, gyr) -> bool:
        """Whether a raw gyro sample's flexion rate is high enough to be used (``min_rate_rad_s``)."""
        h = self._hinge
        return abs(h[0] * gyr[0] + h[1] * gyr[1] + h[2] * gyr[2]) >= self.settings.min_rate_rad_s

    def add(self, gyr, theta: float, hand_rate_base: np.ndarray) -> bool:
        """One gyro sample (raw, sensor frame, rad/s), the phalanx angle (rad) and the hand's rate in the
        finger base frame (rad/s). Returns whether the sample was used (and the correction changed)."""
        if not self.flexing(gyr):
            return False
        m = self._mount_rows
        gx, gy, gz = gyr
        wx = m[0][0] * gx + m[0][1] * gy + m[0][2] * gz          # f = M gyr, the reading in the phalanx frame
        f1 = m[1][0] * gx + m[1][1] * gy + m[1][2] * gz
        f2 = m[2][0] * gx + m[2][1] * gy + m[2][2] * gz
        c, s = math.cos(theta), math.sin(theta)
        w1, w2 = hand_rate_base[1], hand_rate_base[2]
        ry = f1 - (c * w1 + s * w2)
        rz = f2 - (-s * w1 + c * w2)
        # the normal equations of the regressors [ω_x, 1] (symmetric 2 x 2), solved in closed form
        self._a00 += wx * wx
        self._a01 += wx
        self._a11 += 1.0
        self._by0 += wx * ry
        self._by1 += ry
        self._bz0 += wx * rz
        self._bz1 += rz
        a00, a01, a11 = self._a00, self._a01, self._a11
        det = a00 * a11 - a01 * a01
        ey = (a11 * self._bz0 - a01 * self._bz1) / det
        ez = -(a11 * self._by0 - a01 * self._by1) / det
        norm = math.hypot(ey, ez)
        if norm > self.settings.max_tilt_rad:
            scale = self.settings.max_tilt_rad / norm
            ey, ez = ey * scale, ez * scale
            norm = math.hypot(ey, ez)
        self.tilt_rad = np.array([ey, ez])
        self.samples += 1
        rot = _rotation_about_yz(ey, ez, norm)
        self.correction = rot if self._straight else self.mount.T @ rot @ self.mount
        return True

    def correct(self, vec) -> list[float]:
        """A raw reading (3,) turned by the current correction (the reading itself while that is the
        identity)."""
        m = self._rows
        if m is None:
            return vec
        x, y, z = vec
        return [m[0][0] * x + m[0][1] * y + m[0][2] * z,
                m[1][0] * x + m[1][1] * y + m[1][2] * z,
                m[2][0] * x + m[2][1] * y + m[2][2] * z]


def _rotation_about_yz(ey: float, ez: float, angle: float) -> np.ndarray:
    """The rotation matrix of the rotation vector ``(0, ey, ez)`` of length ``angle`` (rad): Rodrigues'
    formula ``I + sin(a)/a K + (1 - cos(a))/a² K²`` with ``1 - cos(a) = 2 sin²(a/2)`` (no cancellation
    for small angles); tested equal to scipy's ``Rotation.from_rotvec`` (``tests/test_mounting.py``)."""
    if angle == 0.0:
        return np.eye(3)
    k1 = math.sin(angle) / angle
    half = math.sin(0.5 * angle)
    k2 = 2.0 * half * half / (angle * angle)
    # K = [[0, -ez, ey], [ez, 0, 0], [-ey, 0, 0]];  K² = [[-(ey²+ez²), 0, 0], [0, -ez², ey ez], [0, ey ez, -ey²]]
    return np.array([[1.0 - k2 * (ey * ey + ez * ez), -k1 * ez, k1 * ey],
                     [k1 * ez, 1.0 - k2 * ez * ez, k2 * ey * ez],
                     [-k1 * ey, k2 * ey * ez, 1.0 - k2 * ey * ey]])
