"""Unit factors and the IMU datasheet figures, written once.

Everything inside the service is SI (DESIGN.md "Conventions"); degrees and milli-g appear only
where a figure is quoted from a source (a datasheet, a clinical range) and are converted here.

MPU-9250 Product Specification, revision 1.1 (InvenSense, 2014; paper ref. [34]), the IMU the
paper's glove carries. The simulator draws its sensor errors from these figures and the
estimators take their default priors from them, both from this module:

* gyroscope rate noise spectral density 0.01 deg/s/√Hz (section 3.1, "Rate Noise Spectral Density");
* gyroscope initial zero-rate-output (ZRO) tolerance ±5 deg/s (section 3.1, "Initial ZRO Tolerance");
* accelerometer noise power spectral density 300 µg/√Hz (section 3.2);
* accelerometer initial zero-g output tolerance ±60 mg on X and Y, ±80 mg on Z (section 3.2).

A tolerance is a bound, not a standard deviation: an offset drawn uniformly inside ``±b`` has the
standard deviation ``b/√3``, which is what the estimators' priors use.
"""
from __future__ import annotations

import numpy as np

from .frames import GRAVITY_M_S2

DEG = np.pi / 180.0
"""One degree, rad."""
MG = 1e-3 * GRAVITY_M_S2
"""One milli-g, m/s² (with the service's gravity magnitude)."""

MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ = 0.01 * DEG
"""Gyroscope rate noise spectral density, rad/s/√Hz."""
MPU9250_GYRO_ZRO_TOLERANCE_RAD_S = 5.0 * DEG
"""Gyroscope initial zero-rate-output tolerance (a bound, per axis), rad/s."""
MPU9250_ACC_NOISE_DENSITY_M_S2_RTHZ = 300e-6 * GRAVITY_M_S2
"""Accelerometer noise power spectral density, m/s²/√Hz."""
MPU9250_ACC_ZERO_G_TOLERANCE_M_S2 = (60 * MG, 60 * MG, 80 * MG)
"""Accelerometer initial zero-g output tolerance (bounds on x, y, z), m/s²."""
MPU9250_ACC_ZERO_G_TYPICAL_M_S2 = 70.0 * MG
"""One figure for the accelerometer zero-g tolerance of any axis (between the 60 and 80 mg), m/s²."""

MPU9250_GYRO_OFFSET_STD_RAD_S = MPU9250_GYRO_ZRO_TOLERANCE_RAD_S / np.sqrt(3.0)
"""Standard deviation of a gyro offset uniform inside the ZRO tolerance, rad/s."""
MPU9250_ACC_OFFSET_STD_M_S2 = MPU9250_ACC_ZERO_G_TYPICAL_M_S2 / np.sqrt(3.0)
"""Standard deviation of an accelerometer offset uniform inside the typical zero-g tolerance, m/s²."""
