"""The intent-labelled gesture benchmark: scoring on scripted trials, discrimination, enrolment."""
import json

import numpy as np
import pytest

from gestures.enrolment import fit_thresholds
from gestures.recognizer import GestureRecognizer, GestureSettings
from service.bench import gestures
from service.model.openxr import joint_poses
from service.pipeline.hand import HandFrame
from service.sim.gesture_script import (ONSET_FRACTION, Step, Subject, Trial, enrolment_steps, gesture_pose,
                                        make_idle_trial, make_trial, quintic_time, tip_distance_m)


def truth_record(trial: Trial, rate_hz: float = 90.0) -> dict:
    """A benchmark record of the true hand of ``trial`` (still, palm down) at ``rate_hz``."""
    calib = trial.calibration()
    motion = trial.finger_motion()
    times = np.arange(0.0, trial.duration_s, 1.0 / rate_hz)
    angles = {f: motion.joint_angles(f, times)[0] for f in calib.fingers}
    rot, pos = np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]]), np.array([0.0, 1.1, -0.35])
    frames = [HandFrame(float(t), k, "right", {f: a[k] for f, a in angles.items()}, {}, rot, pos,
                        joint_poses(calib, {f: a[k] for f, a in angles.items()}, rot, pos), {})
              for k, t in enumerate(times)]
    return {"frames": frames, "scored_from_s": trial.scored_from_s, "end_s": float(times[-1]),
            "steps": [(s.kind, s.intent, s.start_s, s.end_s) for s in trial.steps],
            "intents": [(i.gesture, i.onset_s, i.release_s, i.kind) for i in trial.intents()],
            "times": {"default": times.tolist()},
            "true_rays": [GestureRecognizer.ray(f)["direction"] for f in frames]}


def scripted(subject: Subject, kinds, hold_s: float = 1.0, transition_s: float = 0.3, enrol: bool = False) -> Trial:
    rng = np.random.default_rng(0)
    steps = enrolment_steps(subject, 0.5, rng) if enrol else []
    t = steps[-1].end_s if steps else 0.5
    scored_from = t
    for kind in kinds:
        intent = kind if kind in gestures.GESTURE_NAMES else "none"
        steps.append(Step(kind, intent, t, transition_s, hold_s, gesture_pose(subject, kind)))
        t += transition_s + hold_s
    return Trial(0, subject, tuple(steps), "slow-rotation", scored_from)


def test_intended_onset_is_where_the_movement_is_80_percent_done():
    tau = quintic_time(ONSET_FRACTION)
    assert tau**3 * (10 - 15 * tau + 6 * tau**2) == pytest.approx(0.8, abs=1e-9)
    trial = scripted(Subject(), ["rest", "point", "rest"])
    it = trial.intents()[1]
    assert it.gesture == "point" and it.onset_s == pytest.approx(trial.steps[1].start_s + tau * 0.3)
    assert it.release_s == pytest.approx(trial.steps[2].start_s + quintic_time(0.2) * 0.3)


def test_a_scripted_trial_gives_the_expected_matches_and_a_late_start_is_a_miss_and_a_false_activation():
    trial = scripted(Subject(), ["rest", "point", "rest", "grasp", "rest", "pinch", "rest", "open", "rest"])
    rec = truth_record(trial)
    rec["runs"] = {"default": gestures.recognise(rec["frames"])}
    s = gestures.score_trial(rec, "default")
    for g in gestures.GESTURE_NAMES:
        assert (s[g]["intents"], s[g]["detected"], s[g]["tp"]) == (1, 1, 1), g
        assert abs(s["onset_s"][g][0]) <= gestures.WINDOW_S
    assert s["false_activations"] == {"rest": 0, "distractor": 0, "gesture": 0}
    assert s["confusion"]["none"]["none"] == 5 and all(s["confusion"][g][g] == 1 for g in gestures.GESTURE_NAMES)
    # the same recogniser firing later than the window: the grasp intent is missed and its start is false
    late = [(g, k, t + (gestures.WINDOW_S + 0.05 if g == "grasp" else 0.0), c, r)
            for g, k, t, c, r in rec["runs"]["default"]["events"]]
    rec["runs"]["late"] = {**rec["runs"]["default"], "events": late}
    s = gestures.score_trial(rec, "late")
    assert (s["grasp"]["intents"], s["grasp"]["detected"], s["grasp"]["tp"]) == (1, 1, 0)
    assert sum(s["false_activations"].values()) == 1
    assert s["point"]["tp"] == 1


def test_match_uses_each_detection_once_and_the_nearest_first():
    intents = [("pinch", 1.0, 2.0, "pinch"), ("pinch", 1.2, 2.5, "pinch")]
    detected = [("pinch", 1.1, 1.5, 1.0, 1.0)]
    matched, unmatched = gestures.match(intents, detected)
    assert len(matched) == 1 and unmatched == []
    matched, unmatched = gestures.match(intents, [("grasp", 1.0, 2.0, 1.0, 1.0)])
    assert matched == {} and unmatched == [0]


def test_trials_vary_and_hold_every_gesture():
    a, b = make_trial(1, 40.0), make_trial(2, 1.0)      # the subject is drawn first, whatever the length
    assert a.subject != b.subject
    kinds = {s.kind for s in a.steps if s.start_s >= a.scored_from_s}
    assert set(gestures.GESTURE_NAMES) <= {s.intent for s in a.steps if s.start_s >= a.scored_from_s}
    assert kinds & {"rest", "half-curl", "fidget", "near-pinch"}
    # the pinch pose closes the tips to the subject's aperture
    sub = Subject(pinch_aperture_m=0.012)
    assert tip_distance_m(sub.calibration(), gesture_pose(sub, "pinch")) == pytest.approx(0.012, abs=0.001)


def test_enrolment_moves_the_pinch_threshold_toward_a_wide_pinch_and_then_detects_it():
    wide = Subject(pinch_aperture_m=0.035)
    trial = scripted(wide, ["rest", "pinch", "rest", "pinch", "rest", "open", "rest", "pinch", "rest"], enrol=True)
    rec = truth_record(trial)
    rec["runs"] = {"default": gestures.recognise(rec["frames"])}
    samples = gestures._enrolment_samples(trial, rec["frames"])
    settings, report = fit_thresholds(samples)
    assert settings.pinch_enter_m > 0.035 > GestureSettings().pinch_enter_m
    assert settings.pinch_exit_m > settings.pinch_enter_m
    before = gestures.score_trial(rec, "default")
    rec["runs"]["enrolled"] = gestures.recognise(rec["frames"], settings)
    after = gestures.score_trial(rec, "enrolled")
    assert before["pinch"]["tp"] == 0 and after["pinch"]["tp"] == after["pinch"]["intents"] == 3
    assert sum(after["false_activations"].values()) == 0


def test_the_rate_bound_is_the_exact_poisson_upper_limit():
    from scipy.optimize import brentq
    from scipy.stats import poisson
    assert gestures.poisson_upper_per_min(0, 10.0) == pytest.approx(-np.log(0.05) / 10.0, rel=1e-9)
    for k in (1, 4):       # the rate at which k or fewer events in 20 min have probability 5 %
        rate = brentq(lambda lam: poisson.cdf(k, lam * 20.0) - 0.05, 1e-6, 10.0)
        assert gestures.poisson_upper_per_min(k, 20.0) == pytest.approx(rate, rel=1e-6)


def test_an_idle_trial_means_nothing_is_mostly_rest_and_the_true_hand_fires_nothing():
    trial = make_idle_trial(7, 60.0)
    scored = [s for s in trial.steps if s.start_s >= trial.scored_from_s]
    assert {s.intent for s in trial.steps} == {"none"}
    rest = sum(s.end_s - s.start_s for s in scored if s.kind == "rest")
    assert rest / (trial.duration_s - trial.scored_from_s) > 0.7
    assert len({s.pose["index"] for s in scored if s.kind == "rest"}) > 3       # the relaxed pose drifts
    rec = truth_record(trial)
    rec["runs"] = {"default": gestures.recognise(rec["frames"])}
    s = gestures.score_trial(rec, "default")
    assert s["minutes"]["rest"] > 0.7 and sum(s["false_activations"].values()) == 0
    assert sum(s[g]["detected"] for g in gestures.GESTURE_NAMES) == 0


def test_enrolment_rejects_missing_labels():
    from gestures.enrolment import EnrolmentError
    with pytest.raises(EnrolmentError, match="'grasp' has 0 frames"):
        fit_thresholds({"rest": [], "grasp": []})
    with pytest.raises(EnrolmentError, match="unknown labels"):
        fit_thresholds({"wave": []})


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("gestures")
    gestures.run(out, quick=True, progress=False)
    return out, json.loads((out / "results.json").read_text())


def test_quick_results_file_has_every_figure(quick):
    out, res = quick
    assert set(res["variants"]) == set(gestures.VARIANTS)
    d = res["variants"]["default"]
    for r in d["gestures"].values():
        assert r["intents"] > 0
        assert {"precision", "recall", "f1", "onset_p50_s", "onset_p95_s", "release_p50_s", "release_p95_s"} <= set(r)
    assert set(d["false_activations"]) == {"rest", "distractor", "gesture"}
    assert set(d["confusion"]) == {"point", "grasp", "pinch", "open", "none"}
    assert d["ray_error_deg"]["frames"] > 0
    assert 0.0 < res["alignment_delay_s"]["p50"] < 0.2
    assert res["idle_trials"] == 1 and res["idle_minutes"] > 0
    assert res["variants"]["default"]["false_activations_idle"]["rest"]["minutes"] > 0
    assert res["variants"]["vector"]["false_activations_idle"] is None
    text = (out / "summary.md").read_text()
    assert "| meant \\ shown |" in text and "| vector |" in text


def test_quick_run_ranks_truth_over_default_over_vector(quick):
    _, res = quick
    v = res["variants"]

    def rank(name):        # fewer misses plus false starts; at equal counts, more frames showing what was meant
        return (v[name]["errors"], -v[name]["agreement"])
    assert rank("truth") < rank("default") < rank("vector")
    assert rank("default") < rank("truth+5deg")


def test_confidence_is_the_laplace_smoothed_precision_per_raw_strength_bin():
    from gestures.confidence import RAW_EDGES, fit_table
    low, high = RAW_EDGES[0] / 2, RAW_EDGES[-1] + 0.1
    starts = [("pinch", low, True)] * 8 + [("pinch", low, False)] * 2 + [("pinch", high, True)] * 3
    table = fit_table(starts)
    assert table["pinch"] == (0.75, 0.5, 0.8)           # (8+1)/(10+2), no data (0+1)/(0+2), (3+1)/(3+2)
    assert table["grasp"] == (0.5, 0.5, 0.5)


def test_start_events_carry_the_calibrated_confidence_and_ends_repeat_it():
    from gestures.confidence import calibrated_confidence
    trial = scripted(Subject(), ["rest", "point", "rest", "pinch", "rest"])
    rec = truth_record(trial)
    events = gestures.recognise(rec["frames"])["events"]
    starts = [e for e in events if e[1] == "start"]
    assert [e[0] for e in starts] == ["point", "pinch"]
    for g, kind, t, conf, raw in events:
        start = next(s for s in starts if s[0] == g and s[2] <= t)
        assert conf == pytest.approx(calibrated_confidence(g, start[4]), abs=1e-4)


def test_the_frames_cache_is_keyed_by_the_code_that_makes_the_frames(tmp_path):
    import shutil
    from pathlib import Path
    root = Path(gestures.__file__).resolve().parent.parent
    copy = tmp_path / "service"
    for package in gestures.FRAME_SOURCES + ("bench",):
        shutil.copytree(root / package, copy / package, ignore=shutil.ignore_patterns("__pycache__"))
    first = gestures.frames_fingerprint(copy)
    assert first == gestures.frames_fingerprint(root)
    (copy / "bench" / "gestures.py").write_text("# scoring only\n")          # the recogniser's side: same frames
    assert gestures.frames_fingerprint(copy) == first
    kernel = copy / "estimators" / "chain.py"
    kernel.write_text(kernel.read_text() + "\n# a changed estimator\n")
    assert gestures.frames_fingerprint(copy) != first


def test_frames_are_cached_under_the_code_loaded_and_not_when_the_files_changed_during_the_run(tmp_path, monkeypatch):
    path = tmp_path / "cache" / "trial.pkl"
    assert gestures.LOADED_FRAMES_FINGERPRINT == gestures.frames_fingerprint()
    monkeypatch.setattr(gestures, "frames_fingerprint", lambda root=None: "0123456789ab")      # a commit landed
    assert not gestures._store(path, {"frames": []}) and not path.exists()
    monkeypatch.undo()
    assert gestures._store(path, {"frames": [1.0]}) and path.exists()


def test_enrolment_keeps_the_defaults_for_a_user_they_already_fit():
    """Holds well inside every default threshold and far from each other: nothing to change; the
    pinch guard's rate limit (2 /s, beyond the curls' range) keeps its value."""
    from gestures.recognizer import Features

    def feats(curls, distance):
        curl = dict(zip(("thumb", "index", "middle", "ring", "little"), curls))
        return [Features(curl, distance, float(np.mean(curls[1:])), 0.0)] * 30

    samples = {"rest": feats((0.3, 0.35, 0.35, 0.35, 0.35), 0.06), "point": feats((0.3, 0.02, 0.9, 0.9, 0.9), 0.07),
               "grasp": feats((0.5, 0.95, 0.95, 0.95, 0.95), 0.05), "pinch": feats((0.4, 0.4, 0.3, 0.3, 0.3), 0.008),
               "open": feats((0.05, 0.02, 0.02, 0.02, 0.02), 0.09)}
    settings, report = fit_thresholds(samples)
    assert settings == GestureSettings()
    assert report["pinch_others_rate_max"]["new"] == GestureSettings().pinch_others_rate_max == 2.0
    # a rest pose inside the open hand's hysteresis band (long curls 0.2: between 0.17 and 0.22) tightens it, and only it
    samples["rest"] = feats((0.3, 0.2, 0.2, 0.2, 0.2), 0.06)
    settings, report = fit_thresholds(samples)
    assert settings.open_curl_exit < 0.2 and settings.open_curl_enter <= GestureSettings().open_curl_enter
    assert settings.model_copy(update={"open_curl_exit": 0.22, "open_curl_enter": 0.17}) == GestureSettings()


CLOSING_FIST_SUBJECT = Subject(hand_length_m=0.18, coupling=0.86, grasp_style="loose", pinch_aperture_m=0.009,
                               rest_deg=(20.7, 26.8))


def closing_fist_trial(transition_s: float) -> Trial:
    """Rest, then a fist whose index and thumb close first (in 45 % of the transition): on the way the tips
    pass each other as in a pinch; then a pinch, for contrast."""
    s = CLOSING_FIST_SUBJECT
    steps = [Step("rest", "none", 0.5, 0.4, 1.0, gesture_pose(s, "rest"))]
    t = steps[-1].end_s
    steps.append(Step("grasp-through-pinch", "grasp", t, transition_s, 1.0, gesture_pose(s, "grasp"),
                      {"index": 0.45, "thumb": 0.45}))
    t = steps[-1].end_s
    steps.append(Step("rest", "none", t, 0.4, 1.0, gesture_pose(s, "rest")))
    t = steps[-1].end_s
    steps.append(Step("pinch", "pinch", t, 0.3, 1.0, gesture_pose(s, "pinch")))
    return Trial(0, s, tuple(steps), "slow-rotation", 0.5)


@pytest.mark.parametrize("transition_s", [0.25, 0.35, 0.45])
def test_a_fist_closing_through_a_pinch_like_pose_gives_no_pinch_and_a_real_pinch_still_starts_in_time(transition_s):
    trial = closing_fist_trial(transition_s)
    rec = truth_record(trial)
    closest = min(tip_distance_m(trial.calibration(), {f: (a[0], a[1]) for f, a in (
        (f, np.degrees(rec["frames"][k].joint_angles[f])) for f in ("thumb", "index", "middle", "ring", "little"))})
        for k in range(len(rec["frames"])) if trial.steps[1].start_s <= rec["frames"][k].t < trial.steps[1].end_s)
    assert closest < GestureSettings().pinch_enter_m          # the fist does pass a pinch-like pose
    rec["runs"] = {"default": gestures.recognise(rec["frames"])}
    detected = gestures._intervals(rec["runs"]["default"]["events"], rec["end_s"])
    assert [d[0] for d in detected] == ["grasp", "pinch"]
    s = gestures.score_trial(rec, "default")
    assert s["grasp"]["tp"] == 1 and s["pinch"]["tp"] == 1 and sum(s["false_activations"].values()) == 0
    assert s["onset_s"]["pinch"][0] <= 0.08


def test_a_pinch_with_half_curled_fingers_straight_after_a_grasp_starts_in_time():
    # every long finger of this pinch curls 0.46-0.55: inside a grasp stay band reaching down to 0.45
    s = Subject(pinch_others="half-curled", coupling=1.0, pinch_aperture_m=0.010)
    pose = gesture_pose(s, "pinch")
    curls = [(a + b + b) / np.degrees(GestureSettings().curl_full_long_rad) for f, (a, b) in pose.items() if f != "thumb"]
    assert 0.45 <= min(curls) < 0.5
    trial = scripted(s, ["rest", "grasp", "pinch", "rest", "grasp", "pinch", "rest"], transition_s=0.35)
    rec = truth_record(trial)
    rec["runs"] = {"default": gestures.recognise(rec["frames"]),
                   "old band": gestures.recognise(rec["frames"], GestureSettings(grasp_curl_exit=0.45))}
    after = gestures.score_trial(rec, "default")
    assert (after["grasp"]["tp"], after["pinch"]["tp"]) == (2, 2) and sum(after["false_activations"].values()) == 0
    assert max(after["onset_s"]["pinch"]) <= 0.125    # from a tight fist: the curls pass 0.5 late in the move, then two dwells
    before = gestures.score_trial(rec, "old band")     # the grasp held by its stay band: the pinches are missed
    assert before["pinch"]["tp"] == 0


LOOSE_FIST_SUBJECT = Subject(hand_length_m=0.167, coupling=0.76, grasp_style="loose", pinch_aperture_m=0.0083,
                             rest_deg=(20.7, 31.7))


@pytest.mark.parametrize("transition_s", [0.35, 0.45])
def test_a_small_loose_fist_closing_every_finger_together_gives_no_pinch(transition_s):
    # the tips pass the pinch distance while middle, ring and little are a third of the way to the fist,
    # closing at under 2 /s: only their curl 0.15 s ahead tells the fist from a pinch
    s = LOOSE_FIST_SUBJECT
    trial = scripted(s, ["rest", "grasp", "rest", "pinch", "rest"], transition_s=transition_s)
    rec = truth_record(trial)
    rec["runs"] = {"default": gestures.recognise(rec["frames"])}
    assert [d[0] for d in gestures._intervals(rec["runs"]["default"]["events"], rec["end_s"])] == ["grasp", "pinch"]
    score = gestures.score_trial(rec, "default")
    assert score["grasp"]["tp"] == score["pinch"]["tp"] == 1 and sum(score["false_activations"].values()) == 0


def test_a_widened_pinch_threshold_still_ends_the_pinch_when_the_tips_part_to_a_near_pinch():
    """A person whose held pinch reads 23 mm: enrolment widens the enter threshold (24 -> 29 mm) to admit it;
    the stay threshold keeps the default band's width only above the widened enter threshold and the hold,
    so that tips parting to 35 mm straight after the pinch (a near-pinch, meaning nothing) end it as without
    enrolment; with the stay threshold moved by the whole widening (37 mm) the pinch stayed on through it."""
    s = Subject(pinch_aperture_m=0.023)
    steps = enrolment_steps(s, 0.5, np.random.default_rng(0))
    t = scored_from = steps[-1].end_s
    for kind, aperture in [("rest", None), ("pinch", None), ("near-pinch", 0.035), ("rest", None), ("pinch", None), ("rest", None)]:
        steps.append(Step(kind, "pinch" if kind == "pinch" else "none", t, 0.3, 1.0, gesture_pose(s, kind, aperture_m=aperture)))
        t += 1.3
    trial = Trial(0, s, tuple(steps), "slow-rotation", scored_from)
    rec = truth_record(trial)
    settings, _ = fit_thresholds(gestures._enrolment_samples(trial, rec["frames"]))
    assert settings.pinch_enter_m > 0.028 and settings.pinch_exit_m < 0.035 < GestureSettings().pinch_exit_m + (
        settings.pinch_enter_m - GestureSettings().pinch_enter_m)
    rec["runs"] = {"enrolled": gestures.recognise(rec["frames"], settings)}
    score = gestures.score_trial(rec, "enrolled")
    assert score["pinch"]["tp"] == score["pinch"]["intents"] == 2 and sum(score["false_activations"].values()) == 0
    assert max(score["release_s"]["pinch"]) < gestures.WINDOW_S + 0.05


def test_a_grasp_hands_over_to_a_pinch_the_hand_has_settled_into():
    """A pinch with the other fingers half curled straight after a tight fist: without the handover the grasp's
    end dwell and then the pinch's start dwell follow one another once the curls pass 0.5 late in the movement;
    with it the grasp ends and the pinch starts on the frame its enter condition has held the start dwell while
    the grasp's stay condition failed and the fingers had settled."""
    s = Subject(pinch_others="half-curled", coupling=1.0, pinch_aperture_m=0.010)
    trial = scripted(s, ["rest", "grasp", "pinch", "rest", "grasp", "pinch", "rest"], transition_s=0.35)
    rec = truth_record(trial)
    rec["runs"] = {"handover": gestures.recognise(rec["frames"]),
                   "none": gestures.recognise(rec["frames"], GestureSettings(handover_rate_max=1e-6))}
    events = rec["runs"]["handover"]["events"]
    for k, (g, kind, t, _, _) in enumerate(events):
        if (g, kind) == ("pinch", "start"):
            assert events[k - 1][:3] == ("grasp", "end", t)          # handed over on one frame
    after, before = gestures.score_trial(rec, "handover"), gestures.score_trial(rec, "none")
    for s_ in (after, before):
        assert (s_["grasp"]["tp"], s_["pinch"]["tp"]) == (2, 2) and sum(s_["false_activations"].values()) == 0
    assert max(after["onset_s"]["pinch"]) <= 0.09 < 0.11 <= min(before["onset_s"]["pinch"])


def test_a_fist_opening_into_rest_through_a_pinch_like_pose_is_not_handed_over_to_a_pinch():
    """The small loose fist opening into rest passes the pinch distance with every finger slowing below the
    handover's rate limit; its tips are parting, which keeps the grasp from handing over to a pinch."""
    trial = scripted(LOOSE_FIST_SUBJECT, ["rest", "grasp", "rest", "pinch", "rest"], transition_s=0.45)
    rec = truth_record(trial)
    for settings, shown in ((GestureSettings(), ["grasp", "pinch"]),
                            (GestureSettings(handover_tips_parting_max_m_s=1.0), ["grasp", "pinch", "pinch"])):
        events = gestures.recognise(rec["frames"], settings)["events"]
        assert [d[0] for d in gestures._intervals(events, rec["end_s"])] == shown
