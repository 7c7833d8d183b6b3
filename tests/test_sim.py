"""Motions, sensor error statistics and recordings."""
import hashlib
import json

import numpy as np
import pytest

from service.model.hand import default_calibration
from service.model.units import DEG, MG
from service.sim.errors import ImuErrorModel
from service.sim.motions import FINGER_MOTIONS, grasp_motion, joint_limits, make_finger_motion
from service.sim.session import SimConfig, simulate, write_recording


@pytest.mark.parametrize("t_m", [0.1, 1.0, 37.0])
def test_grasp_motion_reaches_the_papers_angles_at_the_stated_times(t_m):
    t_d = 0.2
    m = grasp_motion(t_m=t_m, t_d=t_d)
    times = np.array([0.0, t_d, t_d + t_m / 3, t_d + t_m])
    phi, dphi, ddphi = m.joint_angles("index", times)
    np.testing.assert_allclose(np.degrees(phi[0]), [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(np.degrees(phi[1]), [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(np.degrees(phi[2]), [-28, 0, 0], atol=1e-9)
    np.testing.assert_allclose(np.degrees(phi[3]), [90, 85, 85], atol=1e-9)
    # C2: at rest at every keyframe
    np.testing.assert_allclose(dphi, 0.0, atol=1e-9)
    np.testing.assert_allclose(ddphi, 0.0, atol=1e-6)
    assert m.duration_s == pytest.approx(t_d + t_m)


def test_profiles_are_c2_continuous():
    m = grasp_motion(t_m=0.3)
    t = np.linspace(0, m.duration_s, 20001)
    phi, dphi, ddphi = m.joint_angles("index", t)
    dt = t[1] - t[0]
    # the numerical derivative of each level matches the analytic next level (no jumps)
    np.testing.assert_allclose(np.gradient(phi, dt, axis=0)[1:-1], dphi[1:-1], atol=2e-3)
    np.testing.assert_allclose(np.gradient(dphi, dt, axis=0)[1:-1], ddphi[1:-1], atol=0.5)
    # no jump in acceleration: consecutive samples differ by at most max|jerk|·dt,
    # max|jerk| = 60 |Δφ| / T³ for the quintic step (|Δφ| <= 118 deg, T = t_m/3 or 2 t_m/3)
    max_jerk = 60 * np.radians(118) / (0.1**3)
    assert np.abs(np.diff(ddphi, axis=0)).max() <= max_jerk * dt


@pytest.mark.parametrize("name", sorted(FINGER_MOTIONS))
def test_motions_respect_joint_limits_and_coupling(name):
    for seed in range(4):
        m = make_finger_motion(name, seed=seed, coupling=0.8)
        t = np.linspace(0, m.duration_s, 4001)
        for f in ("thumb", "index", "middle", "ring", "little"):
            phi, _, _ = m.joint_angles(f, t)
            for j, (lo, hi) in enumerate(joint_limits(f)):
                assert phi[:, j].min() >= lo - 1e-12, (name, f, j)
                assert phi[:, j].max() <= hi + 1e-12, (name, f, j)
            if f != "thumb" and name != "grasp":
                np.testing.assert_allclose(phi[:, 2], 0.8 * phi[:, 1], atol=1e-12)


def test_white_noise_and_offset_statistics_match_the_datasheet_figures():
    rng = np.random.default_rng(7)
    model = ImuErrorModel.named("both")
    n, s, rate = 20000, 400, 200.0
    offsets = model.draw_offsets(rng, s)
    gyr, acc = model.corrupt(rng, np.zeros((n, 1, 3)), np.zeros((n, 1, 3)), rate,
                             (offsets[0][:1], offsets[1][:1]))
    # noise: 0.01 deg/s/sqrt(Hz) and 300 ug/sqrt(Hz) at 100 Hz bandwidth
    g_sigma, a_sigma = 0.01 * DEG * 10.0, 300e-6 * 9.81 * 10.0
    assert model.gyro_sigma(rate) == pytest.approx(g_sigma)
    rel_err = 4 / np.sqrt(2 * n)  # 4 standard errors of a sample standard deviation
    np.testing.assert_allclose((gyr - offsets[0][:1]).std(axis=0), g_sigma, rtol=rel_err)
    np.testing.assert_allclose((acc - offsets[1][:1]).std(axis=0), a_sigma, rtol=rel_err)
    np.testing.assert_allclose(gyr.mean(axis=0)[0], offsets[0][0], atol=4 * g_sigma / np.sqrt(n))
    # offsets: uniform within +-5 deg/s and +-60/60/80 mg -> std = bound / sqrt(3)
    assert np.all(np.abs(offsets[0]) <= 5 * DEG)
    assert np.all(np.abs(offsets[1]) <= np.array([60, 60, 80]) * MG)
    se = 4 / np.sqrt(2 * s) * 1.2
    np.testing.assert_allclose(offsets[0].std(axis=0), 5 * DEG / np.sqrt(3), rtol=se)
    np.testing.assert_allclose(offsets[1].std(axis=0), np.array([60, 60, 80]) * MG / np.sqrt(3), rtol=se)
    assert np.all(np.abs(offsets[0].mean(axis=0)) < 4 * 5 * DEG / np.sqrt(3 * s))


def test_noise_free_simulation_equals_ideal_readings():
    sess = simulate(SimConfig(motion="point", noise="none"))
    np.testing.assert_array_equal(sess.gyr, sess.gyr_ideal)
    np.testing.assert_array_equal(sess.acc, sess.acc_ideal)
    assert sess.gyr.shape == (len(sess.t), 10, 3)
    assert np.all(sess.pose_position == sess.pose_position[0])  # still hand, no jitter


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_seeded_recordings_are_reproducible_bit_for_bit(tmp_path):
    cfg = SimConfig(motion="random", t_m_s=2.0, hand_motion="slow-rotation", noise="both", seed=11)
    a, b, c = tmp_path / "a.jsonl", tmp_path / "b.jsonl", tmp_path / "c.jsonl"
    write_recording(simulate(cfg), a)
    write_recording(simulate(cfg), b)
    write_recording(simulate(SimConfig(motion="random", t_m_s=2.0, hand_motion="slow-rotation", noise="both", seed=12)), c)
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)


def test_truth_messages_carry_the_true_angles(tmp_path):
    sess = simulate(SimConfig(motion="grasp", t_m_s=0.5, noise="none"))
    path = tmp_path / "g.jsonl"
    write_recording(sess, path)
    truths = [json.loads(l) for l in path.read_text().splitlines() if '"truth"' in l]
    assert len(truths) == len(sess.t)
    last = truths[-1]["fingers"]["index"]
    assert np.degrees([last["mcp"], last["pip"], last["dip"]]) == pytest.approx([90, 85, 85])
    assert set(truths[0]["fingers"]["thumb"]) == {"mcp", "ip"}


def test_occluded_poses_are_marked_invalid():
    from service.sim.errors import OpticalModel
    sess = simulate(SimConfig(motion="open", optical=OpticalModel(occlusions_s=((0.5, 1.0),))))
    inside = (sess.pose_t >= 0.5) & (sess.pose_t < 1.0)
    assert inside.any()
    assert not sess.pose_valid[inside].any() and sess.pose_valid[~inside].all()
    msgs = [m for m in sess.messages() if m["type"] == "pose" and not m["valid"]]
    assert len(msgs) == inside.sum() and all("position" not in m for m in msgs)


def test_pose_latency_orders_messages_by_arrival():
    sess = simulate(SimConfig(motion="open", noise="white"))
    latency = sess.optical.latency_s
    assert latency > 0
    arrivals = [m["t"] + (latency if m["type"] == "pose" else 0.0)
                for m in sess.messages(include_truth=False) if "t" in m]
    assert np.all(np.diff(arrivals) >= 0)
    assert sum(1 for m in sess.messages(include_truth=False) if m["type"] == "pose") == len(sess.pose_t)


def test_bad_simulation_settings_are_rejected():
    with pytest.raises(ValueError, match="unknown motion"):
        simulate(SimConfig(motion="wave"))
    with pytest.raises(ValueError, match="noise must be one of"):
        simulate(SimConfig(noise="loud"))
    with pytest.raises(ValueError, match="rate"):
        simulate(SimConfig(rate_hz=0.0))
    with pytest.raises(ValueError, match="hand must be"):
        simulate(SimConfig(hand="middle"))


def test_calibration_overrides_and_errors():
    calib = default_calibration("right")
    new = calib.with_overrides({"index": {"lengths": [0.05, 0.03, 0.02], "coupling": 0.7}})
    assert new.finger("index").lengths_m == (0.05, 0.03, 0.02)
    assert new.finger("index").coupling == 0.7
    assert new.finger("middle") == calib.finger("middle")
    with pytest.raises(ValueError, match=r"calibration.fingers.index.lengths: expected 3 values"):
        calib.with_overrides({"index": {"lengths": [0.05, 0.03]}})
    with pytest.raises(ValueError, match="unknown finger 'pinky'"):
        calib.with_overrides({"pinky": {}})
    with pytest.raises(ValueError, match=r"sensors\[0\].phalanx"):
        calib.with_overrides({"thumb": {"sensors": [{"id": "thumb.1", "phalanx": 2}]}})
