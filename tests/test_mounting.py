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
    turning hand: the fit finds ``ε`` (to second order in it) and the cross axes' offsets, and its
    correction turns the raw readings back into the phalanx frame."""
    rng = np.random.default_rng(7)
    eps = np.radians([3.0, -4.0])
    tilt = Rotation.from_rotvec([0.0, *eps]).as_matrix()
    mount = tilt @ calibrated                                   # true sensor -> phalanx
    offset = np.radians([5.0, -3.0, 4.0])
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
    # the same regression's constant terms are the cross axes' offsets in the frame of the corrected reading,
    # the tilt's turn of the calibrated phalanx frame's (the regressor ω_x is the raw reading, b_x in it):
    # 2-4 deg/s found to 0.1 deg/s; in the calibrated phalanx frame they are 0.35 deg/s away (b_x 5 deg/s)
    np.testing.assert_allclose(fit.cross_offsets, (tilt @ calibrated @ offset)[1:], atol=np.radians(0.1))
    omega_p = np.array([2.0, -1.0, 0.5])
    np.testing.assert_allclose(calibrated @ np.array(fit.correct(mount.T @ omega_p)), omega_p, atol=0.01)


@pytest.mark.parametrize("calibrated", [np.eye(3), np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])])
def test_clipped_gyro_samples_stay_out_of_the_fit(calibrated):
    """Noise-free readings of a tilted sensor with offsets, 1500 ordinary flexion samples and 20 fists whose
    hinge rate peaks at 2800 deg/s (a gyro's full scale is 2000), the hinge on the sensor's x axis or (turned
    by its calibrated mounting) on its y axis: a clipped sample's hinge-axis rate ``ω_x`` is too small, so its
    cross-axis residual (the tilt's ``-ε_z ω_x`` of the true rate) is mis-fit, and a fist's flexion is
    one-signed, so the misfit lands in the tilt (about 0.5 deg) and the offsets (here up to 0.25 deg/s). Left
    out of the fit (the default: any raw axis at full scale) the offsets and the tilt come out as without the
    fists."""
    clip = np.radians(2000.0)
    eps = np.radians([3.0, -4.0])
    tilt = Rotation.from_rotvec([0.0, *eps]).as_matrix()
    offset = np.radians([1.0, -3.0, 4.0])
    tau = np.linspace(0.0, 1.0, 31)
    fist = np.radians(2800.0) * 16.0 * tau**2 * (1.0 - tau) ** 2

    def fitted(fit_clipped):
        rng = np.random.default_rng(7)
        fit = HingeAxisFit(calibrated, MountingFitSettings(fit_clipped=fit_clipped))
        for rate in np.concatenate([rng.normal(0.0, 6.0, 1500), np.tile(fist, 20)]):
            theta, w_base = rng.uniform(-0.2, 1.8), rng.normal(0.0, 1.5, 3)
            omega_p = rot_x(theta).T @ w_base + rate * np.array([1.0, 0.0, 0.0])
            fit.add(np.clip((tilt @ calibrated).T @ omega_p + offset, -clip, clip), theta, w_base)
        return np.degrees(fit.cross_offsets - (tilt @ calibrated @ offset)[1:]), np.degrees(fit.tilt_rad - eps)

    offsets_error, tilt_error = fitted(False)
    assert np.abs(offsets_error).max() < 0.15 and np.abs(tilt_error).max() < 0.05
    _, tilt_error = fitted(True)
    assert np.abs(tilt_error).max() > 0.3


def test_the_offsets_variance_is_their_error_when_they_are_drawn_from_the_prior():
    """The offsets' variance (``HingeAxisFit.cross_offsets_var``, σ² a00 / det of the regression's normal
    equations) is their posterior variance: with offsets and tilts drawn from the fit's priors and the
    cross-axis residuals carrying white noise of ``residual_std_rad_s`` (the linear model exactly), the
    offsets' mean squared error over 300 fits of 40 samples, each divided by its variance, is 1 (to its
    sampling error, about 0.05); before any sample the variance is the prior's."""
    st = MountingFitSettings()
    assert HingeAxisFit(np.eye(3)).cross_offsets_var == pytest.approx(st.offset_std_rad_s ** 2, rel=1e-12)
    rng = np.random.default_rng(3)
    z = []
    for _ in range(300):
        eps, b = rng.normal(0.0, st.prior_std_rad, 2), rng.normal(0.0, st.offset_std_rad_s, 2)
        fit = HingeAxisFit(np.eye(3), MountingFitSettings(max_tilt_rad=1.0))
        wx_mean = rng.normal(0.0, 4.0)                   # some fits see one-signed flexions: a01 large
        for _ in range(40):
            wx = wx_mean + rng.normal(0.0, 3.0)
            wx = wx if abs(wx) >= st.min_rate_rad_s else np.copysign(st.min_rate_rad_s, wx)
            theta, w = rng.uniform(-0.2, 1.8), rng.normal(0.0, 1.5, 3)
            c, s = np.cos(theta), np.sin(theta)
            # the cross-axis residuals' first-order model: -ε_z ω_x + b_y and ε_y ω_x + b_z
            fy = c * w[1] + s * w[2] - eps[1] * wx + b[0] + rng.normal(0.0, st.residual_std_rad_s)
            fz = -s * w[1] + c * w[2] + eps[0] * wx + b[1] + rng.normal(0.0, st.residual_std_rad_s)
            assert fit.add([wx, fy, fz], theta, w)
        z.extend((fit.cross_offsets - b) ** 2 / fit.cross_offsets_var)
    assert 0.85 < np.mean(z) < 1.15


@pytest.mark.parametrize("cross_axis_std", [0.012, 0.0])
def test_a_known_cross_axis_leak_is_recovered_from_a_still_finger_on_a_turning_hand(cross_axis_std):
    """A gyro whose hinge-axis reading picks up 2 % and -1.5 % of its cross-axis rates (cross-axis
    sensitivity, MPU-9250 ±2 %), noise-free, with offsets, on a finger still on a turning hand: the
    relative rate is offset plus leak, so the fit recovers the two sensitivities (to within their product
    with the cross axes' own sensitivities, which the regressors carry, and the ridge prior's shrinkage,
    about 3 % each here) and the corrected hinge-axis reading is the true rate. With the fit
    off (``cross_axis_std = 0``) the leak stays in the reading."""
    rng = np.random.default_rng(11)
    sensitivity = np.eye(3) + np.array([[0.0, 0.02, -0.015], [0.01, 0.0, -0.02], [0.015, 0.005, 0.0]])
    offset = np.radians([2.0, -3.0, 1.0])
    fit = HingeAxisFit(np.eye(3), MountingFitSettings(cross_axis_std=cross_axis_std))
    for _ in range(5000):
        theta = rng.uniform(-0.2, 1.8)
        w_base = rng.normal(0.0, [0.5, 2.0, 2.0])      # (slower about the hinge axis: the tilt fit takes 2 rad/s and more)
        raw = sensitivity @ (rot_x(theta).T @ w_base) + offset
        assert not fit.add(raw, theta, w_base)          # no flexion: nothing for the tilt fit
    omega_p = np.array([0.3, 2.5, -2.0])                # the hinge rate and the hand's cross rates
    error = fit.correct_gyro(sensitivity @ omega_p + offset)[0] - offset[0] - omega_p[0]
    if cross_axis_std == 0.0:
        assert fit.quiet_samples == 0 and abs(error) > 0.07
        return
    assert fit.quiet_samples == 5000
    np.testing.assert_allclose(fit.cross_axis, [0.02, -0.015], rtol=0.08)
    assert abs(error) < 0.004                           # the leak was 0.08 rad/s


def test_a_still_hand_tells_the_offsets_whatever_the_angles_error():
    """A finger flexing slowly (below the tilt fit's 2 rad/s) on a hand turning at most 0.15 rad/s across
    the hinge, noise-free readings with offsets, the fit given angles 5 deg off: the cross axes read the
    hand's rate turned by the angle plus their offsets, and a 5 deg error of the angle turns 0.15 rad/s by
    0.75 deg/s at most, on average much less, so the offsets come out to 0.15 deg/s (the slow samples carry the
    tilt times a small ``ω_x``, which the regression takes with them); the tilt is left alone (no sample is
    fast). With ``still_rate_rad_s = 0`` nothing is learned (the offsets stay 0: 2-3 deg/s wrong)."""
    eps = np.radians([3.0, -4.0])
    tilt = Rotation.from_rotvec([0.0, *eps]).as_matrix()
    offset = np.radians([1.0, -3.0, 2.5])

    def fitted(still_rate):
        rng = np.random.default_rng(4)
        fit = HingeAxisFit(np.eye(3), MountingFitSettings(still_rate_rad_s=still_rate))
        for _ in range(2000):
            theta, rate = rng.uniform(-0.2, 1.8), rng.uniform(-1.5, 1.5)
            w_base = np.r_[rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1, 2)]
            omega_p = rot_x(theta).T @ w_base + rate * np.array([1.0, 0.0, 0.0])
            assert not fit.add(tilt.T @ omega_p + offset, theta + np.radians(5.0), w_base)
        assert fit.samples == 0 and np.array_equal(fit.tilt_rad, np.zeros(2))
        return np.degrees(fit.cross_offsets - (tilt @ offset)[1:]), fit.cross_offsets_var

    st = MountingFitSettings()
    error, var = fitted(st.still_rate_rad_s)
    assert np.abs(error).max() < 0.15
    # their variance is the offsets' sums' (the tilt's have no sample: their variance is still the prior's)
    assert var < 0.05 * st.offset_std_rad_s ** 2
    error, var = fitted(0.0)
    assert np.abs(error).min() > 2.0 and var == pytest.approx(st.offset_std_rad_s ** 2, rel=1e-12)


def test_a_still_sample_needs_the_gyro_to_agree_and_the_optics_window_full():
    """The optics report a hand rate of exactly zero at their first pose (and one lagging after it) while
    the hand turns at 1.5 rad/s across the hinge: a finger still on it reads that turn on its gyro's cross
    axes, far above what the offsets can make of a still hand's (0.2 rad/s and the MPU-9250's ±5 deg/s per
    axis), so the sample is not a still one; taken as one, the turn lands in the offsets, ~80 deg/s off for
    the session (a still sample's residual is the gyro's rate less the optics'). Slow samples of a hand the
    gyro agrees is still tell the offsets, but only while the optics' window is full (``admit_still``).
    The fit and its compiled kernel alike."""
    from service.pipeline.mounting import HandMountings, HandMountingsReference

    calib = default_calibration("right")
    ids = ("index.1",)
    n_phi = sum(g.n_phalanges for g in calib.fingers.values())
    phi, started = np.zeros(n_phi), np.ones(len(calib.fingers), dtype=np.bool_)
    zero_rate = np.ascontiguousarray(np.r_[np.eye(3).ravel(), np.zeros(9)])     # the first pose: no rate yet
    offset = np.radians([1.0, -3.0, 2.5])
    base = calib.finger("index").base_matrix()
    turning = base @ np.array([0.0, 1.5, 0.0])          # across the index's hinge, metacarpus frame
    rng = np.random.default_rng(3)
    for cls in (HandMountings, HandMountingsReference):
        fits = cls(calib)
        rows = fits.rows(ids)
        for _ in range(50):
            w_p = base.T @ turning + rng.normal(0.0, 0.05, 3)          # the phalanx's rate, finger still
            fits.fit(rows, np.array([[w_p + offset, [0.0, 0.0, 9.8]]]), zero_rate, phi, started)
        np.testing.assert_array_equal(fits.cross_offsets(rows), np.zeros((1, 2)), err_msg=cls.__name__)
        fits.admit_still(False)                            # a hand still, the optics' window not full yet
        still = [np.array([[rng.normal(0.0, 0.01, 3) + offset, [0.0, 0.0, 9.8]]]) for _ in range(400)]
        for raw in still:
            fits.fit(rows, raw, zero_rate, phi, started)
        np.testing.assert_array_equal(fits.cross_offsets(rows), np.zeros((1, 2)), err_msg=cls.__name__)
        fits.admit_still(True)
        for raw in still:
            fits.fit(rows, raw, zero_rate, phi, started)
        error = np.degrees(fits.cross_offsets(rows)[0] - offset[1:])
        assert np.abs(error).max() < 1.0, (cls.__name__, error)      # the prior's pull: 0.25 deg/s


def test_a_nan_gyro_sample_stays_out_of_the_fit():
    """A NaN reading (the protocol refuses them, the fit's own API does not) on a still hand, where slow samples
    enter the offsets' sums, and in a fast flexion: the fit and its compiled kernel leave it out, so the offsets
    and their variance stay finite and as they were."""
    from service.pipeline.mounting import HandMountings, HandMountingsReference

    calib = default_calibration("right")
    ids = ("index.1",)
    n_phi = sum(g.n_phalanges for g in calib.fingers.values())
    phi, started = np.full(n_phi, 0.3), np.ones(len(calib.fingers), dtype=np.bool_)
    still_hand = np.ascontiguousarray(np.r_[np.eye(3).ravel(), np.zeros(9)])
    for cls in (HandMountings, HandMountingsReference):
        fits = cls(calib)
        rows = fits.rows(ids)
        out = np.zeros((1, 3))
        good = np.array([[[0.5, 0.01, -0.02], [0.0, 0.0, 9.8]]])
        assert fits.fit(rows, good, still_hand, phi, started) == 0
        before = fits.cross_offsets(rows, out).copy()
        assert before[0, 1] != 0.0
        for gyr in ([np.nan, 0.01, -0.02], [0.5, np.nan, -0.02], [6.0, 0.01, np.nan]):
            fits.fit(rows, np.array([[gyr, [0.0, 0.0, 9.8]]]), still_hand, phi, started)
            np.testing.assert_array_equal(fits.cross_offsets(rows, out), before, err_msg=f"{cls.__name__} {gyr}")
            assert fits.samples("index.1") == 0


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
        np.testing.assert_allclose(fits[True].tilt_rad(sid), eps[k], atol=np.radians(0.25))
    assert fits[False] is None
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


TOL = 1e-9


def _random_rotation(rng):
    return Rotation.from_rotvec(rng.normal(0.0, 0.6, 3)).as_matrix()


def _hand_flat(rng):
    rot = _random_rotation(rng)
    return np.ascontiguousarray(np.concatenate([rot.ravel(), rng.normal(0.0, 2.0, 3), rng.normal(0.0, 2.0, 3),
                                                rng.normal(0.0, 5.0, 3)]))


def _assert_same_fits(kernel, reference):
    for sid in reference.places:
        assert kernel.samples(sid) == reference.samples(sid), sid
        np.testing.assert_allclose(kernel.tilt_rad(sid), reference.tilt_rad(sid), rtol=0, atol=TOL, err_msg=sid)
        np.testing.assert_allclose(kernel.correction(sid), reference.correction(sid), rtol=0, atol=TOL, err_msg=sid)
        assert kernel.quiet_samples(sid) == reference.quiet_samples(sid), sid
        np.testing.assert_allclose(kernel.cross_axis(sid), reference.cross_axis(sid), rtol=0, atol=TOL, err_msg=sid)
    rows = np.array([j for j, _, _ in reference.places.values()] + [-1], dtype=np.int64)
    np.testing.assert_allclose(kernel.cross_offsets(rows), reference.cross_offsets(rows), rtol=0, atol=TOL)
    with_var = [f.cross_offsets(rows, np.zeros((len(rows), 3))) for f in (kernel, reference)]
    np.testing.assert_allclose(with_var[0], with_var[1], rtol=0, atol=TOL)


def test_the_compiled_fits_equal_the_reference_on_random_ticks():
    """``HandMountings`` (numba) against ``HandMountingsReference`` (``HingeAxisFit`` per sensor) on
    random ticks: sensors with and without a calibrated mounting, samples missing from ticks, the
    back-of-hand IMU (no fit), saturated gyro samples, fingers not started, and a calibration change that
    keeps some fits and restarts the one whose mounting changed."""
    from service.model.hand import METACARPUS_SENSOR_ID
    from service.pipeline.mounting import HandMountings, HandMountingsReference

    rng = np.random.default_rng(5)
    calib = default_calibration("right")
    index = calib.finger("index")
    tilted = tuple(replace(sp, mounting=tuple(Rotation.from_matrix(_random_rotation(rng)).as_quat())) for sp in index.sensors)
    calib = replace(calib, fingers={**calib.fingers, "index": replace(index, sensors=tilted)})
    ids = list(calib.sensor_ids) + [METACARPUS_SENSOR_ID]
    n_phi = sum(g.n_phalanges for g in calib.fingers.values())
    kernel, reference = HandMountings(calib), HandMountingsReference(calib)
    used = 0
    for tick in range(600):
        if tick == 300:       # a new mounting for index.2: its fit restarts, the others are kept
            index = calib.finger("index")
            moved = (index.sensors[0], replace(index.sensors[1], mounting=tuple(Rotation.from_rotvec([0.1, 0.0, 0.2]).as_quat())))
            calib = replace(calib, fingers={**calib.fingers, "index": replace(index, sensors=moved)})
            kernel, reference = HandMountings(calib, previous=kernel), HandMountingsReference(calib, previous=reference)
            assert kernel.samples("index.2") == 0 and kernel.samples("index.1") > 0
        present = tuple(s for s in rng.permutation(ids).tolist() if rng.random() > 0.15)     # some missing
        raw = np.stack([rng.normal(0.0, 4.0, (len(present), 3)), rng.normal(0.0, 12.0, (len(present), 3))], axis=1)
        raw[:, 0, 0] += rng.choice([-6.0, 0.0, 6.0], len(present))       # fast flexion about a hinge axis
        if tick % 50 == 7 and present:
            raw[0, 0] = [34.9, -34.9, 34.9]                             # a saturated gyro sample
        rows = kernel.rows(present)
        np.testing.assert_allclose(kernel.correct(rows, raw), reference.correct(rows, raw), rtol=0, atol=TOL)
        hand, phi = _hand_flat(rng), rng.uniform(-0.3, 1.4, n_phi)
        if tick % 4 == 1:
            hand[12:15] *= 0.02                     # a hand nearly still: slow samples tell the offsets
            raw[:, 0, 1:] *= 0.02                   # and the gyros' cross axes agree, mostly
        for fits in (kernel, reference):
            fits.admit_still(tick % 16 != 5)        # now and then the optics' window not full
        started = rng.random(len(calib.fingers)) > 0.1
        n = kernel.fit(rows, raw, hand, phi, started)
        assert n == reference.fit(rows, raw, hand, phi, started)
        used += n
        _assert_same_fits(kernel, reference)
    assert used > 1000
    assert sum(kernel.quiet_samples(sid) for sid in calib.sensor_ids) > 40       # the cross-axis fits ran too


def _recording_with_faults():
    """A realistic recording of a glove whose two index sensors sit turned on their phalanges, as its
    calibration states (the fits then work behind a calibrated mounting), with a saturated gyro sample,
    a missing sample and an occlusion."""
    from service.sim.errors import OpticalModel

    calib = _tilted(np.radians([[4.0, -3.0], [-2.5, 4.5]]))
    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=7, duration_s=3.0,
                       calibration=calib, optical=OpticalModel(occlusions_s=((2.2, 2.4),)))
    messages = list(simulate(config).messages(include_truth=False))
    imu = [i for i, m in enumerate(messages) if m["type"] == "imu"]
    saturated = messages[imu[3000]]
    saturated["gyr"] = [40.0, saturated["gyr"][1], -40.0]        # beyond ±2000 deg/s
    return [m for i, m in enumerate(messages) if i != imu[3301]]   # one sample missing


def test_the_compiled_fits_equal_the_reference_through_the_pipeline():
    from service.pipeline.mounting import HandMountingsReference

    class ReferenceSession(HandSession):
        mountings = HandMountingsReference

    messages = _recording_with_faults()
    assert any(m["type"] == "calibration" for m in messages)
    runs = {}
    for cls in (HandSession, ReferenceSession):
        session = cls("right")
        frames = [f for m in messages for f in session.handle(parse_message(m)).frames]
        runs[cls] = (frames, session._mount_fits)
    (compiled, fits), (reference, reference_fits) = runs[HandSession], runs[ReferenceSession]
    assert len(compiled) == len(reference) > 200
    assert {f.status["optics"] for f in compiled} == {"tracking", "occluded"}
    assert fits.samples("index.1") > 100 and not np.allclose(fits.correction("index.1"), np.eye(3), atol=1e-3)
    assert fits.quiet_samples("index.1") > 20 and np.any(fits.cross_axis("index.1") != 0.0)
    _assert_same_fits(fits, reference_fits)
    for c, r in zip(compiled, reference):
        assert c.t == r.t and c.modes == r.modes
        for finger, phi in r.joint_angles.items():
            np.testing.assert_allclose(c.joint_angles[finger], phi, rtol=0, atol=TOL, err_msg=f"{finger} at t={c.t}")


def _clipped_run(peak_deg_s: float, sign: float, shape: str):
    """Noise-free gyro readings (200 Hz) of one sensor through a flexion whose hinge rate peaks at
    ``peak_deg_s``: a parabola in time (the reconstruction's own assumption) or a minimum-jerk bell
    (``30 τ² (1 - τ)²``, not a parabola) of a fist's distal phalanx (220 deg: a rate of 2800 deg/s
    takes it 0.15 s), clipped at ±2000 deg/s; and the true angle change, rad."""
    dt, rng_rad = 0.005, np.radians(2000.0)
    peak = np.radians(peak_deg_s)
    if shape == "parabola":
        half = 0.1                                          # the rate falls from its peak to 0 in 0.1 s
        t = np.arange(-half, half + dt / 2, dt) + 0.0013     # samples not aligned with the peak
        rate = peak * np.clip(1.0 - (t / half) ** 2, 0.0, None)
        true = peak * 4.0 * half / 3.0                         # the area of the parabola
    else:
        duration = 1.875 * np.radians(220.0) / peak           # a 220 deg flexion peaking at ``peak``
        tau = np.arange(0.0, 1.0 + 1e-9, dt / duration)
        rate = peak * 30.0 * tau**2 * (1.0 - tau) ** 2 / 1.875
        true = np.radians(220.0)
    rate = np.concatenate([np.zeros(3), rate, np.zeros(3)]) * sign
    gyr = np.zeros((len(rate), 3))
    gyr[:, 0] = np.clip(rate, -rng_rad, rng_rad)
    gyr[:, 1] = 0.3                                             # the hand turning about another axis
    return gyr, sign * true, np.sum(np.abs(rate) > rng_rad)


def _true_rate(peak_deg_s: float, sign: float, shape: str) -> np.ndarray:
    """The unclipped hinge rate of ``_clipped_run``, rad/s."""
    dt, peak = 0.005, np.radians(peak_deg_s)
    if shape == "parabola":
        t = np.arange(-0.1, 0.1 + dt / 2, dt) + 0.0013
        rate = peak * np.clip(1.0 - (t / 0.1) ** 2, 0.0, None)
    else:
        duration = 1.875 * np.radians(220.0) / peak
        tau = np.arange(0.0, 1.0 + 1e-9, dt / duration)
        rate = peak * 30.0 * tau**2 * (1.0 - tau) ** 2 / 1.875
    return np.concatenate([np.zeros(3), rate, np.zeros(3)]) * sign


@pytest.mark.parametrize("shape", ["parabola", "bell"])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_clipped_gyro_run_gets_back_the_angle_it_missed(shape, sign):
    """A flexion whose hinge rate peaks at 1.4x the gyro's full scale: integrated, the clipped readings
    miss the part above the range (tens of degrees); with the reconstruction the readings integrate to
    the true angle change to within a tenth of what was missed for a parabolic peak (its area is exact
    from the entry slope and the run's length; the sampling errs by part of a sample in a run of about
    twenty) and a fifth for a minimum-jerk bell (not a parabola: in the limit of fine sampling the
    formula gives 7 % less than its area, and the one-sample rise before the crossing is steeper than
    the slope at it, in a run of about ten samples). The other axes are
    left alone, the compiled kernel equals its reference, and with the reconstruction off the whole
    area stays missing."""
    from service.pipeline.mounting import HandMountings, HandMountingsReference

    gyr, true, n_clipped = _clipped_run(2800.0, sign, shape)
    assert n_clipped >= 5
    calib = default_calibration("right")
    ids = ("index.2",)
    dt = 0.005
    results = {}
    for name, cls, settings in (("kernel", HandMountings, MountingFitSettings()),
                                ("reference", HandMountingsReference, MountingFitSettings()),
                                ("off", HandMountings, MountingFitSettings(clip_range_rad_s=0.0))):
        fits = cls(calib, settings)
        rows = fits.rows(ids)
        out = np.array([fits.correct(rows, np.array([[g, [0.0, 0.0, 9.8]]]))[0, 0] for g in gyr])
        results[name] = out
    np.testing.assert_allclose(results["kernel"], results["reference"], rtol=0, atol=1e-9)
    missed = true - np.sum(gyr[:, 0]) * dt
    assert abs(np.degrees(missed)) > 10.0
    assert np.sum(results["off"][:, 0]) * dt == pytest.approx(true - missed, abs=1e-12)
    error = true - np.sum(results["kernel"][:, 0]) * dt
    assert abs(error) < (0.1 if shape == "parabola" else 0.2) * abs(missed)
    np.testing.assert_array_equal(results["kernel"][:, 1:], gyr[:, 1:])


@pytest.mark.parametrize("shape", ["parabola", "bell"])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_clipped_run_is_filled_in_while_it_lasts(shape, sign):
    """While a run is clipped, each sample gets the excess of the parabola through the entry slope that
    lasts twice as long as the run so far (its median length when nothing else is known), and the run's
    end gets the rest of the whole missed angle. For a parabola, in the limit of fine sampling, the
    angle integrated from the readings is then never off by more than half of what the run misses in
    all (``s n² / 12`` against ``s n² / 6``), and its RMS error over the run is 0.24 of what it is
    without the fill-in (``x³/3 - x²/4`` against ``x²/2 - x³/3`` over the run's fraction ``x``); the
    bounds 0.65 and 0.5 allow for the one-sample rise before the crossing, which is not the slope at
    it. A minimum-jerk bell, which the parabola only approximates (and whose one-sample rise is steeper
    than its slope at the crossing), is only required to be nearer than without the fill-in. The
    compiled kernel equals its reference."""
    from service.pipeline.mounting import HandMountings, HandMountingsReference

    gyr, true, n_clipped = _clipped_run(2800.0, sign, shape)
    rate = _true_rate(2800.0, sign, shape)
    clipped = np.abs(rate) > np.radians(2000.0)
    dt = 0.005
    calib = default_calibration("right")
    out = {}
    for name, cls in (("kernel", HandMountings), ("reference", HandMountingsReference)):
        fits = cls(calib, MountingFitSettings())
        rows = fits.rows(("index.2",))
        out[name] = np.array([fits.correct(rows, np.array([[g, [0.0, 0.0, 9.8]]]))[0, 0, 0] for g in gyr])
    np.testing.assert_allclose(out["kernel"], out["reference"], rtol=0, atol=1e-9)
    missed = abs(np.sum(rate - gyr[:, 0]) * dt)
    running = np.abs(np.cumsum(rate - out["kernel"]) * dt)[clipped]
    without = np.abs(np.cumsum(rate - gyr[:, 0]) * dt)[clipped]
    assert without.max() > 0.9 * missed
    rms = lambda e: np.sqrt(np.mean(e**2))  # noqa: E731
    if shape == "parabola":
        assert running.max() < 0.65 * missed
        assert rms(running) < 0.5 * rms(without)
    else:
        assert rms(running) < rms(without)


def test_a_long_clipped_run_is_left_alone():
    """A reading held at full scale for longer than ``clip_max_samples`` is no peak: what its first
    samples were given while it might have been one is taken back after it, so the readings integrate
    to the clipped ones, and nothing is added after the run's first reading."""
    from service.pipeline.mounting import HandMountings

    calib = default_calibration("right")
    fits = HandMountings(calib, MountingFitSettings(clip_max_samples=10))
    rows = fits.rows(("index.2",))
    rates = np.radians(np.r_[np.linspace(0.0, 1999.0, 5), np.full(11, 2000.0), [1500.0, 0.0]])
    out = np.array([fits.correct(rows, np.array([[[r, 0.0, 0.0], [0.0, 0.0, 9.8]]]))[0, 0, 0] for r in rates])
    assert np.sum(out) == pytest.approx(np.sum(rates), abs=1e-9)
    np.testing.assert_array_equal(out[:4], rates[:4])
    np.testing.assert_array_equal(out[-1:], rates[-1:])
