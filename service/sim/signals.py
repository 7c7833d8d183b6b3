"""Smooth scalar signals with analytic first and second derivatives.

Every motion in the simulator is built from these, so the simulated angular accelerations are exact
and finite (C2 profiles): quintic "minimum-jerk" steps (zero velocity and acceleration at both ends)
and sinusoids.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


class SmoothSignal(Protocol):
    """Anything with ``eval(t) -> (value, rate, acceleration)``."""

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class QuinticStep:
    """A change by ``delta`` between ``start_s`` and ``start_s + duration_s`` with the profile
    ``s(τ) = 10τ³ - 15τ⁴ + 6τ⁵`` (C2: velocity and acceleration vanish at both ends)."""

    start_s: float
    duration_s: float
    delta: float

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        T = self.duration_s
        tau = np.clip((t - self.start_s) / T, 0.0, 1.0)
        inside = (t > self.start_s) & (t < self.start_s + T)
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
        ds = np.where(inside, 30.0 * tau**2 * (1.0 - tau) ** 2 / T, 0.0)
        dds = np.where(inside, 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau) / T**2, 0.0)
        return self.delta * s, self.delta * ds, self.delta * dds


@dataclass(frozen=True)
class Sinusoid:
    """``amplitude · sin(2π frequency_hz · t + phase_rad)``."""

    amplitude: float
    frequency_hz: float
    phase_rad: float = 0.0

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = 2.0 * np.pi * self.frequency_hz
        arg = w * t + self.phase_rad
        return (self.amplitude * np.sin(arg), self.amplitude * w * np.cos(arg),
                -self.amplitude * w**2 * np.sin(arg))


@dataclass(frozen=True)
class Signal:
    """``initial`` plus a sum of quintic steps and sinusoids. ``eval`` returns value, rate, acceleration."""

    initial: float = 0.0
    steps: tuple[QuinticStep, ...] = field(default_factory=tuple)
    waves: tuple[Sinusoid, ...] = field(default_factory=tuple)

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        x = np.full(t.shape, self.initial)
        dx = np.zeros(t.shape)
        ddx = np.zeros(t.shape)
        for part in (*self.steps, *self.waves):
            a, b, c = part.eval(t)
            x += a
            dx += b
            ddx += c
        return x, dx, ddx

    def final(self) -> float:
        """Value after the last step, ignoring sinusoids."""
        return self.initial + sum(s.delta for s in self.steps)


def keyframes(initial: float, segments: list[tuple[float, float, float]]) -> Signal:
    """A signal that moves through targets: ``segments`` = ``[(start_s, duration_s, target), ...]``
    in time order; each segment moves from the previous target to ``target`` with a quintic step."""
    steps = []
    value = initial
    for start, duration, target in segments:
        if duration <= 0:
            raise ValueError(f"keyframe segment at t={start} s has non-positive duration {duration} s")
        steps.append(QuinticStep(start, duration, target - value))
        value = target
    return Signal(initial, tuple(steps))


@dataclass(frozen=True)
class Modulated:
    """``carrier.initial + window(t) · (carrier(t - t0) - carrier.initial)``, exact derivatives
    (product rule): lets an oscillation fade in and out smoothly."""

    carrier: Signal
    window: Signal
    t0: float = 0.0

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c, dc, ddc = self.carrier.eval(np.asarray(t, dtype=float) - self.t0)
        c = c - self.carrier.initial
        w, dw, ddw = self.window.eval(t)
        return (self.carrier.initial + w * c, dw * c + w * dc, ddw * c + 2.0 * dw * dc + w * ddc)
