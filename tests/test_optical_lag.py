"""The optical hand acceleration's lag and what ``chain`` makes of it (``estimators/chain.py``, "The
optics' acceleration"): the pipeline's quadratic fit returns the acceleration of its window's middle
(so it lags by half the window, by the fit's arithmetic), ``chain``'s smoothed acceleration predicts
that error from the fit's own change, and widening the accelerometer along it keeps a still finger on a
fast-reaching hand nearer its angle."""
import numpy as np
import pytest

from service.bench.accuracy import _wrap
from service.estimators.chain import Chain, ChainSettings
from service.model.hand import default_calibration
from service.pipeline.hand import HandSession, PipelineSettings
from service.pipeline.optical import OpticalTrack
from service.protocol import parse_message
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate

JERK = np.array([40.0, -20.0, 10.0])         # m/s³: p(t) = JERK t³ / 6, a(t) = JERK t
WINDOW_S = 0.15
POSE_HZ = 90.0


def _optics_on_a_constant_jerk():
    """The optics' view of a noise-free constant-jerk path at 200 Hz from 0.5 s to 1.5 s, poses added as
    they arrive (each as soon as it covers a query): per query time its motion, and the mean time of
    the poses in its fit window."""
    track = OpticalTrack(window_s=WINDOW_S, timeout_s=0.1)
    pose_t = np.arange(0.0, 1.6, 1.0 / POSE_HZ)
    added = 0
    for t in np.arange(0.5, 1.5, 1.0 / 200.0):
        while not track.covers(t):
            tp = float(pose_t[added])
            track.add(tp, JERK * tp**3 / 6.0, [0.0, 0.0, 0.0, 1.0], True)
            added += 1
        motion, tracking = track.at(float(t))
        assert tracking
        covering = pose_t[added - 1]
        yield t, motion, np.mean(pose_t[(pose_t >= t - WINDOW_S) & (pose_t <= covering)])


def _fit_on_a_constant_jerk():
    query, fitted, middle = zip(*((t, m.acceleration, mid) for t, m, mid in _optics_on_a_constant_jerk()))
    return np.array(query), np.array(fitted), np.array(middle)


def test_the_optical_fit_returns_the_acceleration_of_its_window_middle():
    # a cubic's odd part about the window's middle projects onto a line: no second derivative
    query, fitted, middle = _fit_on_a_constant_jerk()
    np.testing.assert_allclose(fitted, JERK * middle[:, None], rtol=1e-6, atol=1e-9)
    lag = query - middle
    assert np.all((lag > 0.06) & (lag < WINDOW_S / 2 + 1e-9))        # half the window less the covering pose


def test_chain_predicts_the_fit_error_from_the_fits_own_change():
    query, fitted, _ = _fit_on_a_constant_jerk()
    geom = default_calibration("right").finger("index")
    est = Chain(geom, ChainSettings(optical_fit_lag_s=WINDOW_S / 2))
    gyr = np.zeros((est.n_sensors, 3))
    acc = np.tile([0.0, 0.0, 9.81], (est.n_sensors, 1))
    predicted = []
    for t, motion, _ in _optics_on_a_constant_jerk():
        est.update_trusted(float(t), gyr, acc, motion)
        predicted.append(motion.acceleration - est._state["hand_acc"])
    actual = fitted - JERK * query[:, None]              # the fit's error: -lag · jerk
    steady = query >= 1.0                                # five lags after the start
    p, a = np.array(predicted)[steady], actual[steady]
    # the same size to within the lag's spread (0.061-0.075 s against the setting's 0.075 s)
    ratio = np.linalg.norm(p.mean(axis=0)) / np.linalg.norm(a.mean(axis=0))
    assert 0.95 < ratio < 1.25
    cosine = -p.mean(axis=0) @ a.mean(axis=0) / (np.linalg.norm(p.mean(axis=0)) * np.linalg.norm(a.mean(axis=0)))
    assert cosine > 0.999                                # along it, opposite in sign: â - ā ≈ λ j, â - a ≈ -λ j


def _still_finger_error(lag_s: float, shared: bool = False):
    """Index and middle held at rest on a hand reaching fast (0.35 m in 0.5 s and back), perfect sensors
    and optics (no jitter, no latency: the fit's lag is the optics' only error), through the pipeline:
    their joint errors, degrees, over the reach and the return (0.3-2.3 s)."""
    session = simulate(SimConfig(noise="none", seed=3, hand_motion="fast-reach", fingers=("index", "middle"),
                                 finger_motion=sequence_motion(t_d=0.3, steps=(("rest", 0.3, 5.0),)), duration_s=2.5))
    params = {"optical_fit_lag_s": lag_s, "gyro_angle_rate_std_rad_s": 0.0}    # the lag's pull alone
    if not shared:          # the widening alone, not the hand's shared acceleration error
        params.update(hand_acc_error_scale=0.0, hand_acc_error_floor_m_s2=0.0)
    hs = HandSession(settings=PipelineSettings(estimator="chain", estimator_params=params))
    t, phi = [], []
    for m in session.messages(include_truth=False):
        for frame in hs.handle(parse_message(m)).frames:
            t.append(frame.t)
            phi.append(np.concatenate([frame.joint_angles["index"], frame.joint_angles["middle"]]))
    t, phi = np.array(t), np.array(phi)
    idx = np.round((t - session.t[0]) * session.config.rate_hz).astype(int)
    truth = np.concatenate([session.joint_angles["index"][idx], session.joint_angles["middle"][idx]], axis=1)
    reach = (t >= 0.3) & (t < 2.3)
    return np.degrees(np.abs(_wrap(phi - truth)))[reach]


@pytest.mark.parametrize("shared", [False, True], ids=["widened", "shared-error-state"])
def test_widening_along_the_fits_error_keeps_a_still_finger_on_a_reaching_hand(shared):
    """The lag error widened along its direction, or (``shared``) taken as the hand's acceleration error
    that every sensor's update shares (the default), against neither."""
    without, widened = _still_finger_error(0.0), _still_finger_error(WINDOW_S / 2, shared)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))        # noqa: E731
    # the lag error's pull on the angles must shrink by a fifth at least, in the RMS and at its worst
    assert rms(widened) < 0.8 * rms(without)
    assert widened.max() < 0.8 * without.max()
