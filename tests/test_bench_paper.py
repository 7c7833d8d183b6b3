"""``fingertrack bench paper --quick``: the files it writes and the findings they must show."""
import csv
import functools

import numpy as np
import pytest

from service.bench import paper
from service.estimators.base import samples_from_session
from service.estimators.madgwick import Madgwick, MadgwickSettings
from service.model.hand import joint_to_phalanx_angles
from service.sim.session import SimConfig, simulate


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    # the estimators' times are checked for their line in the summary only: timed once each, not the
    # best of three (11 -> 4 s of CPU)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(paper, "timing", functools.partial(paper.timing, repeats=1))
        paper.run(out, quick=True, progress=False)
    with open(out / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    return out, rows


def _rms(rows, series, estimator):
    sel = {float(r["t_m"]): float(r["rms_deg"]) for r in rows if r["series"] == series and r["estimator"] == estimator}
    t = np.array(sorted(sel))
    return t, np.array([sel[x] for x in t])


def test_outputs_are_complete(quick):
    out, rows = quick
    assert list(rows[0].keys()) == ["series", "t_m", "estimator", "seed", "rms_mcp_deg", "rms_pip_deg", "rms_dip_deg", "rms_deg"]
    assert {r["series"] for r in rows} == {"white", "offset", "both"}
    assert {r["estimator"] for r in rows} == {m.label for m in paper.METHODS}
    assert len(rows) == 3 * len(paper.METHODS) * len(paper.durations(True))
    for name in ("fig10.png", "fig9.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Switching / Madgwick streaming time ratio" in (out / "summary.md").read_text()


def test_with_zero_offset_integration_wins_short_and_loses_long_crossing_near_one_second(quick):
    _, rows = quick
    t, vec = _rms(rows, "offset", "vector")
    _, integ = _rms(rows, "offset", "integration")
    assert np.all(integ[t < 0.5] < vec[t < 0.5])
    assert np.all(integ[t > 2.0] > vec[t > 2.0])
    # the crossover lies between 0.3 s and 3.2 s
    first_loss = t[np.argmax(integ > vec)]
    assert 0.3 < first_loss <= 3.2


def test_switching_and_madgwick_stay_close_to_the_better_of_the_two(quick):
    """The paper's claim, as a median over the durations. Per duration it does not hold robustly: at
    t_m <= 0.3 s the grasp needs up to 8000 deg/s and 40 g and single transients dominate, so Madgwick's
    ratio to the better of vector observation and integration swings with the noise draw (1.9, 3.2,
    10.2 and 3.0 for seeds 0, 1, 2 and 4 at t_m = 0.1 s); a per-duration bound would be fitted to one
    seed. (Switching equals integration at short durations with a known start: its half is trivial.)"""
    _, rows = quick
    for series in ("offset", "both"):
        _, vec = _rms(rows, series, "vector")
        _, integ = _rms(rows, series, "integration")
        better = np.minimum(vec, integ)
        for name in ("switching", "madgwick-0.1"):
            _, est = _rms(rows, series, name)
            assert np.median(est / better) <= 2.0, (series, name, est, better)


def test_too_small_beta_diverges_over_long_motions(quick):
    _, rows = quick
    t, small = _rms(rows, "offset", "madgwick-0.01")
    _, large = _rms(rows, "offset", "madgwick-0.1")
    assert small[-1] > 5 * small[t == 1.0][0]
    assert small[-1] > 10 * large[-1]


def test_too_large_beta_hurts_fast_motion(quick):
    _, rows = quick
    t, small = _rms(rows, "white", "madgwick-0.01")
    _, large = _rms(rows, "white", "madgwick-0.1")
    assert large[t == 1.0][0] > 1.3 * small[t == 1.0][0]


def test_the_mechanism_is_the_fingers_own_acceleration():
    # a large gain pulls the estimate toward the accelerometer, which in fast motion measures the
    # finger's own acceleration; with g_k of eq. 2 in the reference (eq. 11) that pull is mostly removed
    sess = simulate(SimConfig(motion="grasp", t_m_s=1.0, noise="white", seed=0, fingers=("index",)))
    smp = samples_from_session(sess, "index")
    truth = sess.joint_angles["index"]
    theta0 = joint_to_phalanx_angles(truth[0])
    geom = sess.calibration.finger("index")

    def rms(beta, kinematic):
        est = Madgwick(geom, MadgwickSettings(beta=beta, kinematic_acceleration=kinematic), initial_theta=theta0)
        return np.sqrt(np.mean(np.degrees(est.run(smp).phi - truth) ** 2))

    assert rms(1.0, False) > 3 * rms(0.01, False)
    assert rms(1.0, True) < 0.5 * rms(1.0, False)


def test_ours_is_most_accurate_on_both(quick):
    _, rows = quick
    summ = paper.summarize([dict(r, seed=int(r["seed"]), rms_deg=float(r["rms_deg"])) for r in rows])
    both = {k: v[0] for k, v in summ["both"].items()}
    assert min(both, key=both.get) == paper.OURS
    assert both[paper.OURS] <= 0.7 * min(both["switching"], both["madgwick-0.03"])
    assert both[paper.OURS] < both["ekf"]
