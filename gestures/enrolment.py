"""Per-user enrolment: fit the recogniser's thresholds to a few seconds of each gesture and of rest.

Input: the recogniser's features (``Features``) on frames the application labelled while it asked
the visitor to hold each gesture and to rest (labels ``point``, ``grasp``, ``pinch``, ``open``,
``rest``). Each condition of each rule (``recognizer.RULES``) is fitted on its own:

* positives: the condition's quantity on the gesture's own frames; ``p`` is their 5th percentile
  on the gesture's side (the 95th for a "at most" condition), so 95 % of the user's gesture passes;
* negatives: the quantity on frames of the other labels that the rule's *other* conditions let
  through (the frames this condition alone must reject), beyond ``p``; ``n`` is the percentile of
  them nearest to ``p`` (5th or 95th);
* the enter threshold goes ``ENTER_FRACTION`` (35 %) of the way from ``p`` to ``n``, the stay
  threshold ``EXIT_FRACTION`` (65 %) of the way (hysteresis between them);
* without negatives the threshold is only widened if needed, to admit ``p`` with the default
  hysteresis band as the margin; if positives and negatives overlap the default is kept and the
  condition is reported as not separable.

Thresholds are clipped to their valid ranges. The result is a new ``GestureSettings`` and a report
per threshold (old value, new value, ``p``, ``n``, how it was set).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from .recognizer import GESTURES, RULES, Condition, Features, GestureRecognizer, GestureSettings

ENROLMENT_LABELS = (*GESTURES, "rest")
ENTER_FRACTION = 0.35
EXIT_FRACTION = 0.65
MIN_FRAMES = 20
"""Fewest frames a label needs (about 0.2 s at 90 Hz)."""


class EnrolmentError(ValueError):
    """The labelled data cannot be used (names the label and what was wrong)."""


def _clip(field: str, value: float) -> float:
    if field.endswith("_m"):
        return float(max(value, 1e-3))
    return float(np.clip(value, 0.0, 1.0))


def fit_thresholds(samples: Mapping[str, Sequence[Features]],
                   base: GestureSettings | None = None) -> tuple[GestureSettings, dict]:
    """Thresholds fitted to the labelled ``samples`` (module docstring), starting from ``base``."""
    base = base or GestureSettings()
    unknown = set(samples) - set(ENROLMENT_LABELS)
    if unknown:
        raise EnrolmentError(f"enrolment: unknown labels {sorted(unknown)}; expected {list(ENROLMENT_LABELS)}")
    for label in ENROLMENT_LABELS:
        n = len(samples.get(label, ()))
        if n < MIN_FRAMES:
            raise EnrolmentError(f"enrolment: label {label!r} has {n} frames, needs at least {MIN_FRAMES}")
    new: dict[str, float] = {}
    report: dict[str, dict] = {}
    for g in GESTURES:
        rule = RULES[g]
        for c in rule.conditions:
            others = [o for o in rule.conditions if o is not c]
            pos = np.array([c.value(x) for x in samples[g]])
            neg = np.array([c.value(x) for label, xs in samples.items() if label != g for x in xs
                            if all(o.holds(x, getattr(base, o.enter)) for o in others)])
            new.update(_fit_condition(c, pos, neg, base, report))
    fitted = base.model_copy(update=new)
    return GestureSettings(**fitted.model_dump()), report


def _fit_condition(c: Condition, pos: np.ndarray, neg: np.ndarray, base: GestureSettings,
                   report: dict) -> dict[str, float]:
    sign = 1.0 if c.above else -1.0            # +1: the gesture lies above the threshold
    p = float(np.percentile(pos, 5 if c.above else 95))
    beyond = neg[sign * (p - neg) > 0]           # negatives on the far side of p
    enter_old = getattr(base, c.enter)
    exit_old = getattr(base, c.exit) if c.exit else None
    band = abs(exit_old - enter_old) if exit_old is not None else 0.1 * abs(enter_old)
    n_nearest = float(np.percentile(beyond, 95 if c.above else 5)) if len(beyond) else None
    overlap = len(neg) > 0 and float(np.mean(sign * (neg - p) >= 0)) > 0.05
    if overlap:
        enter, exit_, how = enter_old, exit_old, "kept: not separable"
    elif n_nearest is not None:
        enter = p + ENTER_FRACTION * (n_nearest - p)
        exit_ = p + EXIT_FRACTION * (n_nearest - p) if exit_old is not None else None
        how = "between gesture and nearest non-gesture"
    else:
        # nothing to reject on this side: only widen, to admit p with the default band as margin
        enter = min(enter_old, p - band) if c.above else max(enter_old, p + band)
        exit_ = (enter - band if c.above else enter + band) if exit_old is not None else None
        how = "widened to admit the gesture" if enter != enter_old else "kept: default admits the gesture"
    out = {c.enter: _clip(c.enter, enter)}
    report[c.enter] = {"old": enter_old, "new": out[c.enter], "p": p, "n": n_nearest, "how": how}
    if c.exit is not None and exit_ is not None:
        out[c.exit] = _clip(c.exit, exit_)
        report[c.exit] = {"old": exit_old, "new": out[c.exit], "p": p, "n": n_nearest, "how": how}
    return out


def samples_from_history(recognizer: GestureRecognizer, segments: Sequence[Mapping]) -> dict[str, list[Features]]:
    """The recogniser's recent features inside labelled segments ``{"label", "start_s", "end_s"}``
    (source clock, s), keyed by label. Raises ``EnrolmentError`` naming a bad segment."""
    samples: dict[str, list[Features]] = {}
    for i, seg in enumerate(segments):
        try:
            label, a, b = seg["label"], float(seg["start_s"]), float(seg["end_s"])
        except (KeyError, TypeError, ValueError):
            raise EnrolmentError(f"enrolment: segments[{i}] needs label, start_s and end_s (seconds), got {seg!r}") from None
        if label not in ENROLMENT_LABELS:
            raise EnrolmentError(f"enrolment: segments[{i}].label {label!r} is not one of {list(ENROLMENT_LABELS)}")
        if not (np.isfinite(a) and np.isfinite(b) and a < b):
            raise EnrolmentError(f"enrolment: segments[{i}] needs finite start_s < end_s, got {a}, {b}")
        samples.setdefault(label, []).extend(Features.from_history(e) for e in recognizer.history if a <= e[0] < b)
    return samples


def enrol(recognizer: GestureRecognizer, segments: Sequence[Mapping],
          base: GestureSettings | None = None) -> tuple[GestureSettings, dict]:
    """Fit thresholds to the labelled segments of the recogniser's recent frames (does not apply them)."""
    return fit_thresholds(samples_from_history(recognizer, segments), base or recognizer.settings)
