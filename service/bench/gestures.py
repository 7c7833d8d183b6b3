"""Gesture benchmark against what the visitor means: ``fingertrack bench gestures [--quick] --out DIR``.

Trials (``service.sim.gesture_script``): each a different simulated person (hand size, DIP/PIP
coupling, gesture styles, pinch aperture, rest pose) doing an enrolment procedure and then a random
script of gestures and of steps that mean nothing (rest, half-curled fingers, fidgeting, a pinch-
like approach), some grasps passing through a pinch-like pose, with a slowly turning or fast-
reaching hand. Labels are the script's intents (intended onset and release), never a recogniser's
output. Sensor errors: the realistic profile where the simulator has it, else offsets plus white
noise ('both'); the optical tracker at its defaults (90 Hz, 20 ms latency, jitter). The pipeline is
told the hand's size but not the coupling, and gets no true start.

Idle trials (``make_idle_trial``) give the false-activation figures enough time in which the visitor
means nothing: minutes of rest (the relaxed pose drifting every 4-12 s) with an occasional distractor,
on the same moving hand; they run through the default estimator and the true hand only and count in
the false-activation rates (with their 95 % Poisson upper bounds), not in F1.

Each trial's messages run through the hand pipeline (``HandSession``, as the service runs it) with
the default estimator and with ``vector``; the recogniser runs on its frames. Variants scored on the
same trials:

* ``default``: the default estimator, default thresholds;
* ``enrolled``: the same frames, thresholds fitted by ``gestures.enrolment`` to the trial's own
  enrolment segment (which is never scored);
* ``vector``: the memoryless vector-observation estimator (a deliberately worse baseline);
* ``truth``: the true hand (true angles and geometry) at the same frame times: the recogniser alone;
* ``truth+5deg``: the true hand plus 5 deg RMS of error on every joint (AR(1), 0.5 s time constant).

Scoring (per variant, scripted part only):

* a detected start matches an intent of the same gesture if it lies within ``WINDOW_S`` (±150 ms)
  of the intended onset (each used once, nearest first); unmatched intents are misses, unmatched
  starts false activations, so a start later than the window is a miss *and* a false activation;
* precision, recall, F1 per gesture; a confusion matrix (rows: intents incl. ``none``; columns: the
  gesture shown for most of the intended interval, or ``none``);
* false activations per minute during rest, during the meaningless distractor steps and during
  gestures (a wrong gesture or a restart);
* onset latency (matched start - intended onset) and release latency (detected end - intended
  release), p50 and p95, on the source clock; the pipeline's alignment delay (a frame's emission on
  the arrival clock minus its timestamp) is reported separately and adds to both;
* pointing-ray error against the true ray (index MCP to tip of the true hand) on frames of matched
  point intents where the variant shows ``point``: median and p95;
* chatter: detected intervals shorter than ``CHATTER_S``, and restarts of a gesture within one
  intended hold;
* agreement: the share of frames inside intended intervals (transitions excluded) on which the
  shown gesture (or none) is the one meant: it counts late onsets, late releases and dropouts by
  their duration.
"""
from __future__ import annotations

import hashlib
import json
import pickle
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from ..model.hand import calibration_message
from ..model.openxr import joint_poses
from ..pipeline.hand import HandFrame, HandSession, PipelineSettings
from ..protocol import parse_message
from ..sim.errors import NOISE_KINDS
from ..sim.gesture_script import GESTURE_NAMES, INTENTS, Trial, make_idle_trial, make_trial
from ..sim.session import SimConfig, simulate

WINDOW_S = 0.15
CHATTER_S = 0.1
TRUTH_NOISE_DEG = 5.0
TRUTH_NOISE_TAU_S = 0.5
NOISE = "realistic" if "realistic" in NOISE_KINDS else "both"
VARIANTS = ("default", "enrolled", "vector", "truth", "truth+5deg")
QUICK = {"seeds": (101, 102), "duration_s": 20.0}
FULL = {"seeds": tuple(range(1, 13)), "duration_s": 60.0}
"""Trials of the quick and the full run (``--trials N`` takes the first N seeds of the full run)."""
QUICK_IDLE = {"seeds": (1101,), "duration_s": 15.0}
FULL_IDLE = {"seeds": tuple(range(1001, 1021)), "duration_s": 120.0}
"""Idle trials (``make_idle_trial``: the visitor means nothing) of the quick and the full run, scored for
false activations only (``--idle-trials N`` takes the first N); the variants that need no second pipeline
run or enrolment: ``default``, ``truth``, ``truth+5deg``. The full run's 20 give about 40 minutes of rest
(1.9 each, and 2.2 on the gesture trials), so that no false activation at rest puts the rate's 95 % upper bound
(3.0 / 40 per minute) under the goal of 1 per 10 minutes, and about 5 minutes of distractors (0.11 each, 2.8 on
the gesture trials), so that one false activation in them puts it (4.74 / 5) under the goal of 1 per minute."""
IDLE_VARIANTS = ("default", "truth", "truth+5deg")
FRAME_SOURCES = ("model", "sim", "estimators", "pipeline", "protocol")
"""The packages of ``service`` whose code makes a trial's frames (simulator, sensor errors, pipeline,
estimators): their source is part of a cached trial's name (``frames_fingerprint``)."""


# -- running a trial --------------------------------------------------------------------------------

def _pipeline(session, trial: Trial, estimator: str) -> tuple[list[HandFrame], list[float]]:
    """Frames of the live pipeline, and each frame's alignment delay (emission on the arrival clock
    minus its timestamp, s). The glove app sends the measured hand size, not the coupling."""
    hand = HandSession("right", PipelineSettings(estimator=estimator))
    frames, delays = [], []
    latency = session.optical.latency_s
    known = calibration_message(trial.known_calibration())
    for m in session.messages(include_truth=False):
        if m["type"] == "calibration":
            m = known
        arrival = m["t"] + latency if m["type"] == "pose" else m.get("t", 0.0)
        for f in hand.handle(parse_message(m)).frames:
            frames.append(f)
            delays.append(arrival - f.t)
    return frames, delays


def _truth_frames(session, trial: Trial, times: np.ndarray, noise_deg: float, seed: int) -> list[HandFrame]:
    """The true hand at ``times`` (plus AR(1) joint-angle error of ``noise_deg`` RMS)."""
    calib = trial.calibration()
    rate = session.config.rate_hz
    idx = np.clip(np.round((times - session.t[0]) * rate).astype(int), 0, len(session.t) - 1)
    rng = np.random.default_rng(seed)
    err = {f: np.zeros((len(times), a.shape[1])) for f, a in session.joint_angles.items()}
    if noise_deg > 0:
        a = np.exp(-np.diff(times, prepend=times[0]) / TRUTH_NOISE_TAU_S)
        sigma = np.radians(noise_deg)
        for f, e in err.items():
            e[0] = rng.normal(0.0, sigma, e.shape[1])
            for k in range(1, len(times)):
                e[k] = a[k] * e[k - 1] + np.sqrt(1.0 - a[k] ** 2) * rng.normal(0.0, sigma, e.shape[1])
    frames = []
    for k, n in enumerate(idx):
        phi = {f: a[n] + err[f][k] for f, a in session.joint_angles.items()}
        rot, pos = session.base.rotation[n], session.base.position[n]
        frames.append(HandFrame(float(times[k]), k, "right", phi, {}, rot, pos, joint_poses(calib, phi, rot, pos), {}))
    return frames


def recognise(frames: list[HandFrame], settings=None) -> dict:
    """Run a fresh recogniser over ``frames``: events ``(gesture, start|end, t, confidence, raw)``,
    the active gesture per frame and the pointing ray per frame (None when not pointing)."""
    from gestures.recognizer import RULES, GestureRecognizer, GestureSettings

    rec = GestureRecognizer(settings or GestureSettings())
    events, active, rays = [], [], []
    for f in frames:
        ann, evs = rec.update(f)
        for e in evs:
            x = rec.features(f)
            x.others_curl_rate, x.index_curl_rate = rec._rate, rec._index_rate      # as the recogniser saw it
            raw = RULES[e["gesture"]].score(x, rec.settings)
            events.append((e["gesture"], e["event"], e["t"], e["confidence"], raw))
        active.append(ann["active"])
        rays.append(ann["ray"]["direction"] if "ray" in ann else None)
    return {"events": events, "active": active, "rays": rays}


def _enrolment_samples(trial: Trial, frames: list[HandFrame]) -> dict:
    """Features of the frames inside each enrolment hold (after the transition plus 0.2 s, before
    the hold's last 0.1 s), keyed by label."""
    from gestures.recognizer import GestureRecognizer

    rec = GestureRecognizer()
    times = np.array([f.t for f in frames])
    samples: dict[str, list] = {}
    for st in trial.steps:
        if st.start_s >= trial.scored_from_s:
            break
        label = st.intent if st.intent != "none" else "rest"
        a, b = st.start_s + st.transition_s + 0.2, st.end_s - 0.1
        samples.setdefault(label, []).extend(rec.features(frames[k]) for k in np.flatnonzero((times >= a) & (times < b)))
    return samples


def frames_fingerprint(root: str | Path | None = None) -> str:
    """A digest of the source code that makes a trial's frames (``FRAME_SOURCES`` under ``root``, the
    ``service`` package by default; every ``.py`` file by its path and content): a change of the
    simulator, the pipeline or an estimator changes it, so a frames cache never serves frames of other
    code."""
    root = Path(root) if root is not None else Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for package in FRAME_SOURCES:
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


LOADED_FRAMES_FINGERPRINT = frames_fingerprint()
"""``frames_fingerprint`` of the code this process loaded (taken when this module is imported, after its
imports have loaded the simulator, the pipeline and the estimators): the name a cached trial's frames get.
Taking it from the files instead when a trial ends would name the frames of the loaded code after a commit
that landed during the run."""


def _store(path: Path, out: dict) -> bool:
    """Write a trial's frames to the cache at ``path`` unless the files on disk are no longer the code this
    process loaded (``LOADED_FRAMES_FINGERPRINT``): a module imported later in the run, such as a kernel
    compiled on first use, would have come from the new files, so the frames may be of a mixture of the two;
    True if written."""
    if frames_fingerprint() != LOADED_FRAMES_FINGERPRINT:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        pickle.dump(out, fh, protocol=pickle.HIGHEST_PROTOCOL)
    return True


def trial_frames(seed: int, duration_s: float, cache_dir: str | Path | None = None, idle: bool = False) -> dict:
    """The expensive part of a trial: the pipeline's frames with the default estimator and with
    ``vector``, the true hand's frames (exact and with error) and the alignment delays. With
    ``cache_dir`` they are kept in a file named by the trial, the noise profile, the estimator and the
    code that made them (``frames_fingerprint``), so the recogniser (which only reads frames) can be
    rescored without rerunning the pipeline, and a changed estimator or simulator is rerun."""
    key = (f"{'idle' if idle else 'trial'}-{seed}-{duration_s:g}s-{NOISE}-{PipelineSettings().estimator}-"
           f"{LOADED_FRAMES_FINGERPRINT}.pkl")
    if cache_dir is not None and (Path(cache_dir) / key).exists():
        with open(Path(cache_dir) / key, "rb") as fh:
            return pickle.load(fh)
    trial = make_idle_trial(seed, duration_s) if idle else make_trial(seed, duration_s)
    session = simulate(SimConfig(motion="sequence", noise=NOISE, seed=seed, calibration=trial.calibration(),
                                 finger_motion=trial.finger_motion(), hand_trajectory=trial.hand_trajectory()))
    default_frames, delays = _pipeline(session, trial, PipelineSettings().estimator)
    times = np.array([f.t for f in default_frames])
    out = {"trial": trial, "frames": {"default": default_frames,
                                      "truth": _truth_frames(session, trial, times, 0.0, seed),
                                      "truth+5deg": _truth_frames(session, trial, times, TRUTH_NOISE_DEG, seed + 10_000)},
           "alignment_delay_s": delays, "idle": idle}
    if not idle:
        out["frames"]["vector"] = _pipeline(session, trial, "vector")[0]
    if cache_dir is not None:
        _store(Path(cache_dir) / key, out)
    return out


def run_trial(seed: int, duration_s: float, cache_dir: str | Path | None = None, idle: bool = False) -> dict:
    """One trial through every variant (an idle trial through ``IDLE_VARIANTS``); returns what scoring
    needs (plain data)."""
    from gestures.enrolment import fit_thresholds
    from gestures.recognizer import GestureRecognizer

    data = trial_frames(seed, duration_s, cache_dir, idle)
    trial, frames = data["trial"], data["frames"]
    runs = {v: recognise(frames[v]) for v in (IDLE_VARIANTS if idle else ("default", "vector", "truth", "truth+5deg"))}
    enrol_report: dict = {}
    if not idle:
        enrolled_settings, enrol_report = fit_thresholds(_enrolment_samples(trial, frames["default"]))
        runs["enrolled"] = recognise(frames["default"], enrolled_settings)
    return {
        "seed": seed, "idle": idle, "subject": trial.subject.__dict__, "hand_motion": trial.hand_motion,
        "scored_from_s": trial.scored_from_s, "end_s": float(frames["default"][-1].t),
        "steps": [(s.kind, s.intent, s.start_s, s.end_s) for s in trial.steps],
        "intents": [(i.gesture, i.onset_s, i.release_s, i.kind) for i in trial.intents()],
        "times": {v: [f.t for f in frames[v]] for v in ("default", "vector") if v in frames},
        "true_rays": [GestureRecognizer.ray(f)["direction"] for f in frames["truth"]],
        "alignment_delay_s": data["alignment_delay_s"], "runs": runs,
        "enrolment": {k: v for k, v in enrol_report.items() if v["old"] != v["new"]},
    }


# -- scoring ------------------------------------------------------------------------------------------

def _intervals(events, end_t: float) -> list[tuple[str, float, float, float, float]]:
    """Detected intervals ``(gesture, start, end, start confidence, start raw score)``."""
    out, open_ = [], {}
    for g, kind, t, conf, raw in events:
        if kind == "start":
            open_[g] = (t, conf, raw)
        elif g in open_:
            t0, c, r = open_.pop(g)
            out.append((g, t0, t, c, r))
    out += [(g, t0, end_t, c, r) for g, (t0, c, r) in open_.items()]
    return sorted(out, key=lambda x: x[1])


def match(intents, detected, window_s: float = WINDOW_S) -> tuple[dict, list[int]]:
    """Match detected intervals to intents of the same gesture by onset (module docstring).
    Returns ``{intent index: detected index}`` and the unmatched detected indices."""
    pairs = sorted((abs(d[1] - it[1]), i, j) for i, it in enumerate(intents) if it[0] in GESTURE_NAMES
                   for j, d in enumerate(detected) if d[0] == it[0] and abs(d[1] - it[1]) <= window_s)
    matched: dict[int, int] = {}
    used: set[int] = set()
    for _, i, j in pairs:
        if i not in matched and j not in used:
            matched[i] = j
            used.add(j)
    return matched, [j for j in range(len(detected)) if j not in used]


def _step_at(steps, t: float):
    for s in steps:
        if s[2] <= t < s[3]:
            return s
    return steps[-1]


def score_trial(rec: dict, variant: str) -> dict:
    """Raw counts and samples of one trial and variant (summed by ``aggregate``)."""
    run = rec["runs"][variant]
    times = np.array(rec["times"]["vector" if variant == "vector" else "default"])
    t0 = rec["scored_from_s"]
    intents = [it for it in rec["intents"] if it[1] >= t0]
    steps = [s for s in rec["steps"] if s[2] >= t0]
    detected = [d for d in _intervals(run["events"], rec["end_s"]) if d[1] >= t0]
    matched, unmatched = match(intents, detected)
    out: dict = {g: {"tp": 0, "intents": 0, "detected": 0} for g in GESTURE_NAMES}
    for it in intents:
        if it[0] in out:
            out[it[0]]["intents"] += 1
    for d in detected:
        out[d[0]]["detected"] += 1
    for i in matched:
        out[intents[i][0]]["tp"] += 1
    out["onset_s"] = {g: [] for g in GESTURE_NAMES}
    out["release_s"] = {g: [] for g in GESTURE_NAMES}
    out["starts"] = [(d[0], d[3], d[4], j not in unmatched) for j, d in enumerate(detected)]
    for i, j in matched.items():
        out["onset_s"][intents[i][0]].append(detected[j][1] - intents[i][1])
        out["release_s"][intents[i][0]].append(detected[j][2] - intents[i][2])
    fa = {"rest": 0, "distractor": 0, "gesture": 0}
    for j in unmatched:
        st = _step_at(steps, detected[j][1])
        fa["rest" if st[0] == "rest" else ("distractor" if st[1] == "none" else "gesture")] += 1
    out["false_activations"] = fa
    out["minutes"] = {
        "rest": sum(s[3] - s[2] for s in steps if s[0] == "rest") / 60.0,
        "distractor": sum(s[3] - s[2] for s in steps if s[1] == "none" and s[0] != "rest") / 60.0,
        "gesture": sum(s[3] - s[2] for s in steps if s[1] != "none") / 60.0,
    }
    # confusion: the label shown for most of each intended interval
    active = np.array([a or "none" for a in run["active"]])
    conf = {r: {c: 0 for c in INTENTS} for r in INTENTS}
    for it in intents:
        sel = active[(times >= it[1]) & (times < it[2])]
        shown = max(INTENTS, key=lambda c: int(np.sum(sel == c))) if len(sel) else "none"
        conf[it[0]][shown] += 1
    out["confusion"] = conf
    # agreement: frames inside intended intervals (transitions excluded) showing what was meant
    inside = np.zeros(len(times), dtype=bool)
    agree = np.zeros(len(times), dtype=bool)
    for it in intents:
        sel = (times >= it[1]) & (times < it[2])
        inside |= sel
        agree |= sel & (active == it[0])
    out["agreement"] = (int(agree.sum()), int(inside.sum()))
    # chatter: short intervals, and restarts within an intended hold
    out["chatter_short"] = sum(1 for d in detected if d[2] - d[1] < CHATTER_S)
    out["chatter_restarts"] = sum(
        sum(1 for j in unmatched if detected[j][0] == intents[i][0] and intents[i][1] < detected[j][1] < intents[i][2])
        for i in matched)
    # pointing ray on matched point intents while the variant shows point
    ray_err = []
    if variant not in ("truth",):
        true_times = np.array(rec["times"]["default"])
        for i in matched:
            if intents[i][0] != "point":
                continue
            for k in np.flatnonzero((times >= intents[i][1]) & (times < intents[i][2])):
                if run["rays"][k] is None:
                    continue
                kt = int(np.clip(np.searchsorted(true_times, times[k]), 0, len(true_times) - 1))
                c = float(np.clip(np.dot(run["rays"][k], rec["true_rays"][kt]), -1.0, 1.0))
                ray_err.append(float(np.degrees(np.arccos(c))))
    out["ray_error_deg"] = ray_err
    return out


def _pct(v, q) -> float:
    return float(np.percentile(v, q)) if len(v) else float("nan")


def aggregate(parts: list[dict]) -> dict:
    """Sum the per-trial scores of one variant into the reported figures."""
    res: dict = {"gestures": {}}
    for g in GESTURE_NAMES:
        tp = sum(p[g]["tp"] for p in parts)
        n_int = sum(p[g]["intents"] for p in parts)
        n_det = sum(p[g]["detected"] for p in parts)
        precision = tp / n_det if n_det else float("nan")
        recall = tp / n_int if n_int else float("nan")
        if not n_int:
            f1 = float("nan") if not n_det else 0.0
        else:
            f1 = 2 * precision * recall / (precision + recall) if n_det and precision + recall > 0 else 0.0
        onset = [x for p in parts for x in p["onset_s"][g]]
        release = [x for p in parts for x in p["release_s"][g]]
        res["gestures"][g] = {"intents": n_int, "detected": n_det, "matched": tp, "precision": precision,
                              "recall": recall, "f1": f1,
                              "onset_p50_s": _pct(onset, 50), "onset_p95_s": _pct(onset, 95),
                              "release_p50_s": _pct(release, 50), "release_p95_s": _pct(release, 95)}
    res["mean_f1"] = float(np.nanmean([r["f1"] for r in res["gestures"].values()]))
    onset_all = [x for p in parts for g in GESTURE_NAMES for x in p["onset_s"][g]]
    release_all = [x for p in parts for g in GESTURE_NAMES for x in p["release_s"][g]]
    res["onset_s"] = {"p50": _pct(onset_all, 50), "p95": _pct(onset_all, 95)}
    res["release_s"] = {"p50": _pct(release_all, 50), "p95": _pct(release_all, 95)}
    res["false_activations"] = false_activation_rates(parts)
    agree = np.sum([p["agreement"] for p in parts], axis=0)
    res["agreement"] = float(agree[0] / agree[1]) if agree[1] else float("nan")
    res["errors"] = sum(r["intents"] - r["matched"] + r["detected"] - r["matched"] for r in res["gestures"].values())
    res["confusion"] = {r: {c: sum(p["confusion"][r][c] for p in parts) for c in INTENTS} for r in INTENTS}
    res["chatter"] = {"short": sum(p["chatter_short"] for p in parts),
                      "restarts": sum(p["chatter_restarts"] for p in parts)}
    rays = [x for p in parts for x in p["ray_error_deg"]]
    res["ray_error_deg"] = {"median": _pct(rays, 50), "p95": _pct(rays, 95), "frames": len(rays)}
    res["starts"] = [s for p in parts for s in p["starts"]]
    return res


def poisson_upper_per_min(count: int, minutes: float, level: float = 0.95) -> float:
    """One-sided upper confidence bound of a Poisson rate, per minute, after ``count`` events in
    ``minutes`` (exact: ``chi2.ppf(level, 2 count + 2) / 2``; 0 events: about 3.0 / minutes at 95 %)."""
    from scipy.stats import chi2

    return float(chi2.ppf(level, 2 * count + 2) / 2.0 / minutes) if minutes > 0 else float("nan")


def false_activation_rates(parts: list[dict]) -> dict:
    """False activations at rest, in distractors and in gestures: count, minutes, per minute and the
    95 % upper bound per minute."""
    out = {}
    for k in ("rest", "distractor", "gesture"):
        n = sum(p["false_activations"][k] for p in parts)
        m = sum(p["minutes"][k] for p in parts)
        out[k] = {"count": n, "minutes": m, "per_min": n / m if m else float("nan"),
                  "upper95_per_min": poisson_upper_per_min(n, m)}
    return out


def score(records: list[dict]) -> dict:
    """Every variant's figures (gesture trials), false activations over gesture and idle trials, the
    alignment delay and the enrolment changes."""
    gesture_recs = [r for r in records if not r.get("idle")]
    idle_recs = [r for r in records if r.get("idle")]
    out = {"window_s": WINDOW_S, "noise": NOISE, "trials": len(gesture_recs), "idle_trials": len(idle_recs),
           "scored_minutes": sum(r["end_s"] - r["scored_from_s"] for r in gesture_recs) / 60.0,
           "idle_minutes": sum(r["end_s"] - r["scored_from_s"] for r in idle_recs) / 60.0,
           "variants": {v: aggregate([score_trial(r, v) for r in gesture_recs]) for v in VARIANTS}}
    for v, res in out["variants"].items():
        idle_parts = [score_trial(r, v) for r in idle_recs if v in r["runs"]]
        res["false_activations"] = false_activation_rates([score_trial(r, v) for r in gesture_recs] + idle_parts)
        res["false_activations_idle"] = false_activation_rates(idle_parts) if idle_parts else None
    delays = [d for r in records for d in r["alignment_delay_s"]]
    out["alignment_delay_s"] = {"p50": _pct(delays, 50), "p95": _pct(delays, 95)}
    out["enrolment_changes"] = {r["seed"]: r["enrolment"] for r in gesture_recs}
    out["confidence"] = confidence_figures(gesture_recs)
    return out


RELIABILITY_EDGES = (0.0, 0.5, 0.7, 0.8, 0.9, 0.95, 1.0001)


def confidence_figures(records: list[dict]) -> dict:
    """The confidence table fitted on this run's trials in ``FIT_SEEDS`` (default variant), and the
    reliability of the shipped confidences on the other trials: per confidence bin, the starts, their
    mean confidence and the observed precision."""
    from gestures.confidence import FIT_SEEDS, fit_table

    def starts(rs, variant):
        return [s for r in rs for s in score_trial(r, variant)["starts"]]

    fit = [r for r in records if r["seed"] in FIT_SEEDS]
    held = [r for r in records if r["seed"] not in FIT_SEEDS]
    rows = []
    for variant in ("default", "enrolled"):
        ss = starts(held, variant)
        for lo, hi in zip(RELIABILITY_EDGES[:-1], RELIABILITY_EDGES[1:]):
            sel = [s for s in ss if lo <= s[1] < hi]
            if sel:
                rows.append({"variant": variant, "confidence": [lo, min(hi, 1.0)], "starts": len(sel),
                             "mean_confidence": float(np.mean([s[1] for s in sel])),
                             "observed_precision": float(np.mean([s[3] for s in sel]))})
    return {"fitted_on_seeds": [r["seed"] for r in fit], "held_out_seeds": [r["seed"] for r in held],
            "table_fitted_here": fit_table((s[0], s[2], s[3]) for s in starts(fit, "default")) if fit else None,
            "reliability": rows}


# -- presenting ---------------------------------------------------------------------------------------

def _ms(v: float) -> str:
    return "-" if not np.isfinite(v) else f"{1e3 * v:.0f}"


def table(result: dict, wall_s: float) -> str:
    v = result["variants"]
    d = v["default"]
    lines = [f"# Gesture benchmark: {result['trials']} trial(s), {result['scored_minutes']:.1f} scored minutes, "
             f"'{result['noise']}' IMU errors; onset window ±{1e3 * result['window_s']:.0f} ms; wall time {wall_s:.0f} s", "",
             "## Default estimator, default thresholds", "",
             "| gesture | intents | detected | matched | precision | recall | F1 | onset p50 / p95 ms | release p50 / p95 ms |",
             "|---|---|---|---|---|---|---|---|---|"]
    for g, r in d["gestures"].items():
        lines.append(f"| {g} | {r['intents']} | {r['detected']} | {r['matched']} | {r['precision']:.3f} | {r['recall']:.3f} | "
                     f"{r['f1']:.3f} | {_ms(r['onset_p50_s'])} / {_ms(r['onset_p95_s'])} | "
                     f"{_ms(r['release_p50_s'])} / {_ms(r['release_p95_s'])} |")
    lines += ["", "Confusion (rows: what the visitor meant; columns: the gesture shown for most of that interval):", "",
              "| meant \\ shown | " + " | ".join(INTENTS) + " |", "|---|" + "---|" * len(INTENTS)]
    for r in INTENTS:
        lines.append(f"| {r} | " + " | ".join(str(d["confusion"][r][c]) for c in INTENTS) + " |")
    a = result["alignment_delay_s"]
    lines += ["", f"Pipeline alignment delay (frame emitted on the arrival clock minus its timestamp; adds to every "
              f"latency above): p50 {_ms(a['p50'])} ms, p95 {_ms(a['p95'])} ms.", "",
              "## Every variant on the same trials", "",
              "| variant | point F1 | grasp F1 | pinch F1 | open F1 | misses + false starts | agreement | false act./min rest | "
              "/min distractors | /min in gestures | onset p50 / p95 ms | ray median / p95 deg | chatter short / restarts |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in v.items():
        fa = r["false_activations"]
        ray = "-" if not np.isfinite(r["ray_error_deg"]["median"]) else \
            f"{r['ray_error_deg']['median']:.2f} / {r['ray_error_deg']['p95']:.2f}"
        lines.append(f"| {name} | " + " | ".join(f"{r['gestures'][g]['f1']:.3f}" for g in GESTURE_NAMES) +
                     f" | {r['errors']} | {r['agreement']:.3f} | {fa['rest']['per_min']:.2f} | {fa['distractor']['per_min']:.2f} | "
                     f"{fa['gesture']['per_min']:.2f} | {_ms(r['onset_s']['p50'])} / {_ms(r['onset_s']['p95'])} | {ray} | "
                     f"{r['chatter']['short']} / {r['chatter']['restarts']} |")
    c = result["confidence"]
    lines += ["", f"Reliability of the start confidence on trials {c['held_out_seeds']} (the table was fitted on trials "
              f"{list(_fit_seeds())}):", "",
              "| thresholds | confidence | starts | mean confidence | observed precision |", "|---|---|---|---|---|"]
    for row in c["reliability"]:
        lo, hi = row["confidence"]
        lines.append(f"| {row['variant']} | {lo:.2f}-{hi:.2f} | {row['starts']} | {row['mean_confidence']:.3f} | "
                     f"{row['observed_precision']:.3f} |")
    fa = d["false_activations"]
    lines += ["", f"False activations on the gesture trials and {result['idle_trials']} idle trial(s) "
              f"({result['idle_minutes']:.1f} scored minutes in which the visitor means nothing; variants "
              f"{', '.join(IDLE_VARIANTS)}; the others on the gesture trials only), with the 95 % upper bound of the rate:", "",
              "| variant | at rest: count / minutes | per min (95 % bound) | in distractors: count / minutes | per min (95 % bound) |",
              "|---|---|---|---|---|"]
    for name, r in v.items():
        a, b = r["false_activations"]["rest"], r["false_activations"]["distractor"]
        lines.append(f"| {name} | {a['count']} / {a['minutes']:.1f} | {a['per_min']:.2f} ({a['upper95_per_min']:.2f}) | "
                     f"{b['count']} / {b['minutes']:.1f} | {b['per_min']:.2f} ({b['upper95_per_min']:.2f}) |")
    lines += ["", f"Time base: rest {fa['rest']['minutes']:.1f} min, distractors {fa['distractor']['minutes']:.1f} min, "
              f"gestures {fa['gesture']['minutes']:.1f} min.", ""]
    return "\n".join(lines)


def _fit_seeds() -> tuple[int, ...]:
    from gestures.confidence import FIT_SEEDS
    return FIT_SEEDS


def _job(args):
    return run_trial(*args)


def run(out_dir: str | Path, quick: bool = False, workers: int = 2, progress: bool = True,
        cache_dir: str | Path | None = None, trials: int | None = None, idle_trials: int | None = None) -> str:
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plan = dict(QUICK if quick else FULL)
    idle = dict(QUICK_IDLE if quick else FULL_IDLE)
    if trials is not None:
        plan["seeds"] = plan["seeds"][:trials]
    if idle_trials is not None:
        idle["seeds"] = idle["seeds"][:idle_trials]
    jobs = [(s, plan["duration_s"], cache_dir, False) for s in plan["seeds"]] + \
           [(s, idle["duration_s"], cache_dir, True) for s in idle["seeds"]]
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=workers) as pool:
        records = list(tqdm(pool.map(_job, jobs), total=len(jobs), desc="bench gestures", unit="trial",
                            disable=not progress))
    result = score(records)
    result["frames_fingerprint"] = LOADED_FRAMES_FINGERPRINT
    for r in result["variants"].values():
        r.pop("starts")
    (out / "results.json").write_text(json.dumps(result, indent=2, default=str))
    text = table(result, time.perf_counter() - start)
    (out / "summary.md").write_text(text)
    return text
