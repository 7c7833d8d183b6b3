"""Sensor error models: IMU white noise and zero offset (MPU-9250 figures, quoted with their source
in ``model.units``), optical tracker errors.

White noise of density ``D`` sampled at ``f_s`` (bandwidth ``f_s/2``) has a standard deviation of
``D · √(f_s / 2)`` per sample. The zero offset is a constant per sensor and axis, drawn uniformly
inside the datasheet tolerance (the tolerance is a bound, not a standard deviation; the resulting
standard deviation is tolerance/√3).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..model.units import (
    DEG,
    MPU9250_ACC_NOISE_DENSITY_M_S2_RTHZ,
    MPU9250_ACC_ZERO_G_TOLERANCE_M_S2,
    MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ,
    MPU9250_GYRO_ZRO_TOLERANCE_RAD_S,
)

NoiseKind = Literal["none", "white", "offset", "both", "realistic"]
PAPER_NOISE_KINDS: tuple[str, ...] = ("none", "white", "offset", "both")
NOISE_KINDS: tuple[str, ...] = PAPER_NOISE_KINDS + ("realistic",)
"""``realistic`` is the datasheet-and-body profile of ``realistic.py``; the others are the paper's series."""


@dataclass(frozen=True)
class ImuErrorModel:
    """IMU errors. Densities in unit/√Hz, offsets as per-axis bounds.

    Attributes:
        white_noise: add white noise.
        zero_offset: add a constant per-axis offset.
        gyro_noise_density_rad_s_rthz: rad/s/√Hz (MPU-9250: 0.01 deg/s/√Hz).
        acc_noise_density_m_s2_rthz: m/s²/√Hz (MPU-9250: 300 µg/√Hz).
        gyro_offset_bound_rad_s: ZRO tolerance, rad/s (MPU-9250: ±5 deg/s).
        acc_offset_bound_m_s2: zero-g tolerance per sensor axis (x, y, z), m/s² (MPU-9250: 60, 60, 80 mg).
    """

    white_noise: bool = False
    zero_offset: bool = False
    gyro_noise_density_rad_s_rthz: float = MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ
    acc_noise_density_m_s2_rthz: float = MPU9250_ACC_NOISE_DENSITY_M_S2_RTHZ
    gyro_offset_bound_rad_s: float = MPU9250_GYRO_ZRO_TOLERANCE_RAD_S
    acc_offset_bound_m_s2: tuple[float, float, float] = MPU9250_ACC_ZERO_G_TOLERANCE_M_S2

    @staticmethod
    def named(kind: str) -> "ImuErrorModel":
        """``none``, ``white``, ``offset`` or ``both`` (the paper's three series plus error-free)."""
        if kind not in PAPER_NOISE_KINDS:
            raise ValueError(f"noise must be one of {PAPER_NOISE_KINDS}, got {kind!r}")
        return ImuErrorModel(white_noise=kind in ("white", "both"), zero_offset=kind in ("offset", "both"))

    def gyro_sigma(self, rate_hz: float) -> float:
        """Per-sample standard deviation of gyro white noise at ``rate_hz``, rad/s."""
        return self.gyro_noise_density_rad_s_rthz * np.sqrt(rate_hz / 2.0)

    def acc_sigma(self, rate_hz: float) -> float:
        """Per-sample standard deviation of accelerometer white noise at ``rate_hz``, m/s²."""
        return self.acc_noise_density_m_s2_rthz * np.sqrt(rate_hz / 2.0)

    def draw_offsets(self, rng: np.random.Generator, n_sensors: int) -> tuple[np.ndarray, np.ndarray]:
        """Constant offsets ``(gyro (S,3) rad/s, acc (S,3) m/s²)``; zeros when ``zero_offset`` is off."""
        if not self.zero_offset:
            return np.zeros((n_sensors, 3)), np.zeros((n_sensors, 3))
        g = rng.uniform(-1.0, 1.0, (n_sensors, 3)) * self.gyro_offset_bound_rad_s
        a = rng.uniform(-1.0, 1.0, (n_sensors, 3)) * np.asarray(self.acc_offset_bound_m_s2)
        return g, a

    def corrupt(self, rng: np.random.Generator, gyr: np.ndarray, acc: np.ndarray, rate_hz: float,
                offsets: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Add offsets ``(S,3)`` and white noise to ideal readings of shape ``(N,S,3)``."""
        gyr = gyr + offsets[0]
        acc = acc + offsets[1]
        if self.white_noise:
            gyr = gyr + rng.normal(0.0, self.gyro_sigma(rate_hz), gyr.shape)
            acc = acc + rng.normal(0.0, self.acc_sigma(rate_hz), acc.shape)
        return gyr, acc


@dataclass(frozen=True)
class OpticalModel:
    """Optical tracker of the metacarpus pose.

    Attributes:
        rate_hz: pose rate, Hz (a headset's hand tracking: 90 Hz).
        latency_s: delay between the pose's measurement time ``t`` and its arrival, s.
        position_jitter_m: standard deviation of white position noise per axis, m.
        orientation_jitter_rad: standard deviation of white rotation noise per axis (small-angle), rad.
        occlusions_s: ``((start, end), ...)`` intervals during which poses arrive with ``valid: false``.
    """

    rate_hz: float = 90.0
    latency_s: float = 0.02
    position_jitter_m: float = 0.0005
    orientation_jitter_rad: float = 0.1 * DEG
    occlusions_s: tuple[tuple[float, float], ...] = ()

    @staticmethod
    def perfect(rate_hz: float = 90.0) -> "OpticalModel":
        return OpticalModel(rate_hz=rate_hz, latency_s=0.0, position_jitter_m=0.0, orientation_jitter_rad=0.0)

    def valid_mask(self, t: np.ndarray) -> np.ndarray:
        valid = np.ones(t.shape, dtype=bool)
        for a, b in self.occlusions_s:
            valid &= ~((t >= a) & (t < b))
        return valid
