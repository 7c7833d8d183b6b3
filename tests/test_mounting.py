"""The flexion-axis (sensor-to-segment) calibration from motion (``service/pipeline/mounting.py``): a
known tilt of a sensor on its phalanx is recovered from its gyro, in closed form and through the live
pipeline."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.frames import rot_x
from service.model.hand import default_calibration
from service.pipeline.hand import HandSession, PipelineSettings
from service.pipeline.mounting import HingeAxisFit, MountingFitSettings
from service.protocol import parse_message
from service.sim.session import SimConfig, simulate


@pytest.mark.parametrize("calibrated", [np.eye(3), Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()])
def test_a_known_tilt_is_recovered_from_noise_free_gyro_samples(calibrated):
    """Readings made exactly (rotations, not their first-order form) from a sensor tilted by ``ε`` (about
    the phalanx's y and z axes) behind a calibrated mounting, with gyro offsets, a flexing finger and a
    turning hand: the fit finds ``ε`` (to second order in it), and its correction turns the raw
    readings back into the phalanx frame."""
    rng = np.random.default_rng(7)
    eps = np.radians([3.0, -4.0])
    tilt = Rotation.from_rotvec([0.0, *eps]).as_matrix()
    mount = tilt @ calibrated                                   # true sensor -> phalanx
    offset = np.radians([1.0, -3.0, 4.0])
    fit = HingeAxisFit(calibrated)
    used = 0
    for _ in range(3000):
        theta = rng.uniform(-0.2, 1.8)
        w_base = rng.normal(0.0, 1.5, 3)
        rate = rng.normal(0.0, 6.0)
        omega_p = rot_x(theta).T @ w_base + rate * np.array([1.0, 0.0, 0.0])
        raw = mount.T @ omega_p + offset
        used += fit.add(raw, theta, w_base)
    assert used > 2000
    np.testing.assert_allclose(fit.tilt_rad, eps, atol=np.radians(0.1))
    omega_p = np.array([2.0, -1.0, 0.5])
    np.testing.assert_allclose(calibrated @ np.array(fit.correct(mount.T @ omega_p)), omega_p, atol=0.01)


def test_slow_samples_are_not_used_and_leave_the_readings_alone():
    fit = HingeAxisFit(np.eye(3))
    assert not fit.add([0.5, 0.2, 0.1], 0.3, np.zeros(3))
    assert fit.samples == 0 and fit.correct([1.0, 2.0, 3.0]) == [1.0, 2.0, 3.0]


def _tilted(eps_by_sensor):
    calib = default_calibration("right")
    index = calib.finger("index")
    sensors = tuple(replace(sp, mounting=tuple(Rotation.from_rotvec([0.0, *eps]).as_quat()))
                    for sp, eps in zip(index.sensors, eps_by_sensor))
    return replace(calib, fingers={**calib.fingers, "index": replace(index, sensors=sensors)})


def test_the_pipeline_learns_the_tilt_and_tracks_better_with_it():
    """Index sensors tilted by a few degrees that the glove's calibration does not know, noise-free
    readings, a moving finger on a turning hand, through the live pipeline: the fit recovers each tilt
    to 0.25 deg (the optical hand rate is a windowed fit, the angle an estimate), and the index error
    is less than half of that with the fit switched off (the tilts leak the hand's turning into the
    hinge rate)."""
    eps = np.radians([[4.0, -3.0], [-2.5, 4.5]])
    sess = simulate(SimConfig(motion="random", hand_motion="random", noise="none", seed=3, duration_s=10.0,
                              fingers=("index",), calibration=_tilted(eps)))
    msgs = [parse_message(m) for m in sess.messages(include_truth=False) if m["type"] != "calibration"]
    err, fits = {}, {}
    for on in (True, False):
        hs = HandSession(settings=PipelineSettings(mounting_fit=on))
        t, phi = [], []
        for m in msgs:
            for frame in hs.handle(m).frames:
                t.append(frame.t)
                phi.append(frame.joint_angles["index"])
        idx = np.round((np.array(t) - sess.t[0]) * sess.config.rate_hz).astype(int)
        later = np.array(t) > 3.0
        err[on] = float(np.degrees(np.sqrt(np.mean((np.array(phi) - sess.joint_angles["index"][idx])[later] ** 2))))
        fits[on] = hs._mount_fits
    for k, sid in enumerate(("index.1", "index.2")):
        np.testing.assert_allclose(fits[True][sid][0].tilt_rad, eps[k], atol=np.radians(0.25))
    assert not fits[False]
    assert err[True] < 0.5 * err[False], err


def _reference_add(state, fit, gyr, theta, w_base):
    """``HingeAxisFit.add`` as first written (numpy's solver, scipy's rotation): the reference of the
    closed forms it uses now."""
    from scipy.spatial.transform import Rotation
    if not fit.flexing(gyr):
        return
    f = fit.mount @ np.asarray(gyr, dtype=float)
    c, s = np.cos(theta), np.sin(theta)
    ry = f[1] - (c * w_base[1] + s * w_base[2])
    rz = f[2] - (-s * w_base[1] + c * w_base[2])
    reg = np.array([f[0], 1.0])
    state["a"] += np.outer(reg, reg)
    state["by"] += reg * ry
    state["bz"] += reg * rz
    tilt = np.array([np.linalg.solve(state["a"], state["bz"])[0], -np.linalg.solve(state["a"], state["by"])[0]])
    norm = float(np.hypot(*tilt))
    if norm > fit.settings.max_tilt_rad:
        tilt *= fit.settings.max_tilt_rad / norm
    state["tilt"] = tilt
    state["correction"] = fit.mount.T @ Rotation.from_rotvec([0.0, tilt[0], tilt[1]]).as_matrix() @ fit.mount


def test_the_closed_forms_equal_numpy_and_scipy():
    from scipy.spatial.transform import Rotation

    from service.pipeline.mounting import _rotation_about_yz
    rng = np.random.default_rng(11)
    for scale in (1e-9, 1e-4, 0.05, 0.2, 3.0):
        for _ in range(50):
            ey, ez = rng.normal(0.0, scale, 2)
            np.testing.assert_allclose(_rotation_about_yz(ey, ez, float(np.hypot(ey, ez))),
                                       Rotation.from_rotvec([0.0, ey, ez]).as_matrix(), rtol=0, atol=1e-14)
    assert np.array_equal(_rotation_about_yz(0.0, 0.0, 0.0), np.eye(3))
    for mount in (np.eye(3), Rotation.from_rotvec(rng.normal(0.0, 0.3, 3)).as_matrix()):
        fit = HingeAxisFit(mount, MountingFitSettings(max_tilt_rad=np.radians(3.0)))   # the clip is reached too
        st = fit.settings
        lam_e, lam_b = (st.residual_std_rad_s / st.prior_std_rad) ** 2, (st.residual_std_rad_s / st.offset_std_rad_s) ** 2
        state = {"a": np.diag([lam_e, lam_b]), "by": np.zeros(2), "bz": np.zeros(2)}
        used = 0
        for _ in range(400):
            gyr = rng.normal(0.0, 4.0, 3) + np.array([0.0, 0.3, -0.2]) * rng.normal(0.0, 4.0)
            theta, w = rng.uniform(-0.3, 1.5), rng.normal(0.0, 1.0, 3)
            _reference_add(state, fit, gyr, theta, w)
            used += fit.add(gyr.tolist(), theta, w)
            if used:
                np.testing.assert_allclose(fit.tilt_rad, state["tilt"], rtol=0, atol=1e-12)
                np.testing.assert_allclose(fit.correction, state["correction"], rtol=0, atol=1e-12)
        assert used > 100
