"""The recogniser's continuous values of one frame (``gestures.recognizer``): curl per finger, the
thumb-index tip distance, grab strength and the pointing ray, in one compiled call.

A frame has five fingers' angles and 26 joint positions; computed with numpy, each value is a handful
of calls on three-element arrays, whose per-call cost is the whole cost. ``frame_values`` packs the
frame once and runs ``values_kernel`` (numba, cached where a writable cache folder exists,
``service.numba_cache_dir``; compiled ahead of serving with the pipeline's kernels,
``service.estimators.warm``). ``reference_values`` is the same computation in numpy,
the definition the kernel is tested against (``tests/test_gesture_values.py``); the kernel keeps its
order of operations (a sum left to right, the norm as the square root of a dot product), so the two
agree to the last bit, not just within tolerance.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from service import JIT_CACHE
from service.model.openxr import JOINT_NAMES, FingerAngles

FINGER_ORDER = ("thumb", "index", "middle", "ring", "little")
LONG = ("index", "middle", "ring", "little")
RAY_JOINTS = ("thumb_tip", "index_tip", "index_proximal")
"""The joints the values read: the pinch is between the first two, the ray runs from the third to the second."""
RAY_MIN_LENGTH_M = 1e-9
"""A pointing ray needs the index finger this long at least (else its direction is undefined), m."""


class Values(NamedTuple):
    """A frame's continuous values: ``curl`` per finger of the frame in [0, 1], ``pinch_distance_m``,
    ``grab_strength`` (mean curl of the long fingers) and the pointing ray (``None`` where the index
    finger has no direction)."""

    curl: dict[str, float]
    pinch_distance_m: float
    grab_strength: float
    ray: dict | None
    rounded: tuple | None = None
    """``frame_values``' only: what a frame's gesture annotation writes, each ``round(value, 4)`` (the curls as
    a dict like ``curl``, the grab strength and the pinch strength before a grasp forces it to 0: the band of
    the tip distance between ``pinch_zero_m`` and ``pinch_full_m``); ``None`` where the kernel left a value to
    Python's ``round`` (``round4_into``)."""


def reference_values(joint_angles, joints, curl_full_long_rad: float, curl_full_thumb_rad: float,
                     pinch_full_m: float = 1.0, pinch_zero_m: float = 1.0) -> Values:
    """The values in numpy: ``Σφ / curl_full`` clipped to [0, 1] per finger; the norm of the
    thumb-to-index tip difference; the mean curl of ``LONG``; the ray from the index MCP joint to its
    tip (origin at the tip) when the finger is longer than ``RAY_MIN_LENGTH_M`` and its tip finite.
    No ``rounded`` annotation (the recogniser then rounds with Python's ``round``; the pinch band's ends
    are not needed)."""
    curl = {}
    for f, phi in joint_angles.items():
        full = curl_full_thumb_rad if f == "thumb" else curl_full_long_rad
        curl[f] = float(np.clip(np.sum(phi) / full, 0.0, 1.0))
    tip_t = joints["thumb_tip"][0]
    tip_i = joints["index_tip"][0]
    base = joints["index_proximal"][0]
    d = tip_i - base
    norm = float(np.linalg.norm(d))
    with np.errstate(invalid="ignore", divide="ignore"):     # an infinite MCP joint: a NaN direction, as the kernel's
        ray = {"origin": tip_i.tolist(), "direction": (d / norm).tolist()} \
            if norm > RAY_MIN_LENGTH_M and np.all(np.isfinite(tip_i)) else None
    return Values(curl, float(np.linalg.norm(tip_t - tip_i)), float(np.mean([curl[f] for f in LONG])), ray)


ROUND_SCALE = 1e4
"""The gesture annotation's values are written to 4 decimals (``round(x, 4)``)."""


@numba.njit(cache=JIT_CACHE)
def round4_into(values, out):  # pragma: no cover - compiled
    """``out[i] = round(values[i], 4)``, the very float Python's ``round`` gives, for every value where that is
    certain without its decimal arithmetic; returns False if some value is left to ``round`` (``out[i]`` then
    unset). Python rounds the exact binary value e = x·10⁴ to the nearest integer k (half to even) and returns
    the float nearest to k/10⁴. Here ``y = x·10⁴`` is rounded to a float, but rounding is monotonic and every
    halfway point h = j + 1/2 with |h| < 10⁷ is a float, so e < h gives y <= h and e > h gives y >= h: where
    ``k = floor(y + 0.5)`` leaves ``d = y - k`` (exact: |y| < 10⁷ and |d| <= 1/2 + an ulp) strictly inside
    (-1/2, 1/2), k - 1/2 < e < k + 1/2 too, k is e's nearest integer and no tie rule applies, and
    ``k / 10⁴``, the correctly rounded quotient of two exact floats, is the float nearest to k/10⁴. The sign
    of a zero is ``x``'s, as Python's. Everything else (y on a halfway point, |y| >= 10⁷, NaN, infinities) is
    left to ``round``."""
    ok = True
    for i in range(values.shape[0]):
        x = values[i]
        y = x * ROUND_SCALE
        if -1e7 < y < 1e7:
            k = np.floor(y + 0.5)
            d = y - k
            if -0.5 < d < 0.5:
                out[i] = math.copysign(k / ROUND_SCALE, x)
                continue
        ok = False
    return ok


@numba.njit(cache=JIT_CACHE)
def values_kernel(phi, ends, full, positions, rows, long_fingers, out):  # pragma: no cover - compiled
    """``out[:n]`` the curls of the ``n = len(ends)`` fingers (finger ``k``'s angles are
    ``phi[ends[k-1]:ends[k]]``, its full curl ``full[k]``); then the tip distance, the mean curl of
    the fingers ``long_fingers``, 1.0 if the ray exists (else 0.0), its origin and direction; the
    joints are ``positions[rows[0]]`` (thumb tip), ``positions[rows[1]]`` (index tip),
    ``positions[rows[2]]`` (index MCP). The order of operations is ``reference_values``'. Then, at
    ``n + 9``, the pinch band of the tip distance (the recogniser's ``_band`` between ``full[n + 1]``, its
    zero, and ``full[n]``, its full strength), and from ``n + 10`` the curls, the mean and the band each
    rounded to 4 decimals (``round4_into``), with 1.0 after them if all were (else 0.0)."""
    n = ends.shape[0]
    start = 0
    for k in range(n):
        s = 0.0                  # from 0.0 and left to right, as numpy's sum of a few terms
        for j in range(start, ends[k]):
            s += phi[j]
        c = s / full[k]
        if c < 0.0:              # a NaN passes, as through np.clip
            c = 0.0
        elif c > 1.0:
            c = 1.0
        out[k] = c
        start = ends[k]
    tip_t = positions[rows[0]]
    tip_i = positions[rows[1]]
    base = positions[rows[2]]
    pinch = tip_t - tip_i
    out[n] = math.sqrt(np.dot(pinch, pinch))
    g = 0.0
    for k in long_fingers:
        g += out[k]
    out[n + 1] = g / long_fingers.shape[0]
    d = tip_i - base
    norm = math.sqrt(np.dot(d, d))
    ok = norm > RAY_MIN_LENGTH_M
    for i in range(3):
        ok = ok and math.isfinite(tip_i[i])
    out[n + 2] = 1.0 if ok else 0.0
    for i in range(3):
        out[n + 3 + i] = tip_i[i]
        out[n + 6 + i] = d[i] / norm if ok else 0.0
    inside, outside = full[n], full[n + 1]
    band = 1.0
    if inside != outside:                   # min(max(b, 0.0), 1.0) as Python's: a NaN and a -0.0 are kept
        band = (out[n] - outside) / (inside - outside)
        if 0.0 > band:
            band = 0.0
        if 1.0 < band:
            band = 1.0
    out[n + 9] = band
    out[n + 10:n + 10 + n] = out[:n]
    out[2 * n + 10] = out[n + 1]
    out[2 * n + 11] = band
    rounded = out[n + 10:2 * n + 12]
    out[2 * n + 12] = 1.0 if round4_into(rounded, rounded) else 0.0


_ROWS_CACHE: dict = {}


def _layout(joint_angles, curl_full_long_rad: float, curl_full_thumb_rad: float, pinch_full_m: float,
            pinch_zero_m: float):
    """The kernel's finger layout of a frame (finger names, angle ends, full curls then the pinch band's
    ends, long-finger rows, the number of angles), kept per distinct layout."""
    key = (tuple(joint_angles), tuple(map(len, joint_angles.values())), curl_full_long_rad, curl_full_thumb_rad,
           pinch_full_m, pinch_zero_m)
    layout = _ROWS_CACHE.get(key)
    if layout is None:
        names = list(key[0])
        ends = np.cumsum(key[1]).astype(np.int64)
        full = np.array([curl_full_thumb_rad if f == "thumb" else curl_full_long_rad for f in names]
                        + [pinch_full_m, pinch_zero_m])
        row_of = {f: k for k, f in enumerate(names)}
        long_rows = np.array([row_of[f] for f in LONG], dtype=np.int64)     # KeyError as the reference
        layout = _ROWS_CACHE[key] = (names, ends, full, long_rows, sum(key[1]))
        if len(_ROWS_CACHE) > 64:                # bounded: settings change rarely
            _ROWS_CACHE.pop(next(iter(_ROWS_CACHE)))
    return layout


def _flat_angles(joint_angles, n: int) -> np.ndarray:
    """Every finger's angles in one float64 array of ``n``, finger after finger: one ``concatenate`` of the
    arrays as they are when that already gives it (the pipeline's float64 vectors), else each made a
    float64 vector first."""
    if not joint_angles:
        return np.zeros(0)
    try:
        phi = np.concatenate(tuple(joint_angles.values()))
    except ValueError:
        phi = None
    if phi is None or phi.dtype != np.float64 or phi.shape != (n,):
        phi = np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in joint_angles.values()])
    return phi


def frame_values(joint_angles, joints, curl_full_long_rad: float, curl_full_thumb_rad: float,
                 pinch_full_m: float = 1.0, pinch_zero_m: float = 1.0) -> Values:
    """``reference_values`` in one ``values_kernel`` call, with the ``rounded`` annotation (its pinch band
    between ``pinch_zero_m`` and ``pinch_full_m``). ``joint_angles`` is the pipeline's ``FingerAngles``
    (its one array is read as it is) or any mapping of finger name to angles; ``joints`` the pipeline's
    ``JointPoses`` (its positions array is read as it is) or any mapping of joint name to
    ``(position, orientation)``. A frame without the long fingers or the joints raises ``KeyError``
    like the reference."""
    if type(joint_angles) is FingerAngles:
        key = (joint_angles.layout, curl_full_long_rad, curl_full_thumb_rad, pinch_full_m, pinch_zero_m)
        kept = _KEPT.get(key)
        if kept is None:
            kept = _keep(key, _layout(joint_angles, curl_full_long_rad, curl_full_thumb_rad, pinch_full_m, pinch_zero_m))
        names, ends, full, long_rows, n_angles = kept
        phi = joint_angles.flat
    else:
        names, ends, full, long_rows, n_angles = _layout(joint_angles, curl_full_long_rad, curl_full_thumb_rad,
                                                         pinch_full_m, pinch_zero_m)
        phi = _flat_angles(joint_angles, n_angles)
    positions = getattr(joints, "positions", None)        # the pipeline's JointPoses: rows in JOINT_NAMES order
    if type(positions) is np.ndarray and positions.dtype is _FLOAT64 and positions.shape == _POSITIONS_SHAPE:
        rows = _RAY_ROWS
    else:
        positions = np.array([joints[j][0] for j in RAY_JOINTS], dtype=np.float64)
        rows = _FIRST_THREE
    n = len(names)
    out = np.empty(2 * n + 13)
    values_kernel(phi, ends, full, positions, rows, long_rows, out)
    v = out.tolist()
    ray = {"origin": v[n + 3:n + 6], "direction": v[n + 6:n + 9]} if v[n + 2] == 1.0 else None
    rounded = (dict(zip(names, v[n + 10:2 * n + 10])), v[2 * n + 10], v[2 * n + 11]) if v[2 * n + 12] == 1.0 else None
    return Values(dict(zip(names, v[:n])), v[n], v[n + 1], ray, rounded)


_KEPT: dict = {}
"""``_layout``'s answer per ``FingerAngles`` layout and settings (a dict lookup, no key built from the angles)."""


def _keep(key, layout):
    if len(_KEPT) > 64:                          # bounded: settings change rarely
        _KEPT.pop(next(iter(_KEPT)))
    _KEPT[key] = layout
    return layout


_FLOAT64 = np.dtype(np.float64)
_POSITIONS_SHAPE = (len(JOINT_NAMES), 3)


_FIRST_THREE = np.arange(3, dtype=np.int64)
_RAY_ROWS = np.array([JOINT_NAMES.index(j) for j in RAY_JOINTS], dtype=np.int64)


# -- the recogniser's step in one call ----------------------------------------------------------------------
# ``GestureRecognizer.update`` on a pipeline frame: ``values_kernel``'s values, then what ``_update`` and
# ``_judge`` compute from them in Python (the other fingers' mean curl, the low-passed rates, the quantities of
# ``recognizer.QUANTITIES``, each rule's enter, score and stay), the same operations in the same order (the
# same numbers: ``tests/test_gesture_values.py`` checks ``update`` against ``update_reference``, whose every
# condition goes through its ``GestureRule``). The recogniser's state machine reads the results.

STEP_RATE_TAU_S = 0.03
"""``recognizer.RATE_TAU_S`` (the kernel's copy, checked equal there)."""
STEP_LOOKAHEAD_S = 0.15
"""``recognizer.PINCH_LOOKAHEAD_S`` (the kernel's copy, checked equal there)."""
STEP_RULES = 4
"""Rules in a step table (``recognizer.GESTURES``)."""
STEP_TERMS = 4
"""The most conditions of one rule."""
STEP_OUT = 4 + 3 * STEP_RULES
"""What ``step_kernel`` writes after ``values_kernel``'s ``2n + 13`` values."""


@numba.njit(cache=JIT_CACHE, inline="always")
def _min_first(a, b):  # pragma: no cover - compiled
    """Python's ``min(a, b)``: ``b`` only if ``b < a`` (a NaN first stays, a NaN second is passed over)."""
    return b if b < a else a


@numba.njit(cache=JIT_CACHE, inline="always")
def _max_first(a, b):  # pragma: no cover - compiled
    """Python's ``max(a, b)``: ``b`` only if ``b > a``."""
    return b if b > a else a


@numba.njit(cache=JIT_CACHE)
def step_kernel(phi, ends, full, positions, rows, long_fingers, fingers, table, t, has_previous, previous_t,
                previous_others, previous_index, previous_pinch, rate, index_rate, tips_rate, out):  # pragma: no cover - compiled
    """``values_kernel`` into ``out[:2n + 13]``, then from ``b = 2n + 13``: the mean curl of middle, ring and
    little, the three low-passed rates (others', index's, tips'; updated from the previous frame's values when
    ``has_previous`` and ``t`` is later than ``previous_t``), and per rule ``g`` of ``table`` (priority order)
    at ``b + 4 + 3g``: 1.0 if its enter condition holds (else 0.0), its score (0.0 where it does not enter) and
    1.0 if its stay condition holds. ``fingers``: the rows in ``out`` of the curls of thumb, index, middle,
    ring and little. ``table[g, kind]`` (kind 0 enter, 1 stay, 2 score): ``table[g, kind, 0, 0]`` terms, then
    term ``c`` at ``table[g, kind, 1 + c]``: quantity index, above (1.0) or below (0.0) or the ideal, the
    threshold."""
    values_kernel(phi, ends, full, positions, rows, long_fingers, out)
    n = ends.shape[0]
    b = 2 * n + 13
    ct, ci, cm, cr, cl = out[fingers[0]], out[fingers[1]], out[fingers[2]], out[fingers[3]], out[fingers[4]]
    others = (((0.0 + cm) + cr) + cl) / 3.0          # (``_mean``: Python's sum from 0, then divided by 3)
    distance = out[n]
    if has_previous and t > previous_t:
        dt = t - previous_t
        k = dt / (dt + STEP_RATE_TAU_S)
        rate += k * ((others - previous_others) / dt - rate)
        index_rate += k * ((ci - previous_index) / dt - index_rate)
        tips_rate += k * ((distance - previous_pinch) / dt - tips_rate)
    out[b] = others
    out[b + 1] = rate
    out[b + 2] = index_rate
    out[b + 3] = tips_rate
    q = np.empty(10)                                 # ``recognizer._quantities``, in ``QUANTITIES``' order
    q[0] = _min_first(_min_first(_min_first(ci, cm), cr), cl)
    q[1] = _max_first(_max_first(_max_first(ci, cm), cr), cl)
    q[2] = ci
    q[3] = ct
    q[4] = _min_first(_min_first(cm, cr), cl)
    q[5] = others
    q[6] = distance
    q[7] = rate
    q[8] = others + STEP_LOOKAHEAD_S * rate
    q[9] = ci + STEP_LOOKAHEAD_S * index_rate
    for g in range(table.shape[0]):
        at = b + 4 + 3 * g
        for kind in range(2):                        # enter, stay: every condition holds (``_all_hold``)
            holds = True
            for c in range(int(table[g, kind, 0, 0])):
                v = q[int(table[g, kind, 1 + c, 0])]
                threshold = table[g, kind, 1 + c, 2]
                if not (v >= threshold if table[g, kind, 1 + c, 1] == 1.0 else v <= threshold):
                    holds = False
                    break
            out[at + 2 * kind] = 1.0 if holds else 0.0
        score = 0.0
        if out[at] == 1.0:                           # the weakest condition's band (``min`` of ``_band``s)
            for c in range(int(table[g, 2, 0, 0])):
                value, inside, outside = q[int(table[g, 2, 1 + c, 0])], table[g, 2, 1 + c, 1], table[g, 2, 1 + c, 2]
                band = 1.0
                if inside != outside:
                    band = (value - outside) / (inside - outside)
                    if 0.0 > band:
                        band = 0.0
                    if 1.0 < band:
                        band = 1.0
                score = band if c == 0 else _min_first(score, band)
        out[at + 1] = score


def step_table(rules) -> np.ndarray:
    """``step_kernel``'s table of ``rules``: per rule (priority order) its enter conditions, its stay
    conditions and its score's terms, each ``(quantity index, above or ideal, threshold)`` as
    ``recognizer._rule_table`` gives them."""
    table = np.zeros((len(rules), 3, 1 + STEP_TERMS, 3))
    for g, (_, enter, stay, score) in enumerate(rules):
        for kind, terms in enumerate((enter, stay, score)):
            table[g, kind, 0, 0] = len(terms)
            for c, (i, second, threshold) in enumerate(terms):
                table[g, kind, 1 + c] = (i, float(second), threshold)
    return table
