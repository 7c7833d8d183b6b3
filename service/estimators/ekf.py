"""EKF baseline (comparison paper II.C.1) on ``filterpy``: one error-state EKF per sensor with the
orientation quaternion and the gyro bias (``rigid.ekf``), measuring the accelerometer against
gravity plus the finger's kinematic acceleration (eq. 2, from the previous estimate, as the modified
Madgwick filter does) and, replacing the magnetometer, the flexion-plane normal from the optical
pose against the hinge axis in sensor coordinates. The phalanx angle is extracted relative to the
metacarpus.

Streaming mode runs each predict/update through ``filterpy.kalman.ExtendedKalmanFilter``; batch
mode runs the same equations vectorised over samples' sensors and runs (``estimators.kalman``).

What the defaults do not do: the accelerometer's zero offset is not a state (as in the comparison
paper), it is only covered by the accelerometer noise ``acc_noise_m_s2``; so a constant offset
biases the estimate by up to ``offset / g`` rad in slow motion.
"""
from __future__ import annotations

import contextlib

import numpy as np
from pydantic import Field

from ..model import quaternion as quat
from ..model.units import DEG, MPU9250_ACC_OFFSET_STD_M_S2, MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ, MPU9250_GYRO_OFFSET_STD_RAD_S
from .base import MODE_FUSED, EstimatorSettings, FingerEstimator, FingerSamples, FingerTrack, lost_optics_variance
from .observations import initial_sensor_theta
from .rigid.ekf import BatchedKalman, FilterpyKalman, inject, measurement_model, process_model


class EkfSettings(EstimatorSettings):
    gyro_noise_density_rad_s_rthz: float = Field(MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ, gt=0.0, description="gyro white noise, rad/s/√Hz (MPU-9250)")
    gyro_bias_walk_rad_s_rts: float = Field(1e-5, ge=0.0, description="gyro bias random walk, rad/s/√s")
    initial_bias_std_rad_s: float = Field(MPU9250_GYRO_OFFSET_STD_RAD_S, gt=0.0, description="prior std of the gyro bias, rad/s")
    initial_angle_std_rad: float = Field(1.0 * DEG, gt=0.0, description="prior std of the attitude when the initial configuration is given, rad")
    unknown_angle_std_rad: float = Field(10.0 * DEG, gt=0.0, description="prior std of the attitude from a first vector observation, rad")
    acc_noise_m_s2: float = Field(MPU9250_ACC_OFFSET_STD_M_S2, gt=0.0, description="accelerometer error std incl. unmodelled offset, m/s²")
    kinematic_uncertainty: float = Field(0.2, ge=0.0, description="added accelerometer std per m/s² of the eq. 6 acceleration bound")
    hinge_noise: float = Field(0.02, gt=0.0, description="std of the hinge-axis (unit vector) measurement, dimensionless")
    second_reference: bool = Field(True, description="measure the flexion-plane normal (replaces the magnetometer)")
    kinematic_acceleration: bool = Field(True, description="include g_k of eq. 2 in the accelerometer reference")


class Ekf(FingerEstimator):
    name = "ekf"
    Settings = EkfSettings

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._kalman = FilterpyKalman()

    def _init_state(self, gyr, acc, hand, theta0):
        s = self.settings
        theta = initial_sensor_theta(self.obs, acc, hand, theta0, self.gravity_world)
        q = quat.from_matrix(self.obs.sensor_theta_to_rotation(hand, theta))
        att = s.initial_angle_std_rad if theta0 is not None else s.unknown_angle_std_rad
        P = np.zeros(theta.shape + (6, 6))
        P[..., :3, :3] = att**2 * np.eye(3)
        P[..., 3:, 3:] = s.initial_bias_std_rad_s**2 * np.eye(3)
        return {"q": q, "bias": np.zeros(theta.shape + (3,)), "P": P, "theta": theta,
                "rate": self.obs.relative_rate(gyr, hand)}

    def reference_lost(self, duration_s: float) -> None:
        if self._state is not None:
            self._state["P"][..., :3, :3] += lost_optics_variance(duration_s) * np.eye(3)

    def _step(self, state, dt, gyr, acc, hand):
        s = self.settings
        rate = self.obs.relative_rate(gyr, hand)
        rate_change = self.obs.rate_change(rate, state["rate"], dt)
        refs_w, refs_s = self.obs.reference_pairs(self.closure, hand, state["theta"], rate, rate_change, acc,
                                                  self.gravity_world, s.kinematic_acceleration, s.second_reference)
        q, F, Q = process_model(state["q"], state["bias"], gyr, dt, s.gyro_noise_density_rad_s_rthz,
                                s.gyro_bias_walk_rad_s_rts)
        P = self._kalman.predict(state["P"], F, Q)
        mu = self.obs.acceleration_bound(self.closure, rate, rate_change)
        sigmas = [np.hypot(s.acc_noise_m_s2, s.kinematic_uncertainty * mu)]
        if s.second_reference:
            sigmas.append(np.full(mu.shape, s.hinge_noise))
        y, H, R = measurement_model(q, refs_w, refs_s, sigmas)
        dx, P = self._kalman.update(P, H, R, y)
        q, bias = inject(q, state["bias"], dx)
        theta = self.obs.rotation_to_sensor_theta(hand, quat.to_matrix(q), state["theta"])
        new = {"q": q, "bias": bias, "P": P, "theta": theta, "rate": rate}
        return new, theta, np.full(theta.shape, MODE_FUSED, np.int8)

    @contextlib.contextmanager
    def _batched(self):
        saved, self._kalman = self._kalman, BatchedKalman()
        try:
            yield
        finally:
            self._kalman = saved

    def run(self, samples: FingerSamples) -> FingerTrack:
        """The same steps with the vectorised Kalman equations instead of filterpy's per-filter objects."""
        with self._batched():
            return super().run(samples)
