"""Motion descriptors: finger joint-angle motions and 6-DoF hand (metacarpus) trajectories.

Every descriptor is built from C2 signals (``signals.py``), so angular accelerations are finite and
known analytically. Finger motions give joint angles ``φ`` (MCP, PIP, DIP; thumb MCP, IP) and keep
the coupling ``φ_DIP = c · φ_PIP`` of the calibration (paper section 2.2; default ``c = 1``), because
the default two-sensor placement cannot observe a violation of it.

Named motions (the ``--motion`` names of ``fingertrack simulate``):

* ``grasp``: the paper's test motion (section 3): static for ``t_d``; MCP extension to -28 deg over
  ``t_m/3``; then MCP flexion to 90 deg with PIP and DIP to 85 deg over ``2 t_m/3``. All four long
  fingers do it; the thumb flexes along (MCP 40 deg, IP 50 deg) in the second phase.
* ``point``: from a relaxed hand, the index stays extended while middle, ring and little flex into
  the palm and the thumb folds over them; then held.
* ``circle``: the circular pointing task of the comparison paper (five circles with an extended
  index in about 3.25 s). The model is planar, so only the flexion component of the circle is
  simulated: the MCP oscillates ±15 deg around 15 deg; abduction is not modelled.
* ``pinch``: index and thumb flex toward each other, the other fingers stay relaxed; then held.
* ``open``: from a relaxed hand to all joints extended (0 deg); then held.
* ``random``: every joint a sum of three sinusoids (0.1-1.5 Hz) inside the anatomical limits.
* ``sequence``: the scripted interaction: point, grasp, release, pinch, open (``DEFAULT_SEQUENCE``),
  each reached in ``t_m`` and held.

Hand trajectories (``--hand-motion``): ``still``; ``slow-rotation`` (rotation about three axes up
to 0.5 rad at 0.1-0.2 Hz, slow sway); ``fast-reach`` (a 0.35 m reach in 0.5 s with a 40 deg turn, and
back); ``random`` (random sinusoidal rotation and translation, for tests).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from ..model.hand import FINGERS, JOINT_LIMITS_RAD, LONG_FINGERS, joint_limits  # noqa: F401 (re-exported)
from ..model.kinematics import BaseMotion
from ..model.units import DEG
from .signals import Modulated, QuinticStep, Signal, Sinusoid, SmoothSignal, keyframes


@dataclass(frozen=True)
class FingerMotion:
    """Joint-angle signals per finger (rad), and the motion's duration in seconds."""

    name: str
    duration_s: float
    joints: Mapping[str, tuple[SmoothSignal, ...]]

    def joint_angles(self, finger: str, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``φ, φ̇, φ̈`` of ``finger`` at times ``t``, each shape (N, n_joints)."""
        parts = [s.eval(t) for s in self.joints[finger]]
        return tuple(np.stack([p[k] for p in parts], axis=-1) for k in range(3))  # type: ignore[return-value]


RELAXED_DEG = {"thumb": (10.0, 10.0), "long": (10.0, 15.0)}
"""Relaxed hand: MCP and PIP of the long fingers, MCP and IP of the thumb, degrees."""


def _pose_motion(name: str, targets_deg: Mapping[str, tuple[float, ...]], t_m: float, t_d: float,
                 hold_s: float, coupling: float) -> FingerMotion:
    """From the relaxed hand to ``targets_deg`` (long: MCP, PIP; thumb: MCP, IP) over ``t_m`` after ``t_d``."""
    joints = {}
    for f in FINGERS:
        kind = "thumb" if f == "thumb" else "long"
        start = RELAXED_DEG[kind]
        goal = targets_deg.get(f, start)
        sig = [keyframes(a * DEG, [(t_d, t_m, b * DEG)]) for a, b in zip(start, goal)]
        if kind == "long":
            sig.append(keyframes(coupling * start[1] * DEG, [(t_d, t_m, coupling * goal[1] * DEG)]))
        joints[f] = tuple(sig)
    return FingerMotion(name, t_d + t_m + hold_s, joints)


def grasp_motion(t_m: float = 1.0, t_d: float = 0.2, coupling: float = 1.0) -> FingerMotion:
    """The paper's test motion (section 3), on all long fingers; see module docstring."""
    if t_m <= 0 or t_d < 0:
        raise ValueError(f"grasp motion needs t_m > 0 and t_d >= 0, got t_m={t_m}, t_d={t_d}")
    t1, t2 = t_d + t_m / 3.0, 2.0 * t_m / 3.0
    joints: dict[str, tuple[SmoothSignal, ...]] = {}
    for f in LONG_FINGERS:
        mcp = keyframes(0.0, [(t_d, t_m / 3.0, -28 * DEG), (t1, t2, 90 * DEG)])
        pip = keyframes(0.0, [(t1, t2, 85 * DEG)])
        dip = keyframes(0.0, [(t1, t2, coupling * 85 * DEG)])
        joints[f] = (mcp, pip, dip)
    joints["thumb"] = (keyframes(0.0, [(t1, t2, 40 * DEG)]), keyframes(0.0, [(t1, t2, 50 * DEG)]))
    return FingerMotion("grasp", t_d + t_m, joints)


REST_DEG = {"thumb": (15.0, 15.0), "long": (20.0, 25.0)}
"""A visitor's hand at rest between gestures: MCP and PIP of the long fingers, MCP and IP of the
thumb, degrees; the gesture benchmark's typical subject (``gesture_script.Subject.rest_deg``, drawn
there from MCP 15-28 and PIP 20-32). Flatter than this (``RELAXED_DEG``) a hand reads as open."""

POSES_DEG: dict[str, dict[str, tuple[float, float]]] = {
    "relaxed": {},
    "rest": {f: REST_DEG["thumb" if f == "thumb" else "long"] for f in FINGERS},
    "point": {"index": (0.0, 5.0), "middle": (80.0, 90.0), "ring": (80.0, 90.0), "little": (80.0, 90.0),
              "thumb": (40.0, 40.0)},
    "grasp": {"index": (85.0, 90.0), "middle": (85.0, 90.0), "ring": (85.0, 90.0), "little": (85.0, 90.0),
              "thumb": (45.0, 50.0)},
    "pinch": {"index": (40.0, 40.0), "thumb": (40.0, 30.0), "middle": (20.0, 25.0), "ring": (20.0, 25.0),
              "little": (20.0, 25.0)},
    "open": {f: (0.0, 0.0) for f in FINGERS},
}
"""Hand poses by name: MCP and PIP of the long fingers (DIP = coupling x PIP), MCP and IP of the
thumb, degrees; fingers not named stay relaxed (``RELAXED_DEG``)."""


def _pose(name: str, finger: str) -> tuple[float, float]:
    kind = "thumb" if finger == "thumb" else "long"
    return POSES_DEG[name].get(finger, RELAXED_DEG[kind])


def point_motion(t_m: float = 0.6, t_d: float = 0.2, coupling: float = 1.0, hold_s: float = 1.0) -> FingerMotion:
    return _pose_motion("point", POSES_DEG["point"], t_m, t_d, hold_s, coupling)


def pinch_motion(t_m: float = 0.6, t_d: float = 0.2, coupling: float = 1.0, hold_s: float = 1.0) -> FingerMotion:
    return _pose_motion("pinch", POSES_DEG["pinch"], t_m, t_d, hold_s, coupling)


def open_motion(t_m: float = 0.6, t_d: float = 0.2, coupling: float = 1.0, hold_s: float = 1.0) -> FingerMotion:
    return _pose_motion("open", POSES_DEG["open"], t_m, t_d, hold_s, coupling)


DEFAULT_SEQUENCE = (("point", 1.2), ("grasp", 1.2), ("rest", 1.0), ("pinch", 1.2), ("open", 1.2))
"""The scripted demo sequence: point, grasp, release, pinch, open; ``(pose, hold seconds)``."""


def sequence_motion(t_m: float = 0.4, t_d: float = 0.5, coupling: float = 1.0,
                    steps: tuple[tuple, ...] = DEFAULT_SEQUENCE) -> FingerMotion:
    """From the hand at rest (``REST_DEG``) through ``steps``: ``(pose name, hold s)`` with a
    transition of ``t_m`` seconds, or ``(pose name, transition s, hold s)``; each transition a C2
    step; starts after ``t_d``."""
    steps = tuple((p[0], t_m, p[1]) if len(p) == 2 else tuple(p) for p in steps)
    joints = {}
    for f in FINGERS:
        kind = "thumb" if f == "thumb" else "long"
        start = REST_DEG[kind]
        segs: list[list[tuple[float, float, float]]] = [[], []]
        t = t_d
        for pose, transition, hold in steps:
            if pose not in POSES_DEG:
                raise ValueError(f"unknown pose {pose!r}; expected one of {sorted(POSES_DEG)}")
            goal = _pose(pose, f)
            for j in range(2):
                segs[j].append((t, transition, goal[j] * DEG))
            t += transition + hold
        sig = [keyframes(start[j] * DEG, segs[j]) for j in range(2)]
        if kind == "long":
            sig.append(keyframes(coupling * start[1] * DEG, [(a, b, coupling * c) for a, b, c in segs[1]]))
        joints[f] = tuple(sig)
    duration = t_d + sum(transition + hold for _, transition, hold in steps)
    return FingerMotion("sequence", duration, joints)


def random_sequence(duration_s: float, seed: int, transition_s: tuple[float, float] = (0.25, 0.6),
                    hold_s: tuple[float, float] = (0.6, 2.0)) -> tuple[tuple[str, float, float], ...]:
    """A random gesture script of about ``duration_s``: poses drawn from ``POSES_DEG`` (never the same
    twice in a row), transition and hold times uniform in the given ranges, seconds."""
    rng = np.random.default_rng(seed)
    names = sorted(POSES_DEG)
    steps, t, current = [], 0.5, "relaxed"
    while t < duration_s - 1.0:
        pose = str(rng.choice([n for n in names if n != current]))
        tr, hold = float(rng.uniform(*transition_s)), float(rng.uniform(*hold_s))
        steps.append((pose, tr, hold))
        t += tr + hold
        current = pose
    return tuple(steps)


def circle_motion(t_m: float = 3.25, t_d: float = 0.2, coupling: float = 1.0, cycles: int = 5) -> FingerMotion:
    """Flexion component of the comparison paper's circular pointing task: ``cycles`` circles in ``t_m``."""
    base = _pose_motion("circle", {}, 1.0, 0.0, 0.0, coupling).joints
    freq = cycles / t_m
    # Amplitude ramps in and out with quintic steps so the motion starts and ends at rest (C2).
    mcp = Signal(15 * DEG, waves=(Sinusoid(15 * DEG, freq, 0.0),))
    ramp_t = 1.0 / freq
    window = keyframes(0.0, [(t_d, ramp_t, 1.0), (t_d + t_m - ramp_t, ramp_t, 0.0)])
    joints = dict(base)
    joints["index"] = (Modulated(mcp, window, t_d), keyframes(5 * DEG, []), keyframes(coupling * 5 * DEG, []))
    return FingerMotion("circle", t_d + t_m, joints)


def random_motion(t_m: float = 10.0, seed: int = 0, coupling: float = 1.0, n_waves: int = 3) -> FingerMotion:
    """Every joint: centre of its range plus ``n_waves`` sinusoids (0.1-1.5 Hz) whose amplitudes sum
    to at most 45% of the range, so the joint limits always hold."""
    rng = np.random.default_rng(seed)
    joints = {}
    for f in FINGERS:
        limits = joint_limits(f)
        sigs = []
        measured = limits if f == "thumb" else limits[:2]
        for lo, hi in measured:
            if f != "thumb" and len(sigs) == 1 and coupling > 0:
                # keep DIP = c·PIP inside the DIP range
                hi = min(hi, limits[2][1] / coupling)
                lo = max(lo, limits[2][0] / coupling)
            centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            amps = rng.dirichlet(np.ones(n_waves)) * 0.9 * half
            waves = tuple(Sinusoid(float(a), float(rng.uniform(0.1, 1.5)), float(rng.uniform(0, 2 * np.pi)))
                          for a in amps)
            sigs.append(Signal(centre, waves=waves))
        if f != "thumb":
            pip = sigs[1]
            sigs.append(Signal(coupling * pip.initial,
                               waves=tuple(Sinusoid(coupling * w.amplitude, w.frequency_hz, w.phase_rad) for w in pip.waves)))
        joints[f] = tuple(sigs)
    return FingerMotion("random", t_m, joints)


FINGER_MOTIONS: dict[str, Callable[..., FingerMotion]] = {
    "grasp": grasp_motion,
    "point": point_motion,
    "circle": circle_motion,
    "pinch": pinch_motion,
    "open": open_motion,
    "random": random_motion,
    "sequence": sequence_motion,
}


def make_finger_motion(name: str, t_m: float | None = None, seed: int = 0, coupling: float = 1.0) -> FingerMotion:
    """Build a named motion; ``t_m`` is the movement duration in seconds (motion default if None)."""
    if name not in FINGER_MOTIONS:
        raise ValueError(f"unknown motion {name!r}; expected one of {sorted(FINGER_MOTIONS)}")
    kwargs: dict = {"coupling": coupling}
    if t_m is not None:
        if not np.isfinite(t_m) or t_m <= 0:
            raise ValueError(f"--tm must be a positive number of seconds, got {t_m}")
        kwargs["t_m"] = t_m
    if name == "random":
        kwargs["seed"] = seed
    return FINGER_MOTIONS[name](**kwargs)


# ---------------------------------------------------------------------------------------------
# Hand (metacarpus) trajectories

PALM_DOWN = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])
"""Metacarpus orientation with the palm facing down and the fingers pointing forward (world -Z):
columns are the metacarpus axes in the world frame (x = -X, y = -Z, z = -Y)."""
DEFAULT_HAND_POSITION_M = np.array([0.0, 1.1, -0.35])
"""Default wrist position in stage space: in front of a standing user at 1.1 m height, metres."""


@dataclass(frozen=True)
class HandTrajectory:
    """``R(t) = Exp(u_1 a_1(t)) Exp(u_2 a_2(t)) Exp(u_3 a_3(t)) R_0`` and ``p(t) = p_0 + Σ_j e_j c_j(t)``,
    with fixed world axes ``u_j`` and C2 signals ``a_j`` (rad) and ``c_j`` (m)."""

    name: str
    initial_rotation: np.ndarray = field(default_factory=lambda: PALM_DOWN.copy())
    initial_position: np.ndarray = field(default_factory=lambda: DEFAULT_HAND_POSITION_M.copy())
    axes: tuple[tuple[float, float, float], ...] = ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    angles: tuple[Signal, Signal, Signal] = (Signal(), Signal(), Signal())
    translation: tuple[Signal, Signal, Signal] = (Signal(), Signal(), Signal())

    def base_motion(self, t: np.ndarray) -> BaseMotion:
        """Exact metacarpus kinematics at times ``t`` (world frame)."""
        t = np.asarray(t, dtype=float)
        n = t.shape[0]
        rot = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        omega = np.zeros((n, 3))
        alpha = np.zeros((n, 3))
        for u, sig in zip(self.axes, self.angles):
            a, da, dda = sig.eval(t)
            k = rot @ np.asarray(u, dtype=float)           # current axis: R_1..R_{j-1} u_j
            dk = np.cross(omega, k)                         # it turns with the frames before it
            alpha = alpha + dda[:, None] * k + da[:, None] * dk
            omega = omega + da[:, None] * k
            rot = rot @ Rotation.from_rotvec(np.asarray(u)[None, :] * a[:, None]).as_matrix()
        rot = rot @ self.initial_rotation
        pos = np.broadcast_to(self.initial_position, (n, 3)).copy()
        vel = np.zeros((n, 3))
        acc = np.zeros((n, 3))
        for j, sig in enumerate(self.translation):
            c, dc, ddc = sig.eval(t)
            pos[:, j] += c
            vel[:, j] += dc
            acc[:, j] += ddc
        return BaseMotion(rot, pos, vel, acc, omega, alpha)


def still_hand(rotation: np.ndarray = PALM_DOWN, position: np.ndarray = DEFAULT_HAND_POSITION_M) -> HandTrajectory:
    return HandTrajectory("still", initial_rotation=np.asarray(rotation), initial_position=np.asarray(position))


def slow_rotation_hand() -> HandTrajectory:
    return HandTrajectory(
        "slow-rotation",
        angles=(Signal(waves=(Sinusoid(0.5, 0.2),)), Signal(waves=(Sinusoid(0.3, 0.15, 1.0),)),
                Signal(waves=(Sinusoid(0.3, 0.1, 2.0),))),
        translation=(Signal(waves=(Sinusoid(0.05, 0.2),)), Signal(waves=(Sinusoid(0.03, 0.13, 0.5),)),
                     Signal(waves=(Sinusoid(0.04, 0.17, 1.5),))),
    )


def fast_reach_hand(period_s: float = 2.0) -> HandTrajectory:
    """A reach forward-up (0.35 m in 0.5 s, turning 40 deg about the vertical) and back, every ``period_s``."""
    steps_z, steps_y, steps_yaw = [], [], []
    for k in range(50):
        t0 = 0.3 + k * period_s
        steps_z += [QuinticStep(t0, 0.5, -0.35), QuinticStep(t0 + 1.0, 0.5, 0.35)]
        steps_y += [QuinticStep(t0, 0.5, 0.1), QuinticStep(t0 + 1.0, 0.5, -0.1)]
        steps_yaw += [QuinticStep(t0, 0.5, 40 * DEG), QuinticStep(t0 + 1.0, 0.5, -40 * DEG)]
    return HandTrajectory(
        "fast-reach",
        angles=(Signal(steps=tuple(steps_yaw)), Signal(), Signal()),
        translation=(Signal(), Signal(steps=tuple(steps_y)), Signal(steps=tuple(steps_z))),
    )


def random_hand(seed: int = 0) -> HandTrajectory:
    rng = np.random.default_rng(seed)
    axes = tuple(tuple(float(v) for v in a / np.linalg.norm(a)) for a in rng.normal(size=(3, 3)))
    angles = tuple(Signal(waves=(Sinusoid(float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.1, 1.0)),
                                          float(rng.uniform(0, 6.28))),)) for _ in range(3))
    trans = tuple(Signal(waves=(Sinusoid(float(rng.uniform(0.02, 0.15)), float(rng.uniform(0.1, 1.0)),
                                         float(rng.uniform(0, 6.28))),)) for _ in range(3))
    r0 = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    return HandTrajectory("random", initial_rotation=r0, axes=axes, angles=angles, translation=trans)  # type: ignore[arg-type]


HAND_MOTIONS: dict[str, Callable[..., HandTrajectory]] = {
    "still": still_hand,
    "slow-rotation": slow_rotation_hand,
    "fast-reach": fast_reach_hand,
    "random": random_hand,
}


def make_hand_motion(name: str, seed: int = 0) -> HandTrajectory:
    if name not in HAND_MOTIONS:
        raise ValueError(f"unknown hand motion {name!r}; expected one of {sorted(HAND_MOTIONS)}")
    return random_hand(seed) if name == "random" else HAND_MOTIONS[name]()
