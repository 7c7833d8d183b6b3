"""Finger model: rest readings, closed forms, and analytic readings against finite differences."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.frames import DEFAULT_GRAVITY_WORLD, GRAVITY_M_S2, apply
from service.model.hand import FINGERS, default_calibration, joint_to_phalanx_angles
from service.model.kinematics import (
    BaseMotion, chain_point, ideal_imu, joint_positions, point_in_metacarpus, point_in_world, sensor_rotation,
)
from service.sim.motions import make_finger_motion, make_hand_motion


def _finger_state(motion, finger, t):
    phi, dphi, ddphi = motion.joint_angles(finger, t)
    return tuple(joint_to_phalanx_angles(x) for x in (phi, dphi, ddphi))


@pytest.mark.parametrize("hand", ["right", "left"])
def test_hand_at_rest_reads_gravity_up_and_zero_rate(hand, rng):
    calib = default_calibration(hand)
    up = -DEFAULT_GRAVITY_WORLD / GRAVITY_M_S2
    for k in range(6):
        rot = Rotation.random(random_state=k).as_matrix()
        base = BaseMotion.still(rot, np.array([0.1, 1.0, -0.2]), 1)
        for geom in calib.fingers.values():
            phi = rng.uniform(-0.2, 1.2, (1, geom.n_phalanges))
            theta = joint_to_phalanx_angles(phi)
            zero = np.zeros_like(theta)
            for sensor in geom.sensors:
                r = ideal_imu(geom, sensor, base, theta, zero, zero)
                r_s = sensor_rotation(geom, sensor, base, theta)
                assert np.linalg.norm(r.acc) == pytest.approx(GRAVITY_M_S2, abs=1e-12)
                # the reading, rotated to the world, points up
                np.testing.assert_allclose(apply(r_s, r.acc)[0] / GRAVITY_M_S2, up, atol=1e-12)
                np.testing.assert_allclose(r.gyr, 0.0, atol=1e-15)


def test_palm_down_straight_finger_reads_minus_z():
    # Palm down: the finger frame's z (palmar) points to the floor, so gravity's reaction is -z.
    calib = default_calibration("right")
    geom = calib.finger("index")
    base = BaseMotion.still(make_hand_motion("still").initial_rotation, np.zeros(3), 1)
    theta = np.zeros((1, 3))
    r = ideal_imu(geom, geom.sensors[0], base, theta, theta, theta)
    np.testing.assert_allclose(r.acc[0], [0.0, 0.0, -GRAVITY_M_S2], atol=1e-12)


def test_constant_rate_rotation_gives_centripetal_acceleration():
    # One phalanx turning at constant omega about the MCP: |a| = omega^2 * p toward the joint (eq. 2).
    geom = default_calibration().finger("index")
    omega, t = 3.0, np.linspace(0, 1, 7)
    theta = np.stack([omega * t, 0 * t, 0 * t], axis=1)
    dtheta = np.stack([omega + 0 * t, 0 * t, 0 * t], axis=1)
    p = chain_point(geom, 0, 0.03, theta, dtheta, np.zeros_like(theta))
    np.testing.assert_allclose(p.acceleration, -omega**2 * p.position, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(p.velocity, axis=1), omega * 0.03, atol=1e-12)


@pytest.mark.parametrize("hand", ["right", "left"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_analytic_readings_match_finite_differences(hand, seed):
    """Random finger motion on a randomly moving, rotating hand: the accelerometer equals the second
    finite difference of the simulated sensor positions, the gyro the finite-difference rotation rate."""
    calib = default_calibration(hand)
    motion = make_finger_motion("random", 5.0, seed=seed)
    traj = make_hand_motion("random", seed=seed + 10)
    t = np.linspace(0.3, 4.7, 23)
    h = 1e-4
    for fname, geom in calib.fingers.items():
        for sensor in geom.sensors:
            def world(ts):
                base = traj.base_motion(ts)
                th = _finger_state(motion, fname, ts)
                loc = chain_point(geom, sensor.phalanx, sensor.offset_m, *th)
                return base, th, point_in_world(base, point_in_metacarpus(geom, loc))

            base, th, pw = world(t)
            r = ideal_imu(geom, sensor, base, *th)
            r_s = sensor_rotation(geom, sensor, base, th[0])
            _, thm, pm = world(t - h)
            _, thp, pp = world(t + h)
            acc_fd = (pp.position - 2 * pw.position + pm.position) / h**2
            acc_model = apply(r_s, r.acc) + DEFAULT_GRAVITY_WORLD
            np.testing.assert_allclose(acc_model, acc_fd, atol=2e-4 * max(1.0, np.abs(acc_fd).max()))
            vel_fd = (pp.position - pm.position) / (2 * h)
            np.testing.assert_allclose(pw.velocity, vel_fd, atol=1e-6)
            r_m = sensor_rotation(geom, sensor, traj.base_motion(t - h), thm[0])
            r_p = sensor_rotation(geom, sensor, traj.base_motion(t + h), thp[0])
            rel = Rotation.from_matrix(np.einsum("nji,njk->nik", r_m, r_p))   # R(t-h)^T R(t+h)
            gyr_fd = rel.as_rotvec() / (2 * h)
            np.testing.assert_allclose(r.gyr, gyr_fd, atol=1e-5)  # O(h^2 |omega|^3) truncation


def test_hand_trajectory_rates_match_finite_differences():
    traj = make_hand_motion("random", seed=3)
    t = np.linspace(0.0, 5.0, 31)
    h = 1e-4
    b, bm, bp = traj.base_motion(t), traj.base_motion(t - h), traj.base_motion(t + h)
    # world-frame angular velocity: R(t+h) R(t-h)^T = Exp(2h omega)
    rel = Rotation.from_matrix(bp.rotation @ np.transpose(bm.rotation, (0, 2, 1)))
    np.testing.assert_allclose(b.angular_velocity, rel.as_rotvec() / (2 * h), atol=1e-6)
    np.testing.assert_allclose(b.angular_acceleration, (bp.angular_velocity - bm.angular_velocity) / (2 * h), atol=1e-5)
    np.testing.assert_allclose(b.acceleration, (bp.position - 2 * b.position + bm.position) / h**2, atol=1e-4)


def test_left_hand_is_mirror_image_and_flexion_is_palmar():
    right, left = default_calibration("right"), default_calibration("left")
    for f in FINGERS:
        gr, gl = right.finger(f), left.finger(f)
        phi = np.array([0.4, 0.5, 0.3][: gr.n_phalanges])
        theta = joint_to_phalanx_angles(phi)
        pr, pl = joint_positions(gr, theta), joint_positions(gl, theta)
        np.testing.assert_allclose(pl, pr * np.array([-1.0, 1.0, 1.0]), atol=1e-15)
    # flexing a long finger moves its tip palmar (+z of the metacarpus frame) on both hands
    for calib in (right, left):
        g = calib.finger("index")
        tip_flexed = joint_positions(g, np.array([0.5, 1.0, 1.5]))[-1]
        tip_straight = joint_positions(g, np.zeros(3))[-1]
        assert tip_flexed[2] > tip_straight[2] + 0.03


def test_joint_positions_closed_form():
    g = default_calibration().finger("index")
    l0, l1, l2 = g.lengths_m
    tip = joint_positions(g, np.array([np.pi / 2, np.pi / 2, np.pi / 2]))[-1]
    # all phalanges point palmar (+z): tip = base + (l0 + l1 + l2) z
    np.testing.assert_allclose(tip, np.asarray(g.base_position_m) + [0, 0, l0 + l1 + l2], atol=1e-15)
