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

**The offsets from a still hand.** The fast flexions teach the tilt, but they are few (seconds of them
in a minute) and a flexion is one-signed while it lasts, so the constant terms ``b`` learn slowly
from them. The residual's other error, the angle's, enters as ``δθ |w_yz|`` (the hand's rate across the
hinge turned by the wrong angle): while the hand turns across the hinge slower than ``still_rate_rad_s``
the cross axes read their offsets whatever the angle's error (0.6 deg/s at 3 deg and 0.2 rad/s), so
such samples of a finger flexing slower than ``min_rate_rad_s`` go into a second set of the same sums,
the offsets' own (``cross_offsets``), and not into the tilt's: their ``ω_x`` is small, so they would
tell the tilt little, and the tilt's residual from the hinge-axis leak is largest there. The hand's rate
is the optics', which is zero at their first pose and lags while the hand turns; a wrong rate enters a
still sample's residual in full, so one is taken only once the optics' fit window is full (the pipeline's
``HandMountings.admit_still``) and where the gyro's own cross axes agree the hand is still (below
``still_rate_rad_s`` plus the offsets' bound, ``still_gyro_margin_rad_s``). A gyro sample
with an axis at full scale is left out of both (its ``ω_x`` is too small, so a fist's peak would be
mis-fit into the tilt and, one-signed, into the offsets, for the session).

The fit turns both the gyro's and the accelerometer's readings by the estimated ``ε`` (the mounting is
one rotation for both), so every estimator reads them as if the sensor sat straight. It uses the
pipeline's current angle ``θ`` (the accelerometer's, which includes ``ε_x`` as the cross axes do) and
nothing the glove cannot give.

**The gyro's cross-axis leak into its hinge-axis reading.** A gyro's cross-axis sensitivity (MPU-9250
±2 %, Product Specification rev. 1.1, section 3.1) makes its hinge-axis reading
``f_x = ω_x + k_y ω_y + k_z ω_z + b_x``: a hand turning at 2-3 rad/s about the phalanx's other axes
reads as a flexion of 2-3 deg/s. The tilt fit above sees the *column* of the gyro's map (how a flexion
appears on the cross axes); for a rotation that is its row too, for cross-axis sensitivity it is not.
While the finger is still on its hand (``|f_x - w_x| <`` ``quiet_rate_rad_s``, with ``w_x`` the hand's
rate about the hinge axis from the optics), ``f_x - w_x = b_x + k_y f_y + k_z f_z``: a ridge regression
of that on ``[1, f_y, f_z]`` (readings turned by the tilt fit's current correction; priors ``k ~ 0 ±
cross_axis_std``, ``b_x ~ 0 ± offset_std``, residual ``residual_std_rad_s``) gives ``(k_y, k_z)``,
and the gyro's hinge-axis reading is corrected by them (``HingeAxisFit.correct_gyro``; the
accelerometer is not). Measured on tuning trials in the README's accuracy section.

**What a clipped gyro run missed.** A fast flexion of the whole finger turns the distal phalanx at up to
1.5 times the gyro's full scale (±2000 deg/s, MPU-9250), so its readings clip for tens of milliseconds
and the angle integrated from them misses up to 50 deg. Near its peak a smooth rate is a parabola, so
the part above the range is one too: rising into the clip at ``s`` (the reading's rise over the two
samples before it, per sample) and clipped for ``n`` samples, it peaks ``h = s n / 4`` above the range
(the parabola through both ends of the run with the entry slope) and missed ``(2/3) h n`` samples' worth
of rate, the area of a parabolic segment. Every estimator integrates it (``HingeAxisFit.reconstruct``,
per gyro axis of the raw reading). While the run lasts its length is not known yet, so each clipped
sample ``j`` (1, 2, ...) gets the excess of the parabola that would last ``2 j`` samples, ``s j / 2``
(twice its length so far: the median of a run's whole length when nothing else is known about it),
and the first reading after the run gets the rest, ``(2/3) h n`` less what its samples were given
(negative when the run ended sooner). For a parabola the integrated angle is then off by at most
about half of the whole missed angle during the run (``s n² / 12`` against ``s n² / 6``) instead of
all of it at the run's end; on the clipped runs of tuning trials 500-519 the angle's RMS error over
the clipped samples fell from 17.9 to 6.5 deg (largest 51.6 -> 24.6 deg). ``h`` is capped at the
range, and a run longer than ``clip_max_samples`` (no longer a peak) gets back nothing: what its
first samples were given is taken back after it. An estimator still treats the clipped samples as
saturated. (Extrapolating the parabola through the last three samples before the clip instead, to
fill in each clipped sample as it comes, missed by 18 deg RMS on the clipped runs of tuning trials
500-519 against 21.6 deg for no reconstruction; the run's length and the entry rise miss by 3.2 deg.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model.hand import FrozenFingers
from ..model.units import DEG, MPU9250_GYRO_OFFSET_STD_RAD_S, MPU9250_GYRO_ZRO_TOLERANCE_RAD_S
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
        cross_axis_std: prior std of each of the gyro's two cross-axis sensitivities of its hinge-axis
            reading (MPU-9250 ±2 %, uniform: 0.012); 0 leaves the hinge-axis reading as it is.
        quiet_rate_rad_s: samples whose rate relative to the hand (the hinge-axis reading less the
            hand's rate about the hinge axis) is below this feed the cross-axis fit: the finger is
            still on the hand, rad/s.
        clip_range_rad_s: the gyro's full scale (MPU-9250 ±2000 deg/s): a reading within 0.1 % of it is
            clipped, and the angle a clipped run missed is added after it (module docstring); 0: not.
        clip_max_samples: a clipped run longer than this many samples is not reconstructed.
        still_rate_rad_s: a sample slower than ``min_rate_rad_s`` still enters the regression while the hand
            turns across the hinge axis slower than this (``|(w_y, w_z)|``): its cross axes then read their
            offsets whatever the angle's error (an angle error ``δθ`` turns what they see of the hand's rate
            by ``δθ |w|``: 0.6 deg/s at 3 deg and 0.2 rad/s), so it tells the offsets (it carries little of
            the tilt, ``ω_x`` being small); 0: only fast flexions, rad/s. The optics' rate is zero at the
            first pose and lags while the hand turns, so a still sample is admitted only while the optics'
            fit window is full (``HandMountings.admit_still``, set by the pipeline) and where the gyro's own
            cross axes agree (``still_gyro_margin_rad_s``).
        still_gyro_margin_rad_s: a still sample's gyro cross-axis rate ``|(f_y, f_z)|`` must be below
            ``still_rate_rad_s`` plus this: what the offsets can add to it, the MPU-9250's zero-rate output
            bound (±5 deg/s per axis, Product Specification rev. 1.1, section 3.1) on both axes, ``√2 ×``;
            0: no such check, rad/s.
        fit_clipped: whether a gyro sample with an axis at full scale (``clip_range_rad_s``; with that 0
            every sample does) enters the fits; it should not: a clipped hinge-axis rate ``ω_x`` is too small, so the tilt term
            ``-ε_z ω_x`` is mis-fit at a fist's peak, and a flexion is one-signed, so the misfit lands in the
            offsets' constant terms, kept for the session (the sums never forget).
    """

    prior_std_rad: float = 1.7 * DEG
    offset_std_rad_s: float = MPU9250_GYRO_OFFSET_STD_RAD_S
    residual_std_rad_s: float = 0.3
    min_rate_rad_s: float = 2.0
    max_tilt_rad: float = 10.0 * DEG
    cross_axis_std: float = 0.012
    quiet_rate_rad_s: float = 0.5
    clip_range_rad_s: float = 2000.0 * DEG
    clip_max_samples: int = 40
    fit_clipped: bool = False
    still_rate_rad_s: float = 0.2
    still_gyro_margin_rad_s: float = math.sqrt(2.0) * MPU9250_GYRO_ZRO_TOLERANCE_RAD_S


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
        self._o = [lam_e, 0.0, lam_b, 0.0, 0.0, 0.0, 0.0]       # the same with the still samples (cross_offsets)
        self.samples = 0
        self.admit_still = True         # the pipeline's: whether the optics' rate is good enough for still samples
        self.still_gyro_rad_s = s.still_rate_rad_s + s.still_gyro_margin_rad_s \
            if s.still_gyro_margin_rad_s > 0 and s.still_rate_rad_s > 0 else 0.0
        self.tilt_rad = np.zeros(2)                  # (ε_y, ε_z)
        self._correction, self._rows = np.eye(3), None          # None: readings pass unchanged
        self._straight = bool(np.array_equal(self.mount, np.eye(3)))
        # the cross-axis fit: normal equations of the regressors [1, f_y, f_z] (3 x 3) and the right-hand
        # side; its solution's last two entries are the cross-axis sensitivities (k_y, k_z)
        lam_k = (s.residual_std_rad_s / s.cross_axis_std) ** 2 if s.cross_axis_std > 0 else 0.0
        self._qa = np.diag([lam_b, lam_k, lam_k])
        self._qb = np.zeros(3)
        self.cross_axis = np.zeros(2)
        self.quiet_samples = 0
        # per raw gyro axis: clipped samples in the current run, the rise into it, the last two
        # readings, how many of them there are and the rate added to the run's samples so far
        self._clip = [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0] for _ in range(3)]

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
        r = self.settings.clip_range_rad_s
        if r > 0 and not self.settings.fit_clipped and max(abs(g) for g in gyr) >= r * (1.0 - 1e-3):
            return False                # clipped: its rates are not what the sensor turned at
        w1, w2 = hand_rate_base[1], hand_rate_base[2]
        m = self._mount_rows
        gx, gy, gz = gyr
        wx = m[0][0] * gx + m[0][1] * gy + m[0][2] * gz          # f = M gyr, the reading in the phalanx frame
        f1 = m[1][0] * gx + m[1][1] * gy + m[1][2] * gz
        f2 = m[2][0] * gx + m[2][1] * gy + m[2][2] * gz
        if not self.flexing(gyr):
            self._add_quiet(gyr, hand_rate_base)
            still_rate = self.settings.still_rate_rad_s if self.admit_still else 0.0
            if not w1 * w1 + w2 * w2 < still_rate ** 2:
                return False
            bound = self.still_gyro_rad_s
            if bound > 0.0 and not f1 * f1 + f2 * f2 < bound * bound:
                return False            # the gyro's own cross axes see the hand turn: the optics' rate lags
            still = True
        else:
            still = False
        c, s = math.cos(theta), math.sin(theta)
        ry = f1 - (c * w1 + s * w2)
        rz = f2 - (-s * w1 + c * w2)
        if not (wx == wx and ry == ry and rz == rz):
            return False                # a NaN would stay in the sums for the session
        o = self._o                 # the offsets' normal equations: every sample used, still ones too
        o[0] += wx * wx
        o[1] += wx
        o[2] += 1.0
        o[3] += wx * ry
        o[4] += ry
        o[5] += wx * rz
        o[6] += rz
        if still:
            return False
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

    @property
    def cross_offsets(self) -> np.ndarray:
        """``(b_y, b_z)``: the gyro's cross-axis offsets as the regression of the cross-axis residuals on
        ``[ω_x, 1]`` solves them with the tilt (its prior ``0 ± offset_std``), rad/s; in the frame of the
        corrected reading ``R(ε) M g`` that the estimators read (to first order ``b_y + ε_z b_x`` and
        ``b_z - ε_y b_x`` of the calibrated phalanx frame's offsets: the regressor ``ω_x`` is the raw reading,
        ``b_x`` in it). The fast flexions and the samples of a still hand teach it (``still_rate_rad_s``,
        module docstring), clipped samples are left out, every sample weighs alike. A still sample is chosen by
        the optical hand rate, which is zero at the first pose and lags while the hand turns, and a wrong rate
        enters the residual in full: so it is taken only once the optics' window is full and where the gyro's
        own cross axes agree (``still_gyro_margin_rad_s``). Error left (RMS per axis over six sensors) on
        tuning trial 522: 2.97, 2.51 and 1.61 deg/s at 1, 3 and 12 s (3.66, 3.83 and 1.31 without those two
        checks, 3.26, 2.86 and 1.80 from the fast flexions alone, 3.3 with none taken off); on 521 1.14, 0.82
        and 0.30 (without the checks 0.68 at 3 s and 0.21 at 12 s, from the fast flexions alone 2.21 and
        0.58, none taken off 3.0)."""
        a00, a01, a11, by0, by1, bz0, bz1 = self._o
        det = a00 * a11 - a01 * a01
        return np.array([(a00 * by1 - a01 * by0) / det, (a00 * bz1 - a01 * bz0) / det])

    @property
    def cross_offsets_var(self) -> float:
        """The variance of each of ``cross_offsets`` as the regression's normal equations give it,
        ``σ² (A⁻¹)₁₁ = σ² a00 / det`` with ``σ = residual_std_rad_s`` (the prior's ``offset_std²`` before any
        sample), (rad/s)²; it takes every sample as independent with the fast flexions' residual std, so it is
        not calibrated (a review: the offsets' mean squared error was 0.13-0.36 of it on tuning trial 521 and
        1.7-3.1 times it on 522)."""
        a00, a01, a11 = self._o[:3]
        return self.settings.residual_std_rad_s ** 2 * a00 / (a00 * a11 - a01 * a01)

    def _add_quiet(self, gyr, hand_rate_base) -> bool:
        """A sample of a finger still on its hand into the cross-axis fit (module docstring): its
        hinge-axis reading (turned by the current correction, phalanx frame) less the hand's rate about
        the hinge axis against ``[1, f_y, f_z]``. Returns whether it was used."""
        if self.settings.cross_axis_std <= 0:
            return False
        f = self.mount @ np.asarray(self.correct(list(gyr)), dtype=float)
        r = f[0] - hand_rate_base[0]
        if not abs(r) < self.settings.quiet_rate_rad_s:
            return False
        reg = np.array([1.0, f[1], f[2]])
        self._qa = self._qa + np.outer(reg, reg)
        self._qb = self._qb + reg * r
        self.cross_axis = np.linalg.solve(self._qa, self._qb)[1:]
        self.quiet_samples += 1
        return True

    def reconstruct(self, gyr) -> list[float]:
        """A raw gyro reading (3,) with the angle a clipped run of each axis missed filled in while the
        run lasts and the rest added to the first reading after it (module docstring), the axes'
        records updated. Call it on every raw reading of the sensor, in order."""
        r = self.settings.clip_range_rad_s
        if r <= 0:
            return list(gyr)
        out = []
        for rec, g in zip(self._clip, gyr):
            n, rise, last1, last2, history, added = rec
            if abs(g) >= r * (1.0 - 1e-3):
                if n == 0.0:
                    rise = (1.0 if g > 0.0 else -1.0) * (last1 - last2) if history >= 2.0 else 0.0
                    added = 0.0
                n += 1.0
                # the parabola's excess at this sample if the run lasts twice as long as so far
                guess = min(0.5 * rise * n, r) if rise > 0.0 and n <= self.settings.clip_max_samples else 0.0
                rec[:] = [n, rise, g, last2, 0.0, added + guess]
                out.append(g + guess if g > 0.0 else g - guess)
                continue
            if n > 0.0:
                # the run's whole missed angle, (2/3) h n with h = s n / 4, less what its samples got
                total = (2.0 / 3.0) * min(0.25 * rise * n, r) * n \
                    if rise > 0.0 and n <= self.settings.clip_max_samples else 0.0
                out.append(g + (total - added) if last1 > 0.0 else g - (total - added))
            else:
                out.append(g)
            rec[:] = [0.0, rise, g, last1, min(history + 1.0, 2.0), 0.0]
        return out

    def correct_gyro(self, vec) -> list[float]:
        """A raw gyro reading (3,) turned by the current correction and with the cross-axis rates' leak
        into its hinge-axis reading taken off (``f_x - k_y f_y - k_z f_z`` in the phalanx frame)."""
        v = self.correct(vec)
        if not self.quiet_samples:
            return v
        f = self.mount @ np.asarray(v, dtype=float)
        leak = self.cross_axis[0] * f[1] + self.cross_axis[1] * f[2]
        return (np.asarray(v, dtype=float) - self.mount[0] * leak).tolist()

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
        st, state, meta, places, row_ids = _fresh_fits(calibration, settings)
        self._st, self.state, self._meta, self.places = st.copy(), state.copy(), meta.copy(), dict(places)
        if previous is not None:
            for j, (sid, name, phalanx) in enumerate(row_ids):
                kept = previous.places.get(sid)
                if kept is not None and kept[1:] == (name, phalanx) and \
                        np.array_equal(previous.state[kept[0], K.M0:K.M0 + 9], state[j, K.M0:K.M0 + 9]):
                    self.state[j, K.C0:] = previous.state[kept[0], K.C0:]
        self._rows: dict[tuple, np.ndarray] = {}

    compiled = True
    """Whether the fits live in ``state`` as the kernels keep them (the hand's steady tick calls the kernels
    on it directly: ``pipeline.tick_kernel``); the reference keeps its own."""

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
        K.correct(self.state, idx, raw, out, self._st)
        return out

    def admit_still(self, on: bool) -> None:
        """Whether the samples of a still hand are taken from now on (``MountingFitSettings.still_rate_rad_s``):
        only while the optics' rate is known, their fit window full of poses since they last came back (it is
        zero at the first pose and lags after it)."""
        self._st[K.ST_STILL_ON] = 1.0 if on else 0.0

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

    def cross_axis(self, sensor_id: str) -> np.ndarray:
        """``(k_y, k_z)``: the gyro's cross-axis sensitivities of its hinge-axis reading as fitted."""
        j = self.places[sensor_id][0]
        return self.state[j, K.LEAK_Y:K.LEAK_Z + 1].copy()

    def quiet_samples(self, sensor_id: str) -> int:
        return int(self.state[self.places[sensor_id][0], K.QUIET_SAMPLES])

    def cross_offsets(self, idx: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``(b_y, b_z)`` (k, 2) of the sensors in state rows ``idx`` (``rows``; -1: zeros), into ``out`` if
        given: the gyro's cross-axis offsets in the frame of the corrected reading as the tilt fit's regression
        on ``[ω_x, 1]`` solves them with the tilt (``HingeAxisFit.cross_offsets``), rad/s. An ``out`` of
        (k, 3) gets each one's variance in its third column (``HingeAxisFit.cross_offsets_var``; 0 where -1)."""
        if out is None:
            out = np.empty((len(idx), 2))
        K.cross_offsets(self.state, idx, out, self._st)
        return out


_FRESH: dict[tuple[int, int], tuple] = {}
"""``_fresh_fits`` of a shared calibration and settings object, by their ids (each entry keeps both alive)."""


def _fresh_fits(calibration, settings: MountingFitSettings) -> tuple:
    """``HandMountings``' arrays before any sample: ``(settings vector, state, meta, places, each row's sensor
    id, finger and phalanx)``, never changed (each hand copies them). Made once per shared calibration
    (``model.hand.FrozenFingers``: the same object for every hand on it, its fingers never changed) and
    settings object, else each time."""
    shared = type(calibration.fingers) is FrozenFingers
    key = (id(calibration), id(settings))
    hit = _FRESH.get(key) if shared else None
    if hit is not None and hit[0] is calibration and hit[1] is settings:
        return hit[2]
    st = np.array([settings.min_rate_rad_s, settings.max_tilt_rad,
                   settings.quiet_rate_rad_s if settings.cross_axis_std > 0 else 0.0,
                   settings.clip_range_rad_s, float(settings.clip_max_samples),
                   0.0 if settings.fit_clipped else settings.clip_range_rad_s,
                   settings.residual_std_rad_s ** 2, settings.still_rate_rad_s, 0.0, 1.0])
    if settings.still_gyro_margin_rad_s > 0 and settings.still_rate_rad_s > 0:
        st[K.ST_STILL_GYRO] = settings.still_rate_rad_s + settings.still_gyro_margin_rad_s
    s = settings
    lam_e = (s.residual_std_rad_s / s.prior_std_rad) ** 2
    lam_b = (s.residual_std_rad_s / s.offset_std_rad_s) ** 2
    lam_k = (s.residual_std_rad_s / s.cross_axis_std) ** 2 if s.cross_axis_std > 0 else 0.0
    rows, meta, places, row_ids = [], [], {}, []
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
            row[K.O00], row[K.O11] = lam_e, lam_b
            row[K.Q00], row[K.Q11], row[K.Q22] = lam_b, lam_k, lam_k
            row[K.STRAIGHT] = float(np.array_equal(mount, np.eye(3)))
            places[sp.id] = (len(rows), name, sp.phalanx)
            row_ids.append((sp.id, name, sp.phalanx))
            rows.append(row)
            meta.append((f, sp.phalanx, offset))
        offset += geom.n_phalanges
    fresh = (st, np.ascontiguousarray(np.array(rows, dtype=float).reshape(len(rows), K.WIDTH)),
             np.array(meta, dtype=np.int64).reshape(len(meta), 3), places, row_ids)
    if shared:
        for array in fresh[:3]:
            array.flags.writeable = False
        if len(_FRESH) >= 64:
            _FRESH.clear()
        _FRESH[key] = (calibration, settings, fresh)
    return fresh


class HandMountingsReference(HandMountings):
    """``HandMountings`` with one ``HingeAxisFit`` per sensor, sample by sample in Python: the reference
    of the compiled kernels (``tests/test_mounting.py``)."""

    compiled = False

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
            if j < 0:
                continue
            fit = self._fits[j]
            gyr = fit.reconstruct(raw[r, 0].tolist())
            out[r, 0] = gyr
            if fit.samples or fit.quiet_samples:
                out[r] = [fit.correct_gyro(gyr), fit.correct(list(raw[r, 1]))]
        return out

    def admit_still(self, on):
        super().admit_still(on)
        for fit in self._fits.values():
            fit.admit_still = bool(on)

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

    def cross_axis(self, sensor_id):
        return self._fits[self.places[sensor_id][0]].cross_axis.copy()

    def quiet_samples(self, sensor_id):
        return self._fits[self.places[sensor_id][0]].quiet_samples

    def cross_offsets(self, idx, out=None):
        b = np.array([self._fits[j].cross_offsets if j >= 0 else np.zeros(2) for j in idx.tolist()]).reshape(-1, 2)
        if out is not None and out.shape[1] > 2:
            var = [self._fits[j].cross_offsets_var if j >= 0 else 0.0 for j in idx.tolist()]
            b = np.column_stack([b, var])
        if out is not None:
            out[...] = b
        return b if out is None else out

