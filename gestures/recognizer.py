"""Point, grasp, pinch and open from hand frames: continuous values, hysteresis, dwell, events.

Continuous values (every frame), in the vocabulary VR toolkits already speak:

* ``curl`` per finger in [0, 1] (as Unity XR Hands' finger shapes): total flexion over a full curl,
  ``Σφ / curl_full`` (long fingers 250 deg, thumb 120 deg);
* ``grab_strength`` in [0, 1] (as Leap/Ultraleap): the mean curl of the four long fingers;
* ``pinch_strength`` in [0, 1]: 1 with the thumb and index tips ``pinch_full_m`` apart or closer,
  0 from ``pinch_zero_m``; forced to 0 while a grasp is active (grab overrides pinch, so a fist
  never also reads as a pinch, a known complaint about other toolkits).

Discrete gestures, at most one at a time, priority grasp > point > pinch > open:

* ``grasp``: every long finger's curl at least ``grasp_curl_enter`` (stays until one drops below
  ``grasp_curl_exit``);
* ``point``: index curl at most ``point_index_enter`` and middle, ring and little at least
  ``point_others_enter`` (thumb free);
* ``pinch``: thumb and index tips within ``pinch_enter_m`` (stays until beyond ``pinch_exit_m``)
  while middle, ring and little are not curled into a fist and not about to be: their mean curl,
  extrapolated ``PINCH_LOOKAHEAD_S`` (0.15 s) ahead at its current rate, at most
  ``pinch_others_curl_max`` (when a pointing hand closes into a fist the index tip sweeps past the
  thumb tip, which is not a pinch; a closing fist passes the pinch distance while the other fingers
  are still half way), and not closing fast (their mean curl rising by at most
  ``pinch_others_rate_max`` per second), and while the index is not about to curl past a pinch: its curl,
  extrapolated ``PINCH_LOOKAHEAD_S`` ahead at its rate (smoothed as the others'), at most
  ``pinch_index_curl_max`` (a fist whose index and thumb close first passes the pinch distance for
  20-40 ms while the others have barely moved; its index is then still closing fast, a pinching index
  is slowing down at about half curl);
* ``open``: every long finger's curl at most ``open_curl_enter`` and the thumb's at most
  ``open_thumb_enter``.

Separate enter and exit thresholds (hysteresis) and dwell times make the events steady: a gesture
starts once its enter condition has held for ``start_dwell_s`` and ends once its stay condition has
failed for ``end_dwell_s`` (or a higher-priority gesture starts). A grasp also hands over to a pinch at
once (``HANDOVER``): it ends, and the pinch starts, when the pinch's enter condition has held
``start_dwell_s`` while the grasp's stay condition fails, the index's and the other fingers' curl rates are
both at most ``handover_rate_max`` in size (the hand has settled) and the thumb and index tips are not
parting (their distance's rate at most ``handover_tips_parting_max_m_s``). Each gesture is one ``GestureRule``
(``RULES``): thresholded conditions on named quantities, which enrolment (``gestures.enrolment``)
fits per user. A start's confidence is calibrated (``gestures.confidence``): the precision observed
on the intent-labelled benchmark for starts of that gesture and raw strength; its end carries the
same confidence. While pointing, every frame carries the pointing ray:
origin at the index fingertip, direction from the index MCP joint to the fingertip (world frame).
"""
from __future__ import annotations

from collections import deque
from operator import itemgetter
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.protocol.outgoing import GestureDict, GestureStateDict, RayDict

from service.model.openxr import FingerAngles

from .confidence import calibrated_confidence
from .values import (_FLOAT64, _POSITIONS_SHAPE, _RAY_ROWS, STEP_LOOKAHEAD_S, STEP_OUT, STEP_RATE_TAU_S, Values,
                     frame_values, step_kernel, step_table)
from .values import _layout as _values_layout

GESTURES = ("grasp", "point", "pinch", "open")   # priority order
_RANK = {g: k for k, g in enumerate(GESTURES)}
FINGER_ORDER = ("thumb", "index", "middle", "ring", "little")
LONG = ("index", "middle", "ring", "little")
OTHERS = ("middle", "ring", "little")
RATE_TAU_S = 0.03
"""Time constant of the low-pass on the other fingers' curl rate, s."""
PINCH_LOOKAHEAD_S = 0.15
"""How far ahead the mean curl of middle, ring and little is extrapolated (at its current rate) for the
pinch guard against a closing fist, s."""
HANDOVER = ("grasp", "pinch")
"""A gesture that hands over to another once the hand has settled into it (module docstring): a pinch
straight after a fist would otherwise wait for the grasp's end dwell and then its own start dwell, one after
the other, once the fingers have passed the grasp's stay threshold late in their movement. A fist opening
into rest passes a pinch-like pose too, slowing as it goes; its tips are parting there, a pinch's are not."""
HISTORY_FRAMES = 6000
"""Frames of features kept for enrolment (``gestures.enrolment``): about 66 s at 90 Hz."""


class GestureSettings(BaseModel):
    """Per-user gesture thresholds (every field has a unit and a default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    curl_full_long_rad: float = Field(float(np.radians(250.0)), gt=0.0, description="total flexion of a fully curled long finger, rad")
    curl_full_thumb_rad: float = Field(float(np.radians(120.0)), gt=0.0, description="total flexion of a fully curled thumb, rad")
    grasp_curl_enter: float = Field(0.6, ge=0.0, le=1.0, description="grasp starts with every long finger's curl above this")
    grasp_curl_exit: float = Field(0.5, ge=0.0, le=1.0, description="grasp ends when one long finger's curl falls below this "
                                   "(above the 0.43-0.47 of a pinch with the other fingers half curled, which a grasp's "
                                   "stay band must not hold)")
    point_index_enter: float = Field(0.2, ge=0.0, le=1.0, description="index curl at most this to start pointing")
    point_index_exit: float = Field(0.35, ge=0.0, le=1.0, description="pointing ends above this index curl")
    point_others_enter: float = Field(0.6, ge=0.0, le=1.0, description="middle/ring/little curl at least this to start pointing")
    point_others_exit: float = Field(0.45, ge=0.0, le=1.0, description="pointing ends when one of them falls below this")
    pinch_enter_m: float = Field(0.024, gt=0.0, description="pinch starts with the thumb and index tips this close, m")
    pinch_exit_m: float = Field(0.032, gt=0.0, description="pinch ends beyond this tip distance, m")
    pinch_others_curl_max: float = Field(0.65, ge=0.0, le=1.0, description="a pinch starts only while the mean curl of "
                                         "middle, ring and little, extrapolated PINCH_LOOKAHEAD_S ahead at its rate, is at "
                                         "most this (a closing fist sweeps the tips past each other)")
    open_curl_enter: float = Field(0.17, ge=0.0, le=1.0, description="open starts with every long finger's curl below this")
    open_curl_exit: float = Field(0.22, ge=0.0, le=1.0, description="open ends when one long finger's curl exceeds this")
    open_thumb_enter: float = Field(0.3, ge=0.0, le=1.0, description="thumb curl at most this to start open")
    open_thumb_exit: float = Field(0.45, ge=0.0, le=1.0, description="open ends above this thumb curl")
    pinch_others_rate_max: float = Field(2.0, gt=0.0, description="a pinch starts only while the mean curl of middle, "
                                         "ring and little rises no faster than this, 1/s (a hand closing into a fist "
                                         "passes through a pinch-like pose)")
    pinch_index_curl_max: float = Field(0.9, ge=0.0, le=1.0, description="a pinch starts only while the index curl, "
                                        "extrapolated PINCH_LOOKAHEAD_S ahead at its rate, is at most this (an index "
                                        "closing into a fist sweeps past the thumb)")
    handover_rate_max: float = Field(2.0, gt=0.0, description="a grasp hands over to a pinch at once (no end dwell, "
                                     "no second start dwell) when the pinch's enter condition has held its start dwell "
                                     "while the grasp's stay condition fails and the curl rates of the index and of "
                                     "middle, ring and little are both at most this in size, 1/s (the hand has settled "
                                     "into the pinch)")
    handover_tips_parting_max_m_s: float = Field(0.0, ge=0.0, description="the grasp hands over to a pinch only while "
                                                 "the thumb-index tip distance grows no faster than this (its rate "
                                                 "smoothed over RATE_TAU_S), m/s; 0: the tips are not parting (a fist "
                                                 "opening into rest passes a pinch-like pose with its tips parting)")
    pinch_full_m: float = Field(0.015, gt=0.0, description="pinch strength 1 at this tip distance or closer, m")
    pinch_zero_m: float = Field(0.07, gt=0.0, description="pinch strength 0 from this tip distance on, m")
    start_dwell_s: float = Field(0.02, ge=0.0, le=1.0, description="an enter condition must hold this long, s")
    end_dwell_s: float = Field(0.03, ge=0.0, le=1.0, description="a stay condition must fail this long, s")


def _band(value: float, inside: float, outside: float) -> float:
    """0 at the outer threshold, 1 at the inner one and beyond (either direction)."""
    if inside == outside:
        return 1.0
    return min(max((value - outside) / (inside - outside), 0.0), 1.0)     # np.clip's value, NaN kept


def _mean(values: list[float]) -> float:
    """``np.mean`` of a few floats, the same number (summed left to right, then divided) without its call."""
    return sum(values) / len(values)


@dataclass
class Features:
    """What the rules look at, per frame: curl per finger in [0, 1], thumb-index tip distance (m),
    grab strength (mean long-finger curl)."""

    curl: dict[str, float]
    pinch_distance_m: float
    grab_strength: float
    others_curl_rate: float = 0.0
    """Rate of the mean curl of middle, ring and little, 1/s (smoothed over ``RATE_TAU_S``)."""
    index_curl_rate: float = 0.0
    """Rate of the index finger's curl, 1/s (smoothed over ``RATE_TAU_S``)."""

    @staticmethod
    def from_history(entry) -> "Features":
        _, curls, distance, rate, index_rate = entry
        curl = dict(zip(FINGER_ORDER, curls))
        return Features(curl, distance, _mean([curl[f] for f in LONG]), rate, index_rate)


QUANTITIES: dict[str, Callable[[Features], float]] = {
    "long_curl_min": lambda x: min(x.curl[f] for f in LONG),
    "long_curl_max": lambda x: max(x.curl[f] for f in LONG),
    "index_curl": lambda x: x.curl["index"],
    "thumb_curl": lambda x: x.curl["thumb"],
    "others_curl_min": lambda x: min(x.curl[f] for f in OTHERS),
    "others_curl_mean": lambda x: _mean([x.curl[f] for f in OTHERS]),
    "pinch_distance_m": lambda x: x.pinch_distance_m,
    "others_curl_rate": lambda x: x.others_curl_rate,
    "others_curl_ahead": lambda x: _mean([x.curl[f] for f in OTHERS]) + PINCH_LOOKAHEAD_S * x.others_curl_rate,
    "index_curl_ahead": lambda x: x.curl["index"] + PINCH_LOOKAHEAD_S * x.index_curl_rate,
}
"""The scalar quantities the rules threshold, by name (curls dimensionless, distances in metres)."""
assert (STEP_RATE_TAU_S, STEP_LOOKAHEAD_S) == (RATE_TAU_S, PINCH_LOOKAHEAD_S)   # (``values.step_kernel``'s copies)


@dataclass(frozen=True)
class Condition:
    """One thresholded quantity of a rule: it holds while ``quantity`` is on the gesture's side of
    the threshold named ``enter`` (to start) or ``exit`` (to stay; no ``exit``: not checked once
    started). ``ideal`` is the value of a perfectly formed gesture (score 1)."""

    quantity: str
    above: bool                 # True: holds for quantity >= threshold; False: for <=
    enter: str                  # GestureSettings field
    exit: str | None
    ideal: float

    def value(self, x: Features) -> float:
        return QUANTITIES[self.quantity](x)

    def holds(self, x: Features, threshold: float) -> bool:
        v = self.value(x)
        return v >= threshold if self.above else v <= threshold

    def score(self, x: Features, s: "GestureSettings") -> float:
        """How far past the enter threshold toward the ideal, in [0, 1]."""
        return _band(self.value(x), self.ideal, getattr(s, self.enter))


@dataclass(frozen=True)
class GestureRule:
    """A gesture: every condition's enter threshold to start, every stay threshold to stay."""

    name: str
    conditions: tuple[Condition, ...]

    def enters(self, x: Features, s: "GestureSettings") -> bool:
        return all(c.holds(x, getattr(s, c.enter)) for c in self.conditions)

    def stays(self, x: Features, s: "GestureSettings") -> bool:
        return all(c.holds(x, getattr(s, c.exit)) for c in self.conditions if c.exit is not None)

    def score(self, x: Features, s: "GestureSettings") -> float:
        """Raw strength of the gesture in [0, 1]: the weakest condition's :meth:`Condition.score`."""
        return min(c.score(x, s) for c in self.conditions)


_QUANTITY_INDEX = {name: i for i, name in enumerate(QUANTITIES)}


def _quantities(x: Features) -> tuple[float, ...] | None:
    """Every quantity of ``QUANTITIES`` on ``x``, in its order, each computed as its entry there (the
    same operations in the same order: the same numbers); None for a frame without one of the five
    fingers (``_judge`` then asks the rules, whose answer may depend on which quantities they read)."""
    c = x.curl
    if len(c) < 5 or not c.keys() >= _FINGERS:
        return None
    ci, cm, cr, cl = c["index"], c["middle"], c["ring"], c["little"]
    others = _mean([cm, cr, cl])
    return (min(ci, cm, cr, cl), max(ci, cm, cr, cl), ci, c["thumb"], min(cm, cr, cl), others, x.pinch_distance_m,
            x.others_curl_rate, others + PINCH_LOOKAHEAD_S * x.others_curl_rate,
            ci + PINCH_LOOKAHEAD_S * x.index_curl_rate)


_FINGERS = frozenset(FINGER_ORDER)
_ZEROS = (0.0,) * len(FINGER_ORDER)
"""A missing finger's curl in ``history`` (``dict.get``'s default, one per finger)."""


def _rule_table(s: "GestureSettings") -> tuple:
    """``RULES`` with ``s``'s thresholds, in priority order: per gesture its name, its enter and its stay
    conditions as ``(quantity index, above, threshold)`` and its score's terms as ``(quantity index,
    ideal, enter threshold)`` (``Condition.holds``, ``Condition.score``)."""
    return tuple(
        (g, tuple((_QUANTITY_INDEX[c.quantity], c.above, getattr(s, c.enter)) for c in RULES[g].conditions),
         tuple((_QUANTITY_INDEX[c.quantity], c.above, getattr(s, c.exit)) for c in RULES[g].conditions if c.exit is not None),
         tuple((_QUANTITY_INDEX[c.quantity], c.ideal, getattr(s, c.enter)) for c in RULES[g].conditions))
        for g in GESTURES)


def _all_hold(q: tuple[float, ...], conditions: tuple) -> bool:
    """Whether every ``(quantity index, above, threshold)`` holds on the quantities ``q`` (``Condition.holds``)."""
    for i, above, threshold in conditions:
        v = q[i]
        if not (v >= threshold if above else v <= threshold):
            return False
    return True


RULES: dict[str, GestureRule] = {
    "grasp": GestureRule("grasp", (Condition("long_curl_min", True, "grasp_curl_enter", "grasp_curl_exit", 1.0),)),
    "point": GestureRule("point", (Condition("index_curl", False, "point_index_enter", "point_index_exit", 0.0),
                                   Condition("others_curl_min", True, "point_others_enter", "point_others_exit", 1.0))),
    "pinch": GestureRule("pinch", (Condition("pinch_distance_m", False, "pinch_enter_m", "pinch_exit_m", 0.0),
                                   Condition("others_curl_ahead", False, "pinch_others_curl_max", None, 0.0),
                                   Condition("others_curl_rate", False, "pinch_others_rate_max", None, 0.0),
                                   Condition("index_curl_ahead", False, "pinch_index_curl_max", None, 0.0))),
    "open": GestureRule("open", (Condition("long_curl_max", False, "open_curl_enter", "open_curl_exit", 0.0),
                                 Condition("thumb_curl", False, "open_thumb_enter", "open_thumb_exit", 0.0))),
}
"""One rule per gesture, in priority order (``GESTURES``)."""


@dataclass
class GestureRecognizer:
    """Stateful recogniser of one hand (module docstring). ``update(frame)`` returns the frame's
    gesture annotation and the events it caused."""

    settings: GestureSettings = field(default_factory=GestureSettings)
    active: str | None = None
    _candidate: str | None = None
    _candidate_since: float | None = None
    _failing_since: float | None = None
    _confidence: float = 0.0
    _previous: tuple[float, float, float, float] | None = None
    _rate: float = 0.0
    _index_rate: float = 0.0
    _tips_rate: float = 0.0
    _handover_since: float | None = None
    _frame_values: tuple = (None, None)
    """The last frame ``features`` read and its ``Values``."""
    _table: tuple | None = None
    """``(settings, _rule_table(settings))`` of the settings object last used (``GestureSettings`` is frozen:
    other thresholds are another object, which rebuilds the table; one changed in place behind pydantic's
    back would not)."""
    _steps: dict = field(default_factory=dict, repr=False, compare=False)
    """``_step``'s layouts: per finger layout (``AnglesLayout``), the settings object it was made with and what
    ``_step`` needs (``_step_layout``)."""
    history: deque = field(default_factory=lambda: deque(maxlen=HISTORY_FRAMES))
    """``(t, curls in FINGER_ORDER, pinch distance m, others' curl rate 1/s)`` of the latest frames."""

    def features(self, frame) -> Features:
        s = self.settings
        v = frame_values(frame.joint_angles, frame.joints, s.curl_full_long_rad, s.curl_full_thumb_rad,
                         s.pinch_full_m, s.pinch_zero_m)
        self._frame_values = (frame, v)
        return Features(v.curl, v.pinch_distance_m, v.grab_strength)

    @staticmethod
    def ray(frame) -> RayDict | None:
        """The pointing ray along the index finger; ``None`` when the finger has no direction (a
        degenerate geometry would otherwise give a NaN direction)."""
        return frame_values(frame.joint_angles, frame.joints, 1.0, 1.0).ray       # curl scales do not matter

    def _ray(self, frame) -> RayDict | None:
        """``ray(frame)``, from the values ``features`` computed for this frame."""
        seen, values = self._frame_values
        return values.ray if seen is frame else self.ray(frame)

    def _event(self, frame, g: str, kind: Literal["start", "end"], confidence: float) -> GestureDict:
        """The protocol's ``gesture`` event (``protocol.outgoing.Gesture``)."""
        ev: GestureDict = {"type": "gesture", "t": frame.t, "gesture": g, "event": kind, "confidence": round(confidence, 4)}
        if g == "point":
            ev["ray"] = self._ray(frame)
        return ev

    def update(self, frame) -> tuple[GestureStateDict, list[GestureDict]]:
        """The frame's gesture annotation and the events it caused (module docstring). A pipeline frame with
        the five fingers goes through ``values.step_kernel`` (``_step``), any other through ``_update``."""
        if type(frame.joint_angles) is FingerAngles:
            done = self._step(frame)
            if done is not None:
                return done
        return self._update(frame, self._judge)

    def _step(self, frame) -> tuple[GestureStateDict, list[GestureDict]] | None:
        """``_update(frame, self._judge)`` with its values, rates, quantities and rules computed in one
        ``values.step_kernel`` call; ``None`` (nothing done) for a frame without the five fingers or without
        the pipeline's joint array."""
        s = self.settings
        angles = frame.joint_angles
        kept = self._steps
        step = kept.get(angles.layout)
        if step is None or step[0] is not s:
            step = self._step_layout(angles, s)
        if len(step) == 1:
            return None
        _, names, ends, full, long_rows, fingers, table, n, curls_of = step
        positions = getattr(frame.joints, "positions", None)
        if type(positions) is not np.ndarray or positions.dtype is not _FLOAT64 or positions.shape != _POSITIONS_SHAPE:
            return None
        t = frame.t
        out = np.empty(2 * n + 13 + STEP_OUT)
        previous = self._previous
        if previous is None:
            step_kernel(angles.flat, ends, full, positions, _RAY_ROWS, long_rows, fingers, table, float(t), False, 0.0, 0.0,
                        0.0, 0.0, self._rate, self._index_rate, self._tips_rate, out)
        else:
            step_kernel(angles.flat, ends, full, positions, _RAY_ROWS, long_rows, fingers, table, float(t), True, *previous,
                        self._rate, self._index_rate, self._tips_rate, out)
        v = out.tolist()
        b = 2 * n + 13
        others, rate, index_rate, self._tips_rate = v[b:b + 4]
        self._rate, self._index_rate = rate, index_rate
        distance = v[n]
        self._previous = (t, others, v[fingers[1]], distance)
        self.history.append((t, curls_of(v), distance, rate, index_rate))
        active = self.active
        # per gesture in priority order: whether its enter condition holds, its score, whether its stay condition holds
        rules = v[b + 4:b + 4 + 3 * len(GESTURES)]
        rank = _RANK.get(active, len(GESTURES))
        steady = (active is None or rules[3 * rank + 2] == 1.0) and 1.0 not in rules[:3 * rank:3]
        candidates, pinch_enters, stays = [], False, True
        if not steady:              # (else ``_advance_steady``, which needs none of them)
            for k, g in enumerate(GESTURES):
                if rules[3 * k] == 1.0:
                    candidates.append((g, rules[3 * k + 1]))
                    pinch_enters = pinch_enters or g == HANDOVER[1]
                if g == active:
                    stays = rules[3 * k + 2] == 1.0
        curl = dict(zip(names, v[:n]))
        ray = {"origin": v[n + 3:n + 6], "direction": v[n + 6:n + 9]} if v[n + 2] == 1.0 else None
        if v[2 * n + 12] == 1.0:
            rounded = (dict(zip(names, v[n + 10:2 * n + 10])), v[2 * n + 10], v[2 * n + 11])
            self._frame_values = (frame, Values(curl, distance, v[n + 1], ray, rounded))
        else:                       # (``round4_into`` left some to Python's ``round``, as ``_update``)
            self._frame_values = (frame, Values(curl, distance, v[n + 1], ray))
            rounded = ({f: round(c, 4) for f, c in curl.items()}, round(v[n + 1], 4),
                       round(_band(distance, s.pinch_full_m, s.pinch_zero_m), 4))
        if steady:
            return self._advance_steady(frame, rounded)
        return self._advance(frame, t, candidates, pinch_enters, stays, rounded)

    def _advance_steady(self, frame, rounded: tuple) -> tuple[GestureStateDict, list[GestureDict]]:
        """``_advance`` on a frame that changes no gesture (most frames): none is active and none enters, or the
        active one stays and none of a higher priority enters. Its candidate is let go, its stay condition's
        and handover's clocks stopped (the active one's), and no event is made; the annotation is ``_advance``'s."""
        active = self.active
        self._candidate = self._candidate_since = None
        if active is not None:
            self._failing_since = self._handover_since = None
        annotation: GestureStateDict = {
            "active": active,
            "curl": rounded[0],
            "grab_strength": rounded[1],
            "pinch_strength": 0.0 if active == "grasp" else rounded[2],
        }
        if active == "point":
            annotation["ray"] = self._ray(frame)
        return annotation, []

    def _step_layout(self, angles, s: "GestureSettings") -> tuple:
        """What ``_step`` needs of a finger layout and settings, kept in ``_steps`` (only the settings where
        the layout lacks one of the five fingers)."""
        kept = self._steps
        if len(kept) > 16:
            kept.clear()
        names = angles.layout.names
        if not _FINGERS <= set(names):
            step = kept[angles.layout] = (s,)
            return step
        table = self._table
        if table is None or table[0] is not s:
            table = self._table = (s, _rule_table(s))
        names_, ends, full, long_rows, n_angles = _values_layout(angles, s.curl_full_long_rad, s.curl_full_thumb_rad,
                                                                 s.pinch_full_m, s.pinch_zero_m)
        fingers = [names.index(f) for f in FINGER_ORDER]
        step = kept[angles.layout] = (s, names_, ends, full, long_rows, np.array(fingers, dtype=np.int64),
                                      step_table(table[1]), len(names_), itemgetter(*fingers))
        return step

    def update_reference(self, frame) -> tuple[GestureStateDict, list[GestureDict]]:
        """``update`` with every rule evaluated by its ``GestureRule`` (``enters``, ``stays``, ``score``
        through ``QUANTITIES``): the definition ``update``'s rule table is tested equal to."""
        return self._update(frame, self._judge_reference)

    def _judge_reference(self, x: Features, s: GestureSettings) -> tuple[list[tuple[str, float]], bool, bool]:
        """The rules on ``x``: the gestures whose enter condition holds with their scores (priority
        order), whether the pinch's holds, and whether the active gesture's stay condition holds."""
        candidates = [(g, RULES[g].score(x, s)) for g in GESTURES if RULES[g].enters(x, s)]
        pinch = any(g == HANDOVER[1] for g, _ in candidates)
        return candidates, pinch, self.active is None or RULES[self.active].stays(x, s)

    def _judge(self, x: Features, s: GestureSettings) -> tuple[list[tuple[str, float]], bool, bool]:
        """``_judge_reference`` from each quantity computed once (``_quantities``) and the rules'
        thresholds read once per settings object (``_rule_table``), without a call per condition."""
        q = _quantities(x)
        if q is None:
            return self._judge_reference(x, s)
        kept = self._table
        if kept is None or kept[0] is not s:
            kept = self._table = (s, _rule_table(s))
        candidates, pinch, stays = [], False, True
        for g, enter, stay, score in kept[1]:
            if _all_hold(q, enter):
                candidates.append((g, min([_band(q[i], ideal, threshold) for i, ideal, threshold in score])))
                pinch = pinch or g == HANDOVER[1]
            if g == self.active:
                stays = _all_hold(q, stay)
        return candidates, pinch, stays

    def _update(self, frame, judge) -> tuple[GestureStateDict, list[GestureDict]]:
        s = self.settings
        x = self.features(frame)
        t = frame.t
        curl = x.curl
        others = _mean([curl[finger] for finger in OTHERS])               # (``QUANTITIES["others_curl_mean"]``)
        if self._previous is not None and t > self._previous[0]:
            dt = t - self._previous[0]
            k = dt / (dt + RATE_TAU_S)           # first-order low-pass of the finite difference
            self._rate += k * ((others - self._previous[1]) / dt - self._rate)
            self._index_rate += k * ((x.curl["index"] - self._previous[2]) / dt - self._index_rate)
            self._tips_rate += k * ((x.pinch_distance_m - self._previous[3]) / dt - self._tips_rate)
        self._previous = (t, others, x.curl["index"], x.pinch_distance_m)
        x.others_curl_rate, x.index_curl_rate = self._rate, self._index_rate
        self.history.append((t, tuple(map(x.curl.get, FINGER_ORDER, _ZEROS)), x.pinch_distance_m, self._rate,
                             self._index_rate))
        # candidates for starting: the highest-priority enter condition that holds
        candidates, pinch_enters, stays = judge(x, s)
        seen, values = self._frame_values
        rounded = values.rounded if seen is frame else None
        if rounded is None:         # not rounded by the kernel (``gestures.values.round4_into``): Python's ``round``
            rounded = ({f: round(v, 4) for f, v in x.curl.items()}, round(x.grab_strength, 4),
                       round(_band(x.pinch_distance_m, s.pinch_full_m, s.pinch_zero_m), 4))
        return self._advance(frame, t, candidates, pinch_enters, stays, rounded)

    def _advance(self, frame, t: float, candidates: list, pinch_enters: bool, stays: bool,
                 rounded: tuple) -> tuple[GestureStateDict, list[GestureDict]]:
        """The state machine on one frame's judgement (``_update``): its annotation (``rounded``: its curls,
        grab strength and pinch band, rounded) and events."""
        s = self.settings
        events: list[GestureDict] = []
        best = candidates[0] if candidates else None
        higher = best is not None and self.active is not None and GESTURES.index(best[0]) < GESTURES.index(self.active)
        if best is not None and (self.active is None or higher):
            if self._candidate != best[0]:
                self._candidate, self._candidate_since = best[0], t
        else:
            self._candidate, self._candidate_since = None, None
        # end the active gesture: its stay condition failed long enough, or a higher one takes over,
        # or (a grasp) it hands over to a pinch the hand has settled into
        if self.active is not None:
            if stays:
                self._failing_since = None
            elif self._failing_since is None:
                self._failing_since = t
            if self.active == HANDOVER[0] and not stays and pinch_enters \
                    and abs(self._rate) <= s.handover_rate_max and abs(self._index_rate) <= s.handover_rate_max \
                    and self._tips_rate <= s.handover_tips_parting_max_m_s:
                if self._handover_since is None:
                    self._handover_since = t
            else:
                self._handover_since = None
            takeover = higher and self._candidate_since is not None and t - self._candidate_since >= s.start_dwell_s - 1e-9
            handover = self._handover_since is not None and t - self._handover_since >= s.start_dwell_s - 1e-9
            if takeover or handover or (self._failing_since is not None and t - self._failing_since >= s.end_dwell_s - 1e-9):
                events.append(self._event(frame, self.active, "end", self._confidence))
                self.active, self._failing_since = None, None
                if handover:           # the pinch's start dwell has already held: it starts on this frame
                    self._candidate, self._candidate_since = HANDOVER[1], self._handover_since
                self._handover_since = None
        # start the candidate once it has held long enough
        if self.active is None and self._candidate is not None and self._candidate_since is not None \
                and t - self._candidate_since >= s.start_dwell_s - 1e-9:
            conf = calibrated_confidence(self._candidate, dict(candidates).get(self._candidate, 0.0))
            self._confidence = conf
            self.active = self._candidate
            self._candidate, self._candidate_since, self._failing_since = None, None, None
            events.append(self._event(frame, self.active, "start", conf))
        annotation: GestureStateDict = {
            "active": self.active,
            "curl": rounded[0],
            "grab_strength": rounded[1],
            "pinch_strength": 0.0 if self.active == "grasp" else rounded[2],
        }
        if self.active == "point":
            annotation["ray"] = self._ray(frame)
        return annotation, events
