"""The inertial-frame core on a finger (``--estimator inertial``): one ``rigid.inertial`` filter per
phalanx IMU, the same compiled kernel the rigid bench runs, with the finger's knowledge added the
way the modified Madgwick filter adds it (paper 2.3):

* the accelerometer input has the predicted kinematic acceleration removed: the hand's, from the
  optical pose, and the finger's own ``g_k`` of eq. 2 from the measured rates (eq. 11's reference
  minus gravity), rotated into the sensor frame with the previous estimate; what is left averages
  to gravity in the core's inertial-frame low-pass;
* the flexion-plane normal from the optical pose is the second reference vector (heading about
  the vertical; the magnetometer's role);
* the phalanx angle is the flexion of the sensor orientation relative to the metacarpus, as in
  ``madgwick``.

The kernel's coefficients depend on the sampling interval: they are computed for ``dt`` rounded to
1 µs and cached, so a jittery glove clock costs a dictionary lookup per sample, not a filter design.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from pydantic import Field

from ..model import quaternion as quat
from .base import MODE_FUSED, EstimatorSettings, FingerEstimator
from .observations import initial_sensor_theta
from .rigid import inertial as rigid_inertial
from .rigid import inertial_kernel as K


class InertialFingerSettings(EstimatorSettings):
    core: rigid_inertial.InertialSettings = Field(
        default_factory=lambda: rigid_inertial.InertialSettings(bias_clip_deg_s=6.0),
        description="the rigid core's parameters; the bias clip covers the MPU-9250's ±5 °/s zero-rate offset")
    kinematic_acceleration: bool = Field(True, description="remove the predicted hand and finger acceleration (eq. 2)")
    second_reference: bool = Field(True, description="use the flexion-plane normal as second reference vector")


@lru_cache(maxsize=256)
def _coefficients(settings: rigid_inertial.InertialSettings, dt_us: int) -> np.ndarray:
    c = rigid_inertial.coefficients(settings, dt_us * 1e-6)
    c.flags.writeable = False
    return c


class InertialFinger(FingerEstimator):
    name = "inertial"
    jit_kernels = True
    kernels = (K.run_sample,)
    Settings = InertialFingerSettings

    def _init_state(self, gyr, acc, hand, theta0):
        theta = initial_sensor_theta(self.obs, acc, hand, theta0, self.gravity_world)
        to_world = rigid_inertial.world_rotation(-self.gravity_world / np.linalg.norm(self.gravity_world))
        q_world = quat.from_matrix(self.obs.sensor_theta_to_rotation(hand, theta))          # (*B, S, 4)
        rows = rigid_inertial.initial_state(self.settings.core, int(np.prod(theta.shape, dtype=int)),
                                            q_world.reshape(-1, 4), to_world)
        return {"core": rows, "q": quat.to_xyzw(q_world), "theta": theta, "rate": self.obs.relative_rate(gyr, hand),
                "to_world": to_world}

    def _step(self, state, dt, gyr, acc, hand):
        s = self.settings
        rate = self.obs.relative_rate(gyr, hand)
        if dt <= 0:                                   # the first sample: the initial configuration
            return dict(state, rate=rate), state["theta"], np.full(state["theta"].shape, MODE_FUSED, np.int8)
        c = _coefficients(s.core, int(round(dt * 1e6)))
        rot_prev = quat.to_matrix(quat.from_xyzw(state["q"]))                                # (*B, S, 3, 3)
        f_in = acc
        if s.kinematic_acceleration:
            rate_change = self.obs.rate_change(rate, state["rate"], dt)
            d_acc = self.obs.accelerometer_reference(self.closure, hand, state["theta"], rate, rate_change,
                                                     self.gravity_world, True)
            kin_world = d_acc + self.gravity_world                     # the reference minus gravity's part
            f_in = acc - np.einsum("...ji,...j->...i", rot_prev, kin_world)
        rows = state["core"].copy()
        g, a = np.ascontiguousarray(gyr.reshape(-1, 3)), np.ascontiguousarray(f_in.reshape(-1, 3))
        if s.second_reference:
            hinge_world, hinge_sensor = self.obs.hinge_reference(hand, acc.shape)
            rw = np.ascontiguousarray(hinge_world.reshape(-1, 3))
            rs = np.ascontiguousarray(hinge_sensor.reshape(-1, 3))
        else:
            rw = rs = g
        out = np.empty((rows.shape[0], 4))
        K.run_sample(rows, g, a, c, rw, rs, s.second_reference, state["to_world"], out)
        q = out.reshape(state["q"].shape)
        theta = self.obs.rotation_to_sensor_theta(hand, quat.to_matrix(quat.from_xyzw(q)), state["theta"])
        new = {"core": rows, "q": q, "theta": theta, "rate": rate, "to_world": state["to_world"]}
        return new, theta, np.full(theta.shape, MODE_FUSED, np.int8)
