"""Per-user enrolment: fit the recogniser's thresholds to a few seconds of each gesture and of rest.

Input: the recogniser's features (``Features``) on frames the application labelled while it asked
the visitor to hold each gesture and to rest (labels ``point``, ``grasp``, ``pinch``, ``open``,
``rest``). Each condition of each rule (``recognizer.RULES``) is fitted on its own, and the fit
keeps the default unless the user's data shows that it is wrong for this user (the defaults are
chosen on many people; a second or two per gesture is too little to place a threshold afresh):

* positives: the condition's quantity on the gesture's own frames: their median ``m`` (the typical
  held value) and their 95th percentile on the far side ``p`` (the 5th for an "at least" condition),
  so 95 % of the hold lies on the gesture's side of ``p``;
* negatives: the quantity on frames of the other labels that the rule's *other* conditions let
  through (the frames this condition alone must reject); ``n`` is their percentile nearest to the
  gesture (5th or 95th);
* margin: three quarters of the default hysteresis band (``MARGIN_FRACTION``; conditions without a
  stay threshold: of 10 % of the default);
* enter: the default, moved only as far as needed to admit the typical hold (``m`` plus the margin)
  and to reject the negatives (``n`` less the margin), so a wide pinch widens it and a neighbouring
  rest pose tightens it; where ``m`` and ``n`` are closer than two margins, half way between them;
* stay: the default moved down with a tightened enter threshold; above a widened one, half the default
  band (moving the whole band with it let a pinch read at 23 mm, widened to enter at 29 mm, stay on at 37 mm
  through tips parting to a 35 mm near-pinch); widened if needed so that the whole hold (``p`` plus the
  margin) stays, and never closer to the negatives than half the margin;
* when the negatives reach into the hold (``n`` on the gesture's side of ``p``) the condition is
  reported not separable and keeps the default.

Thresholds are kept within the ranges ``GestureSettings`` declares for them. The result is a new
``GestureSettings`` and a report per threshold (old value, new value, ``m``, ``p``, ``n``, how it was
set).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from .recognizer import GESTURES, RULES, Condition, Features, GestureRecognizer, GestureSettings

ENROLMENT_LABELS = (*GESTURES, "rest")
MARGIN_FRACTION = 0.75
"""Margin between a fitted threshold and the data it must admit or reject, as a fraction of the
default hysteresis band (of 10 % of the default threshold where a condition has no stay threshold).
Chosen on the tuning trials 201-220 (60 s each, seeds disjoint from the scored ones): misses and false
starts with enrolment 16, 11, 14, 14 at 0.5, 0.75, 1.0, 1.5 against 17 with the defaults."""
MIN_FRAMES = 20
"""Fewest frames a label needs (about 0.2 s at 90 Hz)."""


class EnrolmentError(ValueError):
    """The labelled data cannot be used (names the label and what was wrong)."""


def _clip(name: str, value: float) -> float:
    """``value`` within the range the settings field ``name`` declares (a strict lower bound is
    kept strict by 1e-6)."""
    bounds = GestureSettings.model_json_schema()["properties"][name]
    lo = max(bounds.get("minimum", -np.inf), bounds.get("exclusiveMinimum", -np.inf) + 1e-6)
    return float(np.clip(value, lo, bounds.get("maximum", np.inf)))


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
    # work in u = sign * value, in which the gesture lies *below* its thresholds
    sign = -1.0 if c.above else 1.0
    u_pos, u_neg = sign * pos, sign * neg
    enter_old = getattr(base, c.enter)
    exit_old = getattr(base, c.exit) if c.exit else None
    e0 = sign * enter_old
    x0 = sign * exit_old if exit_old is not None else None
    band = (x0 - e0) if x0 is not None and x0 > e0 else 0.1 * abs(enter_old)
    margin = MARGIN_FRACTION * band
    m, p = float(np.median(u_pos)), float(np.percentile(u_pos, 95))
    n = float(np.percentile(u_neg, 5)) if len(u_neg) else np.inf
    if n <= p:
        e, x, how = e0, x0, "kept: not separable"
    else:
        margin = min(margin, (n - m) / 2.0)      # a narrow gap: the enter threshold half way
        e = float(np.clip(e0, m + margin, n - margin))
        x = None
        if x0 is not None:
            x = min(max(x0 + min(e - e0, 0.0), e + (x0 - e0) / 2.0, p + margin), n - margin / 2.0)
        if e > e0:
            how = "widened to admit the gesture"
        elif e < e0:
            how = "tightened to reject other labels"
        else:
            how = "kept: default admits the gesture and rejects the others"
        if x is not None and x != x0 and e == e0:
            how += "; stay threshold moved"

    def value(u: float) -> float:
        return float(sign * u)

    out = {c.enter: _clip(c.enter, value(e))}
    fig = {"m": value(m), "p": value(p), "n": value(n) if np.isfinite(n) else None, "how": how}
    report[c.enter] = {"old": enter_old, "new": out[c.enter], **fig}
    if c.exit is not None and x is not None:
        out[c.exit] = _clip(c.exit, value(x))
        report[c.exit] = {"old": exit_old, "new": out[c.exit], **fig}
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
