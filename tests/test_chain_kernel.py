"""The compiled ``chain`` kernel (``estimators/chain_kernel.py``) equals its numpy reference
(``implementation="reference"``) to 1e-9: on random states and inputs (every branch: saturated gyro
and accelerometer, untracked hand, the optical fit's lag error, batch rows, every finger shape), for a whole hand in one
call (``ChainHand``: five fingers, one of them on a single sensor, each with its own step), and on a realistic
simulated recording through the hand pipeline with a saturated sample, a dropped sample, a sensor
falling silent, an optical loss and a reference pose (without the hand's shared acceleration error, which
only the one call for a hand has); that shared error against ``ChainHand.advance_reference``."""
from dataclasses import replace

import numpy as np
import pytest

from service.estimators.chain import BG, TH, Chain, ChainHand, ChainSettings, HoldLog
from service.estimators import chain_kernel as K
from service.estimators.chain_kernel import GA_START, GS, N_STATE
from service.estimators.base import FingerSamples, samples_from_session
from service.model.hand import default_calibration
from service.model.kinematics import BaseMotion
from service.pipeline.hand import HandSession, PipelineSettings
from service.pipeline.mounting import MountingFitSettings
from service.protocol import parse_message
from service.sim.errors import OpticalModel
from service.sim.session import SimConfig, simulate
from scipy.spatial.transform import Rotation

TOL = 1e-9


def _random_hand(rng, batch):
    rot = Rotation.random(int(np.prod(batch, dtype=int)) or 1, random_state=rng).as_matrix().reshape(batch + (3, 3))
    v = lambda scale: rng.normal(0.0, scale, batch + (3,))       # noqa: E731
    return BaseMotion(rot, v(0.3), v(1.0), v(5.0), v(3.0), v(30.0))


def _random_state(rng, est):
    b, s = est.batch_shape, est.n_sensors
    x = np.concatenate([rng.uniform(-1.0, 2.0, b + (s, 1)), rng.normal(0.0, 0.05, b + (s, 1)),
                        rng.normal(0.0, 0.5, b + (s, 3)), rng.normal(0.0, 0.03, b + (s, 9)),
                        rng.normal(0.0, 0.02, b + (s, 1))], axis=-1)
    a = rng.normal(0.0, 0.05, b + (s, N_STATE, N_STATE))
    P = a @ np.swapaxes(a, -1, -2) + 1e-4 * np.eye(N_STATE)       # symmetric positive definite
    return {"x": x, "P": P, "rate": rng.normal(0.0, 3.0, b + (s,)), "hand_acc": rng.normal(0.0, 5.0, b + (3,))}


@pytest.mark.parametrize("finger, batch, extra", [("index", (), ()), ("thumb", (), ()), ("middle", (3,), ()),
                                                  ("ring", (2, 2), ()), ("little", (), ((0, 1.0),))])
def test_kernel_step_equals_the_reference_on_random_inputs(finger, batch, extra):
    rng = np.random.default_rng(["index", "thumb", "middle", "ring", "little"].index(finger))
    geom = default_calibration("right").finger(finger)
    if extra:           # a sensor silent: one sensor left, closed by a second coupling
        geom = replace(geom, sensors=geom.sensors[1:])
    settings = dict(optical_fit_lag_s=0.07, gyro_range_rad_s=30.0, acc_range_m_s2=150.0)
    compiled = Chain(geom, ChainSettings(**settings), batch_shape=batch, extra_couplings=extra)
    reference = Chain(geom, ChainSettings(**settings, implementation="reference"), batch_shape=batch,
                      extra_couplings=extra)
    s = compiled.n_sensors
    for trial in range(12):
        state = _random_state(rng, compiled)
        untracked = trial % 3 == 1
        compiled._hand_untracked = reference._hand_untracked = untracked
        dt = 0.0 if trial == 0 else rng.uniform(0.001, 0.02)
        gyr = rng.normal(0.0, 4.0, batch + (s, 3))
        acc = rng.normal(0.0, 12.0, batch + (s, 3))
        if trial % 4 == 2:
            gyr[..., 0, 1] = 31.0                    # past the gyro's full scale
        if trial % 4 == 3:
            acc[..., -1, 2] = -160.0                 # past the accelerometer's
        hand = _random_hand(rng, batch)
        new_r, theta_r, mode_r = reference._step({k: v.copy() for k, v in state.items()}, dt, gyr, acc, hand)
        new_c, theta_c, mode_c = compiled._step({k: v.copy() for k, v in state.items()}, dt, gyr, acc, hand)
        np.testing.assert_allclose(theta_c, theta_r, rtol=0, atol=TOL)
        np.testing.assert_array_equal(mode_c, mode_r)
        for key in ("x", "rate", "hand_acc"):
            np.testing.assert_allclose(new_c[key], new_r[key], rtol=0, atol=TOL, err_msg=key)
        np.testing.assert_allclose(new_c["P"], new_r["P"], rtol=1e-9, atol=1e-15)


def test_one_call_for_the_hand_equals_the_reference_finger_by_finger():
    rng = np.random.default_rng(11)
    # without the hand's shared acceleration error (it couples the fingers; its own test is below)
    settings = dict(optical_fit_lag_s=0.07, gyro_range_rad_s=30.0, acc_range_m_s2=150.0, hand_acc_error_scale=0.0,
                    hand_acc_error_floor_m_s2=0.0)
    calib = default_calibration("right")
    pairs = []
    for name, geom in calib.fingers.items():
        extra = ()
        if name == "ring":               # a sensor silent: one sensor left, closed by a second coupling
            geom, extra = replace(geom, sensors=geom.sensors[1:]), ((0, 1.0),)
        compiled = Chain(geom, ChainSettings(**settings), extra_couplings=extra)
        reference = Chain(geom, ChainSettings(**settings, implementation="reference"), extra_couplings=extra)
        state, t0 = _random_state(rng, compiled), rng.uniform(0.0, 0.01)
        for est in (compiled, reference):
            est._state, est._t_last = {k: v.copy() for k, v in state.items()}, t0
        pairs.append((compiled, reference))
    together = ChainHand()
    for tick, t in enumerate((0.02, 0.03, 0.045, 0.05)):
        if tick == 2:                    # a known configuration replaces one finger's state: stacked again
            for est in pairs[1]:
                est.known_configuration(np.array([0.3, 0.5, 0.4]), 0.05)
        for compiled, reference in pairs:
            compiled._hand_untracked = reference._hand_untracked = bool(rng.integers(2))
        hand = _random_hand(rng, ())
        gyr = [rng.normal(0.0, 4.0, (c.n_sensors, 3)) for c, _ in pairs]
        acc = [rng.normal(0.0, 12.0, (c.n_sensors, 3)) for c, _ in pairs]
        gyr[0][0, 1] = 31.0 if tick == 1 else gyr[0][0, 1]       # past the gyro's full scale
        acc[3][-1, 2] = -160.0 if tick == 3 else acc[3][-1, 2]   # past the accelerometer's
        assert all(ChainHand.takes(c, t) for c, _ in pairs)
        phi, modes, phalanx_start, sensor_start = together.advance(t, [c for c, _ in pairs], np.concatenate(gyr),
                                                                   np.concatenate(acc), hand)
        for f, (compiled, reference) in enumerate(pairs):
            est = reference.update_trusted(t, gyr[f], acc[f], hand)
            np.testing.assert_allclose(phi[phalanx_start[f]:phalanx_start[f + 1]], est.phi, rtol=0, atol=TOL)
            assert modes[sensor_start[f]:sensor_start[f + 1]] == est.mode.tolist()
            for key in ("x", "rate", "hand_acc"):
                np.testing.assert_allclose(compiled._state[key], reference._state[key], rtol=0, atol=TOL, err_msg=key)
            np.testing.assert_allclose(compiled._state["P"], reference._state["P"], rtol=1e-9, atol=1e-15)
            assert compiled.last_t == t
            # the running integrals for a reference pose's hold, kept by the one call as by each finger
            n = compiled._hold._n
            assert n == reference._hold._n == tick + 1
            for key in ("_t", "_r", "_g"):
                np.testing.assert_allclose(getattr(compiled._hold, key)[:n], getattr(reference._hold, key)[:n],
                                           rtol=0, atol=TOL, err_msg=key)


def _assert_logs_equal(log, expected, label):
    n = expected._n
    assert log._n == n, label
    for key in ("_t", "_r", "_g"):
        np.testing.assert_array_equal(getattr(log, key)[:n], getattr(expected, key)[:n], err_msg=f"{label} {key}")


def test_the_hand_calls_hold_logs_equal_each_fingers_own_to_the_last_bit_through_halvings_and_a_restack():
    """The kernel keeps every finger's running integrals for a reference pose's hold (``HoldLog``) in one hand
    log: bit for bit what ``HoldLog.add`` gives each finger with the same rates and readings, through the
    halving of a full log (capacity 6: full after 6 ticks, then every 3) and a restack (a known configuration
    replaces one finger's state: every finger's history is copied into the new hand log), with the fingers'
    steps differing."""
    rng = np.random.default_rng(21)
    calib = default_calibration("right")
    fingers, own = [], []
    for f, geom in enumerate(calib.fingers.values()):
        est = Chain(geom)
        est._state, est._t_last = _random_state(rng, est), 0.01 - 0.002 * f
        est._hold = HoldLog(est.n_sensors, capacity=6)
        fingers.append(est)
        own.append(HoldLog(est.n_sensors, capacity=6))
    together = ChainHand()
    for tick in range(14):
        t = 0.02 + 0.005 * tick
        if tick == 8:
            fingers[1].known_configuration(np.array([0.3, 0.5, 0.4]), 0.05)
        dts = [t - e._t_last for e in fingers]
        gyr = rng.normal(0.0, 4.0, (sum(e.n_sensors for e in fingers), 3))
        acc = rng.normal(0.0, 12.0, gyr.shape)
        _, _, _, sensor_start = together.advance(t, fingers, gyr, acc, _random_hand(rng, ()))
        for f, e in enumerate(fingers):
            rows = slice(sensor_start[f], sensor_start[f + 1])
            own[f].add(t, dts[f], e._state["rate"], gyr[rows])
            _assert_logs_equal(e._hold, own[f], f"finger {f} at tick {tick}")
    assert own[0]._n == 5 and own[0]._t[0] == 0.02 + 0.005 * 9          # halved at ticks 6, 9 and 12


def test_a_batchs_hold_log_equals_tick_by_tick_to_the_last_bit_through_halvings():
    """``HoldLog.add_many`` (``Chain.run``: the running integrals accumulated over a batch) equals ``add`` tick by
    tick, from an empty log and a part-full one, through the halving of a full log (capacity 8)."""
    rng = np.random.default_rng(22)
    batched, ticks = HoldLog(2, capacity=8), HoldLog(2, capacity=8)
    t0 = 0.0
    for n in (5, 2, 9, 1, 13):
        t = t0 + 0.005 * np.arange(1, n + 1)
        dts = np.diff(t, prepend=t0) if t0 else np.concatenate([[0.0], np.diff(t)])
        rate, gyr = rng.normal(0.0, 3.0, (n, 2)), rng.normal(0.0, 3.0, (n, 2, 3))
        batched.add_many(t, dts, rate, gyr)
        for k in range(n):
            ticks.add(float(t[k]), float(dts[k]), rate[k], gyr[k])
        _assert_logs_equal(batched, ticks, f"after {n} ticks")
        t0 = t[-1]
    with pytest.raises(ValueError, match="capacity"):          # a full log keeps its newer half: even sizes only
        HoldLog(2, capacity=5)


def test_a_runs_hold_log_over_several_batches_equals_the_sample_by_sample_log():
    """``Chain.run`` (``estimate``'s batch path) keeps the hold's running integrals over several batches in a
    row as ``update`` does sample by sample: the same times, and the integrals equal but for rounding (the
    batch's relative rate and a later batch's first step are computed apart from the kernel's)."""
    sess = simulate(SimConfig(motion="random", hand_motion="random", noise="realistic", seed=3, duration_s=1.0,
                              fingers=("index",)))
    smp = samples_from_session(sess, "index")
    geom = sess.calibration.finger("index")
    batched, streamed = Chain(geom), Chain(geom)
    cuts = (0, 37, 38, 120, len(smp))
    for a, b in zip(cuts, cuts[1:]):
        h = smp.hand
        batched.run(FingerSamples(smp.t[a:b], smp.gyr[a:b], smp.acc[a:b], BaseMotion(
            h.rotation[a:b], h.position[a:b], h.velocity[a:b], h.acceleration[a:b], h.angular_velocity[a:b],
            h.angular_acceleration[a:b])))
    for k in range(len(smp)):
        streamed.update(*smp.sample(k))
    n = streamed._hold._n
    assert batched._hold._n == n == len(smp)
    np.testing.assert_array_equal(batched._hold._t[:n], streamed._hold._t[:n])
    for key in ("_r", "_g"):
        np.testing.assert_allclose(getattr(batched._hold, key)[:n], getattr(streamed._hold, key)[:n], rtol=0,
                                   atol=1e-12, err_msg=key)


def _faulty_recording():
    """A realistic recording with the faults a glove and a tracker produce, as messages."""
    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=7, duration_s=2.0,
                       reference_hold_s=0.6, optical=OpticalModel(occlusions_s=((1.2, 1.45),)))
    messages = list(simulate(config).messages(include_truth=False))
    imu = [i for i, m in enumerate(messages) if m["type"] == "imu"]
    saturated = messages[imu[300]]                        # t = 0.15 s
    saturated["gyr"] = [40.0, saturated["gyr"][1], 0.0]   # beyond ±2000 deg/s
    saturated["acc"] = [0.0, 170.0, 0.0]                  # beyond ±16 g
    dropped = {imu[901], imu[1503]}                       # one sample of two sensors missing
    silent = {i for i in imu if messages[i]["id"] == "middle.2" and 1.6 <= messages[i]["t"] < 1.75}
    return [m for i, m in enumerate(messages) if i not in dropped and i not in silent]


def test_kernel_equals_the_reference_through_the_pipeline_on_a_faulty_recording():
    messages = _faulty_recording()
    assert any(m["type"] == "reference_pose" for m in messages)
    runs = {}
    for impl in ("compiled", "reference"):
        # the hand's shared acceleration error and the gyros' angle are ChainHand's (the compiled pipeline's
        # one call per tick), which the reference pipeline does not take; they have their own tests
        params = {"implementation": impl, "hand_acc_error_scale": 0.0, "hand_acc_error_floor_m_s2": 0.0,
                  "gyro_angle_rate_std_rad_s": 0.0}
        session = HandSession("right", PipelineSettings(estimator_params=params))
        frames = [f for m in messages for f in session.handle(parse_message(m)).frames]
        runs[impl] = (frames, session.counters)
    compiled, reference = runs["compiled"][0], runs["reference"][0]
    assert len(compiled) == len(reference) > 150
    assert runs["compiled"][1].references_applied == 1
    statuses = {f.status["optics"] for f in compiled}
    assert statuses == {"tracking", "occluded"}
    assert any(f.status["sensors"]["middle.2"]["silent"] for f in compiled)
    for c, r in zip(compiled, reference):
        assert c.t == r.t and c.modes == r.modes
        for finger, phi in r.joint_angles.items():
            np.testing.assert_allclose(c.joint_angles[finger], phi, rtol=0, atol=TOL, err_msg=f"{finger} at t={c.t}")


@pytest.mark.parametrize("implementation", ["compiled", "reference"])
def test_a_clipped_gyro_stops_the_accelerometer_updates_of_the_whole_finger(implementation):
    """The chain's kinematic terms take every sensor's rate and rate change, so while one gyro of a
    finger is clipped they are unknown for every sensor of it: the other sensor's accelerometer must
    not move its state, whatever it reads (the same state as with any other reading), while with
    both gyros in range it does."""
    rng = np.random.default_rng(5)
    geom = default_calibration("right").finger("index")
    est = Chain(geom, ChainSettings(implementation=implementation))
    state = _random_state(rng, est)
    hand = _random_hand(rng, ())
    gyr = rng.normal(0.0, 2.0, (2, 3))
    acc_a, acc_b = rng.normal(0.0, 9.0, (2, 3)), rng.normal(0.0, 9.0, (2, 3))
    acc_b[0] = acc_a[0]                             # only the second sensor's reading differs

    def step(g, a):
        return est._step({k: v.copy() for k, v in state.items()}, 0.005, g, a, hand)[0]["x"][1]

    clipped = gyr.copy()
    clipped[0, 1] = 2001.0 * np.pi / 180.0          # the first sensor's gyro past ±2000 deg/s
    np.testing.assert_allclose(step(clipped, acc_a), step(clipped, acc_b), rtol=0, atol=1e-8)   # σ = 1e6 m/s²
    assert np.abs(step(gyr, acc_a) - step(gyr, acc_b)).max() > 1e-3


def test_the_hands_shared_acceleration_error_equals_its_reference():
    """``ChainHand`` with the hand's acceleration error ``δ`` as a state every sensor shares: the kernel's
    sequential joint updates (each sensor's ``[x_k, δ]``, every other sensor moved by its correlation with
    ``δ``) equal ``advance_reference`` on random states, cross-covariances and inputs, with a clipped gyro,
    a clipped accelerometer, a finger on a single sensor, a restack and a tick with the optics lost."""
    rng = np.random.default_rng(12)
    settings = dict(optical_fit_lag_s=0.07, gyro_range_rad_s=30.0, acc_range_m_s2=150.0, hand_acc_error_scale=0.5,
                    hand_acc_error_floor_m_s2=0.2)
    calib = default_calibration("right")
    runs = {"kernel": [], "reference": []}
    for name, geom in calib.fingers.items():
        extra = ()
        if name == "ring":               # a sensor silent: one sensor left, closed by a second coupling
            geom, extra = replace(geom, sensors=geom.sensors[1:]), ((0, 1.0),)
        ests = [Chain(geom, ChainSettings(**settings), extra_couplings=extra) for _ in runs]
        state, t0 = _random_state(rng, ests[0]), rng.uniform(0.0, 0.01)
        for est, key in zip(ests, runs):
            est._state, est._t_last = {k: v.copy() for k, v in state.items()}, t0
            runs[key].append(est)
    hands = {key: ChainHand() for key in runs}
    for key in runs:
        hands[key]._stack(runs[key], np.zeros(3))
    n = hands["kernel"]._cx.shape[0]
    cx, dl = rng.normal(0.0, 0.02, (n, N_STATE, 3)), rng.normal(0.0, 1.0, 3)
    a = rng.normal(0.0, 0.5, (3, 3))
    for h in hands.values():
        h._cx[:], h._dl[:], h._pd[:] = cx, dl, a @ a.T + 0.1 * np.eye(3)
    for tick, t in enumerate((0.02, 0.025, 0.035, 0.04, 0.05)):
        if tick == 2:                    # a known configuration replaces one finger's state: stacked again
            for est in (runs["kernel"][1], runs["reference"][1]):
                est.known_configuration(np.array([0.3, 0.5, 0.4]), 0.05)
        for f in range(len(runs["kernel"])):
            runs["kernel"][f]._hand_untracked = runs["reference"][f]._hand_untracked = tick == 3
        hand = _random_hand(rng, ())
        gyr = [rng.normal(0.0, 4.0, (c.n_sensors, 3)) for c in runs["kernel"]]
        acc = [rng.normal(0.0, 12.0, (c.n_sensors, 3)) for c in runs["kernel"]]
        gyr[0][0, 1] = 31.0 if tick == 1 else gyr[0][0, 1]       # past the gyro's full scale
        acc[3][-1, 2] = -160.0 if tick == 4 else acc[3][-1, 2]   # past the accelerometer's
        out = hands["kernel"].advance(t, runs["kernel"], np.concatenate(gyr), np.concatenate(acc), hand)
        want = hands["reference"].advance_reference(t, runs["reference"], np.concatenate(gyr), np.concatenate(acc), hand)
        # the outputs too: every finger's joint angles and every sensor's mode
        np.testing.assert_allclose(out[0], want[0], rtol=0, atol=TOL, err_msg="joint angles")
        assert out[1] == want[1] and list(out[2:]) == list(want[2:])
        k, r = hands["kernel"], hands["reference"]
        assert np.abs(k._dl - dl).max() > 1e-3 or tick == 3        # δ moves (it restarts while the optics are lost)
        for got, want, what in ((k._x, r._x, "x"), (k._rate, r._rate, "rate"), (k._hand_acc, r._hand_acc, "hand_acc"),
                                (k._dl, r._dl, "delta"), (k._cx, r._cx, "C")):
            np.testing.assert_allclose(got, want, rtol=0, atol=TOL, err_msg=what)
        np.testing.assert_allclose(k._p, r._p, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(k._pd, r._pd, rtol=1e-9, atol=1e-15)
        dl = k._dl.copy()


def test_the_shared_error_update_is_the_textbook_kalman_update_of_the_augmented_state():
    """An independent reference for the shared acceleration error δ: for a finger with one sensor, one
    step of ``ChainHand.advance_reference`` equals the Kalman update of the augmented state [x, δ] written
    out directly (the 17 + 3 states' covariance as one block matrix, the Joseph form), and the
    measurement's sensitivity to δ, M, equals finite differences of the predicted specific force."""
    from service.estimators import chain_kernel as K
    from service.estimators.chain import BA, GA, GA_START, GS

    rng = np.random.default_rng(3)
    geom = default_calibration("right").fingers["little"]
    geom = replace(geom, sensors=geom.sensors[1:])
    st = ChainSettings(optical_fit_lag_s=0.07, hand_acc_error_scale=0.5, hand_acc_error_floor_m_s2=0.2)
    est = Chain(geom, st, extra_couplings=((0, 1.0),))
    state = _random_state(rng, est)
    est._state, est._t_last = {k: v.copy() for k, v in state.items()}, 0.0
    h = ChainHand()
    h._stack([est], np.zeros(3))
    cx0, dl0, a = rng.normal(0, 0.02, (1, N_STATE, 3)), rng.normal(0, 1, 3), rng.normal(0, 0.5, (3, 3))
    pd0 = a @ a.T + 0.1 * np.eye(3)
    h._cx[:], h._dl[:], h._pd[:] = cx0, dl0, pd0
    hand, gyr, acc, t = _random_hand(rng, ()), rng.normal(0, 1, (1, 3)), rng.normal(0, 9, (1, 3)), 0.01

    # prediction: δ a first-order Gauss-Markov process, x by the filter's own prediction
    ref = Chain(geom, st, extra_couplings=((0, 1.0),))
    ref._state, ref._t_last = {k: v.copy() for k, v in state.items()}, 0.0
    tau, scale, floor = h._jp[:3]
    q = scale**2 * np.sum((hand.acceleration - state["hand_acc"]) ** 2) + floor**2
    d = np.exp(-t / tau)
    dl, pd, cx = dl0 * d, d * d * pd0 + (1 - d * d) * q * np.eye(3), cx0[0] * d
    x_pred, _, _, rate, prev, P_pred = ref._predict_reference(ref._state, t, gyr, hand)
    fs = t * ref.obs.hinge_rate(gyr) if est._settings_vector[K.ST_GS_LEARN] > 0.5 else np.zeros(1)
    cx[TH] = cx[TH] - t * cx[BG] - fs[0] * cx[GS]         # the angle's prediction moves its cross-covariance
    with_dl = replace(hand, acceleration=hand.acceleration + dl)

    def predicted(h_motion, th):
        force, u, _, sigma, _ = ref._measure_reference(t, gyr, acc, h_motion, th, rate, prev)
        c, s = np.cos(th[0]), np.sin(th[0])
        rx = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
        gm = np.eye(3) + x_pred[0, GA].reshape(3, 3)
        return force[0], gm @ rx @ u[0] + x_pred[0, BA], sigma[0], rx, gm, u[0]

    th = x_pred[:, TH].copy()
    f, p0, sig, rx, gm, u = predicted(with_dl, th)
    m_code = gm @ rx @ est.obs.base.T @ hand.rotation.T
    m_diff = np.column_stack([(predicted(replace(with_dl, acceleration=with_dl.acceleration + 1e-6 * e), th)[1] - p0) / 1e-6
                              for e in np.eye(3)])
    assert np.allclose(m_diff, m_code, atol=1e-7)
    H = np.zeros((3, N_STATE + 3))
    c, s = np.cos(th[0]), np.sin(th[0])
    H[:, TH] = gm @ np.array([0, -s * u[1] + c * u[2], -c * u[1] - s * u[2]])
    H[:, BA] = np.eye(3)
    for i in range(3):
        H[i, GA_START + 3 * i:GA_START + 3 * i + 3] = rx @ u
    H[:, N_STATE:] = m_code
    P = np.block([[P_pred[0], cx], [cx.T, pd]])
    R = sig**2 * np.eye(3)
    gain = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    if est._settings_vector[K.ST_GS_LEARN] <= 0.5:
        gain[GS] = 0.0
    z = np.concatenate([x_pred[0], dl]) + gain @ (f - p0)
    joseph = np.eye(N_STATE + 3) - gain @ H
    P_new = joseph @ P @ joseph.T + gain @ R @ gain.T

    h.advance_reference(t, [est], gyr, acc, hand)
    assert np.allclose(est._state["x"][0], z[:N_STATE], rtol=0, atol=1e-12)
    assert np.allclose(h._dl, z[N_STATE:], rtol=0, atol=1e-12)
    assert np.allclose(est._state["P"][0], P_new[:N_STATE, :N_STATE], rtol=0, atol=1e-12)
    assert np.allclose(h._cx[0], P_new[:N_STATE, N_STATE:], rtol=0, atol=1e-12)
    assert np.allclose(h._pd, P_new[N_STATE:, N_STATE:], rtol=0, atol=1e-12)


def _shared_error_finger(rng):
    """An index finger (two sensors) with the shared acceleration error δ on, and a random state for it."""
    st = ChainSettings(optical_fit_lag_s=0.07, hand_acc_error_scale=0.5, hand_acc_error_floor_m_s2=0.2,
                       acc_range_m_s2=150.0)
    est = Chain(default_calibration("right").fingers["index"], st)
    state = _random_state(rng, est)
    state["x"][:, TH] = [0.3, 0.8]
    return est, state


@pytest.mark.parametrize("implementation", ["kernel", "reference"])
def test_a_later_sensors_predicted_angle_follows_its_offset_corrected_in_the_same_tick(implementation):
    """Within a tick the first sensor's update moves the second sensor's gyro offset b_g through its
    correlation with δ before the second sensor's own update. That correction is of the state before
    the prediction ``θ ← θ + dt (ω̄ - b_g - ...)``, so the angle the second sensor starts its own update
    from must move by ``-dt Δb_g``: with the second accelerometer clipped (no update of its own), its
    final angle with an offset-δ correlation differs from the one without it by exactly ``-dt Δb_g``."""
    rng = np.random.default_rng(21)
    results = []
    est0, state = _shared_error_finger(rng)
    hand, gyr, acc, dt = _random_hand(rng, ()), rng.normal(0.0, 1.0, (2, 3)), rng.normal(0.0, 9.0, (2, 3)), 0.01
    acc[1] = [0.0, 160.0, 0.0]                                   # past the accelerometer's full scale
    cx0, dl0 = rng.normal(0.0, 0.02, (2, N_STATE, 3)), rng.normal(0.0, 1.0, 3)
    cx0[1] = 0.0
    for correlated in (False, True):
        est = Chain(est0.geom, est0.settings)
        est._state, est._t_last = {k: v.copy() for k, v in state.items()}, 0.0
        h = ChainHand()
        h._stack([est], np.zeros(3))
        h._cx[:], h._dl[:], h._pd[:] = cx0, dl0, 0.3 * np.eye(3)
        if correlated:
            h._cx[1, BG] = [0.05, -0.04, 0.03]
        advance = h.advance if implementation == "kernel" else h.advance_reference
        advance(dt, [est], gyr, acc, hand)
        results.append(est._state["x"][1].copy())
    moved = results[1][BG] - results[0][BG]
    assert abs(moved) > 1e-3
    assert results[1][TH] - results[0][TH] == pytest.approx(-dt * moved, abs=1e-10)


@pytest.mark.parametrize("implementation", ["kernel", "reference"])
def test_the_shared_error_decays_over_the_time_since_it_was_advanced_across_a_rebuild(implementation):
    """δ is a first-order Gauss-Markov process of the optics (time constant τ): when the fingers are
    rebuilt (a calibration, an estimator switch, every sensor silent and back) and the new estimators
    join after their own first step, δ must have decayed over the whole time since it was last
    advanced, ``δ e^{-T/τ}`` and ``P_δ e^{-2T/τ} + (1 - e^{-2T/τ}) q I``, not over the new filters' one step
    (accelerometers clipped: no measurement moves it)."""
    rng = np.random.default_rng(22)
    est0, state = _shared_error_finger(rng)
    est = Chain(est0.geom, est0.settings)
    est._state, est._t_last = {k: v.copy() for k, v in state.items()}, 0.0
    h = ChainHand()
    advance = h.advance if implementation == "kernel" else h.advance_reference
    clipped = np.tile([0.0, 160.0, 0.0], (2, 1))
    advance(0.01, [est], rng.normal(0.0, 1.0, (2, 3)), clipped, _random_hand(rng, ()))
    a = rng.normal(0.0, 0.5, (3, 3))
    h._dl[:], h._pd[:] = [1.5, -0.7, 0.4], a @ a.T + 0.1 * np.eye(3)
    dl1, pd1 = h._dl.copy(), h._pd.copy()
    rebuilt = Chain(est0.geom, est0.settings)                    # began alone at t = 0.2 (its own first step)
    rebuilt._state, rebuilt._t_last = {k: v.copy() for k, v in est._state.items()}, 0.2
    hand = _random_hand(rng, ())
    advance(0.205, [rebuilt], rng.normal(0.0, 1.0, (2, 3)), clipped, hand)
    tau, scale, floor = h._jp[:3]
    q = scale**2 * np.sum((hand.acceleration - est._state["hand_acc"]) ** 2) + floor**2
    d = np.exp(-(0.205 - 0.01) / tau)
    np.testing.assert_allclose(h._dl, d * dl1, rtol=0, atol=1e-8)
    np.testing.assert_allclose(h._pd, d * d * pd1 + (1 - d * d) * q * np.eye(3), rtol=0, atol=1e-8)
    # a time before the last one (the source's clock stepped back): δ restarts from its prior
    again = Chain(est0.geom, est0.settings)
    again._state, again._t_last = {k: v.copy() for k, v in est._state.items()}, 0.0
    advance(0.1, [again], rng.normal(0.0, 1.0, (2, 3)), clipped, _random_hand(rng, ()))
    np.testing.assert_allclose(h._dl, 0.0, rtol=0, atol=1e-8)
    np.testing.assert_allclose(h._pd, floor**2 * np.eye(3), rtol=0, atol=1e-8)
    # estimators of other settings for δ (an estimator switch): δ restarts from their prior
    h._dl[:] = 1.0
    switched = Chain(est0.geom, est0.settings.model_copy(update={"hand_acc_error_floor_m_s2": 0.4}))
    switched._state = {k: v.copy() for k, v in est._state.items()}
    h._stack([switched], np.zeros(3))
    assert h._dl.tolist() == [0.0] * 3 and np.allclose(h._pd, 0.4**2 * np.eye(3), rtol=0, atol=1e-15)


def test_a_hand_turning_across_the_hinge_tells_each_still_sensors_angle_through_its_gyros_cross_axes():
    """A finger still on a hand turning at 2 rad/s about the finger base's y axis: each phalanx at angle θ
    sees that rate turned by -θ, so its gyro's cross axes tell θ whatever the accelerometer says. With the
    states 5 deg off (no mounting turn carried yet), one measurement after the tick moves each angle by the
    Kalman gain of its variance against the measurement's, ``(0.1 / 2)² · 0.15 s / dt`` (the optical rate's
    error, counted once per fit window): closed form, and the cross-covariance with δ by the same gain.
    Turning about an oblique axis for 2 s of ticks (no prediction between them), the 5 deg fall as repeated
    measurements average, to 0.46 deg. About the hinge
    axis itself the same rate tells nothing (the angle is unobservable there), nor while
    the finger flexes on the hand (its own rate is on the hinge axis, but the reading is not a still
    phalanx's), nor with the optics lost: the states stay as they were."""
    geom = default_calibration("right").finger("index")
    est = Chain(geom)
    s = est.settings
    truth = np.array([0.4, 0.9])
    dt, w_rate = 0.005, 2.0
    hand = ChainHand()
    p0 = np.diag(np.r_[[0.05**2], np.full(N_STATE - 1, 1e-4)])
    p0[GA_START:GA_START + 9, GA_START:GA_START + 9] = 0.0         # no mounting turn carried yet
    cx0 = np.full((N_STATE, 3), 1e-3)

    def run(w_base, flex=0.0, untracked=False, ticks=1):
        x = np.zeros((2, N_STATE))
        x[:, TH] = truth + np.radians(5.0)
        est._state = {"x": x, "P": np.stack([p0, p0]), "rate": np.zeros(2), "hand_acc": np.zeros(3)}
        est._hand_untracked = untracked
        hand._stack([est], np.zeros(3))
        hand._cx[:] = cx0
        omega = est.obs.base @ w_base                                   # R_M = I: world = metacarpus
        motion = BaseMotion(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), omega, np.zeros(3))
        gyr = []
        for k, th in enumerate(truth):
            c, sn = np.cos(th), np.sin(th)
            seen = np.array([w_base[0] + flex, c * w_base[1] + sn * w_base[2], -sn * w_base[1] + c * w_base[2]])
            gyr.append(est.obs.mount[k].T @ seen)                        # phalanx -> sensor frame
        for _ in range(ticks):
            hand._gyro_angles(np.array(gyr), motion, np.array([dt]), np.array([untracked]))
        return hand._x.copy(), hand._p.copy(), hand._cx.copy()

    x, p, cx = run(np.array([0.0, w_rate, 0.0]))
    r = (s.gyro_angle_rate_std_rad_s / w_rate) ** 2 * s.gyro_angle_window_s / dt
    gain = 0.05**2 / (0.05**2 + r)
    np.testing.assert_allclose(x[:, TH] - truth, (1.0 - gain) * np.radians(5.0), rtol=1e-9)
    np.testing.assert_allclose(p[:, TH, TH], 0.05**2 * (1.0 - gain), rtol=1e-9)
    np.testing.assert_allclose(cx[:, TH], np.tile((1.0 - gain) * cx0[TH], (2, 1)), rtol=1e-9)
    assert gain > 0.03                  # one tick's worth: the rate's error is counted once per fit window
    # a hand turning about an oblique axis (part of it about the hinge): over 2 s of ticks the cross axes
    # alone give each sensor's angle, as n measurements of variance r average: the error falls to r / (r + n P)
    oblique = np.array([0.7, 1.4, -1.0])
    x, p, cx = run(oblique, ticks=400)
    r = (s.gyro_angle_rate_std_rad_s / np.hypot(oblique[1], oblique[2])) ** 2 * s.gyro_angle_window_s / dt
    np.testing.assert_allclose(x[:, TH] - truth, np.radians(5.0) * r / (r + 400 * 0.05**2), rtol=1e-6)
    assert np.abs(np.degrees(x[:, TH] - truth)).max() < 0.5
    for case in (dict(w_base=np.array([w_rate, 0.0, 0.0])), dict(w_base=np.array([0.0, w_rate, 0.0]), flex=3.0),
                 dict(w_base=np.array([0.0, w_rate, 0.0]), untracked=True)):
        x, p, cx = run(**case)
        np.testing.assert_array_equal(x[:, TH], truth + np.radians(5.0))
        np.testing.assert_array_equal(p[:, TH, TH], [0.05**2] * 2)


def test_the_kernels_gyro_angles_equal_the_reference():
    """``chain_kernel._gyro_angles`` (the end of the hand's one call) equals ``ChainHand._gyro_angles`` in numpy
    on random states and cross-covariances of a whole hand turning fast across its fingers' hinge axes, the
    fingers' phalanges nearly still on it (so that measurements are taken), with one finger's gyro clipped,
    one with the optics lost, one just started (no step), one on a fallback closure (a sensor silent: its gyro
    scale state held, which the measurement must leave as it is), with and without cross-axis offsets taken
    off the readings: x, P and the cross-covariances with δ to 1e-12."""
    rng = np.random.default_rng(31)
    calib = default_calibration("right")
    ests = [Chain(replace(geom, sensors=geom.sensors[1:]), extra_couplings=((0, 1.0),)) if name == "ring"
            else Chain(geom) for name, geom in calib.fingers.items()]
    ring = list(calib.fingers).index("ring")
    hand = ChainHand()
    taken = held_taken = 0
    for trial in range(6):
        for e in ests:
            e._state = _random_state(rng, e)
            e._state["x"][:, GA_START:GA_START + 9] *= 0.3
        hand._stack(ests, np.zeros(3))
        hand._cx[:] = rng.normal(0.0, 0.01, hand._cx.shape)
        # offsets on odd trials, with their variance (a third column) on every other of them
        hand.cross_offsets = np.c_[rng.normal(0.0, 0.05, (hand._x.shape[0], 2)),
                                   rng.uniform(0.0, 0.01, (hand._x.shape[0], int(trial % 4 == 3)))] if trial % 2 else None
        rot = Rotation.random(random_state=rng).as_matrix()
        omega = rot @ rng.normal(0.0, 3.0, 3)
        motion = BaseMotion(rot, np.zeros(3), np.zeros(3), np.zeros(3), omega, np.zeros(3))
        # each sensor reads the hand's rate seen from its phalanx at its state's angle, plus a little
        gyr = []
        for e in ests:
            w = e.obs.base.T @ rot.T @ omega
            for k, th in enumerate(e._state["x"][:, TH]):
                c, sn = np.cos(th), np.sin(th)
                seen = np.array([w[0], c * w[1] + sn * w[2], -sn * w[1] + c * w[2]]) + rng.normal(0.0, 0.05, 3)
                gyr.append(e.obs.mount[k].T @ seen)
        gyr = np.array(gyr)
        gyr[hand._sensor_start[1], 2] = 40.0 if trial % 2 else gyr[hand._sensor_start[1], 2]     # clipped
        dts = np.full(len(ests), 0.005)
        dts[3] = 0.0 if trial % 3 == 0 else dts[3]
        untracked = np.zeros(len(ests), dtype=np.bool_)
        untracked[2] = trial % 2 == 0
        before, p_before, cx_before = hand._x.copy(), hand._p.copy(), hand._cx.copy()
        arrays = [hand._x.copy(), hand._p.copy(), hand._cx.copy()]
        K._gyro_angles(motion.flat, gyr, dts, untracked, hand._sensor_start, hand._geo, hand._geo_start, hand._st,
                       *arrays, np.empty(N_STATE), hand._cross_offsets())
        hand._gyro_angles(gyr, motion, dts, untracked)
        for a, b, key in zip(arrays, (hand._x, hand._p, hand._cx), ("x", "P", "cx")):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, err_msg=f"{key} in trial {trial}")
        moved = np.any(hand._x != before, axis=1)
        taken += int(np.sum(moved))
        r = hand._sensor_start[ring]                        # the held scale: exactly as it was
        held_taken += bool(moved[r])
        assert hand._x[r, GS] == before[r, GS] and hand._p[r, GS, GS] == p_before[r, GS, GS]
        assert np.array_equal(hand._cx[r, GS], cx_before[r, GS])
    assert taken >= 10 and held_taken >= 2


def test_the_gyros_cross_axis_offsets_bias_its_angle_unless_taken_off():
    """A still finger on a hand turning at 1.7 rad/s across the hinge, its sensors turned on their phalanges
    (as its calibration states), its gyros reading cross-axis offsets of 4 and 3 deg/s across the rate
    (phalanx frame; MPU-9250 ±5 deg/s): the cross axes then tell the angle
    turned by about |b| / |w| (2.3 and 1.7 deg), and 400 ticks of that measurement
    settle on it, not on the angle (closed form: the state moves from its start toward the measured angle by
    ``n P / (r + n P)``). With the offsets taken off (``ChainHand.cross_offsets``, as the pipeline sets them
    from the flexion-axis fit) the same ticks settle on the angle, to 0.5 deg (taken off in the sensor's frame,
    before the mounting, they would not). Offsets known only to their prior (none taken off, their variance
    ``σ_b²`` given) make each measurement count less: its variance is ``(σ_rate² + σ_b²) / |w|²`` per window,
    so the same ticks move the state less far toward the biased angle."""
    index = default_calibration("right").finger("index")
    # sensors turned on their phalanges as the calibration states: the offsets are in the phalanx frame the
    # mounting turns the reading into, not in the sensor's own
    turned = (Rotation.from_rotvec([0.3, -0.2, 0.5]), Rotation.from_rotvec([-0.4, 0.1, 0.2]))
    geom = replace(index, sensors=tuple(replace(sp, mounting=tuple(r.as_quat())) for sp, r in zip(index.sensors, turned)))
    truth = np.array([0.4, 0.9])
    w_base, dt, ticks = np.array([0.7, 1.4, -1.0]), 0.005, 400
    p0 = np.diag(np.r_[[0.05**2], np.full(N_STATE - 1, 1e-4)])
    p0[GA_START:GA_START + 9, GA_START:GA_START + 9] = 0.0         # no mounting turn carried yet
    seen = []
    for th in truth:
        c, sn = np.cos(th), np.sin(th)
        seen.append([w_base[0], c * w_base[1] + sn * w_base[2], -sn * w_base[1] + c * w_base[2]])
    seen = np.array(seen)
    # (b_y, b_z) per sensor in the phalanx frame, 4 and -3 deg/s across the rate each phalanx sees
    across = np.c_[-seen[:, 2], seen[:, 1]] / np.hypot(seen[:, 1], seen[:, 2])[:, None]
    b = np.radians([[4.0], [-3.0]]) * across

    def settle(taken_off, var=None):
        est = Chain(geom)
        x = np.zeros((2, N_STATE))
        x[:, TH] = truth + np.radians(5.0)
        est._state = {"x": x, "P": np.stack([p0, p0]), "rate": np.zeros(2), "hand_acc": np.zeros(3)}
        est._hand_untracked = False
        hand = ChainHand()
        hand._stack([est], np.zeros(3))
        hand.cross_offsets = b.copy() if taken_off else None
        if var is not None:
            hand.cross_offsets = np.c_[np.zeros((2, 2)), np.full(2, var)]
        omega = est.obs.base @ w_base                                   # R_M = I: world = metacarpus
        motion = BaseMotion(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), omega, np.zeros(3))
        reading = seen + np.c_[np.zeros(2), b]
        gyr = np.array([est.obs.mount[k].T @ reading[k] for k in range(2)])   # phalanx -> sensor frame
        for _ in range(ticks):
            hand._gyro_angles(gyr, motion, np.array([dt]), np.array([False]))
        return hand._x[:, TH] - truth, reading

    s = ChainSettings()
    r = (s.gyro_angle_rate_std_rad_s / np.hypot(w_base[1], w_base[2])) ** 2 * s.gyro_angle_window_s / dt
    keep = r / (r + ticks * 0.05**2)                     # what is left of the start's distance to the measured angle
    error, reading = settle(False)
    bias = np.arctan2(seen[:, 2], seen[:, 1]) - np.arctan2(reading[:, 2], reading[:, 1])   # measured angle - truth
    np.testing.assert_allclose(error, bias + (np.radians(5.0) - bias) * keep, rtol=1e-6)
    assert np.all(np.abs(np.degrees(error)) > 1.5)
    error, _ = settle(True)
    np.testing.assert_allclose(error, np.radians(5.0) * keep, rtol=1e-6)
    assert np.abs(np.degrees(error)).max() < 0.5
    var = MountingFitSettings().offset_std_rad_s ** 2
    r_var = (s.gyro_angle_rate_std_rad_s ** 2 + var) / (w_base[1] ** 2 + w_base[2] ** 2) * s.gyro_angle_window_s / dt
    keep_var = r_var / (r_var + ticks * 0.05**2)
    error, _ = settle(False, var)
    np.testing.assert_allclose(error, bias + (np.radians(5.0) - bias) * keep_var, rtol=1e-6)
    assert keep_var > 1.2 * keep


def test_the_kernels_gyro_angles_equal_the_numpy_step_after_the_kernel_through_the_pipeline(monkeypatch):
    """Through the hand pipeline on a realistic recording with a turning hand (and its faults): the frames with
    the gyro angles in the kernel equal those with the numpy step run after a kernel call without it, to 1e-9;
    and the step acts (the frames differ from those with it off)."""
    messages = _faulty_recording()

    def frames(params=None):
        session = HandSession("right", PipelineSettings(estimator_params=params or {}))
        return [f for m in messages for f in session.handle(parse_message(m)).frames]

    compiled, off = frames(), frames({"gyro_angle_rate_std_rad_s": 0.0})
    kernel_advance = ChainHand.advance

    def numpy_after_the_kernel(self, t, estimators, gyr, acc, hand):
        if not self._stacked(estimators):
            self._stack(estimators, hand.acceleration)
        dts = np.array([t - e._t_last for e in estimators])
        untracked = np.array([e._hand_untracked for e in estimators])
        kept = self._st[:, K.ST_GA_RATE_STD].copy()
        self._st[:, K.ST_GA_RATE_STD] = 0.0                # the kernel without the step
        out = kernel_advance(self, t, estimators, gyr, acc, hand)
        self._st[:, K.ST_GA_RATE_STD] = kept
        self._gyro_angles(gyr, hand, dts, untracked)
        return out

    monkeypatch.setattr(ChainHand, "advance", numpy_after_the_kernel)
    reference = frames()
    assert len(compiled) == len(reference) == len(off) > 150
    for c, r in zip(compiled, reference):
        assert c.t == r.t and c.modes == r.modes
        for finger, phi in r.joint_angles.items():
            np.testing.assert_allclose(c.joint_angles[finger], phi, rtol=0, atol=TOL, err_msg=f"{finger} at t={c.t}")
    assert max(np.abs(c.joint_angles[f] - o.joint_angles[f]).max() for c, o in zip(compiled, off) for f in c.joint_angles) > 1e-4


def test_the_gyro_angle_read_from_a_simulated_turning_hand_is_each_sensors_phalanx_angle():
    """Against the simulator's own kinematics (noise-free, a hand turning about random axes so the hand's
    rotation is not the identity; the thumb, whose base frame is turned out of the hand's plane, and the
    index): at every tick the step takes, the angle it reads from the simulated gyro readings and hand
    motion is the simulated phalanx angle. A state put at the truth is not moved (the innovation is
    nothing), one put 5 deg off either way is moved back toward it, on many ticks and sensors. A wrong
    frame (the hand's rotation or a finger base transposed) or a wrong sign fails it."""
    from service.model.hand import joint_to_phalanx_angles
    session = simulate(SimConfig(noise="none", seed=2, hand_motion="random", fingers=("thumb", "index"), duration_s=1.0))
    ests = [Chain(session.calibration.finger(f)) for f in ("thumb", "index")]
    hand = ChainHand()
    p0 = np.diag(np.r_[[0.05**2], np.full(N_STATE - 1, 1e-4)])
    p0[GA_START:GA_START + 9, GA_START:GA_START + 9] = 0.0
    taken = 0
    for i in range(0, len(session.t), 4):
        motion = BaseMotion(*(getattr(session.base, k)[i] for k in BaseMotion.__dataclass_fields__))
        truth = np.concatenate([joint_to_phalanx_angles(session.joint_angles[e.geom.name][i])[
            [sp.phalanx for sp in e.geom.sensors]] for e in ests])
        moved = {}
        for off in (0.0, np.radians(5.0), -np.radians(5.0)):
            for e, rows in zip(ests, (slice(0, 2), slice(2, 4))):
                x = np.zeros((2, N_STATE))
                x[:, TH] = truth[rows] + off
                e._state = {"x": x, "P": np.stack([p0, p0]), "rate": np.zeros(2), "hand_acc": np.zeros(3)}
                e._hand_untracked = False
            hand._stack(ests, np.zeros(3))
            hand._gyro_angles(session.gyr[i], motion, np.array([0.005, 0.005]), np.array([False, False]))
            moved[off] = hand._x[:, TH] - (truth + off)
        took = moved[np.radians(5.0)] != 0.0
        assert np.array_equal(took, moved[-np.radians(5.0)] != 0.0)
        assert np.all(np.abs(moved[0.0]) < 1e-6)
        assert np.all(moved[np.radians(5.0)][took] < 0.0) and np.all(moved[-np.radians(5.0)][took] > 0.0)
        taken += int(took.sum())
    assert taken > 40


def test_the_gyro_angle_of_a_sensor_turned_on_its_phalanx_is_the_angle_less_the_mounting_state():
    """The index's sensors sit turned by 4 deg about the hinge axis, which its calibration does not know
    (simulated, noise-free, a turning hand). The gyro then reads the phalanx angle plus that turn, which
    the filter carries as the mounting state ``G = -√2 · 4 deg`` along the hinge rotation (as the
    accelerometer sees it, item 5): with the state at the truth and that mounting, the step finds nothing
    to correct; with the mounting's sign flipped it would find 8 deg."""
    from service.model.hand import joint_to_phalanx_angles
    from service.estimators.chain import GA, _HINGE_ROTATION
    turn = np.radians(4.0)
    calib = default_calibration("right")
    index = calib.finger("index")
    sensors = tuple(replace(sp, mounting=tuple(Rotation.from_rotvec([turn, 0.0, 0.0]).as_quat())) for sp in index.sensors)
    turned = replace(calib, fingers={**calib.fingers, "index": replace(index, sensors=sensors)})
    session = simulate(SimConfig(noise="none", seed=3, hand_motion="random", fingers=("index",), duration_s=1.0,
                                 calibration=turned))
    est = Chain(index)                                          # the nominal calibration: no turn known
    hand = ChainHand()
    p0 = np.diag(np.r_[[0.05**2], np.full(N_STATE - 1, 1e-4)])
    taken = 0
    for i in range(0, len(session.t), 2):
        motion = BaseMotion(*(getattr(session.base, k)[i] for k in BaseMotion.__dataclass_fields__))
        truth = joint_to_phalanx_angles(session.joint_angles["index"][i])[[sp.phalanx for sp in index.sensors]]
        moved = {}
        for off in (0.0, np.radians(5.0)):
            x = np.zeros((2, N_STATE))
            x[:, TH] = truth + off
            x[:, GA] = -np.sqrt(2.0) * turn * _HINGE_ROTATION
            est._state = {"x": x, "P": np.stack([p0, p0]), "rate": np.zeros(2), "hand_acc": np.zeros(3)}
            est._hand_untracked = False
            hand._stack([est], np.zeros(3))
            hand._gyro_angles(session.gyr[i], motion, np.array([0.005]), np.array([False]))
            moved[off] = hand._x[:, TH] - (truth + off)
        took = moved[np.radians(5.0)] != 0.0
        assert np.all(np.abs(moved[0.0]) < 1e-6) and np.all(moved[np.radians(5.0)][took] < 0.0)
        taken += int(took.sum())
    assert taken > 20


def test_the_default_live_pipeline_takes_the_gyro_angle():
    """The hand's one call in the live pipeline (the default settings) takes the gyro's angle, with the gyros'
    cross-axis offsets taken off: on a hand turning across the hinges its frames differ from those with the
    measurement off and from those with the offsets left on (a call left out of the hand's path, or the
    offsets not passed to it, would leave them equal), each stacked sensor given its own fit's offsets."""
    session = simulate(SimConfig(noise="both", seed=2, hand_motion="random", fingers=("index",), duration_s=1.5))
    messages = [parse_message(m) for m in session.messages(include_truth=False)]
    out, sessions = {}, {}
    for key, params in (("on", {}), ("off", {"gyro_angle_rate_std_rad_s": 0.0}),
                        ("offsets left on", {"gyro_angle_cross_offsets": False})):
        hs = sessions[key] = HandSession("right", PipelineSettings(estimator_params=params))
        out[key] = np.array([f.joint_angles["index"] for m in messages for f in hs.handle(m).frames])
    assert out["on"].shape == out["off"].shape and np.abs(out["on"] - out["off"]).max() > 1e-3
    # each stacked sensor gets its own fit's offsets (they differ from sensor to sensor by now)
    hs = sessions["on"]
    ids = tuple(sp.id for e in hs._together._estimators for sp in e.geom.sensors)
    fits = hs._mount_fits
    own = np.concatenate([fits.cross_offsets(fits.rows((sid,)), np.empty((1, 3))) for sid in ids])
    np.testing.assert_array_equal(hs._together.cross_offsets, own)
    assert len(ids) == 2 and np.abs(own[0, :2] - own[1, :2]).min() > 1e-4 and np.all(own[:, 2] > 0.0)
    # and it takes the gyros' cross-axis offsets off as the flexion-axis fit finds them
    assert np.abs(out["on"] - out["offsets left on"]).max() > 1e-4
