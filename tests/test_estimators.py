"""Estimators: closed forms, noise-free accuracy, signs, streaming == batch, state, bad input."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.hand import default_calibration, joint_to_phalanx_angles
from service.model.kinematics import BaseMotion, ideal_imu
from service.estimators.base import FingerSamples, samples_from_session, MODE_FAST, MODE_NO_INFO
from service.estimators.registry import REGISTRY
from service.estimators.switching import Switching
from service.estimators.vector import VectorObservation
from service.sim.session import SimConfig, simulate

ALL = sorted(REGISTRY)
FINGERS = ("thumb", "index", "middle", "ring", "little")


def _rms_deg(track, truth, skip=0):
    err = np.degrees(track.phi - truth)[skip:]
    return np.sqrt((err**2).mean(axis=0))


def _run(name, sess, finger, settings=None):
    est = REGISTRY[name](sess.calibration.finger(finger), settings=settings,
                         initial_theta=joint_to_phalanx_angles(sess.joint_angles[finger][0]))
    return est.run(samples_from_session(sess, finger))


@pytest.fixture(scope="module")
def grasp_sessions():
    return {hm: simulate(SimConfig(motion="grasp", t_m_s=3.0, noise="none", hand_motion=hm, seed=2))
            for hm in ("still", "slow-rotation", "fast-reach")}


def test_vector_observation_is_exact_in_static_poses():
    rng = np.random.default_rng(0)
    for hand in ("right", "left"):
        calib = default_calibration(hand)
        for k in range(5):
            base = BaseMotion.still(Rotation.random(random_state=k).as_matrix(), np.zeros(3), 1)
            for finger, geom in calib.fingers.items():
                phi = rng.uniform(0.0, 1.0, (1, geom.n_phalanges))
                if geom.n_phalanges == 3:
                    phi[:, 2] = geom.coupling * phi[:, 1]
                theta = joint_to_phalanx_angles(phi)
                z = np.zeros_like(theta)
                acc = np.stack([ideal_imu(geom, s, base, theta, z, z).acc for s in geom.sensors], axis=1)
                est = VectorObservation(geom)
                out = est.update(0.0, np.zeros_like(acc[0]), acc[0], BaseMotion(
                    base.rotation[0], base.position[0], base.velocity[0], base.acceleration[0],
                    base.angular_velocity[0], base.angular_acceleration[0]))
                inplane_ok = out.mode != MODE_NO_INFO
                if inplane_ok.all():
                    np.testing.assert_allclose(out.phi, phi[0], atol=1e-9)


def test_integration_stays_within_0_1_deg_over_10_s():
    sess = simulate(SimConfig(motion="random", t_m_s=10.0, noise="none", hand_motion="random", seed=4))
    for finger in FINGERS:
        tr = _run("integration", sess, finger)
        assert np.abs(np.degrees(tr.phi - sess.joint_angles[finger])).max() < 0.1


@pytest.mark.parametrize("name", ["switching", "madgwick", "ekf", "chain", "inertial"])
@pytest.mark.parametrize("hand_motion", ["still", "slow-rotation", "fast-reach"])
def test_noise_free_accuracy_within_half_a_degree(grasp_sessions, name, hand_motion):
    sess = grasp_sessions[hand_motion]
    skip = 200 if name == "madgwick" else 0           # Madgwick: after its 1 s convergence time
    settings = None
    if name == "switching":
        # its error model describes the sensors (eqs. 7-8): here, error-free ones
        settings = REGISTRY[name].Settings(gyro_error_rad_s=1e-4, acc_error_m_s2=1e-3)
    for finger in FINGERS:
        rms = _rms_deg(_run(name, sess, finger, settings), sess.joint_angles[finger], skip)
        assert rms.max() < 0.5, (finger, rms)


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("hand", ["right", "left"])
def test_signs_flexion_positive_extension_negative(name, hand):
    sess = simulate(SimConfig(motion="grasp", t_m_s=1.5, noise="none", hand=hand, seed=0))
    t = sess.t - sess.t[0]
    extended = np.argmin(np.abs(t - (0.2 + 0.5)))      # MCP at -28 deg
    flexed = len(t) - 1                                  # MCP 90, PIP/DIP 85 deg
    for finger in ("index", "little"):
        tr = _run(name, sess, finger)
        assert tr.phi[extended, 0] < np.radians(-20)
        assert np.all(tr.phi[flexed] > np.radians(60))


@pytest.mark.parametrize("name", ALL)
def test_streaming_equals_batch_and_split_runs_resume(name):
    sess = simulate(SimConfig(motion="random", t_m_s=1.5, noise="both", hand_motion="random", seed=5))
    geom = sess.calibration.finger("index")
    smp = samples_from_session(sess, "index")
    theta0 = joint_to_phalanx_angles(sess.joint_angles["index"][0])
    batch = REGISTRY[name](geom, initial_theta=theta0).run(smp)
    streamer = REGISTRY[name](geom, initial_theta=theta0)
    stream = np.array([streamer.update(*smp.sample(k)).phi for k in range(len(smp))])
    np.testing.assert_allclose(stream, batch.phi, rtol=0, atol=1e-9)
    # split: run half, save the state, run the rest in a fresh estimator restored from it
    half = len(smp) // 2
    first = REGISTRY[name](geom, initial_theta=theta0)
    a = first.run(_slice(smp, 0, half))
    second = REGISTRY[name](geom)
    second.state = first.state
    b = second.run(_slice(smp, half, len(smp)))
    np.testing.assert_allclose(np.concatenate([a.phi, b.phi]), batch.phi, rtol=0, atol=1e-9)


def _slice(smp, i, j):
    h = smp.hand
    return FingerSamples(smp.t[i:j], smp.gyr[i:j], smp.acc[i:j], BaseMotion(
        h.rotation[i:j], h.position[i:j], h.velocity[i:j], h.acceleration[i:j],
        h.angular_velocity[i:j], h.angular_acceleration[i:j]))


@pytest.mark.parametrize("name", ALL)
def test_batch_dimensions_equal_separate_runs(name):
    """(N, B, S, 3) input equals B separate (N, S, 3) runs (qmt-style broadcasting check)."""
    sessions = [simulate(SimConfig(motion="grasp", t_m_s=0.5, noise="both", seed=s)) for s in (1, 2, 3)]
    geom = sessions[0].calibration.finger("middle")
    single = [_run(name, s, "middle").phi for s in sessions]
    smps = [samples_from_session(s, "middle") for s in sessions]
    h = sessions[0].base
    stacked_hand = BaseMotion(*(np.stack([getattr(x.hand, f) for x in smps], axis=1) for f in
                                ("rotation", "position", "velocity", "acceleration", "angular_velocity", "angular_acceleration")))
    stacked = FingerSamples(smps[0].t, np.stack([x.gyr for x in smps], axis=1), np.stack([x.acc for x in smps], axis=1), stacked_hand)
    theta0 = np.stack([joint_to_phalanx_angles(s.joint_angles["middle"][0]) for s in sessions])
    out = REGISTRY[name](geom, initial_theta=theta0, batch_shape=(3,)).run(stacked)
    for b in range(3):
        np.testing.assert_allclose(out.phi[:, b], single[b], rtol=0, atol=1e-9)


def test_horizontal_flexion_plane_has_no_information_and_switching_integrates():
    # metacarpus rotated so that its x (hinge) axis points up: gravity along the hinge axis
    rot = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    sess = simulate(SimConfig(motion="point", noise="white", seed=3))
    hand = BaseMotion.still(rot, np.zeros(3), len(sess.t))
    geom = sess.calibration.finger("index")
    theta = np.stack([joint_to_phalanx_angles(sess.joint_angles["index"])] * 1, axis=0)[0]
    from service.model.kinematics import ideal_imu as imu
    dtheta = joint_to_phalanx_angles(sess.joint_rates["index"])
    readings = [imu(geom, s, hand, theta, dtheta, np.gradient(dtheta, sess.t, axis=0)) for s in geom.sensors]
    smp = FingerSamples(sess.t, np.stack([r.gyr for r in readings], 1), np.stack([r.acc for r in readings], 1), hand)
    vo = VectorObservation(geom).run(smp)
    assert np.all(vo.mode == MODE_NO_INFO)
    sw = Switching(geom, initial_theta=theta[0]).run(smp)
    assert np.all(sw.mode == MODE_FAST)
    assert np.abs(np.degrees(sw.phi - sess.joint_angles["index"])).max() < 0.5


@pytest.mark.parametrize("name", ALL)
def test_bad_samples_are_rejected_and_leave_the_state_untouched(name):
    sess = simulate(SimConfig(motion="open", noise="both", seed=1))
    smp = samples_from_session(sess, "ring")
    est = REGISTRY[name](sess.calibration.finger("ring"))
    for k in range(5):
        est.update(*smp.sample(k))
    before = est.state
    t, gyr, acc, hand = smp.sample(5)
    bad_gyr = gyr.copy()
    bad_gyr[0, 1] = np.nan
    cases = [
        ((t, bad_gyr, acc, hand), "gyr: contains non-finite"),
        ((t, gyr, acc[:, :2], hand), r"acc: expected shape \(2, 3\)"),
        ((smp.t[3], gyr, acc, hand), "time must increase"),
        ((float("inf"), gyr, acc, hand), "t: must be finite"),
        ((t, gyr, np.full_like(acc, np.inf), hand), "acc: contains non-finite"),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            est.update(*args)
        _assert_state_equal(est.state, before)
    # and it continues exactly as if nothing had happened
    ref = REGISTRY[name](sess.calibration.finger("ring"))
    for k in range(6):
        expected = ref.update(*smp.sample(k))
    np.testing.assert_array_equal(est.update(*smp.sample(5)).phi, expected.phi)


def _assert_state_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], dict):
            _assert_state_equal(a[k], b[k])
        else:
            np.testing.assert_array_equal(a[k], b[k])


def test_unknown_settings_are_errors():
    from pydantic import ValidationError
    with pytest.raises(ValidationError, match="bta"):
        REGISTRY["madgwick"].Settings(bta=0.1)
    with pytest.raises(ValidationError):
        REGISTRY["madgwick"].Settings(beta=-1.0)


def test_an_estimator_spec_is_validated_once_and_builds_the_named_estimator():
    from pydantic import ValidationError
    from service.estimators.registry import EstimatorSpec, make_estimator
    spec = EstimatorSpec.of("madgwick", {"beta": "0.05"})               # strings from the edge are converted
    assert spec.settings == REGISTRY["madgwick"].Settings(beta=0.05)
    est = make_estimator(spec, default_calibration().finger("index"), batch_shape=(2,))
    assert isinstance(est, REGISTRY["madgwick"]) and est.settings is spec.settings and est.batch_shape == (2,)
    with pytest.raises(ValueError, match="unknown estimator 'kalman'"):
        EstimatorSpec.of("kalman")
    with pytest.raises(ValidationError, match="bta"):
        EstimatorSpec.of("madgwick", {"bta": 0.1})


def test_chain_closure_rejects_unobservable_placements():
    geom = default_calibration().finger("index")
    from dataclasses import replace
    one = replace(geom, sensors=geom.sensors[:1])
    with pytest.raises(ValueError, match="cannot determine"):
        REGISTRY["vector"](one)


def test_observation_model_equals_the_simulator_kinematics():
    """The estimators' predicted specific force (all sensors at once, cross-product matrices) equals
    the model's point kinematics for random finger states on a randomly moving hand."""
    from service.estimators.observations import FingerObservations
    from service.model.kinematics import chain_point, point_in_metacarpus, point_in_world
    from service.sim.motions import make_hand_motion
    rng = np.random.default_rng(21)
    calib = default_calibration("left")
    base = make_hand_motion("random", seed=4).base_motion(np.linspace(0, 3, 9))
    g = np.array([0.0, -9.81, 0.0])
    for finger in FINGERS:
        geom = calib.finger(finger)
        n = geom.n_phalanges
        theta, dtheta, ddtheta = (rng.normal(0, s, (9, n)) for s in (0.8, 3.0, 40.0))
        got = FingerObservations(geom).reference_force_world(base, theta, g, dtheta, ddtheta)
        for k, sensor in enumerate(geom.sensors):
            local = chain_point(geom, sensor.phalanx, sensor.offset_m, theta, dtheta, ddtheta)
            expected = point_in_world(base, point_in_metacarpus(geom, local)).acceleration - g
            np.testing.assert_allclose(got[:, k], expected, atol=1e-10)
