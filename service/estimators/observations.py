"""What one finger's IMUs say about its phalanx angles, shared by every estimator.

* ``relative_rate`` (paper 2.2.3 with a moving hand): the phalanx's angular rate relative to the
  metacarpus about the hinge axis, ``θ̇_k = x·(R_mount ω_S) - x·(R_Bᵀ R_Mᵀ ω_M)``: the gyro minus
  the hand's angular velocity from the optical pose. It does not depend on ``θ`` (rotation about
  ``x`` leaves ``x`` fixed), so integrating it is exact in the planar model.
* ``reference_force`` (eqs. 2 and 5 with a moving hand): the specific force the sensor would read if
  its phalanx were at ``θ = 0``, expressed in the finger base frame:
  ``u_k = R_Bᵀ R_Mᵀ (a_k - g)`` with ``a_k`` the sensor's world acceleration. With ``finger_rates``
  it includes the finger's own acceleration (the paper's ``g_k`` of eq. 11); without, only the
  hand's (the paper's ``a_0`` of 2.2.2, plus the hand's rotation terms at the sensor's position).
* ``ChainClosure``: joint angles from per-sensor phalanx angles plus the coupling.
* ``vector_angle`` (2.2.2): ``f_k ≈ R_x(θ)ᵀ u_k`` gives ``θ = atan2(u_z, u_y) - atan2(f_z, f_y)``.
  The in-plane magnitude ``|u_yz|`` measures how much information it carries (eq. 7): zero when the
  flexion plane is horizontal.
"""
from __future__ import annotations

import numpy as np

from ..model.frames import apply_transpose
from ..model.hand import FingerGeometry, joint_limits, joint_to_phalanx_angles
from ..model.kinematics import BaseMotion


_KEPT: dict[tuple, tuple] = {}
"""Constants made for a finger geometry object (``ChainClosure.of``, ``FingerObservations.of``), by the object's
identity: the geometries of a shared calibration (``model.hand.default_calibration``,
``HandCalibration.with_overrides``) are the same objects for every hand on it, so those hands share one set.
Each entry keeps its geometry alive (no other object gets its id meanwhile)."""


_PLAIN = (int, float, np.int64, np.float64)
"""Number types whose ``repr`` tells apart any two values (a key's text)."""


def _kept(kind: str, geom: FingerGeometry, detail: str, build):
    """What ``build()`` makes for ``geom`` (and ``detail``), made once while kept: its arrays read-only, as
    it is shared."""
    key = (kind, id(geom), detail)
    hit = _KEPT.get(key)
    if hit is not None and hit[0] is geom:
        return hit[1]
    value = build()
    for array in vars(value).values():
        if isinstance(array, np.ndarray):
            array.flags.writeable = False
    if len(_KEPT) >= 512:
        _KEPT.clear()
    _KEPT[key] = (geom, value)
    return value


class ChainClosure:
    """Joint angles from the measured phalanx angles plus the coupling (DESIGN.md, paper section 2.2).

    Sensor ``k`` on phalanx ``i_k`` measures ``θ_{i_k} = Σ_{j<=i_k} φ_j``. Where that leaves a long
    finger's joints undetermined, the coupling ``φ_DIP = c φ_PIP`` is added; ``extra_couplings``
    ``[(j, c_j), ...]`` (meaning ``φ_{j+1} = c_j φ_j``) may add more, e.g. as a fallback when a sensor
    is silent. The least-squares solution is used when sensors are redundant.
    ``phi = theta_sensors @ matrix.T``.
    """

    def __init__(self, geom: FingerGeometry, phalanx_of_sensor: list[int] | None = None,
                 extra_couplings: list[tuple[int, float]] = ()):
        n = geom.n_phalanges
        phalanges = [s.phalanx for s in geom.sensors] if phalanx_of_sensor is None else phalanx_of_sensor
        rows = [np.array([1.0 if j <= i else 0.0 for j in range(n)]) for i in phalanges]
        a = np.array(rows).reshape(len(rows), n)
        couplings = ([(1, geom.coupling)] if n == 3 else []) + list(extra_couplings)
        for j, c in couplings:                               # φ_{j+1} - c φ_j = 0
            if np.linalg.matrix_rank(a) >= n:
                break
            row = np.zeros(n)
            row[j + 1], row[j] = 1.0, -c
            a = np.vstack([a, row])
        if np.linalg.matrix_rank(a) < n:
            raise ValueError(
                f"finger {geom.name!r}: sensors on phalanges {sorted(phalanges)} with the coupling cannot "
                f"determine its {n} joint angles; add a sensor")
        self.matrix = np.linalg.pinv(a)[:, : len(phalanges)]
        self.phalanges = phalanges

    @classmethod
    def of(cls, geom: FingerGeometry, extra_couplings: tuple[tuple[int, float], ...] = ()) -> "ChainClosure":
        """The closure of ``geom``'s own sensors with ``extra_couplings``, shared (read-only) by every
        estimator of that geometry object and couplings (its pseudo-inverse computed once)."""
        if not all(type(v) in _PLAIN for pair in extra_couplings for v in pair):
            return cls(geom, extra_couplings=list(extra_couplings))     # (its own: no exact text to key it by)
        return _kept("closure", geom, repr(tuple(extra_couplings)),
                     lambda: cls(geom, extra_couplings=list(extra_couplings)))

    def joint_angles(self, theta_sensors: np.ndarray) -> np.ndarray:
        """``θ`` per sensor (..., S) to joint angles ``φ`` (..., n)."""
        return theta_sensors @ self.matrix.T

    phalanx_angles = staticmethod(joint_to_phalanx_angles)
    """Joint angles ``φ`` (..., n) to phalanx angles ``θ`` (``model.hand``)."""


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap to ``(-π, π]``."""
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


class FingerObservations:
    """Constants of one finger's sensors and the observation functions (module docstring).

    Shapes: ``gyr``/``acc`` (..., S, 3); hand arrays (..., 3) / (..., 3, 3); phalanx angles (..., n).
    """

    def __init__(self, geom: FingerGeometry):
        self.geom = geom
        self.mount = np.stack([s.mounting_matrix() for s in geom.sensors])          # (S,3,3) sensor->phalanx
        self.hinge_in_sensor = self.mount[:, 0, :]                                   # x of the phalanx, sensor coords
        self.base = geom.base_matrix()                                               # finger base -> metacarpus
        self.phalanx = np.array([s.phalanx for s in geom.sensors])
        self.offset = np.array([s.offset_m for s in geom.sensors])
        self.base_position = np.asarray(geom.base_position_m)
        self.max_length = max(geom.lengths_m)
        n = geom.n_phalanges
        # _lever[k, j]: length of phalanx j on the way from the MCP joint to sensor k (eq. 1)
        self._lever = np.array([[geom.lengths_m[j] if j < s.phalanx else (s.offset_m if j == s.phalanx else 0.0)
                                 for j in range(n)] for s in geom.sensors])
        # _prefix[k, j] = 1 if phalanx j lies between the metacarpus and sensor k's phalanx (eq. 6)
        self._prefix = (self._lever > 0) | (np.arange(n)[None, :] <= self.phalanx[:, None])
        self._chain_factor = (self.phalanx + 1) * self.max_length                    # (i_k + 1) l_max
        # each sensor's phalanx angle lies in the sum of the joint ranges up to it; angles are
        # reported on the 2π branch centred on that range
        limits = np.array(joint_limits(geom.name))
        lo = np.array([limits[: i + 1, 0].sum() for i in self.phalanx])
        hi = np.array([limits[: i + 1, 1].sum() for i in self.phalanx])
        self.branch_low = 0.5 * (lo + hi) - np.pi

    @classmethod
    def of(cls, geom: FingerGeometry) -> "FingerObservations":
        """``geom``'s observation constants, shared (read-only) by every estimator of that geometry object."""
        return _kept("observations", geom, "", lambda: cls(geom))

    def to_branch(self, theta: np.ndarray) -> np.ndarray:
        """Per-sensor angles (..., S) onto the anatomical 2π branch."""
        return self.branch_low + np.mod(theta - self.branch_low, 2.0 * np.pi)

    def relative_rate(self, gyr: np.ndarray, hand: BaseMotion) -> np.ndarray:
        """Hinge-axis angular rate of each phalanx relative to the metacarpus (..., S), rad/s."""
        return self.hinge_rate(gyr) - self.hand_rate_in_base(hand)[..., None, 0]

    def hinge_rate(self, gyr: np.ndarray) -> np.ndarray:
        """What each gyro reads about its phalanx's hinge axis (..., S), rad/s."""
        return np.einsum("sj,...sj->...s", self.hinge_in_sensor, gyr)

    def hand_rate_in_base(self, hand: BaseMotion) -> np.ndarray:
        """The hand's angular velocity in the finger base frame, ``R_Bᵀ R_Mᵀ ω_M`` (..., 3), rad/s."""
        return apply_transpose(hand.rotation, hand.angular_velocity) @ self.base

    def phalanx_force(self, acc: np.ndarray) -> np.ndarray:
        """Specific force in each phalanx frame (..., S, 3): ``R_mount f``."""
        return np.einsum("sij,...sj->...si", self.mount, acc)

    def hinge_axis_world(self, hand: BaseMotion) -> np.ndarray:
        """The flexion-plane normal (hinge axis ``x``) in the world frame (..., 3)."""
        return hand.rotation @ self.base[:, 0]

    def hinge_reference(self, hand: BaseMotion, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """The second reference vector of the attitude filters, in place of a magnetometer: the
        flexion-plane normal in the world (from the optical pose) and in each sensor's frame, both
        broadcast to ``shape`` (..., S, 3)."""
        return (np.broadcast_to(self.hinge_axis_world(hand)[..., None, :], shape),
                np.broadcast_to(self.hinge_in_sensor, shape))

    def reference_force_metacarpus(self, hand: BaseMotion, theta: np.ndarray, gravity_world: np.ndarray,
                                   dtheta: np.ndarray | None = None, ddtheta: np.ndarray | None = None) -> np.ndarray:
        """``R_Mᵀ (a_k - g)`` (..., S, 3): the specific force of sensor ``k`` at phalanx angles ``theta``
        (..., n) in the metacarpus frame (``model.kinematics`` formula, all sensors at once):
        ``R_Mᵀ(a_M - g) + α×ρ + ω×(ω×ρ) + 2 ω×ρ' + ρ''`` with hand rates in metacarpus coordinates."""
        c, s = np.cos(theta), np.sin(theta)
        y = np.zeros(theta.shape + (3,))                                            # y_j (..., n, 3)
        y[..., 1], y[..., 2] = c, s
        base_t = self.base.T
        rho = self.base_position + (self._lever @ y) @ base_t                        # eq. 1, (..., S, 3)
        # α×ρ + ω×(ω×ρ) = (K_α + K_ω K_ω) ρ with cross-product matrices: one product for all sensors
        rot_t, hand_terms, k_w = hand.body_terms                                    # once per hand state
        lin = np.einsum("...ij,...j->...i", rot_t, hand.acceleration - gravity_world)[..., None, :]
        out = lin + rho @ np.swapaxes(hand_terms, -1, -2)
        if dtheta is not None:
            z = np.zeros(theta.shape + (3,))                                        # z_j = dy_j/dθ_j
            z[..., 1], z[..., 2] = -s, c
            vel = (self._lever @ (dtheta[..., None] * z)) @ base_t
            out = out + vel @ (-2.0 * k_w)                                          # 2 ω×ρ' (row form: ρ' K_ωᵀ)
            if ddtheta is not None:
                acc = ddtheta[..., None] * z - dtheta[..., None] ** 2 * y              # eq. 2 terms
                out = out + (self._lever @ acc) @ base_t
        return out

    def reference_force_world(self, hand: BaseMotion, theta: np.ndarray, gravity_world: np.ndarray,
                              dtheta: np.ndarray | None = None, ddtheta: np.ndarray | None = None) -> np.ndarray:
        """``a_k - g`` (..., S, 3) in the world frame (the accelerometer reference of eq. 11)."""
        m = self.reference_force_metacarpus(hand, theta, gravity_world, dtheta, ddtheta)
        return np.einsum("...ij,...sj->...si", hand.rotation, m)

    def reference_force(self, hand: BaseMotion, theta: np.ndarray, gravity_world: np.ndarray,
                        dtheta: np.ndarray | None = None, ddtheta: np.ndarray | None = None) -> np.ndarray:
        """``u_k = R_Bᵀ R_Mᵀ (a_k - g)`` (..., S, 3) in the finger base frame."""
        return self.reference_force_metacarpus(hand, theta, gravity_world, dtheta, ddtheta) @ self.base

    def acceleration_bound(self, closure, rates: np.ndarray, rate_changes: np.ndarray) -> np.ndarray:
        """``|μ̂|`` of eq. 6 per sensor (..., S), m/s²: ``(i_k + 1) l_max √(ω̇_max² + ω_max⁴)`` with the
        largest relative rate and rate change of phalanges ``0..i_k`` (unmeasured ones from ``closure``)."""
        w_all = np.abs(np.cumsum(closure.joint_angles(rates), axis=-1))
        dw_all = np.abs(np.cumsum(closure.joint_angles(rate_changes), axis=-1))
        w_max = np.max(w_all[..., None, :] * self._prefix, axis=-1)
        dw_max = np.max(dw_all[..., None, :] * self._prefix, axis=-1)
        return self._chain_factor * np.sqrt(dw_max**2 + w_max**4)

    def vector_angle(self, force_phalanx: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(θ (..., S), |u_yz| (..., S))``: phalanx angle from the in-plane direction of the specific
        force (2.2.2, the paper's ``atan2``), on the anatomical branch, and the in-plane magnitude of
        the reference (eq. 7)."""
        theta = self.to_branch(np.arctan2(reference[..., 2], reference[..., 1])
                               - np.arctan2(force_phalanx[..., 2], force_phalanx[..., 1]))
        return theta, np.hypot(reference[..., 1], reference[..., 2])

    def sensor_theta_to_rotation(self, hand: BaseMotion, theta_sensor: np.ndarray) -> np.ndarray:
        """Sensor-to-world rotations (..., S, 3, 3) for per-sensor phalanx angles (..., S)."""
        c, s = np.cos(theta_sensor), np.sin(theta_sensor)
        rx = np.zeros(theta_sensor.shape + (3, 3))
        rx[..., 0, 0] = 1.0
        rx[..., 1, 1], rx[..., 1, 2], rx[..., 2, 1], rx[..., 2, 2] = c, -s, s, c
        rb = hand.rotation @ self.base                                               # (..., 3, 3)
        return rb[..., None, :, :] @ rx @ self.mount

    def rotation_to_sensor_theta(self, hand: BaseMotion, r_sensor: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """Phalanx angle (..., S) from sensor-to-world rotations (..., S, 3, 3): the flexion of
        ``R_Bᵀ R_Mᵀ R_S R_mountᵀ`` (robust to out-of-plane error), unwrapped next to ``previous``."""
        rb = hand.rotation @ self.base
        rel = np.swapaxes(rb, -1, -2)[..., None, :, :] @ r_sensor @ np.swapaxes(self.mount, -1, -2)
        raw = np.arctan2(rel[..., 2, 1] - rel[..., 1, 2], rel[..., 1, 1] + rel[..., 2, 2])
        return previous + wrap_angle(raw - previous)

    def accelerometer_reference(self, closure, hand: BaseMotion, theta_sensors: np.ndarray, rate: np.ndarray,
                                rate_change: np.ndarray, gravity_world: np.ndarray, kinematic: bool) -> np.ndarray:
        """World-frame accelerometer reference ``a_k - g`` (..., S, 3) at the per-sensor angles of the
        previous estimate, with the finger's own acceleration ``g_k`` of eq. 2 from the measured rates
        and their change when ``kinematic`` (the paper's eq. 11 reference), else the hand's only."""
        theta_all, rate_all, rc_all = self.chain(closure, theta_sensors, rate, rate_change)
        if kinematic:
            return self.reference_force_world(hand, theta_all, gravity_world, rate_all, rc_all)
        return self.reference_force_world(hand, theta_all, gravity_world)

    def reference_pairs(self, closure, hand: BaseMotion, theta_sensors: np.ndarray, rate: np.ndarray,
                        rate_change: np.ndarray, acc: np.ndarray, gravity_world: np.ndarray, kinematic: bool,
                        second_reference: bool) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The vector pairs an attitude filter corrects with (world references, what the sensor
        measures of them; each (..., S, 3)): the accelerometer against ``accelerometer_reference``
        (eq. 11), and with ``second_reference`` the flexion-plane normal (``hinge_reference``)."""
        world = [self.accelerometer_reference(closure, hand, theta_sensors, rate, rate_change, gravity_world, kinematic)]
        sensor = [acc]
        if second_reference:
            hinge_world, hinge_sensor = self.hinge_reference(hand, acc.shape)
            world.append(hinge_world)
            sensor.append(hinge_sensor)
        return world, sensor

    @staticmethod
    def rate_change(rate: np.ndarray, previous: np.ndarray, dt: float) -> np.ndarray:
        """Backward difference of the relative rates, rad/s² (zero on the first sample)."""
        return (rate - previous) / dt if dt > 0 else np.zeros_like(rate)

    @staticmethod
    def chain(closure, *per_sensor: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per-sensor quantities (..., S) (angles, rates, rate changes) to every phalanx (..., n)
        through the chain closure (linear, so rates and accelerations close like angles)."""
        return tuple(np.cumsum(closure.joint_angles(x), axis=-1) for x in per_sensor)


def vector_observation(obs: FingerObservations, closure: ChainClosure, acc: np.ndarray, hand: BaseMotion,
                       gravity_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(θ per sensor, in-plane magnitude)`` (2.2.2) for samples (..., S, 3), vectorised over ``...``.
    The hand's rotation terms at the sensor need the sensor's position, which needs ``θ``: two
    passes, the first with the finger straight, the second at the first pass's angles."""
    theta_all = np.zeros(acc.shape[:-2] + (obs.geom.n_phalanges,))
    f = obs.phalanx_force(acc)
    for _ in range(2):
        u = obs.reference_force(hand, theta_all, gravity_world)
        theta_s, inplane = obs.vector_angle(f, u)
        theta_all = ChainClosure.phalanx_angles(closure.joint_angles(theta_s))
    return theta_s, inplane


def initial_sensor_theta(obs: FingerObservations, acc: np.ndarray, hand: BaseMotion, theta0: np.ndarray | None,
                         gravity_world: np.ndarray) -> np.ndarray:
    """Per-sensor phalanx angles (*B, S) to start from: ``theta0`` (*B, n) if known, else the first
    sample's vector observation (closed by the finger's own coupling only)."""
    if theta0 is not None:
        return np.array(theta0[..., obs.phalanx], dtype=float)
    return vector_observation(obs, ChainClosure.of(obs.geom), acc, hand, gravity_world)[0]
