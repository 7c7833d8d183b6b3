"""Gyro integration (paper 2.2.3): ``θ_{k,t} = int(θ_{k,t-1}, ω)`` from a known initial estimate.

The integrated rate is the phalanx's rate relative to the metacarpus about the hinge axis
(``observations.relative_rate``: gyro minus the hand's angular velocity from the optics). The step
is the classical Runge-Kutta (RK4) step of ``θ̇ = ω(t)`` with ``ω`` linearly interpolated between
samples; for this scalar equation, whose right side does not depend on ``θ``, RK4 reduces exactly to
the trapezoid rule ``θ_t = θ_{t-1} + dt (ω_{t-1} + ω_t) / 2``, which is what is computed.

Without an initial estimate the first sample's vector observation is used.
"""
from __future__ import annotations

import numpy as np

from .base import MODE_FAST, EstimatorSettings, FingerEstimator, FingerSamples, FingerTrack
from .observations import initial_sensor_theta


def rk4_step_linear_rate(theta: np.ndarray, rate_prev: np.ndarray, rate: np.ndarray, dt: float) -> np.ndarray:
    """RK4 for ``θ̇ = ω(t)``, ``ω`` linear on the step: k1 = ω0, k2 = k3 = (ω0+ω1)/2, k4 = ω1."""
    mid = 0.5 * (rate_prev + rate)
    return theta + dt / 6.0 * (rate_prev + 4.0 * mid + rate)


class IntegrationSettings(EstimatorSettings):
    pass


class GyroIntegration(FingerEstimator):
    name = "integration"
    Settings = IntegrationSettings

    def _init_state(self, gyr, acc, hand, theta0):
        return {"theta": initial_sensor_theta(self.obs, acc, hand, theta0, self.gravity_world), "rate": self.obs.relative_rate(gyr, hand)}

    def _step(self, state, dt, gyr, acc, hand):
        rate = self.obs.relative_rate(gyr, hand)
        theta = rk4_step_linear_rate(state["theta"], state["rate"], rate, dt)
        return {"theta": theta, "rate": rate}, theta, np.full(theta.shape, MODE_FAST, dtype=np.int8)

    def run(self, samples: FingerSamples) -> FingerTrack:
        """Vectorised: the same increments, summed in the same order by ``np.cumsum``."""
        self._validate_batch(samples)
        n = len(samples)
        if n == 0:
            return super().run(samples)
        rate = self.obs.relative_rate(samples.gyr, samples.hand)                    # (N, *B, S)
        if self._state is None:
            first = samples.sample(0)
            self._state = self._init_state(first[1], first[2], first[3], self._initial_theta)
            dt0 = 0.0
        else:
            dt0 = float(samples.t[0]) - self._t_last  # type: ignore[operator]
        t = np.asarray(samples.t, dtype=float)
        dt = np.diff(t, prepend=t[0] - dt0).reshape((n,) + (1,) * (rate.ndim - 1))
        prev = np.concatenate([self._state["rate"][None], rate[:-1]], axis=0)
        increments = rk4_step_linear_rate(0.0, prev, rate, dt)                      # the same step, from 0
        theta = np.cumsum(np.concatenate([self._state["theta"][None], increments], axis=0), axis=0)[1:]
        self._state = {"theta": theta[-1].copy(), "rate": rate[-1].copy()}
        self._t_last = float(t[-1])
        return self._track(t, theta, np.full(theta.shape, MODE_FAST, dtype=np.int8))
