"""The switching estimator (paper 2.2.4-2.2.5): vector observation in slow motion, gyro integration in
fast motion, choosing per phalanx the method whose error bound is smaller.

Error bounds, per sensor ``k`` on phalanx ``i_k``:

* slow-motion (vector observation) error, eqs. 6-7:
  ``Δθ_g = (|μ̂| + acc_error) / |g_yz|`` with ``|μ̂| = (i_k + 1) l_max √(ω̇_max² + ω_max⁴)`` (eq. 6),
  where ``ω_max``, ``ω̇_max`` are the largest measured relative rates and rate changes of phalanges
  ``0..i_k`` (rates of unmeasured phalanges follow from the chain closure), ``g_yz`` the in-plane
  reference (``observations``) and ``acc_error`` the accelerometer's error (zero offset and noise),
  which the paper's bound leaves out; with a horizontal flexion plane ``Δθ_g = ∞``;
* fast-motion (integration) error, eq. 8 and step 2: ``Δθ_ω(t_i) = Δθ(t_{i-1}) + (t_i - t_{i-1}) |Δω|``.

Mode selection (section 2.2.5, steps 1-4): in fast mode switch to slow when ``Δθ_g < Δθ_ω`` and set
``Δθ := Δθ_g``; in slow mode switch to fast when ``Δθ_ω < Δθ_g``, continuing the integration from the
previous estimate, and set ``Δθ := Δθ_ω``; then estimate with the selected method.

A known initial estimate (the paper's "known accurate initial estimate") starts in fast mode with
``Δθ = 0``; otherwise the first vector observation starts slow mode with ``Δθ = Δθ_g``.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ..model.units import MPU9250_ACC_OFFSET_STD_M_S2, MPU9250_GYRO_OFFSET_STD_RAD_S
from .base import LOST_RATE_RAD_S, MODE_FAST, MODE_SLOW, EstimatorSettings, FingerEstimator, FingerSamples, FingerTrack
from .integration import rk4_step_linear_rate
from .observations import vector_observation


class SwitchingSettings(EstimatorSettings):
    gyro_error_rad_s: float = Field(MPU9250_GYRO_OFFSET_STD_RAD_S, gt=0.0,
                                    description="|Δω|, average gyro error, rad/s (MPU-9250 ZRO ±5 deg/s, as its std)")
    acc_error_m_s2: float = Field(MPU9250_ACC_OFFSET_STD_M_S2, ge=0.0,
                                  description="accelerometer error magnitude, m/s² (MPU-9250 zero-g ±60-80 mg, as its std)")
    min_inplane_m_s2: float = Field(1e-6, gt=0.0, description="in-plane reference below which Δθ_g = ∞, m/s²")


class Switching(FingerEstimator):
    name = "switching"
    Settings = SwitchingSettings

    def slow_error_bound(self, rates: np.ndarray, rate_changes: np.ndarray, inplane: np.ndarray) -> np.ndarray:
        """``Δθ_g`` (eq. 7) per sensor from relative rates and their derivatives per sensor (..., S)."""
        mu = self.obs.acceleration_bound(self.closure, rates, rate_changes)                   # eq. 6
        with np.errstate(divide="ignore"):
            bound = (mu + self.settings.acc_error_m_s2) / inplane                              # eq. 7
        return np.where(inplane > self.settings.min_inplane_m_s2, bound, np.inf)

    def _init_state(self, gyr, acc, hand, theta0):
        rate = self.obs.relative_rate(gyr, hand)
        shape = self.batch_shape + (self.n_sensors,)
        if theta0 is not None:
            theta = np.array(theta0[..., self.obs.phalanx], dtype=float)
            return {"theta": theta, "rate": rate, "error": np.zeros(shape), "mode": np.full(shape, MODE_FAST, np.int8)}
        theta, inplane = vector_observation(self.obs, self.vector_closure, acc, hand, self.gravity_world)
        err = self.slow_error_bound(rate, np.zeros(shape), inplane)
        # no information at all (horizontal flexion plane): integrate from the held estimate
        mode = np.where(np.isfinite(err), MODE_SLOW, MODE_FAST).astype(np.int8)
        return {"theta": theta, "rate": rate, "error": err, "mode": mode}

    def reference_lost(self, duration_s: float) -> None:
        # the integration bound grows as if the hand had turned unseen at the lost-optics rate (eq. 8)
        if self._state is not None:
            self._state["error"] = self._state["error"] + LOST_RATE_RAD_S * duration_s

    def _observe(self, gyr, acc, hand, prev_rate, dt):
        """Steps 1-2 for samples (..., S): rates, vector observation and its error bound. Depends on
        the previous sample only through ``prev_rate`` and ``dt``, so batch mode evaluates it for all
        samples at once."""
        rate = self.obs.relative_rate(gyr, hand)
        with np.errstate(divide="ignore", invalid="ignore"):
            rate_change = np.where(dt > 0, (rate - prev_rate) / np.where(dt > 0, dt, 1.0), 0.0)
        theta_g, inplane = vector_observation(self.obs, self.vector_closure, acc, hand, self.gravity_world)
        return rate, theta_g, self.slow_error_bound(rate, rate_change, inplane)

    def _select(self, state, dt, rate, theta_g, err_g):
        """Steps 3-4 (the only recursive part)."""
        err_w = state["error"] + dt * self.settings.gyro_error_rad_s                           # eq. 8
        fast = state["mode"] == MODE_FAST                                                      # step 3
        now_fast = np.where(fast, ~(err_g < err_w), err_w < err_g)
        error = np.where(now_fast, err_w, err_g)
        theta_w = rk4_step_linear_rate(state["theta"], state["rate"], rate, dt)                 # step 4
        theta = np.where(now_fast, theta_w, theta_g)
        mode = np.where(now_fast, MODE_FAST, MODE_SLOW).astype(np.int8)
        return {"theta": theta, "rate": rate, "error": error, "mode": mode}, theta, mode

    def _step(self, state, dt, gyr, acc, hand):
        return self._select(state, dt, *self._observe(gyr, acc, hand, state["rate"], dt))

    def run(self, samples: FingerSamples) -> FingerTrack:
        """Steps 1-2 vectorised over all samples, then a lean loop over steps 3-4."""
        return self._run_split(samples, self._observe, self._select)
