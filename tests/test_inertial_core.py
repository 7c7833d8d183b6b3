"""The inertial-frame core (``rigid/inertial.py``): compiled kernel == numpy reference, gyro error
estimation on closed-form cases, the second reference, bad input."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.estimators.rigid import inertial_kernel as K
from service.estimators.rigid.filters import InertialImu
from service.estimators.rigid.inertial import InertialSettings

RATE = 200.0


def spinning_body(seed=3, seconds=150.0, scale=(0.01, -0.008, 0.005), bias=(0.01, -0.005, 0.008)):
    """A body tumbling at up to ~12 rad/s about its (fixed) centre: exact orientation (rates held
    over each sample interval, so the strapdown integration is exact), accelerometer = gravity +
    noise, gyro with a per-axis scale-factor error, a bias and noise. World frame z up."""
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE)
    t = np.arange(n) / RATE
    f, a, p = rng.uniform(0.05, 0.4, (3, 3)), rng.uniform(2, 5, (3, 3)), rng.uniform(0, 2 * np.pi, (3, 3))
    w = np.stack([np.sum(a[i][:, None] * np.sin(2 * np.pi * f[i][:, None] * t + p[i][:, None]), 0) for i in range(3)], 1)
    steps = Rotation.from_rotvec(w[1:] / RATE)
    q = np.empty((n, 4))
    r = Rotation.identity()
    q[0] = r.as_quat()
    for k in range(1, n):
        r = r * steps[k - 1]
        q[k] = r.as_quat()
    acc = Rotation.from_quat(q).inv().apply([0.0, 0.0, 9.81]) + rng.normal(0, 0.05, (n, 3))
    gyr = w * (1 + np.asarray(scale)) + np.asarray(bias) + rng.normal(0, 0.003, (n, 3))
    return q, gyr, acc


def inclination_deg(q_est_xyzw, q_true_xyzw, up=(0.0, 0.0, 1.0)):
    a = Rotation.from_quat(q_est_xyzw).inv().apply(up)
    b = Rotation.from_quat(q_true_xyzw).inv().apply(up)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


@pytest.fixture(scope="module")
def body():
    return spinning_body()


def test_scale_factor_error_is_estimated_and_removes_the_drift(body):
    q, gyr, acc = body
    with_scale = InertialImu(1 / RATE, up=(0, 0, 1))
    without = InertialImu(1 / RATE, InertialSettings(scale_sigma_init=0.0), up=(0, 0, 1))
    e_with = inclination_deg(with_scale.run(gyr, acc), q)
    e_without = inclination_deg(without.run(gyr, acc), q)
    last = slice(-30 * int(RATE), None)
    rms_with, rms_without = np.sqrt(np.mean(e_with[last] ** 2)), np.sqrt(np.mean(e_without[last] ** 2))
    _, scale = with_scale.gyro_errors
    np.testing.assert_allclose(scale, [0.01, -0.008, 0.005], atol=0.003)
    assert np.all(without.gyro_errors[1] == 0.0)
    assert rms_with < 0.6 and rms_with < 0.3 * rms_without


def test_bias_at_rest_is_the_mean_gyro_reading():
    rng = np.random.default_rng(5)
    n = int(30 * RATE)
    bias = np.radians([0.8, -0.5, 0.3])                      # within the 2 deg/s clip
    tilt = Rotation.from_euler("xy", [20, -35], degrees=True)
    acc = tilt.inv().apply([0.0, 0.0, 9.81]) + rng.normal(0, 0.02, (n, 3))
    gyr = bias + rng.normal(0, 0.002, (n, 3))
    f = InertialImu(1 / RATE, up=(0, 0, 1))
    q = f.run(gyr, acc)
    np.testing.assert_allclose(f.gyro_errors[0], bias, atol=np.radians(0.02))
    assert f.state[0, K.REST] == 1.0
    assert inclination_deg(q[-1:], tilt.as_quat()[None])[0] < 0.2


@pytest.mark.parametrize("second", [False, True])
def test_compiled_kernel_equals_the_numpy_reference(body, second):
    q, gyr, acc = body
    n, b = 1500, 3
    sl = slice(2000, 2000 + n)
    # the third sensor spins 8x faster: strapdown half-angles up to ~0.25 rad, beyond the kernel's
    # series for sin/cos (0.1 rad), so both of its branches are compared
    g = np.stack([gyr[sl], gyr[sl] * 1.01, gyr[sl] * 8.0 + 0.01], axis=1)
    a = np.stack([acc[sl], acc[sl][:, [1, 2, 0]], acc[sl] * 1.02], axis=1)
    g[300:310, 1] = np.nan                                   # missing gyro samples
    a[400:405, 2] = np.nan                                   # missing accelerometer samples
    a[500, 0] = 0.0                                          # an all-zero accelerometer reading
    rw = rs = None
    if second:
        east_s = Rotation.from_quat(q[sl]).inv().apply([1.0, 0.0, 0.0])
        rw = np.tile([1.0, 0.0, 0.0], (n, b, 1))
        rs = np.repeat(east_s[:, None], b, axis=1)
        rs[600:650, 1] = np.nan                              # missing references are skipped
    kw = dict(up=(0.0, 1.0, 0.0), batch_shape=(b,))          # a y-up world exercises the frame change
    fast, ref = InertialImu(1 / RATE, engine="numba", **kw), InertialImu(1 / RATE, engine="numpy", **kw)
    out = fast.run(g, a, 1 / RATE, rw, rs)
    assert np.all(np.isfinite(out)) and np.all(np.isfinite(fast.state[:, K.X:K.P + 36]))
    np.testing.assert_allclose(out, ref.run(g, a, 1 / RATE, rw, rs), atol=1e-9)
    np.testing.assert_allclose(fast.state, ref.state, atol=1e-9)
    stream = InertialImu(1 / RATE, engine="numba", **kw)
    for k in range(n):
        last = stream.update(g[k], a[k], 1 / RATE, None if rw is None else rw[k], None if rs is None else rs[k])
    np.testing.assert_allclose(last, fast.quaternion, atol=1e-12)
    np.testing.assert_allclose(stream.state, fast.state, atol=1e-12)


def test_second_reference_fixes_the_heading(body):
    q, gyr, acc = body
    # the true heading starts 60 deg away from where the filter starts (identity)
    truth = Rotation.from_euler("z", 60, degrees=True) * Rotation.from_quat(q)
    east_s = truth.inv().apply([1.0, 0.0, 0.0])
    f = InertialImu(1 / RATE, up=(0, 0, 1))
    est = f.run(gyr, acc, None, np.tile([1.0, 0.0, 0.0], (len(q), 1)), east_s)
    err = (Rotation.from_quat(est[-2000:]).inv() * truth[-2000:]).magnitude()
    assert np.degrees(np.max(err)) < 2.0
    free = InertialImu(1 / RATE, up=(0, 0, 1)).run(gyr, acc)
    err_free = (Rotation.from_quat(free[-2000:]).inv() * truth[-2000:]).magnitude()
    assert np.degrees(np.median(err_free)) > 50.0             # without it the heading error stays


def test_bad_input_is_skipped_without_touching_the_state(body):
    q, gyr, acc = body
    f = InertialImu(1 / RATE, up=(0, 0, 1))
    f.run(gyr[:500], acc[:500])
    before = f.state.copy()
    f.update([np.nan, 0.0, 0.0], [0.0, 0.0, np.inf])
    np.testing.assert_array_equal(f.state, before)
    with pytest.raises(ValueError, match="built for dt"):
        f.update(gyr[500], acc[500], 0.01)
    with pytest.raises(ValueError, match="sampling interval"):
        InertialImu(0.0)
    with pytest.raises(ValueError, match="engine"):
        InertialImu(0.005, engine="fortran")


def test_with_the_scale_states_off_it_is_vqf(body):
    """The shared part (inertial-frame low-pass, full inclination correction, bias from motion and
    from rests) equals VQF's 6D filter, the peer library, on a rest followed by tumbling."""
    import vqf
    q, gyr, acc = body
    rng = np.random.default_rng(8)
    rest = int(10 * RATE)
    tilt = Rotation.from_quat(q[0])
    g = np.concatenate([np.radians([0.4, -0.3, 0.2]) + rng.normal(0, 0.002, (rest, 3)), gyr[: int(40 * RATE)]])
    a = np.concatenate([tilt.inv().apply([0.0, 0.0, 9.81]) + rng.normal(0, 0.02, (rest, 3)), acc[: int(40 * RATE)]])
    expected = vqf.VQF(1 / RATE).updateBatch(np.ascontiguousarray(g), np.ascontiguousarray(a))["quat6D"]
    ours = InertialImu(1 / RATE, InertialSettings(scale_sigma_init=0.0), up=(0, 0, 1)).run(g, a)
    ours_wxyz = np.concatenate([ours[:, 3:], ours[:, :3]], axis=1)
    sign = np.sign(np.sum(ours_wxyz * expected, axis=1))[:, None]
    np.testing.assert_allclose(ours_wxyz * sign, expected, atol=1e-9)
