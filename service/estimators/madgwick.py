"""The modified Madgwick filter (paper 2.3, eqs. 9-19): one orientation quaternion per sensor,
corrected toward two reference vectors, gravity (with the finger's kinematic acceleration ``g_k``
of eq. 2 from the previous estimate) and the flexion-plane normal from the optical pose, which
replaces the magnetometer. The phalanx angle is then extracted relative to the metacarpus.

The quaternion is the sensor's orientation relative to the world (``E``), so the raw gyro is
integrated (eq. 9); the hand's rotation enters through the references. The core step is
``rigid.madgwick.madgwick_step``.

Adaptive beta (the closing remark of 2.3.2): with ``adaptive_beta`` the gain is lowered while the
finger accelerates, ``β_t = β · a_ref / (a_ref + |μ̂|)`` with ``|μ̂|`` the eq. 6 bound from the
measured rates, so spurious accelerations disturb the estimate less during fast movements.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ..model import quaternion as quat
from .base import MODE_FUSED, EstimatorSettings, FingerEstimator
from .observations import initial_sensor_theta
from .rigid.madgwick import madgwick_step


class MadgwickSettings(EstimatorSettings):
    beta: float = Field(0.03, ge=0.0, description="gradient-step gain β of eq. 18, rad/s")
    adaptive_beta: bool = Field(False, description="lower β during fast motion (2.3.2)")
    adaptive_ref_m_s2: float = Field(2.0, gt=0.0, description="acceleration at which adaptive β halves, m/s²")
    kinematic_acceleration: bool = Field(True, description="include g_k of eq. 2 in the gravity reference (eq. 11)")
    second_reference: bool = Field(True, description="use the flexion-plane normal as second reference vector")


class Madgwick(FingerEstimator):
    name = "madgwick"
    Settings = MadgwickSettings

    def _init_state(self, gyr, acc, hand, theta0):
        theta = initial_sensor_theta(self.obs, acc, hand, theta0, self.gravity_world)
        q = quat.from_matrix(self.obs.sensor_theta_to_rotation(hand, theta))
        return {"q": q, "theta": theta, "rate": self.obs.relative_rate(gyr, hand)}

    def _step(self, state, dt, gyr, acc, hand):
        s = self.settings
        rate = self.obs.relative_rate(gyr, hand)
        rate_change = self.obs.rate_change(rate, state["rate"], dt)
        refs_world, refs_sensor = self.obs.reference_pairs(self.closure, hand, state["theta"], rate, rate_change, acc,
                                                           self.gravity_world, s.kinematic_acceleration,
                                                           s.second_reference)
        beta = s.beta
        if s.adaptive_beta:
            mu = self.obs.acceleration_bound(self.closure, rate, rate_change)
            beta = s.beta * s.adaptive_ref_m_s2 / (s.adaptive_ref_m_s2 + mu)
        q = madgwick_step(state["q"], gyr, dt, beta, refs_world, refs_sensor)
        theta = self.obs.rotation_to_sensor_theta(hand, quat.to_matrix(q), state["theta"])
        return {"q": q, "theta": theta, "rate": rate}, theta, np.full(theta.shape, MODE_FUSED, np.int8)
