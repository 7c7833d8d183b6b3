"""Complementary filter baseline (comparison paper II.C.2, after Comotti et al.): an orientation from
the reference vectors by Gauss-Newton, merged with the gyro-integrated orientation that starts from
the filter's own last output, ``θ_t = α (θ_{t-1} + ∫ω dt) + (1 - α) θ_obs``.

In the planar finger model the reference vectors are gravity (from the accelerometer, hand
acceleration removed) and the flexion-plane normal (from the optical pose, replacing the
magnetometer); the orientation that aligns both exactly is a rotation about the hinge axis by the
vector-observation angle, so the Gauss-Newton stage converges in one step to ``vector`` (2.2.2) and
is computed in closed form. The comparison paper ran ``α = 0.85`` (chosen in pilot experiments at a
100 Hz accelerometer rate); that is the default here. Where the observation carries no information
(horizontal flexion plane) only the gyro term is used.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from .base import MODE_FUSED, EstimatorSettings, FingerEstimator, FingerSamples, FingerTrack
from .integration import rk4_step_linear_rate
from .observations import initial_sensor_theta, vector_observation


class ComplementarySettings(EstimatorSettings):
    alpha: float = Field(0.85, ge=0.0, le=1.0, description="weight of the gyro-propagated angle per sample, dimensionless")
    min_inplane_m_s2: float = Field(1.0, gt=0.0, description="in-plane reference below which the observation is ignored, m/s²")


class Complementary(FingerEstimator):
    name = "cf"
    Settings = ComplementarySettings

    def _init_state(self, gyr, acc, hand, theta0):
        return {"theta": initial_sensor_theta(self.obs, acc, hand, theta0, self.gravity_world), "rate": self.obs.relative_rate(gyr, hand)}

    def _observe(self, gyr, acc, hand, prev_rate=None, dt=None):
        rate = self.obs.relative_rate(gyr, hand)
        theta_obs, inplane = vector_observation(self.obs, self.vector_closure, acc, hand, self.gravity_world)
        return rate, theta_obs, inplane >= self.settings.min_inplane_m_s2

    def _blend(self, state, dt, rate, theta_obs, informative):
        gyro = rk4_step_linear_rate(state["theta"], state["rate"], rate, dt)
        # blend on the circle: the observation is moved next to the gyro angle first
        obs = gyro + np.mod(theta_obs - gyro + np.pi, 2.0 * np.pi) - np.pi
        alpha = np.where(informative, self.settings.alpha, 1.0)
        theta = alpha * gyro + (1.0 - alpha) * obs
        return {"theta": theta, "rate": rate}, theta, np.full(theta.shape, MODE_FUSED, np.int8)

    def _step(self, state, dt, gyr, acc, hand):
        return self._blend(state, dt, *self._observe(gyr, acc, hand))

    def run(self, samples: FingerSamples) -> FingerTrack:
        """Observations vectorised over all samples, then a lean loop over the blend."""
        return self._run_split(samples, self._observe, self._blend)
