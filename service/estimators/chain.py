"""``chain``: our estimator. A per-phalanx extended Kalman filter that keeps what the paper's
estimators throw away.

What it uses that the others ignore:

1. **Sensor errors as states.** Each sensor's state is ``[θ, b_g, b_ax, b_ay, b_az]``: its phalanx
   angle, the gyro zero offset about the hinge axis (the only gyro axis that matters in the planar
   model) and the full 3-axis accelerometer zero offset (in phalanx coordinates). Switching, Madgwick
   and the EKF baseline treat the accelerometer offset as noise, which leaves a constant tilt error
   of up to ``offset/g`` (about 3.5 deg for 60 mg) in every slow phase.
2. **The known starting configuration.** When the initial configuration is given (as in the paper's
   test, or after a calibration pose), its prior is tight (``initial_angle_std_rad``, 1 deg). With
   the hand pose known, the expected specific force is then known, so the first samples reveal the
   accelerometer offset (all of it along the hinge axis, the in-plane part to within the prior's
   1 deg · g), and the drift of the angle against the accelerometer reveals the gyro offset. Later
   motion through different orientations keeps both observable, so they keep improving. (A
   zero-rate detector was tried and dropped: slow motion is indistinguishable from rest over short
   windows, and its false detections corrupted the gyro offset; measured on the grasp motion.)
3. **Both IMUs of a finger jointly through the chain model.** The accelerometer is predicted with
   the full eq. 2 kinematics (tangential and centripetal terms of every phalanx between the MCP joint
   and the sensor, the unmeasured proximal phalanx from the coupling), using both sensors' angles and
   bias-corrected rates, so fast motion is modelled instead of being a disturbance. What remains
   unmodelled (the rate change is a causal difference) inflates the accelerometer noise in
   proportion to the eq. 6 bound.

Process model (per sensor, trapezoid/RK4 step as in ``integration``):
``θ ← θ + dt (ω̄ - b_g)``, ``F = [[1, -dt, 0], [0, 1, 0], [0, 0, I3]]``,
``Q = diag(σ_ω² dt, σ_bg² dt, σ_ba² dt I3)``.
Measurement: ``f = R_x(θ)ᵀ u + b_a`` with ``u`` the reference force of the chain model
(``observations.reference_force``); ``∂f/∂θ = [0, -sin θ u_y + cos θ u_z, -cos θ u_y - sin θ u_z]``,
``∂f/∂b_a = I``; noise ``σ_a² + (κ |μ̂|)²`` with ``|μ̂|`` the eq. 6 bound.

Not used: the coupling as a soft constraint. With the default placement (sensors on phalanges 1 and
2) the coupling is what determines the MCP angle, so there is no redundancy to soften; with sensors
on all three phalanges it would be, and is left for later. The hand kinematics are taken as given
(from the optics); their errors are not states.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ..model.units import DEG, MPU9250_ACC_OFFSET_STD_M_S2, MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ, MPU9250_GYRO_OFFSET_STD_RAD_S
from . import kalman
from .base import MODE_FAST, MODE_FUSED, EstimatorSettings, FingerEstimator, lost_optics_variance
from .integration import initial_sensor_theta

N_STATE = 5


class ChainSettings(EstimatorSettings):
    gyro_noise_density_rad_s_rthz: float = Field(MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ, gt=0.0, description="gyro white noise, rad/s/√Hz")
    gyro_bias_walk_rad_s_rts: float = Field(1e-5, ge=0.0, description="gyro offset random walk, rad/s/√s")
    acc_bias_walk_m_s2_rts: float = Field(1e-4, ge=0.0, description="accelerometer offset random walk, m/s²/√s")
    initial_gyro_bias_std_rad_s: float = Field(MPU9250_GYRO_OFFSET_STD_RAD_S, gt=0.0, description="prior std of the gyro offset (MPU-9250 ±5 deg/s), rad/s")
    initial_acc_bias_std_m_s2: float = Field(MPU9250_ACC_OFFSET_STD_M_S2, gt=0.0, description="prior std of the accelerometer offset (MPU-9250 ±60-80 mg), m/s²")
    initial_angle_std_rad: float = Field(1.0 * DEG, gt=0.0, description="prior std of a given initial configuration, rad")
    unknown_angle_std_rad: float = Field(10.0 * DEG, gt=0.0, description="prior std when starting from a vector observation, rad")
    acc_noise_m_s2: float = Field(0.03, gt=0.0, description="accelerometer white noise per sample, m/s² (MPU-9250 at 200 Hz)")
    kinematic_uncertainty: float = Field(0.1, ge=0.0, description="added accelerometer std per m/s² of the eq. 6 bound")


class Chain(FingerEstimator):
    name = "chain"
    Settings = ChainSettings

    def _init_state(self, gyr, acc, hand, theta0):
        s = self.settings
        theta = initial_sensor_theta(self, acc, hand, theta0)
        P = np.zeros(theta.shape + (N_STATE, N_STATE))
        known_std = getattr(self, "_known_std_rad", None) or s.initial_angle_std_rad
        P[..., 0, 0] = (known_std if theta0 is not None else s.unknown_angle_std_rad) ** 2
        P[..., 1, 1] = s.initial_gyro_bias_std_rad_s**2
        P[..., 2:, 2:] = s.initial_acc_bias_std_m_s2**2 * np.eye(3)
        return {"x": np.concatenate([theta[..., None], np.zeros(theta.shape + (4,))], axis=-1),
                "P": P, "rate": self.obs.relative_rate(gyr, hand)}

    def known_configuration(self, theta: np.ndarray, std_rad: float) -> None:
        """A measurement ``θ_{i_k} = theta[i_k]`` of every sensor's phalanx angle (a phalanx angle sums
        ``i_k + 1`` joints, each known to ``std_rad``): it corrects the angle and, through the
        covariance the filter has built up between angle and offsets, the offsets too. Before the first
        sample it becomes the initial configuration."""
        if self._state is None:
            self.reset(initial_theta=theta)
            self._known_std_rad = std_rad
            return
        theta = np.broadcast_to(np.asarray(theta, dtype=float), self.batch_shape + (self.geom.n_phalanges,))
        phalanges = [sp.phalanx for sp in self.geom.sensors]
        measured = theta[..., phalanges]
        x, P = self._state["x"], self._state["P"]
        H = np.zeros(measured.shape + (1, N_STATE))
        H[..., 0, 0] = 1.0
        R = (np.array([(p + 1) * std_rad**2 for p in phalanges])[..., None, None]
             * np.ones(measured.shape + (1, 1)))
        # the innovation on the angle's own 2π branch
        y = (np.mod(measured - x[..., 0] + np.pi, 2.0 * np.pi) - np.pi)[..., None]
        dx, P = kalman.update(P, H, R, y)
        self._state = {**self._state, "x": x + dx, "P": P}

    def reference_lost(self, duration_s: float) -> None:
        if self._state is not None:
            self._state["P"][..., 0, 0] += lost_optics_variance(duration_s)

    def _step(self, state, dt, gyr, acc, hand):
        s = self.settings
        x, P = state["x"], state["P"]
        rate_meas = self.obs.relative_rate(gyr, hand)
        force = self.obs.phalanx_force(acc)

        # predict
        bg = x[..., 1]
        rate = rate_meas - bg
        prev_rate = state["rate"] - bg
        theta_pred = x[..., 0] + dt * 0.5 * (prev_rate + rate)
        x = np.concatenate([theta_pred[..., None], x[..., 1:]], axis=-1)
        F = np.broadcast_to(np.eye(N_STATE), P.shape).copy()
        F[..., 0, 1] = -dt
        q_diag = np.array([s.gyro_noise_density_rad_s_rthz**2, s.gyro_bias_walk_rad_s_rts**2]
                          + [s.acc_bias_walk_m_s2_rts**2] * 3) * dt
        P = kalman.predict(P, F, np.diag(q_diag))

        # accelerometer through the chain model (both sensors' angles and corrected rates)
        rate_change = self.obs.rate_change(rate, prev_rate, dt)
        theta_all, rate_all, rc_all = self.obs.chain(self.closure, theta_pred, rate, rate_change)
        u = self.obs.reference_force(hand, theta_all, self.gravity_world, rate_all, rc_all)
        c, sn = np.cos(theta_pred), np.sin(theta_pred)
        uy, uz = u[..., 1], u[..., 2]
        predicted = np.stack([u[..., 0], c * uy + sn * uz, -sn * uy + c * uz], axis=-1) + x[..., 2:]
        y = force - predicted
        H = np.zeros(rate.shape + (3, N_STATE))
        H[..., 1, 0] = -sn * uy + c * uz
        H[..., 2, 0] = -c * uy - sn * uz
        H[..., :, 2:] = np.eye(3)
        mu = self.obs.acceleration_bound(self.closure, rate, rate_change)
        sigma = np.hypot(s.acc_noise_m_s2, s.kinematic_uncertainty * mu)
        R = (sigma**2)[..., None, None] * np.eye(3)
        dx, P = kalman.update(P, H, R, y)
        x = x + dx
        theta = x[..., 0]
        # "fast" while the accelerometer carries little weight (eq. 6 bound above g/2), else "fused"
        mode = np.where(mu > 0.5 * np.linalg.norm(self.gravity_world), MODE_FAST, MODE_FUSED).astype(np.int8)
        return {"x": x, "P": P, "rate": rate_meas}, theta, mode
