"""The ``reference_pose`` message: protocol, estimators, pipeline, recordings, the Python client (the
round trip through a live service is in ``test_service.py``)."""
import asyncio

import numpy as np
import pytest

from service.estimators.base import FingerSamples, samples_from_session
from service.model.kinematics import BaseMotion
from dataclasses import replace

from scipy.spatial.transform import Rotation

from service.estimators.chain import Chain, ChainSettings, HoldLog
from service.estimators.chain_kernel import GA_START, GS
from service.model.hand import default_calibration
from service.model.hand import joint_to_phalanx_angles
from clients.client import Publisher
from service.pipeline.hand import HandSession, PipelineSettings
from service.pipeline.offline import load_recording, run_with_references
from service.protocol import ProtocolError, ReferencePose, parse_line, parse_message
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate, write_recording

def test_protocol_accepts_flat_and_joint_angles_and_names_what_is_wrong():
    flat = parse_message({"type": "reference_pose", "t0": 0.0, "t1": 2.0, "pose": "flat"})
    assert flat.joint_angles(["index", "thumb"]) == {"index": [0.0, 0.0, 0.0], "thumb": [0.0, 0.0]}
    given = parse_message({"type": "reference_pose", "t0": 1.0, "t1": 1.5,
                           "pose": {"index": {"mcp": 0.1, "pip": 0.2, "dip": 0.3}}})
    assert given.joint_angles(["index", "middle"]) == {"index": [0.1, 0.2, 0.3]}
    for bad, words in [({"t0": 2.0, "t1": 1.0, "pose": "flat"}, "t1"),
                       ({"t0": 0.0, "t1": 1.0, "pose": {"index": {"mcp": 0.0}}}, "pose.index"),
                       ({"t0": 0.0, "t1": 1.0, "pose": {"thumb": {"mcp": 0.0, "ip": 4.0}}}, "pose.thumb.ip"),
                       ({"t0": 0.0, "t1": 1.0, "pose": "fist"}, "pose"),
                       ({"t0": 0.0, "pose": "flat"}, "t1")]:
        with pytest.raises(ProtocolError) as err:
            parse_message({"type": "reference_pose", **bad})
        assert words in err.value.detail


def test_chain_takes_a_known_configuration_as_a_measurement():
    """A still finger whose vector observation is biased by accelerometer offsets: a reference with a
    tight std moves the angles toward the reference, and the offsets to what explains the reading.
    Both sensors in one update whose errors share the joints below the lower sensor: with the angle
    priors ``p`` (independent filters) and ``R = std² [[2, 2], [2, 3]]`` (phalanx 1 sums two joints,
    phalanx 2 three, the first two shared), the error becomes ``R (diag(p) + R)⁻¹`` times itself."""
    sess = simulate(SimConfig(motion="open", noise="offset", seed=3, duration_s=3.0, fingers=("index",)))
    samples = samples_from_session(sess, "index")
    est = Chain(sess.calibration.finger("index"), settings=ChainSettings(mounting_hinge_std_rad=0.0))
    est.run(samples)
    truth = joint_to_phalanx_angles(sess.joint_angles["index"][-1])
    before = est.state["filter"]["x"][:, 0] - truth[[1, 2]]
    p = est.state["filter"]["P"][:, 0, 0]
    std = np.radians(0.1)
    est.known_configuration(truth, std)
    after = est.state["filter"]["x"][:, 0] - truth[[1, 2]]
    r = np.array([[2.0, 2.0], [2.0, 3.0]]) * std**2
    np.testing.assert_allclose(after, r @ np.linalg.solve(np.diag(p) + r, before), atol=1e-12)
    assert np.abs(before).max() > 1e-3 and np.all(np.abs(after) < np.abs(before))


@pytest.mark.parametrize("seed, path", [(1, "update"), (4, "run")])
def test_a_reference_pose_hold_measures_each_gyro_offset(seed, path):
    """A finger held still on a still hand from an unknown start, the gyros with the simulated offsets (no
    white noise): over the hold each gyro's relative hinge-axis rate is its offset, so with the hold's
    measurement weighted as exact (``hold_rate_std_rad_s`` tiny, no scale term) the offsets after the
    reference are the simulated ones, where the accelerometer alone leaves them 0.2-0.9 deg/s off after
    the same 2 s (the hold's own reference update without its interval moves them by their correlation
    with the angle only). Sample by sample (the live pipeline's path) or in one batch (``estimate``'s)."""
    sess = simulate(SimConfig(motion="point", hand_motion="still", noise="offset", seed=seed, duration_s=2.0,
                              fingers=("index",), reference_hold_s=2.0))
    samples = samples_from_session(sess, "index")
    n = int(np.searchsorted(samples.t, 2.0 + 1e-9))
    assert np.abs(sess.joint_rates["index"][:n]).max() == 0.0
    ids = [sp.id for sp in sess.calibration.finger("index").sensors]
    offset = np.array([sess.gyr_offset[sess.sensor_ids.index(i)][0] for i in ids])
    settings = ChainSettings(hold_rate_std_rad_s=1e-6, gyro_scale_uncertainty=0.0)
    err = {}
    for hold in (None, (float(samples.t[0]), float(samples.t[n - 1]))):
        est = Chain(sess.calibration.finger("index"), settings=settings)
        if path == "run":
            est.run(FingerSamples(samples.t[:n], samples.gyr[:n], samples.acc[:n],
                                  BaseMotion(*(getattr(samples.hand, k)[:n] for k in BaseMotion.__dataclass_fields__))))
        else:
            for k in range(n):
                est.update(*samples.sample(k))
        est.known_configuration(joint_to_phalanx_angles(sess.joint_angles["index"][n - 1]), 0.03, hold_s=hold)
        err[hold is not None] = np.degrees(np.abs(est.state["filter"]["x"][:, 1] - offset))
    assert np.all(err[True] < 0.02), err
    assert np.any(err[False] > 0.2), err


def _hold_log(rate, gyr):
    """A hold's log over 0 .. 2 s at 200 Hz for two sensors, the relative rate ``rate(t)`` (rad/s) and the
    gyro reading ``gyr(t)`` (3,) alike for both."""
    log = HoldLog(2)
    for k in range(401):
        t = 0.005 * k
        log.add(t, 0.005 if k else 0.0, np.full(2, rate(t)), np.tile(gyr(t), (2, 1)))
    return log


def test_a_hold_in_which_the_finger_turned_on_its_hand_leaves_the_offsets_alone():
    """A finger held still over 2 s with an offset of 0.02 rad/s is read: its integrated rate is the
    offset's line, nothing strays from it, and the offsets move toward 0.02 rad/s. The same finger turning
    7 deg in the hold's last 0.3 s (a minimum-jerk turn on a still hand), and one whose second half is
    0.5 rad/s faster, strayed from the line by the angle they turned less the line's share of it (0.25 rad
    for the step: closed form), beyond the stillness limit: the offsets and their covariance stay as they
    were. (The halves' mean rates differ by 7 deg/s for the first: a check of them against 15 deg/s read
    it, and left the offsets about 3 deg/s off.) A still finger on a hand turning at up to 4 rad/s, its gyro's
    hinge-axis reading leaking 3 % of the reading's x and 2 % of its y (MPU-9250 scale and cross-axis
    errors), is read: the fit of the gyro's map takes up the leak (5 deg of it, beyond the limit unfitted;
    9.9 deg/s between the halves)."""
    sess = simulate(SimConfig(motion="point", hand_motion="still", noise="offset", seed=1, duration_s=1.0,
                              fingers=("index",)))
    samples = samples_from_session(sess, "index")
    est = Chain(sess.calibration.finger("index"))
    for k in range(len(samples.t)):
        est.update(*samples.sample(k))
    x0, p0 = est.state["filter"]["x"].copy(), est.state["filter"]["P"].copy()
    limit = est.settings.hold_still_max_rad
    turn = np.radians(7.0)

    def min_jerk_rate(t):
        u = min(max((t - 1.7) / 0.3, 0.0), 1.0)
        return turn / 0.3 * 30.0 * u**2 * (1.0 - u)**2

    still_hand = lambda t: np.zeros(3)
    turning = lambda t: 4.0 * np.sin(np.pi * t) * np.array([0.6, 0.8, 0.0])
    t = 0.005 * np.arange(401)
    u = np.clip((t - 1.7) / 0.3, 0.0, 1.0)
    turned = turn * (10 * u**3 - 15 * u**4 + 6 * u**5)
    logs = [("still", _hold_log(lambda t: 0.02, still_hand), 0.0, True),
            ("turned 7 deg", _hold_log(lambda t: 0.02 + min_jerk_rate(t), still_hand),
             np.abs(turned - t * turned[-1] / 2.0).max(), False),
            ("second half faster", _hold_log(lambda t: 0.02 + (0.5 if t > 1.0 else 0.0), still_hand), 0.25, False),
            ("turning hand", _hold_log(lambda t: 0.02 + turning(t) @ [0.03, 0.02, 0.0], turning), None, True)]
    for name, log, stray, read in logs:
        rate, _, moved = log.mean(0.0, 2.0, 0.5, est.settings.gyro_scale_uncertainty)
        if name == "still":
            np.testing.assert_allclose(rate, 0.02, atol=1e-12)
        if stray is not None:
            np.testing.assert_allclose(moved, stray, rtol=0.005, atol=1e-12, err_msg=name)  # the log sums 5 ms rectangles
        else:                                           # the leak, fitted, leaves nothing to speak of
            assert np.degrees(moved).max() < 0.1, (name, moved)
        assert np.all((moved < limit) == read), (name, moved)
        est._hold = log
        x, p = x0.copy(), p0.copy()
        est._hold_offsets(x, p, (0.0, 2.0))
        assert (np.array_equal(x, x0) and np.array_equal(p, p0)) != read, name
        if read:                                        # a still finger: the offsets move toward 0.02 rad/s
            assert np.all(np.abs(x[:, 1] - 0.02) < np.abs(x0[:, 1] - 0.02)), name


def test_the_hold_leaves_a_held_gyro_scale_state_alone():
    """A finger on a fallback closure (one sensor silent) holds its gyro scale state: the kernel zeroes
    its gain row, since learning the scale there is what sank an earlier attempt (item 6 of chain.py's
    docstring). Its live sensor's offset and scale were learned together before the other fell silent, so
    after ``inherit`` their covariance is not zero, and the hold's offset measurement moved the held
    scale through it, and so did the reference's angle update through ``P[θ, GS]``. A still hold now moves
    the offset toward its 0.02 rad/s with the Joseph-form covariance of that gain, and the whole reference
    pose leaves the scale state and its variance exactly as they were."""
    sess = simulate(SimConfig(motion="point", hand_motion="still", noise="offset", seed=1, duration_s=1.0,
                              fingers=("index",)))
    samples = samples_from_session(sess, "index")
    geom = sess.calibration.finger("index")
    full = Chain(geom)
    for k in range(len(samples.t) - 1):
        full.update(*samples.sample(k))
    held = Chain(replace(geom, sensors=geom.sensors[:1]), extra_couplings=[(0, 1.0)],    # index.2 silent
                 initial_theta=joint_to_phalanx_angles(sess.joint_angles["index"][-1]))
    held.inherit(full)
    t, gyr, acc, hand = samples.sample(len(samples.t) - 1)
    held.update(t, gyr[:1], acc[:1], hand)
    x0, p0 = held.state["filter"]["x"].copy(), held.state["filter"]["P"].copy()
    assert abs(p0[0, GS, 1]) > 1e-3 * np.sqrt(p0[0, GS, GS] * p0[0, 1, 1])
    held._hold = _hold_log(lambda t: 0.02, lambda t: np.array([0.0, 0.0, 0.5]))
    x, p = x0.copy(), p0.copy()
    held._hold_offsets(x, p, (0.0, 2.0))
    assert x[0, GS] == x0[0, GS] and p[0, GS, GS] == p0[0, GS, GS]
    assert abs(x[0, 1] - 0.02) < abs(x0[0, 1] - 0.02) and p[0, 1, 1] < p0[0, 1, 1]
    # the covariance of a gain with its scale row zeroed is the Joseph form (I - K h) P (I - K h)ᵀ + K r Kᵀ
    h = np.zeros(len(x0[0]))
    h[1] = 1.0
    r = held.settings.hold_rate_std_rad_s**2 + (held.settings.gyro_scale_uncertainty * 0.5) ** 2
    k = p0[0] @ h / (h @ p0[0] @ h + r)
    k[GS] = 0.0
    i_kh = np.eye(len(h)) - np.outer(k, h)
    np.testing.assert_allclose(p[0], i_kh @ p0[0] @ i_kh.T + r * np.outer(k, k), rtol=0, atol=1e-15)
    # the whole reference pose (the hold, then the angle update through P[θ, GS]) leaves it alone too
    held._state = {**held._state, "x": x0.copy(), "P": p0.copy()}
    held.known_configuration(joint_to_phalanx_angles(sess.joint_angles["index"][-1]) + 0.1, 0.05, hold_s=(0.0, 2.0))
    x, p = held.state["filter"]["x"], held.state["filter"]["P"]
    assert x[0, GS] == x0[0, GS] and p[0, GS, GS] == p0[0, GS, GS]
    assert abs(x[0, 0] - x0[0, 0]) > 1e-3                      # the angle did move


def _mounted(delta_rad):
    """The default right hand with index.1 and index.2 turned on their phalanges by ``delta_rad`` about
    the hinge axis (the sensor-to-phalanx rotation ``R_x(δ)``)."""
    calib = default_calibration("right")
    index = calib.finger("index")
    sensors = tuple(replace(sp, mounting=tuple(Rotation.from_rotvec([d, 0.0, 0.0]).as_quat()))
                    for sp, d in zip(index.sensors, delta_rad))
    return replace(calib, fingers={**calib.fingers, "index": replace(index, sensors=sensors)})


@pytest.mark.parametrize("seed", [1, 2])
def test_a_reference_pose_calibrates_the_mounting_turn_about_the_hinge_axis(seed):
    """Sensors mounted with a known turn ``δ`` about the hinge axis that the glove's calibration does not
    know (it says identity); noise-free readings of a pointing finger on a still hand. The accelerometer
    alone sees only ``θ + δ``; a known configuration (exact, given to 0.01 deg) separates the two. With
    the accelerometer weighted as the noise-free sensor it is here and no room for offsets (which a
    single orientation of the hand cannot tell from the turn), the filter's hinge-axis state
    (``G_zy = -G_yz = -δ``, a small-angle rotation) is ``δ`` itself, and the angles after the reference
    are right instead of off by ``δ`` as without the state."""
    rng = np.random.default_rng(seed)
    delta = rng.choice([-1.0, 1.0], 2) * np.radians(rng.uniform(2.0, 5.0, 2))
    sess = simulate(SimConfig(motion="point", hand_motion="still", noise="none", seed=seed, duration_s=6.0,
                              fingers=("index",), calibration=_mounted(delta)))
    nominal = default_calibration("right").finger("index")
    samples = samples_from_session(sess, "index")
    t1 = 2.0
    k1 = int(np.searchsorted(samples.t, t1 - 1e-9))
    pose = dict(zip(("mcp", "pip", "dip"), (float(a) for a in sess.joint_angles["index"][k1])))
    ref = parse_message({"type": "reference_pose", "t0": t1 - 1.0, "t1": t1, "pose": {"index": pose}})
    later = samples.t > t1
    truth = np.cumsum(sess.joint_angles["index"], axis=1)[:, [1, 2]][later]
    err = {}
    for hinge_std in (0.0, 0.03):
        est = Chain(nominal, settings=ChainSettings(mounting_hinge_std_rad=hinge_std, acc_scale_uncertainty=0.01,
                                                    initial_acc_bias_std_m_s2=1e-4))
        track = run_with_references(est, samples, "index", [ref], np.radians(0.01))
        phal = np.cumsum(track.phi, axis=1)[:, [1, 2]][later]
        err[hinge_std] = np.degrees(np.sqrt(np.mean((phal - truth) ** 2, axis=0)))
    x = est.state["filter"]["x"]
    np.testing.assert_allclose(-x[:, GA_START + 7], delta, atol=np.radians(0.1))
    np.testing.assert_allclose(x[:, GA_START + 5], delta, atol=np.radians(0.1))
    assert np.all(err[0.03] < 0.2), err
    assert np.all(err[0.0] > 0.5 * np.degrees(np.abs(delta))), err


def _recording_with_hold(tmp_path, seed=4):
    config = SimConfig(motion="sequence", noise="both", seed=seed, reference_hold_s=2.0,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8))))
    sess = simulate(config)
    path = tmp_path / "ref.jsonl"
    write_recording(sess, path)
    return sess, path


def test_recording_carries_the_reference_to_estimate_and_the_pipeline(tmp_path):
    sess, path = _recording_with_hold(tmp_path)
    rec = load_recording(path)
    assert [(r.t0, r.t1, r.pose) for r in rec.references] == [(0.0, 2.0, "flat")]
    geom = rec.calibration.finger("index")
    samples, _ = rec.finger_samples("index")
    after = samples.t > 2.0
    truth = sess.joint_angles["index"][after]
    with_ref = run_with_references(Chain(geom), samples, "index", rec.references,
                                   PipelineSettings().reference_pose_std_rad).phi
    without = Chain(geom).run(samples).phi
    # applied at t1 and nowhere else: identical before, different after
    np.testing.assert_array_equal(with_ref[~after], without[~after])
    assert np.abs(with_ref[after] - without[after]).max() > 1e-4
    # the hold is flat to within 3 deg per joint: the estimate stays inside that
    assert np.degrees(np.sqrt(np.mean((with_ref[after] - truth) ** 2))) < 3.0
    # live pipeline: the same message, applied once, reported in the status
    hs = HandSession()
    frames = [f for line in open(path) for f in hs.handle(parse_line(line)).frames]
    assert frames[-1].status["reference_poses"] == {"applied": 1, "stale": 0}


def test_a_reference_older_than_the_processed_time_is_stale(tmp_path):
    sess, path = _recording_with_hold(tmp_path, seed=5)
    hs = HandSession()
    msgs = [parse_line(line) for line in open(path)]
    ref = next(m for m in msgs if isinstance(m, ReferencePose))
    frames = [f for m in msgs if m is not ref for f in hs.handle(m).frames]
    hs.handle(ref)                                           # arrives after the whole recording
    assert hs.status()["reference_poses"] == {"applied": 0, "stale": 1} and frames


def test_client_rejects_a_malformed_reference_before_sending():
    pub = Publisher("http://127.0.0.1:9", "s", "t")
    with pytest.raises(ProtocolError):
        asyncio.run(pub.send_reference_pose(0.0, 1.0, {"index": {"mcp": 0.0}}))
