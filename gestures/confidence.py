"""Calibrated gesture confidence: how often a start like this one was what the visitor meant.

A start's raw strength is its rule's score on the frame it fires (``GestureRule.score``: how far past
the enter threshold toward the ideal pose the weakest condition is, in [0, 1]). Starts fire soon
after the threshold is crossed, so raw strengths are small and say little on their own (a start
event used to carry them as its confidence: 0.03 for a perfectly good pinch).

The confidence a start carries is instead the *observed precision* of starts of that gesture with a
raw strength in the same bin, measured on intent-labelled benchmark trials (``fingertrack bench
gestures``; fitted on the trials in ``FIT_SEEDS`` and checked on the others, whose reliability table
the benchmark prints): a confidence of 0.9 means that 9 in 10 such starts matched an intended
gesture within the onset window. Precision per bin is Laplace-smoothed, ``(matched + 1) / (n + 2)``.
An end event carries the confidence of the start it ends.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

RAW_EDGES = (0.05, 0.15)
"""Raw-strength bin edges: bins ``[0, 0.05)``, ``[0.05, 0.15)``, ``[0.15, 1]``."""
FIT_SEEDS = (201, 202, 203, 204)
"""Trials the table was fitted on (``bench gestures`` trials of 60 s with these seeds): tuning trials,
disjoint from the full run's (1-12) and the quick run's (101, 102), so every scored trial is held out."""

CONFIDENCE_TABLE: dict[str, tuple[float, float, float]] = {
    "grasp": (0.5, 0.875, 0.95),
    "point": (0.5, 0.5, 0.958),
    "pinch": (0.667, 0.923, 0.917),
    "open": (0.5, 0.75, 0.955),
}
"""Observed precision per gesture and raw-strength bin (``fit_table`` on ``FIT_SEEDS``)."""


def raw_bin(raw: float) -> int:
    return int(np.searchsorted(RAW_EDGES, raw, side="right"))


def calibrated_confidence(gesture: str, raw: float) -> float:
    """The confidence of a ``gesture`` start with raw strength ``raw`` (module docstring)."""
    return CONFIDENCE_TABLE[gesture][raw_bin(raw)]


def fit_table(starts: Iterable[tuple[str, float, bool]]) -> dict[str, tuple[float, ...]]:
    """Observed precision per gesture and bin from ``(gesture, raw strength, matched)`` starts."""
    counts: dict[str, np.ndarray] = {g: np.zeros((len(RAW_EDGES) + 1, 2)) for g in CONFIDENCE_TABLE}
    for g, raw, ok in starts:
        counts[g][raw_bin(raw)] += (1.0, float(ok))
    return {g: tuple(round(float((c[b, 1] + 1.0) / (c[b, 0] + 2.0)), 3) for b in range(len(c)))
            for g, c in counts.items()}
