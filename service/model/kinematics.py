"""Planar three-link finger kinematics on a moving, rotating hand, and ideal IMU readings.

Paper equations (section 2.1), in the finger base frame ``e_c``:

* eq. 1: sensor position ``s_k = Σ_{i<i_k} r_i + h_k`` with ``r_i = l_i y_i``, ``h_k = p_k y_{i_k}``;
* eq. 2: sensor acceleration ``g_k = a_0 + Σ ([ω̇_i × r_i] - ω_i² r_i) + [ω̇_{i_k} × h_k] - ω_{i_k}² h_k``;
* eq. 3: reading ``f_k = <e_k, g - g_k>``.

Extension to a moving base. The paper assumes the metacarpus does not rotate (its eq. 2 only carries
the translation ``a_0``). Here the metacarpus frame ``M`` moves with position ``p_M``, orientation
``R_M``, angular velocity ``ω_M`` and angular acceleration ``α_M`` (world frame). For a point with
position ``ρ`` in ``M`` moving with velocity ``ρ'`` and acceleration ``ρ''`` relative to ``M``
(both from eqs. 1-2 rotated by the finger base frame), with ``r = R_M ρ``:

    a = a_M + α_M × r + ω_M × (ω_M × r) + 2 ω_M × (R_M ρ') + R_M ρ''

(translation, Euler, centripetal, Coriolis and relative terms). The gyro sees the hand's rotation
plus the joint rates: ``ω_S = R_Sᵀ ω_M + R_mountᵀ θ̇_i x``, with ``R_S = R_M R_B R_x(θ_i) R_mount``.

Sign convention (DESIGN.md): accelerometers report specific force ``f = R_Sᵀ (a - g)`` so a sensor
at rest reads +|g| along its up-pointing axis; the paper's eq. 3 has the opposite sign.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .frames import DEFAULT_GRAVITY_WORLD, apply, apply_transpose, palmar_axis, phalanx_axis, rot_x, skew
from .hand import FingerGeometry, MetacarpusImu, SensorPlacement


@dataclass(frozen=True)
class BaseMotion:
    """Kinematics of the metacarpus frame over ``N`` samples, all in the world frame, SI units.

    Attributes: ``rotation`` (N,3,3) metacarpus-to-world; ``position`` (N,3) m; ``velocity`` (N,3) m/s;
    ``acceleration`` (N,3) m/s²; ``angular_velocity`` (N,3) rad/s; ``angular_acceleration`` (N,3) rad/s².
    """

    rotation: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    angular_velocity: np.ndarray
    angular_acceleration: np.ndarray

    @cached_property
    def body_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(R_Mᵀ, K_α + K_ω K_ω, K_ω)`` in metacarpus coordinates (``K_v`` the cross-product matrix
        of ``v``; ω, α the hand's rates rotated into ``M``): ``(K_α + K_ω K_ω) ρ = α×ρ + ω×(ω×ρ)`` for
        any point ``ρ`` of ``M``. The same for every finger at one hand state, so computed once per
        ``BaseMotion`` (which is immutable) and kept."""
        rot_t = np.swapaxes(self.rotation, -1, -2)
        w = np.einsum("...ij,...j->...i", rot_t, self.angular_velocity)
        dw = np.einsum("...ij,...j->...i", rot_t, self.angular_acceleration)
        k_w = skew(w)
        return rot_t, skew(dw) + k_w @ k_w, k_w

    @cached_property
    def flat(self) -> np.ndarray:
        """``(..., 18)`` C-contiguous float64: rotation (row-major), acceleration, angular velocity and
        angular acceleration, the layout compiled kernels read (``estimators.chain_kernel``). Computed
        once per ``BaseMotion`` (shared by every finger of a hand state) and kept."""
        r = np.asarray(self.rotation, dtype=float)
        return np.ascontiguousarray(np.concatenate(
            [r.reshape(r.shape[:-2] + (9,)), np.asarray(self.acceleration, dtype=float),
             np.asarray(self.angular_velocity, dtype=float), np.asarray(self.angular_acceleration, dtype=float)],
            axis=-1))

    @staticmethod
    def still(rotation: np.ndarray, position: np.ndarray, n: int) -> "BaseMotion":
        z = np.zeros((n, 3))
        return BaseMotion(
            np.broadcast_to(rotation, (n, 3, 3)).copy(), np.broadcast_to(position, (n, 3)).copy(),
            z, z.copy(), z.copy(), z.copy(),
        )


@dataclass(frozen=True)
class PointMotion:
    """Position, velocity and acceleration of a point, shape (N,3) each."""

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


def chain_point(
    geom: FingerGeometry, phalanx: int, offset_m: float,
    theta: np.ndarray, dtheta: np.ndarray, ddtheta: np.ndarray,
) -> PointMotion:
    """A point ``offset_m`` along phalanx ``phalanx``, in the finger base frame (eqs. 1-2 without ``a_0``).

    ``theta``, ``dtheta``, ``ddtheta``: phalanx angles relative to the metacarpus and their first
    two time derivatives, shape (..., n_phalanges), rad, rad/s, rad/s². Returns (..., 3) arrays.
    """
    theta = np.asarray(theta, dtype=float)
    pos = np.zeros(theta.shape[:-1] + (3,))
    vel = np.zeros_like(pos)
    acc = np.zeros_like(pos)
    for i in range(phalanx + 1):
        length = geom.lengths_m[i] if i < phalanx else offset_m
        y = phalanx_axis(theta[..., i])
        z = palmar_axis(theta[..., i])
        w = dtheta[..., i : i + 1]
        pos += length * y                                               # eq. 1
        vel += length * w * z                                           # ω_i × r_i = l θ̇ z_i
        acc += length * (ddtheta[..., i : i + 1] * z - w**2 * y)        # eq. 2: [ω̇_i × r_i] - ω_i² r_i
    return PointMotion(pos, vel, acc)


def point_in_metacarpus(geom: FingerGeometry, local: PointMotion) -> PointMotion:
    """Express a finger-base-frame point in the metacarpus frame (constant base transform)."""
    rb = geom.base_matrix()
    return PointMotion(
        np.asarray(geom.base_position_m) + local.position @ rb.T,
        local.velocity @ rb.T,
        local.acceleration @ rb.T,
    )


def point_in_world(base: BaseMotion, rel: PointMotion) -> PointMotion:
    """World kinematics of a point moving relative to the metacarpus (module docstring formula)."""
    r = apply(base.rotation, rel.position)
    v_rel = apply(base.rotation, rel.velocity)
    a_rel = apply(base.rotation, rel.acceleration)
    w, dw = base.angular_velocity, base.angular_acceleration
    pos = base.position + r
    vel = base.velocity + np.cross(w, r) + v_rel
    acc = (base.acceleration + np.cross(dw, r) + np.cross(w, np.cross(w, r))
           + 2.0 * np.cross(w, v_rel) + a_rel)
    return PointMotion(pos, vel, acc)


def sensor_rotation(geom: FingerGeometry, sensor: SensorPlacement, base: BaseMotion, theta: np.ndarray) -> np.ndarray:
    """Sensor-to-world rotation ``R_S = R_M R_B R_x(θ_i) R_mount``, shape (N,3,3)."""
    return base.rotation @ geom.base_matrix() @ rot_x(theta[..., sensor.phalanx]) @ sensor.mounting_matrix()


@dataclass(frozen=True)
class ImuReadings:
    """Ideal (error-free) readings of one IMU: ``gyr`` rad/s and ``acc`` m/s² (specific force), sensor frame."""

    gyr: np.ndarray
    acc: np.ndarray


def ideal_imu(
    geom: FingerGeometry, sensor: SensorPlacement, base: BaseMotion,
    theta: np.ndarray, dtheta: np.ndarray, ddtheta: np.ndarray,
    gravity_world: np.ndarray = DEFAULT_GRAVITY_WORLD,
) -> ImuReadings:
    """Error-free gyroscope and accelerometer readings of ``sensor`` (module docstring)."""
    local = chain_point(geom, sensor.phalanx, sensor.offset_m, theta, dtheta, ddtheta)
    world = point_in_world(base, point_in_metacarpus(geom, local))
    r_s = sensor_rotation(geom, sensor, base, theta)
    acc = apply_transpose(r_s, world.acceleration - gravity_world)       # eq. 3, DESIGN.md sign
    joint_rate = dtheta[..., sensor.phalanx : sensor.phalanx + 1] * np.array([1.0, 0.0, 0.0])
    gyr = apply_transpose(r_s, base.angular_velocity) + joint_rate @ sensor.mounting_matrix()
    return ImuReadings(gyr, acc)


def metacarpus_imu(placement: MetacarpusImu, base: BaseMotion,
                   gravity_world: np.ndarray = DEFAULT_GRAVITY_WORLD) -> ImuReadings:
    """Error-free readings of the IMU on the back of the hand: a point fixed to the metacarpus (the
    module docstring's formula with no motion relative to it), in the sensor frame."""
    n = base.rotation.shape[:-2]
    fixed = PointMotion(np.broadcast_to(np.asarray(placement.position_m, dtype=float), n + (3,)),
                        np.zeros(n + (3,)), np.zeros(n + (3,)))
    world = point_in_world(base, fixed)
    r_s = base.rotation @ placement.mounting_matrix()
    return ImuReadings(apply_transpose(r_s, base.angular_velocity), apply_transpose(r_s, world.acceleration - gravity_world))


def joint_positions(geom: FingerGeometry, theta: np.ndarray) -> np.ndarray:
    """Positions of the MCP joint, every following joint and the fingertip in the metacarpus frame.

    ``theta`` (..., n) phalanx angles; returns (..., n+1, 3), metres.
    """
    theta = np.asarray(theta, dtype=float)
    r = np.asarray(geom.lengths_m)[..., :, None] * phalanx_axis(theta)   # r_i = l_i y_i
    chain = np.concatenate([np.zeros(theta.shape[:-1] + (1, 3)), np.cumsum(r, axis=-2)], axis=-2)
    return np.asarray(geom.base_position_m) + chain @ geom.base_matrix().T
