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
from . import mounting_kernel as K


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


class HandMountings:
    """Every finger sensor's flexion-axis fit of one hand, kept in the flat arrays of the compiled
    kernels (``mounting_kernel.py``): per tick one call turns the raw readings (``correct``) and one
    adds the gyro samples (``fit``), the same arithmetic as ``HingeAxisFit`` on each sensor (its
    reference, ``HandMountingsReference``). ``previous`` hands over the fits of the sensors whose
    finger, phalanx and calibrated mounting stay the same."""

    def __init__(self, calibration, settings: MountingFitSettings = MountingFitSettings(),
                 previous: "HandMountings | None" = None):
        self.settings = settings
        self._st = np.array([settings.min_rate_rad_s, settings.max_tilt_rad])
        s = settings
        lam_e = (s.residual_std_rad_s / s.prior_std_rad) ** 2
        lam_b = (s.residual_std_rad_s / s.offset_std_rad_s) ** 2
        rows, meta, self.places = [], [], {}
        offset = 0
        for f, (name, geom) in enumerate(calibration.fingers.items()):
            base = geom.base_matrix()
            for sp in geom.sensors:
                mount = np.asarray(sp.mounting_matrix(), dtype=float)
                row = np.zeros(K.WIDTH)
                row[K.M0:K.M0 + 9] = mount.ravel()
                row[K.B0:K.B0 + 9] = base.ravel()
                row[K.C0:K.C0 + 9] = np.eye(3).ravel()
                row[K.A00], row[K.A11] = lam_e, lam_b
                row[K.STRAIGHT] = float(np.array_equal(mount, np.eye(3)))
                kept = previous.places.get(sp.id) if previous is not None else None
                if kept is not None and kept[1:] == (name, sp.phalanx) and \
                        np.array_equal(previous.state[kept[0], K.M0:K.M0 + 9], row[K.M0:K.M0 + 9]):
                    row[K.C0:] = previous.state[kept[0], K.C0:]
                self.places[sp.id] = (len(rows), name, sp.phalanx)
                rows.append(row)
                meta.append((f, sp.phalanx, offset))
            offset += geom.n_phalanges
        self.state = np.ascontiguousarray(np.array(rows, dtype=float).reshape(len(rows), K.WIDTH))
        self._meta = np.array(meta, dtype=np.int64).reshape(len(meta), 3)
        self._rows: dict[tuple, np.ndarray] = {}

    def __bool__(self) -> bool:
        return bool(self.places)

    def rows(self, ids: tuple) -> np.ndarray:
        """The state rows of a tick's sensor ids (-1: no fit), kept per order of ids (a glove sends
        its sensors in the same order tick after tick)."""
        idx = self._rows.get(ids)
        if idx is None:
            if len(self._rows) > 64:
                self._rows.clear()
            places = self.places
            idx = self._rows[ids] = np.array([places[s][0] if s in places else -1 for s in ids], dtype=np.int64)
        return idx

    def correct(self, idx: np.ndarray, raw: np.ndarray) -> np.ndarray:
        """A tick's raw readings ``raw`` (k, 2, 3) (gyro, accelerometer) turned by their sensors'
        current corrections (``HingeAxisFit.correct``)."""
        out = np.empty_like(raw)
        K.correct(self.state, idx, raw, out)
        return out

    def fit(self, idx: np.ndarray, raw: np.ndarray, hand_flat: np.ndarray, phi: np.ndarray,
            started: np.ndarray) -> int:
        """A tick's raw samples into the fits (``HingeAxisFit.add`` on each whose finger ``started``
        (per finger) and which flexes fast enough), with the hand's motion ``BaseMotion.flat`` and the
        fingers' joint angles ``phi`` one after another in calibration order. Returns the number used."""
        return K.fit(self.state, self._meta, idx, raw, hand_flat, phi, started, self._st)

    def tilt_rad(self, sensor_id: str) -> np.ndarray:
        """``(ε_y, ε_z)`` of a sensor, rad."""
        j = self.places[sensor_id][0]
        return self.state[j, K.TILT_Y:K.TILT_Z + 1].copy()

    def correction(self, sensor_id: str) -> np.ndarray:
        """The rotation applied to a sensor's raw readings (3, 3)."""
        j = self.places[sensor_id][0]
        return self.state[j, K.C0:K.C0 + 9].reshape(3, 3).copy()

    def samples(self, sensor_id: str) -> int:
        return int(self.state[self.places[sensor_id][0], K.SAMPLES])


class HandMountingsReference(HandMountings):
    """``HandMountings`` with one ``HingeAxisFit`` per sensor, sample by sample in Python: the reference
    of the compiled kernels (``tests/test_mounting.py``)."""

    def __init__(self, calibration, settings: MountingFitSettings = MountingFitSettings(),
                 previous: "HandMountingsReference | None" = None):
        super().__init__(calibration, settings)
        self._fits: dict[int, HingeAxisFit] = {}
        self._bases, self._ids = [], []
        for name, geom in calibration.fingers.items():
            for sp in geom.sensors:
                j = self.places[sp.id][0]
                old = previous.places.get(sp.id) if previous is not None else None
                mount = sp.mounting_matrix()
                keep = old is not None and old[1:] == (name, sp.phalanx) and \
                    np.array_equal(previous._fits[old[0]].mount, mount)
                self._fits[j] = previous._fits[old[0]] if keep else HingeAxisFit(mount, settings)
                self._bases.append(geom.base_matrix())

    def correct(self, idx, raw):
        out = np.array(raw, dtype=float)
        for r, j in enumerate(idx.tolist()):
            if j >= 0 and self._fits[j].samples:
                out[r] = [self._fits[j].correct(list(raw[r, 0])), self._fits[j].correct(list(raw[r, 1]))]
        return out

    def fit(self, idx, raw, hand_flat, phi, started):
        w_metacarpus = hand_flat[:9].reshape(3, 3).T @ hand_flat[12:15]
        used = 0
        for r, j in enumerate(idx.tolist()):
            if j < 0:
                continue
            f, phalanx, offset = self._meta[j].tolist()
            if not started[f]:
                continue
            w_base = (self._bases[j].T @ w_metacarpus).tolist()
            used += self._fits[j].add(raw[r, 0].tolist(), sum(phi[offset:offset + phalanx + 1].tolist()), w_base)
        return used

    def tilt_rad(self, sensor_id):
        return self._fits[self.places[sensor_id][0]].tilt_rad.copy()

    def correction(self, sensor_id):
        return np.array(self._fits[self.places[sensor_id][0]].correction, dtype=float)

    def samples(self, sensor_id):
        return self._fits[self.places[sensor_id][0]].samples
