"""A reference hold before a motion: the hand is held flat (every joint near 0) for ``hold_s``, then
blends into the motion. This is what a glove app asks the user for ("lay your hand flat") and then
announces with a ``reference_pose`` message (``{"type": "reference_pose", "t0": .., "t1": .., "pose":
"flat"}``).

A person does not hold a hand exactly flat: each joint stays at a small constant deviation, drawn
uniformly within ``±deviation_rad`` (3 deg: the hand on a table, fingers extended but not forced), so
the message's "flat" is right only to within that. The DIP keeps the coupling (``c`` times the PIP's
deviation).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .motions import FingerMotion
from .signals import QuinticStep, SmoothSignal

DEG = np.pi / 180.0
REFERENCE_DEVIATION_RAD = 3.0 * DEG
BLEND_S = 0.5
"""Time from the end of the hold to the motion, s."""


@dataclass(frozen=True)
class Blend:
    """``(1 - s(t)) · hold + s(t) · motion(t - shift)`` with ``s`` a quintic step from 0 to 1 over
    ``[start_s, start_s + duration_s]``: exact derivatives by the product rule (C2)."""

    hold: float
    motion: SmoothSignal
    shift_s: float
    start_s: float
    duration_s: float

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        s, ds, dds = QuinticStep(self.start_s, self.duration_s, 1.0).eval(t)
        m, dm, ddm = self.motion.eval(t - self.shift_s)
        d = m - self.hold
        return self.hold + s * d, ds * d + s * dm, dds * d + 2.0 * ds * dm + s * ddm


def with_reference_hold(motion: FingerMotion, hold_s: float, rng: np.random.Generator,
                        coupling: float = 1.0, deviation_rad: float = REFERENCE_DEVIATION_RAD) -> FingerMotion:
    """``motion`` preceded by a flat hold of ``hold_s`` seconds (module docstring) and a ``BLEND_S``
    blend into the motion's start; the motion's own time starts after the blend."""
    if hold_s <= 0:
        raise ValueError(f"reference hold must be a positive number of seconds, got {hold_s}")
    shift = hold_s + BLEND_S
    joints = {}
    for finger, signals in motion.joints.items():
        dev = list(rng.uniform(-deviation_rad, deviation_rad, len(signals)))
        if len(signals) == 3:
            dev[2] = coupling * dev[1]
        joints[finger] = tuple(Blend(float(d), sig, shift, hold_s, BLEND_S) for d, sig in zip(dev, signals))
    return FingerMotion(f"{motion.name}+reference", motion.duration_s + shift, joints)
