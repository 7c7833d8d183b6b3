"""``fingertrack bench accuracy --quick`` and the default estimator's behaviour across rebuilds."""
import json

import numpy as np
import pytest

from service.bench import accuracy
from service.estimators.chain import Chain
from service.pipeline.hand import HandSession, PipelineSettings
from service.protocol import parse_message
from service.model.units import MG
from service.sim.session import SimConfig, simulate


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("accuracy")
    summary = accuracy.run(out, quick=True, progress=False)
    return out, summary


def test_quick_writes_every_output(quick):
    out, summary = quick
    for name in ("results.csv", "events.csv", "results.json", "summary.md", "accuracy.png"):
        assert (out / name).stat().st_size > 0, name
    assert "Coupling mismatch" in summary and "Convergence without a reference pose" in summary
    rows = (out / "results.csv").read_text().splitlines()
    # 1 trial x 2 conditions x 3 estimators x 8 joints (thumb 2, index 3, middle 3)
    assert len(rows) == 1 + 2 * 3 * 8
    assert "(seeds 0-0)" in summary
    assert {row.split(",")[0] for row in rows[1:]} == {"0"}


def test_first_seed_must_be_a_whole_number_not_below_zero(tmp_path, capsys):
    from service.cli import main
    with pytest.raises(SystemExit):
        main(["bench", "accuracy", "--out", str(tmp_path), "--first-seed", "-1"])
    assert "--first-seed" in capsys.readouterr().err


def test_quick_discriminates_the_crude_baseline(quick):
    """The memoryless vector observation must score clearly worse than the filters: a benchmark that
    ranks it near them measures nothing."""
    out, _ = quick
    agg = json.loads((out / "results.json").read_text())
    for cond in ("reference", "none"):
        assert agg[cond]["vector"]["mean_rms_deg"] > 1.5 * agg[cond]["chain"]["mean_rms_deg"], cond
        assert agg[cond]["vector"]["p95_deg"] > agg[cond]["chain"]["p95_deg"], cond


class _Forgetful(Chain):
    """The chain filter as it was: a rebuilt estimator learns its offsets again from zero."""

    name = "chain-forgetful"

    def inherit(self, previous):
        pass


def _dropout_run(estimator_cls, session, drop=("index.2", 6.0, 6.5)):
    sid, a, b = drop
    hs = HandSession(settings=PipelineSettings(estimator="chain"))
    hs._make_estimator = lambda geom, theta0, extra=(): estimator_cls(   # same settings, chosen class
        geom, settings=estimator_cls.Settings(), initial_theta=theta0, extra_couplings=extra)
    hs._build_fingers()
    t, phi = [], []
    for m in session.messages(include_truth=False):
        if m["type"] == "imu" and m["id"] == sid and a <= m["t"] < b:
            continue
        for f in hs.handle(parse_message(m)).frames:
            t.append(f.t)
            phi.append(f.joint_angles["index"])
    t, phi = np.array(t), np.array(phi)
    truth = session.joint_angles["index"][np.round(t * session.config.rate_hz).astype(int)]
    return t, np.degrees(np.sqrt(np.mean((phi - truth) ** 2, axis=1)))


def test_a_rebuilt_chain_keeps_its_offsets():
    """A 0.5 s dropout of one sensor, accelerometer offsets up to 60-80 mg (the MPU-9250 tolerance),
    a slowly turning hand. An estimator that forgets its offsets tilts by up to offset/g (up to 4.7°)
    until it learns them again; one that keeps them is back to its undisturbed error. Bounds: within
    1 s of the sensor's return a 0.25 s running RMS is back within 1.5x the undisturbed RMS before the
    dropout (the benchmark's recovery, the issue's goal), the RMS over that second stays far below
    the offset tilt, and a forgetful copy is more than twice as far off in it. (The RMS over the
    whole second also reaches the first fast flexion after the return, where the gyro scale state,
    learned on data without a scale error, adds a few tenths of a degree: 1.65x here.)"""
    session = simulate(SimConfig(motion="random", noise="both", seed=2, hand_motion="slow-rotation",
                                 duration_s=10.0, fingers=("index",)))
    tilt_deg = np.degrees(80 * MG / 9.81)
    t, err = _dropout_run(Chain, session)
    before = np.sqrt(np.mean(err[(t >= 3.0) & (t < 6.0)] ** 2))
    after = np.sqrt(np.mean(err[(t >= 6.5) & (t < 7.5)] ** 2))       # the second after the return
    assert accuracy._recovery(t, err, 6.5, 1.5 * before) <= 1.0
    assert after < 0.25 * tilt_deg
    t2, err2 = _dropout_run(_Forgetful, session)
    forgot = np.sqrt(np.mean(err2[(t2 >= 6.5) & (t2 < 7.5)] ** 2))
    assert forgot > 2.0 * after                          # the test can tell the two apart

@pytest.mark.parametrize("seed", [3, 4])
def test_a_returning_sensor_is_placed_by_its_own_accelerometer(seed):
    """The same design on the seeds where the fallback closure carried the silent distal phalanx far
    off (the finger's MCP and PIP move independently here, against the closure PIP = MCP): the
    returning sensor must not restart as if that guess were a known configuration. Bounds from the
    physics, not from a run: 0.5 s after its return the sensor's accelerometer has given 100 samples,
    each placing the angle to the filter's per-sample std of 0.3 rad (``acc_scale_uncertainty``), so
    together to 0.3/√100 rad = 1.7°: the finger is then within half the tilt a forgotten offset
    would cause (offset/g); and within 1 s a 0.25 s running RMS is back within 1.5x the undisturbed
    error (the issue's recovery goal)."""
    session = simulate(SimConfig(motion="random", noise="both", seed=seed, hand_motion="slow-rotation",
                                 duration_s=10.0, fingers=("index",)))
    tilt_deg = np.degrees(80 * MG / 9.81)
    t, err = _dropout_run(Chain, session)
    rms = lambda a, b: np.sqrt(np.mean(err[(t >= a) & (t < b)] ** 2))   # noqa: E731
    assert rms(6.3, 6.5) > 2.0 * tilt_deg           # the closure's guess was far off when the sensor returned
    assert rms(7.0, 8.0) < 0.5 * tilt_deg
    assert accuracy._recovery(t, err, 6.5, 1.5 * rms(3.0, 6.0)) <= 1.0


def _fast_reach_as_the_optics_return():
    """A benchmark trial whose 0.74 s occlusion ends while the hand reaches fast (7.7 m/s²)."""
    trial = accuracy.make_trial(503, 12.0)
    (a, b), = trial.occlusions
    session = accuracy.simulate_trial(trial)
    return trial, session, a, b


def test_the_hand_acceleration_counts_as_known_once_the_optical_fit_window_refilled():
    """Right after the optics return, their fit window holds too few poses for an acceleration and
    reports none: the estimators must go on treating the hand's acceleration as unknown until the
    window holds only poses since the return (``pose_window_s``), and not longer."""
    trial, session, a, b = _fast_reach_as_the_optics_return()
    hs = HandSession(settings=PipelineSettings(estimator="chain"))
    window = hs.settings.pose_window_s
    seen = []
    for m in accuracy.trial_messages(session, trial, True):
        for f in hs.handle(m).frames:
            seen.append((f.t, hs._fingers["index"].estimator._hand_untracked))
    t = np.array([s[0] for s in seen])
    untracked = np.array([s[1] for s in seen])
    latency = 0.05                      # the optical stream's latency and timeout around the edges
    assert not untracked[(t > a - 1.0) & (t < a - latency)].any()
    assert untracked[(t > a + 0.2) & (t < b + window - latency)].all()
    assert not untracked[(t > b + window + latency) & (t < b + 2.0)].any()


def test_a_fast_reach_as_the_optics_return_is_not_read_as_a_tilt():
    """The same trial through the pipeline: read as no acceleration, the reach (7.7 m/s² as the optics
    return) would tilt every accelerometer's gravity by atan(a/g) = 38°. Through the occlusion the
    hand's orientation was carried on by the finger gyros, so the angles need only a small widening
    when it ends (``lost_optics_drift_rad_s``); in the 0.5 s after the return every joint stays within
    a quarter of that tilt."""
    trial, session, a, b = _fast_reach_as_the_optics_return()
    t, phi = accuracy.run_pipeline(accuracy.trial_messages(session, trial, True), "chain", {})
    idx = np.round((t - session.t[0]) * session.config.rate_hz).astype(int)
    err = np.concatenate([np.degrees(np.abs(accuracy._wrap(phi[f] - session.joint_angles[f][idx])))
                          for f in accuracy.FINGERS], axis=1)
    acc = np.linalg.norm(session.base.acceleration[int(round(b * session.config.rate_hz))])
    tilt_deg = np.degrees(np.arctan2(acc, 9.81))
    assert tilt_deg > 30.0                           # the trial is what it claims
    assert err[(t >= b) & (t < b + 0.5)].max() < 0.25 * tilt_deg
