"""Gesture trials with intent labels: what the visitor means, and when, for the gesture benchmark.

A trial is one simulated person (``Subject``: hand size, DIP/PIP coupling, gesture styles, pinch
aperture, rest pose) performing a random script of steps. Every step says what the hand does (its
``kind``) and what the visitor means by it (its ``intent``: ``point``, ``grasp``, ``pinch``,
``open`` or ``none``). The labels come from the script alone, never from a recogniser.

Kinds of step:

* the four gestures in the subject's style: ``point`` (thumb tucked over the fist or held out),
  ``grasp`` (tight or loose fist; sometimes the index and thumb close first, so the hand passes
  through a pinch-like pose on the way: ``grasp-through-pinch``), ``pinch`` (the other fingers
  relaxed or half curled; the tips close to the subject's aperture), ``open`` (flat or slightly
  relaxed fingers);
* steps that mean nothing (intent ``none``): ``rest`` (the subject's relaxed hand),
  ``half-curl`` (every long finger half curled, short of a fist), ``fidget`` (small quick random
  finger movements around the rest pose), ``near-pinch`` (thumb and index approach to 30-45 mm and
  stay there, as when reaching toward an object without taking it).

Every held pose gets a per-step random perturbation of each joint (``JOINT_JITTER_DEG``); a pinch
then closes index and thumb together back to the subject's aperture (the tips touch however the
joints are set). The hand
itself sways and turns slowly, or reaches fast (``fast-reach``: 0.35 m in 0.5 s every 2 s), with
any gesture held meanwhile.

Intended moments: the visitor means a gesture from the moment its forming movement is
``ONSET_FRACTION`` (80 %) complete until the moment the movement out of it is ``RELEASE_FRACTION``
(20 %) complete. Transitions are quintic (minimum-jerk) steps, so these moments follow in closed
form from the step's start and duration (``quintic_time``).

What a glove app can know (``Trial.known_calibration``): the hand's size (measured once at fitting)
but not the person's DIP/PIP coupling, so the pipeline is told the subject's phalanx lengths with the
default coupling 1.0.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import brentq

from ..model.hand import FINGERS, HAND_LENGTH_M, HandCalibration, default_calibration
from ..model.openxr import joint_poses
from .motions import DEG, FingerMotion, fast_reach_hand, slow_rotation_hand, HandTrajectory
from .signals import keyframes

GESTURE_NAMES = ("point", "grasp", "pinch", "open")
INTENTS = (*GESTURE_NAMES, "none")
NONE_KINDS = ("rest", "half-curl", "fidget", "near-pinch")
NONE_WEIGHTS = (0.4, 0.2, 0.2, 0.2)
ONSET_FRACTION = 0.8
RELEASE_FRACTION = 0.2
JOINT_JITTER_DEG = 4.0
"""Standard deviation of the per-step perturbation of every held joint angle, degrees."""


def quintic_time(fraction: float) -> float:
    """The normalised time ``τ`` at which a quintic step ``10τ³ - 15τ⁴ + 6τ⁵`` has covered ``fraction``."""
    return float(brentq(lambda tau: tau**3 * (10 - 15 * tau + 6 * tau**2) - fraction, 0.0, 1.0, xtol=1e-12))


@dataclass(frozen=True)
class Subject:
    """One person: hand length (m), DIP = ``coupling`` x PIP, styles, pinch aperture (m, distance
    between the thumb and index tip joints while pinching) and relaxed pose (long MCP, PIP; deg)."""

    hand_length_m: float = HAND_LENGTH_M
    coupling: float = 1.0
    point_thumb: str = "tucked"          # or "out"
    grasp_style: str = "tight"           # or "loose"
    pinch_others: str = "relaxed"        # or "half-curled"
    open_style: str = "flat"             # or "relaxed"
    pinch_aperture_m: float = 0.010
    rest_deg: tuple[float, float] = (20.0, 25.0)

    @staticmethod
    def draw(rng: np.random.Generator) -> "Subject":
        return Subject(
            hand_length_m=float(rng.uniform(0.165, 0.21)),
            coupling=float(rng.uniform(0.75, 1.0)),
            point_thumb=str(rng.choice(["tucked", "out"])),
            grasp_style=str(rng.choice(["tight", "loose"])),
            pinch_others=str(rng.choice(["relaxed", "half-curled"])),
            open_style=str(rng.choice(["flat", "relaxed"])),
            pinch_aperture_m=float(rng.uniform(0.006, 0.016)),
            rest_deg=(float(rng.uniform(15.0, 28.0)), float(rng.uniform(20.0, 32.0))),
        )

    def calibration(self, hand: str = "right") -> HandCalibration:
        """The true geometry: the default hand scaled to ``hand_length_m`` with this coupling."""
        calib = default_calibration(hand, self.hand_length_m)  # type: ignore[arg-type]
        return replace(calib, fingers={n: replace(g, coupling=self.coupling) if n != "thumb" else g
                                       for n, g in calib.fingers.items()})


Pose = dict[str, tuple[float, float]]
"""Long fingers: (MCP, PIP) deg, DIP = coupling x PIP; thumb: (MCP, IP) deg."""


def tip_distance_m(calib: HandCalibration, pose_deg: Pose) -> float:
    """Distance between the thumb and index tip joints in ``pose_deg``, m."""
    phi = {}
    for f in FINGERS:
        a, b = pose_deg[f]
        g = calib.finger(f)
        phi[f] = np.radians([a, b]) if f == "thumb" else np.radians([a, b, g.coupling * b])
    j = joint_poses(calib, phi, np.eye(3), np.zeros(3))
    return float(np.linalg.norm(j["thumb_tip"][0] - j["index_tip"][0]))


def rest_pose(subject: Subject) -> Pose:
    m, p = subject.rest_deg
    return {"thumb": (15.0, 15.0), **{f: (m, p) for f in ("index", "middle", "ring", "little")}}


def _with_aperture(subject: Subject, calib: HandCalibration, base: Pose, aperture_m: float) -> Pose:
    """``base`` with index and thumb opened or closed together by ``d`` deg so that the tips are
    ``aperture_m`` apart (the closest value on a 0.25 deg grid)."""
    best, best_err = base, np.inf
    for d in np.arange(-15.0, 40.0, 0.25):
        pose = dict(base)
        pose["index"] = (base["index"][0] - d, base["index"][1] - d)
        pose["thumb"] = (base["thumb"][0] - d, base["thumb"][1] - d)
        err = abs(tip_distance_m(calib, pose) - aperture_m)
        if err < best_err:
            best, best_err = pose, err
    return best


def gesture_pose(subject: Subject, kind: str, calib: HandCalibration | None = None,
                 aperture_m: float | None = None) -> Pose:
    """The subject's pose for a step kind (without the per-step jitter)."""
    calib = calib or subject.calibration()
    rest = rest_pose(subject)
    if kind == "point":
        fist = (80.0, 90.0) if subject.grasp_style == "tight" else (65.0, 75.0)
        thumb = (40.0, 40.0) if subject.point_thumb == "tucked" else (0.0, 5.0)
        return {"thumb": thumb, "index": (0.0, 5.0), "middle": fist, "ring": fist, "little": fist}
    if kind in ("grasp", "grasp-through-pinch"):
        fist = (85.0, 95.0) if subject.grasp_style == "tight" else (62.0, 70.0)
        return {"thumb": (45.0, 50.0), **{f: fist for f in ("index", "middle", "ring", "little")}}
    if kind in ("pinch", "near-pinch"):
        others = (20.0, 25.0) if subject.pinch_others == "relaxed" else (35.0, 40.0)
        base = {"thumb": (40.0, 30.0), "index": (40.0, 40.0), "middle": others, "ring": others, "little": others}
        target = subject.pinch_aperture_m if aperture_m is None else aperture_m
        return _with_aperture(subject, calib, base, target)
    if kind == "open":
        if subject.open_style == "flat":
            return {f: (0.0, 0.0) for f in FINGERS}
        return {"thumb": (8.0, 8.0), **{f: (5.0, 6.0) for f in ("index", "middle", "ring", "little")}}
    if kind in ("rest", "fidget"):
        return rest
    if kind == "half-curl":
        return {"thumb": (5.0, 5.0), **{f: (35.0, 42.0) for f in ("index", "middle", "ring", "little")}}
    raise ValueError(f"unknown step kind {kind!r}")


@dataclass(frozen=True)
class Step:
    """One scripted step: move to ``pose`` over ``transition_s`` from ``start_s``, hold ``hold_s``.
    ``lead`` gives fingers that finish their move early (fraction of the transition); ``wiggles``
    are extra keyframes ``(finger, joint, start_s, duration_s, target_deg)`` during the hold."""

    kind: str
    intent: str
    start_s: float
    transition_s: float
    hold_s: float
    pose: Pose
    lead: dict[str, float] = field(default_factory=dict)
    wiggles: tuple[tuple[str, int, float, float, float], ...] = ()

    @property
    def end_s(self) -> float:
        return self.start_s + self.transition_s + self.hold_s


@dataclass(frozen=True)
class Intent:
    """What the visitor means from ``onset_s`` to ``release_s`` (source clock, s); ``kind`` is the
    step kind that carries it."""

    gesture: str
    onset_s: float
    release_s: float
    kind: str


def _jittered(pose: Pose, rng: np.random.Generator) -> Pose:
    return {f: (a + float(rng.normal(0.0, JOINT_JITTER_DEG)), b + float(rng.normal(0.0, JOINT_JITTER_DEG)))
            for f, (a, b) in pose.items()}


@dataclass(frozen=True)
class Trial:
    """A subject, a script and a hand trajectory; everything derived from one seed."""

    seed: int
    subject: Subject
    steps: tuple[Step, ...]
    hand_motion: str
    scored_from_s: float = 0.0
    """Steps before this time are the enrolment (``enrolment_steps``), not scored, s."""

    @property
    def duration_s(self) -> float:
        return self.steps[-1].end_s if self.steps else 0.5

    def calibration(self, hand: str = "right") -> HandCalibration:
        return self.subject.calibration(hand)

    def known_calibration(self, hand: str = "right") -> HandCalibration:
        """What the glove app tells the pipeline: the measured hand size, the default coupling."""
        return default_calibration(hand, self.subject.hand_length_m)  # type: ignore[arg-type]

    def hand_trajectory(self) -> HandTrajectory:
        return fast_reach_hand() if self.hand_motion == "fast-reach" else slow_rotation_hand()

    def finger_motion(self) -> FingerMotion:
        """Joint-angle signals of the script (C2; DIP = coupling x PIP)."""
        c = self.subject.coupling
        start = rest_pose(self.subject)
        joints = {}
        for f in FINGERS:
            segs: list[list[tuple[float, float, float]]] = [[], []]
            for st in self.steps:
                dur = st.transition_s * st.lead.get(f, 1.0)
                for j in range(2):
                    segs[j].append((st.start_s, dur, st.pose[f][j] * DEG))
                    segs[j] += [(t0, d, v * DEG) for (wf, wj, t0, d, v) in st.wiggles if wf == f and wj == j]
            sig = [keyframes(start[f][j] * DEG, segs[j]) for j in range(2)]
            if f != "thumb":
                sig.append(keyframes(c * start[f][1] * DEG, [(a, b, c * v) for a, b, v in segs[1]]))
            joints[f] = tuple(sig)
        return FingerMotion("gesture-trial", self.duration_s, joints)

    def intents(self) -> list[Intent]:
        """Every step's intent interval (module docstring), in time order; ``none`` steps too."""
        on, off = quintic_time(ONSET_FRACTION), quintic_time(RELEASE_FRACTION)
        out = []
        for k, st in enumerate(self.steps):
            nxt = self.steps[k + 1] if k + 1 < len(self.steps) else None
            release = nxt.start_s + off * nxt.transition_s if nxt is not None else st.end_s
            out.append(Intent(st.intent, st.start_s + on * st.transition_s, release, st.kind))
        return out


ENROLMENT_ORDER = ("rest", "point", "rest", "grasp", "rest", "pinch", "rest", "open", "rest")
ENROLMENT_HOLD_S = 1.5
ENROLMENT_TRANSITION_S = 0.35


def enrolment_steps(subject: Subject, start_s: float, rng: np.random.Generator,
                    calib: HandCalibration | None = None) -> list[Step]:
    """The enrolment procedure: rest, then each gesture held ``ENROLMENT_HOLD_S`` with rest between
    (9 steps of 1.85 s: about 17 s); the intents are the labels the application shows the visitor."""
    calib = calib or subject.calibration()
    steps, t = [], start_s
    for kind in ENROLMENT_ORDER:
        pose = _jittered(gesture_pose(subject, kind, calib), rng)
        if kind == "pinch":
            pose = _with_aperture(subject, calib, pose, subject.pinch_aperture_m)
        steps.append(Step(kind, kind if kind in GESTURE_NAMES else "none", t, ENROLMENT_TRANSITION_S,
                          ENROLMENT_HOLD_S, pose))
        t += ENROLMENT_TRANSITION_S + ENROLMENT_HOLD_S
    return steps


def _fidget_wiggles(pose: Pose, start_s: float, hold_s: float, rng: np.random.Generator) -> list:
    """Small quick MCP movements of random fingers (+-15 deg and back) during a hold."""
    wiggles, tw = [], start_s
    while tw < start_s + hold_s - 0.3:
        f = str(rng.choice(FINGERS))
        d = float(rng.uniform(0.15, 0.3))
        wiggles.append((f, 0, tw, d, pose[f][0] + float(rng.uniform(-15.0, 15.0))))
        wiggles.append((f, 0, tw + d, d, pose[f][0]))
        tw += 2 * d + float(rng.uniform(0.0, 0.2))
    return wiggles


def make_trial(seed: int, duration_s: float, subject: Subject | None = None,
               kinds: tuple[str, ...] | None = None, hand_motion: str | None = None,
               enrolment: bool = True) -> Trial:
    """A random trial: the enrolment procedure (``enrolment_steps``, optional), then about
    ``duration_s`` of a random script: after a gesture, a meaningless step (probability 0.65;
    kinds weighted by ``NONE_WEIGHTS``) or another gesture; after a meaningless step, a gesture;
    the next gesture drawn among the least used so far, never the same twice in a row; transitions 0.2-0.45 s, holds 0.6-1.8 s (rest 1-3 s)."""
    rng = np.random.default_rng(seed)
    subject = subject or Subject.draw(rng)
    hand_motion = hand_motion or str(rng.choice(["slow-rotation", "fast-reach"]))
    calib = subject.calibration()
    gestures = kinds or GESTURE_NAMES
    steps: list[Step] = enrolment_steps(subject, 0.5, rng, calib) if enrolment else []
    t = steps[-1].end_s if steps else 0.5
    scored_from, end, previous = t, t + duration_s, "rest"
    used = {k: 0 for k in gestures}
    while t < end - 2.0:
        if previous in GESTURE_NAMES and rng.uniform() < 0.65:
            kind = str(rng.choice(NONE_KINDS, p=NONE_WEIGHTS))
        else:
            candidates = [k for k in gestures if k != previous]
            fewest = min(used[k] for k in candidates)
            kind = str(rng.choice([k for k in candidates if used[k] == fewest]))
            used[kind] += 1
        intent = kind if kind in GESTURE_NAMES else "none"
        if kind == "grasp" and rng.uniform() < 0.3:
            kind = "grasp-through-pinch"
        transition = float(rng.uniform(0.2, 0.45))
        hold = float(rng.uniform(1.0, 3.0) if kind == "rest" else rng.uniform(0.6, 1.8))
        aperture = float(rng.uniform(0.032, 0.045)) if kind == "near-pinch" else None
        pose = _jittered(gesture_pose(subject, kind, calib, aperture), rng)
        if kind in ("pinch", "near-pinch"):      # the tips still close to the aperture (contact holds)
            pose = _with_aperture(subject, calib, pose, subject.pinch_aperture_m if aperture is None else aperture)
        lead = {"index": 0.45, "thumb": 0.45} if kind == "grasp-through-pinch" else {}
        wiggles = _fidget_wiggles(pose, t + transition, hold, rng) if kind == "fidget" else []
        steps.append(Step(kind, intent, t, transition, hold, pose, lead, tuple(wiggles)))
        t += transition + hold
        previous = intent if intent != "none" else kind
    return Trial(seed, subject, tuple(steps), hand_motion, scored_from)


IDLE_SETTLE_S = 5.0
"""The first rest of an idle trial, not scored: the estimators settle without a true start, s."""
IDLE_DISTRACTOR_P = 0.25
"""Probability of a meaningless distractor step between two rests of an idle trial."""


def make_idle_trial(seed: int, duration_s: float, subject: Subject | None = None,
                    hand_motion: str | None = None) -> Trial:
    """A trial in which the visitor means nothing (for false activations at rest): after an unscored
    first rest of ``IDLE_SETTLE_S``, about ``duration_s`` of rests (a new relaxed pose every 4-12 s,
    reached over 0.5-1.5 s, the same per-step joint variation as other trials) with, between two rests,
    a distractor (``half-curl``, ``fidget`` or ``near-pinch``; probability ``IDLE_DISTRACTOR_P``, held
    1-3 s). No enrolment."""
    rng = np.random.default_rng(seed)
    subject = subject or Subject.draw(rng)
    hand_motion = hand_motion or str(rng.choice(["slow-rotation", "fast-reach"]))
    calib = subject.calibration()
    steps = [Step("rest", "none", 0.5, 0.5, IDLE_SETTLE_S - 1.0, _jittered(rest_pose(subject), rng))]
    t = steps[-1].end_s
    scored_from, end = t, t + duration_s
    while t < end - 2.0:
        kind = "rest"
        if steps[-1].kind == "rest" and rng.uniform() < IDLE_DISTRACTOR_P:
            kind = str(rng.choice(NONE_KINDS[1:]))
        transition = float(rng.uniform(0.5, 1.5) if kind == "rest" else rng.uniform(0.2, 0.45))
        hold = float(rng.uniform(4.0, 12.0) if kind == "rest" else rng.uniform(1.0, 3.0))
        aperture = float(rng.uniform(0.032, 0.045)) if kind == "near-pinch" else None
        pose = _jittered(gesture_pose(subject, kind, calib, aperture), rng)
        if aperture is not None:
            pose = _with_aperture(subject, calib, pose, aperture)
        wiggles = _fidget_wiggles(pose, t + transition, hold, rng) if kind == "fidget" else []
        steps.append(Step(kind, "none", t, transition, hold, pose, {}, tuple(wiggles)))
        t += transition + hold
    return Trial(seed, subject, tuple(steps), hand_motion, scored_from)
