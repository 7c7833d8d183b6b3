"""The rigid-IMU cores against peer implementations: ahrs (Madgwick), filterpy (Kalman), scipy (quaternions)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.estimators import kalman
from service.model import quaternion as quat
from service.estimators.rigid.ekf import BatchedKalman, FilterpyKalman
from service.estimators.rigid.madgwick import madgwick_step


def test_madgwick_without_second_reference_equals_ahrs():
    ahrs = pytest.importorskip("ahrs")
    rng = np.random.default_rng(3)
    n, dt, beta = 400, 1.0 / 200.0, 0.041
    gyr = rng.normal(0, 0.8, (n, 3))
    acc = np.array([0.5, -0.3, 9.6]) + rng.normal(0, 0.6, (n, 3))
    peer = ahrs.filters.Madgwick(gain=beta, Dt=dt)
    q_peer = np.array([0.9, 0.1, -0.3, 0.2])
    q_peer /= np.linalg.norm(q_peer)
    q_ours = q_peer.copy()
    for k in range(n):
        q_peer = peer.updateIMU(q_peer, gyr=gyr[k], acc=acc[k], dt=dt)
        q_ours = madgwick_step(q_ours, gyr[k], dt, beta, [np.array([0.0, 0.0, 1.0])], [acc[k]])
        np.testing.assert_allclose(q_ours, q_peer, rtol=0, atol=1e-9)


def test_madgwick_converges_to_both_references():
    # a static sensor: the filter must find the orientation that maps both references
    truth = Rotation.from_euler("xyz", [20, -35, 50], degrees=True)
    up, north = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0])
    acc, mag = truth.inv().apply(up) * 9.81, truth.inv().apply(north)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for _ in range(4000):
        q = madgwick_step(q, np.zeros(3), 0.01, 0.5, [up, north], [acc, mag])
    got = Rotation.from_quat(quat.to_xyzw(q))
    assert (got.inv() * truth).magnitude() < np.radians(0.2)


def test_quaternion_helpers_match_scipy():
    rng = np.random.default_rng(1)
    a, b = Rotation.random(20, random_state=2), Rotation.random(20, random_state=3)
    qa, qb = quat.from_xyzw(a.as_quat()), quat.from_xyzw(b.as_quat())
    prod = Rotation.from_quat(quat.to_xyzw(quat.multiply(qa, qb)))
    assert np.allclose((prod.inv() * (a * b)).magnitude(), 0, atol=1e-12)
    np.testing.assert_allclose(quat.to_matrix(qa), a.as_matrix(), atol=1e-12)
    v = rng.normal(size=(20, 3))
    e = Rotation.from_quat(quat.to_xyzw(quat.exp_rotvec(v)))
    assert np.allclose((e.inv() * Rotation.from_rotvec(v)).magnitude(), 0, atol=1e-12)
    np.testing.assert_allclose(quat.exp_rotvec(np.zeros((1, 3))), [[1, 0, 0, 0]])


def test_batched_kalman_equals_filterpy():
    rng = np.random.default_rng(5)
    n, m, batch = 6, 6, (3, 2)
    A = rng.normal(size=batch + (n, n))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(n)
    F = np.eye(n) + 0.05 * rng.normal(size=batch + (n, n))
    Q = 0.01 * np.eye(n) * np.ones(batch + (1, 1))
    H = rng.normal(size=batch + (m, n))
    R = 0.2 * np.eye(m) * np.ones(batch + (1, 1))
    y = rng.normal(size=batch + (m,))
    fp, bk = FilterpyKalman(), BatchedKalman()
    P1, P2 = fp.predict(P, F, Q), bk.predict(P, F, Q)
    np.testing.assert_allclose(P1, P2, rtol=1e-12, atol=1e-12)
    (dx1, Pa), (dx2, Pb) = fp.update(P1, H, R, y), bk.update(P2, H, R, y)
    np.testing.assert_allclose(dx1, dx2, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(Pa, Pb, rtol=1e-10, atol=1e-12)
    # Joseph form keeps the covariance symmetric
    np.testing.assert_allclose(Pb, np.swapaxes(Pb, -1, -2), atol=1e-12)
    assert kalman.predict is BatchedKalman.predict


def _rigid_body(seed=0, n=4000, rate=200.0, gyro_bias=(0.0, 0.0, 0.0)):
    """A rigid IMU on the simulator's randomly moving hand: ideal readings plus a gyro bias."""
    from service.sim.motions import make_hand_motion
    traj = make_hand_motion("random", seed=seed)
    t = np.arange(n) / rate
    b = traj.base_motion(t)
    g = np.array([0.0, -9.81, 0.0])
    acc = np.einsum("nji,nj->ni", b.rotation, b.acceleration - g)
    gyr = np.einsum("nji,nj->ni", b.rotation, b.angular_velocity) + np.asarray(gyro_bias)
    return t, b.rotation, gyr, acc


def _inclination_deg(q_xyzw, rot_true):
    up_est = Rotation.from_quat(q_xyzw).inv().apply([0.0, 1.0, 0.0])
    up_true = np.einsum("nji,j->ni", rot_true, [0.0, 1.0, 0.0])
    return np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, axis=1), -1, 1)))


@pytest.mark.parametrize("core", ["madgwick", "ekf", "inertial"])
def test_rigid_cores_track_inclination_of_a_moving_body(core):
    from service.estimators.rigid.filters import EkfImu, InertialImu, MadgwickImu
    t, rot, gyr, acc = _rigid_body(gyro_bias=(0.02, -0.01, 0.015))
    f = {"madgwick": lambda: MadgwickImu(beta=0.05), "ekf": lambda: EkfImu(use_filterpy=False),
         "inertial": lambda: InertialImu(1 / 200.0)}[core]()
    f.quaternion = Rotation.from_matrix(rot[0]).as_quat()
    q = f.run(gyr, acc, 1 / 200.0)
    incl = _inclination_deg(q, rot)
    # the body accelerates (up to 1.4 m/s²), which a gravity reference cannot tell apart: ~2 deg is physics
    assert np.sqrt(np.mean(incl[400:] ** 2)) < 3.0


def test_second_reference_removes_heading_drift():
    from service.estimators.rigid.filters import EkfImu, MadgwickImu
    t, rot, gyr, acc = _rigid_body(gyro_bias=(0.02, -0.01, 0.015))
    north = np.array([0.0, 0.0, -1.0])
    north_s = np.einsum("nji,j->ni", rot, north)
    for f in (MadgwickImu(beta=0.05), EkfImu(use_filterpy=False)):
        f.quaternion = Rotation.from_matrix(rot[0]).as_quat()
        q = f.run(gyr, acc, 1 / 200.0, np.tile(north, (len(t), 1)), north_s)
        err = (Rotation.from_quat(q[-1]).inv() * Rotation.from_matrix(rot[-1])).magnitude()
        assert np.degrees(err) < 2.0


def test_fast_objective_equals_the_explicit_formula():
    from service.estimators.rigid.madgwick import objective_and_jacobian, objective_and_jacobian_fast
    rng = np.random.default_rng(9)
    q = quat.normalize(rng.normal(size=(7, 2, 4)))
    d, s = rng.normal(size=(7, 2, 3)), rng.normal(size=(7, 2, 3))
    f1, j1 = objective_and_jacobian(q, d, s)
    f2, j2 = objective_and_jacobian_fast(q, d, s)
    np.testing.assert_allclose(f2, f1, atol=1e-13)
    np.testing.assert_allclose(j2, j1, atol=1e-13)


@pytest.mark.parametrize("second", [False, True])
def test_compiled_madgwick_equals_the_numpy_reference(second):
    from service.estimators.rigid.filters import MadgwickImu
    rng = np.random.default_rng(11)
    n, b = 500, 3
    gyr = rng.normal(0, 1.0, (n, b, 3))
    acc = np.array([0.4, -0.2, 9.7]) + rng.normal(0, 1.0, (n, b, 3))
    rw = np.tile([1.0, 0.0, 0.0], (n, b, 1)) if second else None
    rs = rng.normal(0, 1.0, (n, b, 3)) if second else None
    if second:
        rs[100:120] = np.nan                                  # missing references are skipped
    fast = MadgwickImu(beta=0.05, up=(0.0, 0.0, 1.0), batch_shape=(b,), engine="numba")
    ref = MadgwickImu(beta=0.05, up=(0.0, 0.0, 1.0), batch_shape=(b,), engine="numpy")
    np.testing.assert_allclose(fast.run(gyr, acc, 0.005, rw, rs), ref.run(gyr, acc, 0.005, rw, rs), atol=1e-12)
    stream = MadgwickImu(beta=0.05, up=(0.0, 0.0, 1.0), batch_shape=(b,), engine="numba")
    last = [stream.update(gyr[k], acc[k], 0.005, None if rw is None else rw[k], None if rs is None else rs[k]) for k in range(n)][-1]
    np.testing.assert_allclose(last, fast.quaternion, atol=1e-12)
