"""Vector observation (paper 2.2.2): each phalanx angle from the direction of the specific force in
the flexion plane, with the hand's acceleration removed.

``θ_k = atan2(u_z, u_y) - atan2(f_z, f_y)`` (the paper's ``atan2(f'_3, f'_2)`` generalised to a
hand in any orientation; ``observations.vector_angle``). The finger's own acceleration ``μ`` is
neglected (eq. 5: valid for slow motion). The hand's rotation terms at the sensor need the sensor's
position, which needs ``θ``: two passes, the first with the finger straight, the second at the
first pass's angles; the same two passes in streaming and batch mode, so no state is involved.

When the flexion plane is nearly horizontal (``|u_yz| < min_inplane_m_s2``, eq. 7) the observation
carries no information: the last informative estimate is held and the mode is ``none``.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ..model.kinematics import BaseMotion
from .base import MODE_NO_INFO, MODE_SLOW, EstimatorSettings, FingerEstimator, FingerSamples, FingerTrack
from .observations import vector_observation


class VectorSettings(EstimatorSettings):
    min_inplane_m_s2: float = Field(1.0, gt=0.0, description="below this in-plane reference magnitude, m/s², "
                                    "the observation is declared uninformative (eq. 7)")


class VectorObservation(FingerEstimator):
    name = "vector"
    Settings = VectorSettings

    def observe(self, acc: np.ndarray, hand: BaseMotion) -> tuple[np.ndarray, np.ndarray]:
        """``(θ per sensor, in-plane magnitude)`` for samples (..., S, 3); vectorised over ``...``."""
        return vector_observation(self.obs, self.closure, acc, hand, self.gravity_world)

    def _init_state(self, gyr, acc, hand, theta0):
        held = np.zeros(self.batch_shape + (self.n_sensors,)) if theta0 is None else theta0[..., self.obs.phalanx]
        return {"held": held, "rate": np.zeros(held.shape)}

    def _observe(self, gyr, acc, hand, prev_rate=None, dt=None):
        theta, inplane = self.observe(acc, hand)
        return theta, inplane >= self.settings.min_inplane_m_s2

    def _hold(self, state, dt, theta, informative):
        held = np.where(informative, theta, state["held"])
        return {"held": held, "rate": state["rate"]}, held, np.where(informative, MODE_SLOW, MODE_NO_INFO).astype(np.int8)

    def _step(self, state, dt, gyr, acc, hand):
        return self._hold(state, dt, *self._observe(gyr, acc, hand))

    def run(self, samples: FingerSamples) -> FingerTrack:
        """Observations vectorised over all samples (in blocks), then the lean hold loop."""
        return self._run_split(samples, self._observe, self._hold)
