"""Robustness campaign: ``fingertrack bench robustness [--quick] [--messages N] [--soak-seconds S] --out DIR``.

Every part runs against a fresh service process (``fingertrack serve`` on a free loopback port, as
deployed, see ``process.py``) and every loop is bounded in count and time:

- **fuzz**: malformed and hostile messages of every kind (random bytes and text, truncated JSON,
  NaN/Infinity, depth bombs, huge numbers, wrong types and shapes, missing and extra fields, non-unit
  quaternions, backwards and huge time, unknown sensors, absurd calibrations, schema-valid extremes,
  hello variants, oversized frames, MessagePack garbage) into attacked sessions, in lockstep: each
  message is followed by a sentinel (a message of unknown type, always answered with an error), so
  every reply belongs to exactly one message. A good glove streams into its own session beside them
  with a subscriber counting its frames. Counted: error replies per message, messages accepted
  without a word, connections dropped (by design or abnormally), stalls (no answer to the sentinel
  within the reply timeout while ``/health`` answers), hangs (no answer to the sentinel and
  ``/health`` silent: the service is killed and a fresh one continues), crashes, tracebacks in the
  service log, and at the end the time until each attacked session streams frames again.
- **extremes**: one schema-valid extreme (gyro 1e300, pose 1e300 m, calibration base 1e300 m,
  phalanx lengths 1e-300 m, time 2**47 s ...) injected by a glove into its own live stream; whether
  and when frames come back, error replies after it, non-finite numbers in what the service sends.
- **never-reading subscribers**: raw WebSocket subscribers that never read, beside a normal one, on
  a real-time stream; whether the service lets them go within a bounded time (subscriber count, bytes
  it still queues for them) and whether the normal one got every frame.
- **connection storm**: connects of four kinds (stream, ingest, aborted with RST, refused token);
  service fds and RSS before and after; sessions a viewer token creates by subscribing.
- **kill -9 while recording**: a glove streams into a recorded session, the service is killed; the
  seconds of sent data missing from the file and whether ``fingertrack replay`` reads it.
- **soak**: one glove in real time with a subscriber; RSS and fd count sampled over time.

Writes ``summary.md`` (checks against the goals), ``results.csv`` (every figure), ``fuzz.csv`` (per
category), ``fuzz_kinds.csv`` (per kind, valid or hostile), ``fuzz_unanswered.csv`` (each hostile message
taken without an error reply, with the session's clock before it), ``extremes.csv``, ``soak.csv`` and
the service logs under ``logs/``.
"""
from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import msgpack

from .process import ServiceProcess, descendants, rss_kib, service_process

SENSORS = ("thumb.0", "thumb.1", "index.1", "index.2", "middle.1", "middle.2", "ring.1", "ring.2",
           "little.1", "little.2")
SENTINEL = {"type": "__sentinel__"}
MSGPACK_SUBPROTOCOL = "fingertrack.msgpack"
TRACEBACK = "Traceback (most recent call last)"
FRAME_TOLERANCE = 10
"""Frames a stream may legitimately miss at its ends: the pipeline's alignment wait (optical
latency 20 ms + reorder window 20 ms) holds back the last ticks, and the first needs a pose."""
MAX_RESTARTS = 5
QUATERNION_TOLERANCE = 1e-3
"""DESIGN.md: a quaternion is unit when its norm is within 1e-3 of 1."""
CLOCK_STEP_S = 0.5
"""The pipeline's default ``clock_step_s``: a sample further back than this from the newest is a clock
step (answered), a sample less far back is a reordered one (in order while its tick waits)."""


# -- hostile messages ------------------------------------------------------------------------------

def _unit_quat(r: random.Random) -> list[float]:
    q = [r.gauss(0, 1) for _ in range(4)]
    n = math.sqrt(sum(x * x for x in q)) or 1.0
    return [x / n for x in q]


def _imu(t: float, r: random.Random) -> dict:
    return {"type": "imu", "t": t, "id": r.choice(SENSORS), "gyr": [r.gauss(0, 0.5) for _ in range(3)],
            "acc": [r.gauss(0, 0.3), r.gauss(0, 0.3), 9.81 + r.gauss(0, 0.3)]}


def _pose(t: float, r: random.Random) -> dict:
    return {"type": "pose", "t": t, "position": [r.uniform(-0.3, 0.3), r.uniform(0.8, 1.4), r.uniform(-0.3, 0.3)],
            "orientation": _unit_quat(r)}


def _batch(t: float, r: random.Random) -> dict:
    return {"type": "imu_batch", "samples": [{k: v for k, v in _imu(t, r).items() if k != "type"} | {"id": s}
                                             for s in SENSORS]}


def _calibration(r: random.Random) -> dict:
    return {"type": "calibration", "fingers": {"index": {"lengths": [0.045, 0.027, 0.02], "coupling": 1.0,
                                                         "base": {"position": [0.02, 0.09, 0.0],
                                                                  "orientation": [0, 0, 0, 1]}}}}


def _valid(t: float, r: random.Random) -> dict:
    return r.choice((_imu, _pose, _batch))(t, r)


def _numeric_paths(msg: dict) -> list[tuple]:
    if msg["type"] == "imu":
        return [("t",), ("gyr", 0), ("acc", 2)]
    if msg["type"] == "pose":
        return [("t",), ("position", 1), ("orientation", 3)]
    return [("samples", 0, "t"), ("samples", 0, "gyr", 1)]


def _set(msg, path, value):
    target = msg
    for p in path[:-1]:
        target = target[p]
    target[path[-1]] = value
    return msg


def _with_literal(msg: dict, path: tuple, literal: str) -> str:
    """The message as JSON text with ``literal`` (e.g. ``1e400``, ``NaN``) written at ``path``."""
    return json.dumps(_set(msg, path, "@@LITERAL@@")).replace('"@@LITERAL@@"', literal)


def _nested(depth: int, r: random.Random) -> str:
    return "[" * depth + "]" * depth if r.random() < 0.5 else '{"a":' * depth + "1" + "}" * depth


VALID = "valid: "
"""The start of the kind of a message the protocol accepts as it is (by the rules of DESIGN.md and the
documented ranges, known when it is generated): any reply, or none, is right for it."""
TIME_PROBE = "time probe"
"""The kind a time probe is generated with (a sample back in time, or at 5e-324 s): whether the service
owes it a reply depends on the session's clock, so the fuzz labels it by ``SessionClock.label``."""


def _is_unit(q: list[float]) -> bool:
    return abs(math.sqrt(sum(x * x for x in q)) - 1.0) <= QUATERNION_TOLERANCE


def _absurd_calibration(r: random.Random) -> tuple[dict, str]:
    """An absurd calibration and its kind."""
    cal = _calibration(r)
    index = cal["fingers"]["index"]
    kind = r.randrange(12)
    if kind == 0:
        index["lengths"] = [1e-300, 1e-300, 1e-300]
        what = "lengths 1e-300 m"
    elif kind == 1:
        index["lengths"] = [5e-324, 5e-324, 5e-324]
        what = "lengths 5e-324 m"
    elif kind == 2:
        index["lengths"] = [r.choice((0.0, -0.03, 1e9)), 0.027, 0.02]
        what = "a length 0, -0.03 or 1e9 m"
    elif kind == 3:
        index["base"]["position"] = [1e300, 0.0, 0.0]
        what = "base 1e300 m"
    elif kind == 4:
        index["base"]["position"] = [r.choice((1e10, -1e15)), 0.0, 0.0]
        what = "base 1e10 or -1e15 m"
    elif kind == 5:
        index["coupling"] = r.choice((-1.0, 2.5, 1e9))
        what = "coupling -1, 2.5 or 1e9"
    elif kind == 6:
        index["sensors"] = [{"id": "index.1", "phalanx": r.choice((-1, 3, 5)), "offset": 0.01}]
        what = "phalanx -1, 3 or 5"
    elif kind == 7:
        cal["fingers"]["sixth"] = {"lengths": [0.04, 0.03]}
        what = "an unknown finger"
    elif kind == 8:
        index["sensors"] = []
        what = VALID + "a finger without sensors (a partly instrumented glove)"
    elif kind == 9:
        index["sensors"] = [{"id": "index.1", "phalanx": 0, "offset": 0.01}] * 2
        what = "a sensor placed twice"
    elif kind == 10:
        offset = r.choice((1e300, 1e-300, -0.01))
        index["sensors"] = [{"id": "index.1", "phalanx": 0, "offset": offset}]
        what = VALID + "sensor offset 1e-300 m (0 within the range 0-0.2 m)" if offset == 1e-300 \
            else "sensor offset 1e300 or -0.01 m"
    else:
        index["sensors"] = [{"id": "index.1", "phalanx": 0, "offset": 0.01, "mounting": [0, 0, 0, 3.0]}]
        what = "a mounting of norm 3"
    return cal, what


def _extreme(t: float, r: random.Random) -> tuple[dict, str]:
    """Schema-valid but physically absurd values, and their kind."""
    kind = r.randrange(5)
    if kind == 0:
        return _set(_imu(t, r), ("gyr", 0), r.choice((1e300, 1e100, -1e50, 1e10))), "gyro 1e10-1e300 rad/s"
    if kind == 1:
        return _set(_imu(t, r), ("acc", 1), r.choice((1e300, -1e100, 1e10))), "acceleration 1e10-1e300 m/s2"
    if kind == 2:
        return _set(_pose(t, r), ("position", 0), r.choice((1e300, 1e100, 1e10, -1e6))), "position 1e6-1e300 m"
    if kind == 3:
        return _set(_batch(t, r), ("samples", 0, "gyr", 2), 1e300), "a batch sample's gyro 1e300 rad/s"
    return _set(_pose(t, r), ("position", 2), 5e-324), VALID + "position 5e-324 m (0 m within the range)"


def _json_message(category: str, t: float, r: random.Random, max_bytes: int) -> str | bytes | tuple:
    """One hostile message of ``category`` for a JSON connection (``bytes``: a binary frame), or
    ``(message, kind)`` where the category holds kinds apart (``VALID``: a message the protocol accepts;
    ``TIME_PROBE``: labelled by the session's clock, ``SessionClock``)."""
    base = _valid(t, r)
    if category == "random_bytes":
        return r.randbytes(r.randrange(1, 300))
    if category == "random_text":
        return "".join(chr(r.randrange(32, 0x2FFF)) for _ in range(r.randrange(1, 200)))
    if category == "truncated_json":
        text = json.dumps(base)
        return text[:r.randrange(1, len(text) - 1)]
    if category == "nan_infinity":
        return _with_literal(base, r.choice(_numeric_paths(base)), r.choice(("NaN", "Infinity", "-Infinity")))
    if category == "depth_bomb":
        depth = r.choice((10, 100, 500, 960, 970, 1000, 5000, 100_000))
        if r.random() < 0.5:
            return _nested(depth, r), f"{depth} levels alone"
        return (json.dumps(base)[:-1] + ',"deep":' + _nested(depth, r) + "}",
                VALID + "10 levels in an unknown field (ignored)" if depth == 10 else f"{depth} levels in an unknown field")
    if category == "huge_numbers":
        literal = r.choice(("1e308", "1e400", "-1e400", "1e-400", "9" * 400, "-" + "9" * 5000, "1" + "0" * 130))
        shown = literal if len(literal) < 10 else f"{len(literal.lstrip('-'))} digits"
        if r.random() < 0.3:
            kind = f"{shown} in an unknown field"
            if literal in ("1e308", "1e-400", "9" * 400, "1" + "0" * 130):
                kind = VALID + kind + " (a finite number, ignored)"
            return json.dumps(base)[:-1] + ',"note":' + literal + "}", kind
        path = r.choice(_numeric_paths(base))
        kind = f"{shown} in a field"
        if literal == "1e-400":       # 0: within every range, but a quaternion with a component 0 may no longer be unit
            if path[0] != "orientation":
                kind = VALID + "1e-400 in a field (0 within the range)"
            elif _is_unit(_set(list(base["orientation"]), path[1:], 0.0)):
                kind = VALID + "1e-400 (0) in a quaternion whose component was near 0 already (still unit within 1e-3)"
            else:
                kind = "1e-400 (0) in a quaternion (no longer unit)"
        return _with_literal(base, path, literal), kind
    if category == "wrong_types":
        return json.dumps(_set(base, r.choice(_numeric_paths(base)),
                               r.choice(("x", None, {}, [], True, [[1, 2, 3]], {"a": 1}))))
    if category == "wrong_shapes":
        kind = r.randrange(4)
        if kind == 0:
            return json.dumps(_set(_imu(t, r), ("gyr",), [0.0] * r.choice((0, 1, 2, 4, 100))))
        if kind == 1:
            return json.dumps(_set(_pose(t, r), ("orientation",), [0.0, 0.0, 1.0]))
        if kind == 2:
            return json.dumps({"type": "imu_batch", "samples": []})
        return json.dumps({"type": "imu_batch", "samples": [_batch(t, r)["samples"][0]] * 4100})
    if category == "missing_fields":
        keys = [k for k in base if k != "type"]
        base.pop(r.choice(keys))
        return json.dumps(base)
    if category == "extra_fields":
        extra = r.choice(("x" * r.randrange(1, 50_000), {"nested": [1, 2, {"a": None}]}, [None] * 100, -1.5))
        return json.dumps(base | {"note": extra}), VALID + "an unknown field (ignored)"
    if category == "non_unit_quaternion":
        q = [x * r.choice((0.0, 0.5, 2.0, 1e6, 1e-12)) for x in _unit_quat(r)]
        # the components are scaled one by one: by chance the norm may still be 1 within the tolerance
        return json.dumps(_set(_pose(t, r), ("orientation",), q)), \
            (VALID + "a unit quaternion after all (within 1e-3)") if _is_unit(q) else "norm 0 to 2e6"
    if category == "backwards_time":     # in order or not by the session's clock: ``SessionClock.label``
        value = r.choice((t - 1.0, t - 100.0, -1.0, -1e9, 0.0, t))
        return json.dumps(_set(_imu(t, r), ("t",), value)), TIME_PROBE
    if category == "huge_time":
        value = r.choice((2.0**47, 2.0**47 + 0.0625, 2.0**52, 1e15, 1e300, 5e-324))
        kind = TIME_PROBE if value == 5e-324 else "beyond 1e10 s"
        return json.dumps(_set(base, ("samples", 0, "t") if base["type"] == "imu_batch" else ("t",), value)), kind
    if category == "unknown_sensors":
        return json.dumps(_set(_imu(t, r), ("id",), r.choice(("ring.7", "index.0", "thumb.2", "foo", "",
                                                              "index.1 ", "INDEX.1", "pinky.1"))))
    if category == "absurd_calibration":
        cal, kind = _absurd_calibration(r)
        return json.dumps(cal), kind
    if category == "extreme_values":
        msg, kind = _extreme(t, r)
        return json.dumps(msg), kind
    if category == "hello_variants":
        protocol, hand = r.choice((1, 2, 0, -1, 10**130)), r.choice(("right", "left", "middle"))
        kind = VALID + "hello" if protocol == 1 and hand != "middle" else "another protocol or hand"
        return json.dumps({"type": "hello", "protocol": protocol, "hand": hand}), kind
    if category == "oversized":
        kind = r.randrange(3)
        if kind == 0:
            return json.dumps(base)[:-1] + ',"pad":"' + "x" * max_bytes + '"}'
        if kind == 1:      # more characters than the limit in bytes, fewer than it in characters
            return json.dumps(base, ensure_ascii=False)[:-1] + ',"pad":"' + "\u00e9" * (max_bytes // 2 + 10) + '"}'
        return "x" * (4 * max_bytes + 1)                   # over the WebSocket frame limit: closed by design
    raise ValueError(f"unknown category {category!r}")


def _msgpack_message(category: str, t: float, r: random.Random, max_bytes: int) -> bytes | tuple:
    """One hostile message of ``category`` for a MessagePack connection, or ``(message, kind)``."""
    base = _valid(t, r)
    if category == "mp_random_bytes":
        return r.randbytes(r.randrange(1, 300))
    if category == "mp_truncated":
        packed = msgpack.packb(base)
        return packed[:r.randrange(1, len(packed) - 1)]
    if category == "mp_depth_bomb":
        return b"\x91" * r.choice((10, 500, 1000, 5000, 100_000)) + b"\xc0"
    if category == "mp_huge_container":
        return r.choice((b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff", b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff"))
    if category == "mp_bin_ext_extra":
        return msgpack.packb(base | {"blob": r.choice((b"\x00\x01", msgpack.ExtType(5, b"xyz"))) })
    if category == "mp_nan_inf":
        path = r.choice(_numeric_paths(base))
        return msgpack.packb(_set(base, path, r.choice((math.nan, math.inf, -math.inf))))
    if category == "mp_nan_extra":
        return msgpack.packb(base | {"note": r.choice((math.nan, math.inf))})
    if category == "mp_uint64":
        return msgpack.packb(_set(base, r.choice(_numeric_paths(base)), 2**64 - 1))
    if category == "mp_nonstring_keys":
        return msgpack.packb({1: 2, **base})
    if category == "mp_non_map":
        return msgpack.packb(r.choice(([1, 2, 3], "imu", 42, None, b"bytes")))
    if category == "mp_extra_data":
        return msgpack.packb(base) + b"\x00\x01"
    if category == "mp_wrong_types":
        return msgpack.packb(_set(base, r.choice(_numeric_paths(base)), r.choice(("x", None, {}, [], True))))
    if category == "mp_extreme_values":
        msg, kind = _extreme(t, r)
        return msgpack.packb(msg), kind
    if category == "mp_absurd_calibration":
        cal, kind = _absurd_calibration(r)
        return msgpack.packb(cal), kind
    if category == "mp_oversized":
        return msgpack.packb(base | {"pad": b"\x00" * (max_bytes + 1)})
    raise ValueError(f"unknown category {category!r}")


JSON_CATEGORIES = {  # category: weight
    "random_bytes": 6, "random_text": 6, "truncated_json": 8, "nan_infinity": 6, "depth_bomb": 4,
    "huge_numbers": 6, "wrong_types": 6, "wrong_shapes": 5, "missing_fields": 6, "extra_fields": 4,
    "non_unit_quaternion": 5, "backwards_time": 6, "huge_time": 2, "unknown_sensors": 5,
    "absurd_calibration": 6, "extreme_values": 5, "hello_variants": 3, "oversized": 0.05,
}
MSGPACK_CATEGORIES = {
    "mp_random_bytes": 6, "mp_truncated": 6, "mp_depth_bomb": 3, "mp_huge_container": 3, "mp_bin_ext_extra": 4,
    "mp_nan_inf": 5, "mp_nan_extra": 3, "mp_uint64": 3, "mp_nonstring_keys": 3, "mp_non_map": 4,
    "mp_extra_data": 4, "mp_wrong_types": 5, "mp_extreme_values": 4, "mp_absurd_calibration": 4,
    "mp_oversized": 0.05,
}


def hostile_message(seed: int, index: int, binary: bool, max_bytes: int = 1 << 20) -> tuple[str, str, str | bytes]:
    """``(category, kind, payload)`` of fuzz message ``index``: deterministic in ``(seed, index)``, so a
    campaign that restarts a hung service continues with the same messages. ``kind`` says what the
    message is within its category (the category itself where it has one kind); a kind that starts
    with ``VALID`` is a message the protocol accepts (any reply or none is right for it); ``TIME_PROBE``
    is a sample whose time is in order or not by the session's clock, which ``SessionClock`` follows."""
    r = random.Random(seed * 1_000_003 + index)
    cats = MSGPACK_CATEGORIES if binary else JSON_CATEGORIES
    category = r.choices(list(cats), weights=list(cats.values()))[0]
    t = 0.001 * index                                        # time moves forward with the campaign
    made = (_msgpack_message if binary else _json_message)(category, t, r, max_bytes)
    payload, kind = made if isinstance(made, tuple) else (made, category)
    return category, kind, payload


class SessionClock:
    """An attacked session's clock as the documented rule defines it (DESIGN.md; ``pipeline/hand.py``),
    followed from the messages sent into the session and the service's replies to them, so that a time
    probe is labelled by what it is to the service, not by the script's own clock:

    - ``newest``: the newest IMU sample time the session took (``None`` before its first). A sample more
      than the clock step (``CLOCK_STEP_S``) from it, forward or back, starts a new clock (answered with
      ``clock_step``): ``newest`` becomes its time and the optics start afresh. A sample within the step
      and after ``newest`` is in order; one within the step at or before it is reordered (taken in
      silence) or late (``time_backwards``), which the reorder window decides: either is right.
    - ``pose``: the newest pose time taken since the clock started; a pose at or before it is late
      (``time_backwards``), a later one is in order.

    ``update`` takes each message with its replies: a message refused as a whole (any error but the
    pipeline's drop notices) leaves the clock alone; a batch's refused samples (``invalid_samples``)
    are left out; a single sample of a sensor the calibration does not place is dropped before its time
    is looked at. ``disagreements`` counts the messages whose ``clock_step`` notice (or its absence)
    differs from what the rule predicts: the measure of how well this clock follows the service's."""

    PIPELINE_CODES = frozenset(("clock_step", "time_backwards", "duplicate", "unknown_sensor", "invalid_samples"))

    def __init__(self) -> None:
        self.newest: float | None = None
        self.pose: float | None = None
        self.disagreements = 0

    @staticmethod
    def _decoded(payload, binary: bool):
        try:
            if binary:
                return msgpack.unpackb(payload) if isinstance(payload, bytes) else None
            return json.loads(payload) if isinstance(payload, str) else None
        except Exception:                            # anything undecodable is refused: no clock effect
            return None

    def label(self, payload, binary: bool) -> str:
        """The kind of a time probe (an ``imu``, a ``pose``, or an ``imu_batch`` whose first sample is the
        probe) before the session takes it: hostile (``VALID`` not prefixed) when the rule owes it a reply."""
        msg = self._decoded(payload, binary)
        kind = msg.get("type") if isinstance(msg, dict) else None
        if kind == "pose":
            t = msg["t"]
            if self.pose is not None and t <= self.pose:
                return "a pose at or before the session's newest pose (late: answered)"
            return VALID + "a pose after the session's newest pose since its clock started (in order)"
        if kind not in ("imu", "imu_batch"):
            raise ValueError(f"a time probe is an imu, imu_batch or pose message, got {kind!r}")
        t = msg["samples"][0]["t"] if kind == "imu_batch" else msg["t"]
        if self.newest is None:
            return VALID + "the session's first sample (starts its clock)"
        if abs(t - self.newest) > CLOCK_STEP_S:
            way = "forward" if t > self.newest else "back"
            return f"{way} more than the clock step from the session's newest sample (a new clock: answered)"
        if t > self.newest:
            return VALID + "after the session's newest sample, within the clock step (in order)"
        return VALID + "at or back less than the clock step from the session's newest sample (reordered, or late)"

    def update(self, payload, binary: bool, outcome: str, replies: list[dict]) -> None:
        """The session took (or refused) this message, answered with ``replies``."""
        if outcome != "replied":                     # a close or a stall: not known to be taken
            return
        msg = self._decoded(payload, binary)
        if not isinstance(msg, dict):
            return
        errors = [m for m in replies if m.get("type") == "error"]
        codes = {m.get("code") for m in errors}
        if codes - self.PIPELINE_CODES:
            return                                   # refused as a whole
        kind = msg.get("type")
        if kind == "pose":
            if "time_backwards" not in codes and (self.pose is None or msg["t"] > self.pose):
                self.pose = msg["t"]
            return
        if kind == "imu":
            samples = [] if "unknown_sensor" in codes else [msg]
        elif kind == "imu_batch":
            refused = {i for m in errors if m.get("code") == "invalid_samples" for i in m.get("samples", ())}
            samples = [x for i, x in enumerate(msg["samples"]) if i not in refused]
        else:
            return
        predicted = False
        for sample in samples:
            t = sample["t"]
            if self.newest is not None and abs(t - self.newest) > CLOCK_STEP_S:
                predicted, self.newest, self.pose = True, t, None
            elif self.newest is None or t > self.newest:
                self.newest = t
        stepped = "clock_step" in codes
        if stepped != predicted:
            self.disagreements += 1
            if stepped and samples:                  # the service's clock is the truth: follow it
                self.newest, self.pose = samples[-1]["t"], None


# -- a lockstep attacker ---------------------------------------------------------------------------

@dataclass
class CategoryStats:
    sent: int = 0
    error_reply: int = 0
    other_reply: int = 0
    silent: int = 0
    closed_by_design: int = 0
    closed_abnormally: int = 0
    closes: Counter = field(default_factory=Counter)
    """close code and reason of the connections closed while answering a message (``None``: no close frame
    received)"""
    stalls: int = 0
    """sentinel not answered within the reply timeout while ``/health`` answered"""
    hangs: int = 0
    crashes: int = 0
    codes: Counter = field(default_factory=Counter)

    def count(self, outcome: str, replies: list[dict]) -> None:
        """One message: what ``Attacker.probe`` saw of it."""
        self.sent += 1
        errors = [m for m in replies if m.get("type") == "error"]
        for m in errors:
            self.codes[m.get("code")] += 1
        for m in replies:
            if m.get("type") == "close":
                self.closes[f"{m['code']} {m['reason'][:60]}"] += 1
        if outcome == "replied":
            if errors:
                self.error_reply += 1
            elif replies:
                self.other_reply += 1
            else:
                self.silent += 1
        elif outcome == "closed_by_design":
            self.closed_by_design += 1
        elif outcome == "stalled":
            self.stalls += 1
        else:
            self.closed_abnormally += 1


class ServiceDown(Exception):
    """The service stopped answering (hang) or exited (crash)."""

    def __init__(self, kind: str):
        super().__init__(kind)
        self.kind = kind


def _decode(data) -> dict:
    return msgpack.unpackb(data) if isinstance(data, bytes) else json.loads(data)


def _is_sentinel_reply(msg: dict) -> bool:
    return msg.get("type") == "error" and msg.get("code") == "unknown_type" and "__sentinel__" in msg.get("detail", "")


async def _health(url: str, timeout_s: float) -> bool:
    """``GET /health`` answers 200 within ``timeout_s``."""
    import urllib.request

    def get():
        with urllib.request.urlopen(url.rstrip("/") + "/health", timeout=timeout_s) as resp:
            return resp.status == 200
    try:
        return await asyncio.to_thread(get)
    except OSError:                                          # refused, reset or timed out
        return False


class Attacker:
    """One source connection into an attacked session; ``probe`` sends a message and the sentinel and
    returns what the service answered to the message."""

    def __init__(self, svc: ServiceProcess, session: str, binary: bool, reply_timeout_s: float):
        self.svc, self.session, self.binary = svc, session, binary
        self.reply_timeout_s = reply_timeout_s
        self.ws = None

    def _encode(self, msg: dict):
        return msgpack.packb(msg) if self.binary else json.dumps(msg)

    async def open(self) -> None:
        from websockets.asyncio.client import connect
        base = self.svc.url.replace("http://", "ws://")
        self.ws = await connect(f"{base}/v1/ingest/{self.session}?token={self.svc.source}", max_size=None,
                                subprotocols=[MSGPACK_SUBPROTOCOL] if self.binary else None,
                                open_timeout=self.reply_timeout_s, ping_interval=None, close_timeout=2)
        await self.ws.send(self._encode({"type": "hello", "protocol": 1, "hand": "right", "source": "robustness"}))
        await asyncio.wait_for(self.ws.recv(), self.reply_timeout_s)

    async def close(self) -> None:
        if self.ws is not None:
            try:
                await asyncio.wait_for(self.ws.close(), 5)
            except Exception:                                # already gone: nothing to close
                pass
            self.ws = None

    async def probe(self, payloads: list) -> list[tuple[str, list[dict]]]:
        """Send the messages, each followed by the sentinel, then read the replies (pipelined: a
        connection is answered in order, so the replies before the k-th sentinel's belong to the k-th
        message). Returns one ``(outcome, replies)`` per message answered, outcome ``"replied"``; when
        the connection closes, the message being answered gets ``"closed_by_design"`` or
        ``"closed_abnormally"`` (its replies end with ``{"type": "close", "code", "reason"}``, not sent by
        the service) and the list ends there (the caller sends the rest again); a message
        whose sentinel is not answered in time while ``/health`` answers is ``"stalled"``. Raises
        :class:`ServiceDown` on a hang or a crash."""
        from websockets.exceptions import ConnectionClosed
        results: list[tuple[str, list[dict]]] = []
        replies: list[dict] = []
        try:
            if self.ws is None:
                await self.open()
            for payload in payloads:
                await self.ws.send(payload)
                await self.ws.send(self._encode(SENTINEL))
            while len(results) < len(payloads):
                msg = _decode(await asyncio.wait_for(self.ws.recv(), self.reply_timeout_s))
                if _is_sentinel_reply(msg):
                    results.append(("replied", replies))
                    replies = []
                else:
                    replies.append(msg)
            return results
        except asyncio.TimeoutError:
            await self.close()
            if not self.svc.alive():
                raise ServiceDown("crash") from None
            if not await _health(self.svc.url, self.reply_timeout_s):
                raise ServiceDown("hang") from None
            return results + [("stalled", replies)]
        except (ConnectionClosed, OSError) as err:
            code = getattr(getattr(err, "rcvd", None), "code", None)
            reason = getattr(getattr(err, "rcvd", None), "reason", "") or type(err).__name__
            await self.close()
            if not self.svc.alive():
                raise ServiceDown("crash") from None
            # 1008 refusal (bad hello), 1009 too big, 1013 try later: the service closed on purpose
            return results + [("closed_by_design" if code in (1008, 1009, 1013) else "closed_abnormally",
                               replies + [{"type": "close", "code": code, "reason": reason}])]


# -- the good glove beside the attack --------------------------------------------------------------

def _shift(msg: dict, dt: float) -> dict:
    if msg["type"] == "imu_batch":
        return {"type": "imu_batch", "samples": [s | {"t": s["t"] + dt} for s in msg["samples"]]}
    if "t" in msg:
        return msg | {"t": msg["t"] + dt}
    return msg


class LoopingGlove:
    """A simulated glove streamed at ``speed`` x real time until stopped, its recording repeated with
    the clock carried on (one IMU period between repeats), with a subscriber on the same session.
    Counts what a user can count: the source time span sent, frames received and ``seq`` gaps."""

    def __init__(self, svc: ServiceProcess, session: str, speed: float, seed: int = 0, seconds: float = 20.0):
        from clients.glove import source_messages
        from ..sim.session import SimConfig
        self.svc, self.session, self.speed = svc, session, speed
        self.messages = source_messages(SimConfig(motion="random", t_m_s=seconds, noise="both",
                                                  hand_motion="slow-rotation", seed=seed))
        times = [s["t"] for _, m in self.messages if m["type"] == "imu_batch" for s in m["samples"]]
        self.period = min(b - a for a, b in zip(times, times[1:]) if b > a)
        self.loop_span = max(times) - min(times) + self.period
        self.first_t = min(times)
        self.last_t = None
        self.frames: list[tuple[float, int, float]] = []           # (arrival, seq, t)
        self.non_finite = 0
        self.stop = asyncio.Event()
        self.pub = None

    async def _subscribe(self, ready: asyncio.Event) -> None:
        from websockets.asyncio.client import connect
        base = self.svc.url.replace("http://", "ws://")
        async with connect(f"{base}/v1/stream/{self.session}?token={self.svc.viewer}", max_size=None) as ws:
            async for data in ws:
                try:
                    msg = json.loads(data, parse_constant=_reject_constant)
                except ValueError:
                    self.non_finite += 1
                    msg = json.loads(data)
                if msg.get("type") == "hello":
                    ready.set()
                elif msg.get("type") == "frame":
                    self.frames.append((time.perf_counter(), msg["seq"], msg["t"]))

    async def run(self) -> None:
        from clients.client import Publisher
        ready = asyncio.Event()
        self.sub_task = asyncio.create_task(self._subscribe(ready))
        await asyncio.wait({asyncio.create_task(ready.wait()), self.sub_task}, return_when=asyncio.FIRST_COMPLETED)
        self.pub = Publisher(self.svc.url, self.session, self.svc.source, hand="right", source="robustness-good")
        t0_wall, loop = time.perf_counter(), 0
        src0 = self.messages[0][0]
        while not self.stop.is_set():
            offset = loop * self.loop_span
            for arrival, m in self.messages:
                if loop and m["type"] in ("hello", "calibration"):
                    continue
                due = t0_wall + (arrival + offset - src0) / self.speed
                await asyncio.sleep(max(0.0, due - time.perf_counter()))
                if self.stop.is_set():
                    break
                m = _shift(m, offset)
                await self.pub.send(m)
                if m["type"] == "imu_batch":
                    self.last_t = m["samples"][-1]["t"]
            loop += 1

    async def finish(self, timeout_s: float) -> dict:
        """Stop sending, wait (bounded) until the subscriber has every frame the service produced,
        and account for them."""
        from clients.client import rest
        self.stop.set()
        if self.pub is not None:
            await self.pub.close()
        # the session's source count drops once the service has handled every message before the
        # close; its frame count is final from then on
        produced, deadline = None, time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            status, sessions = await asyncio.to_thread(rest, self.svc.url, "GET", "/v1/sessions", self.svc.admin)
            mine = next((s for s in sessions if s["session"] == self.session), None) if status == 200 else None
            if mine is not None and mine["sources"] == 0:
                produced = mine["frames_out"]
                if len(self.frames) >= produced:
                    break
            await asyncio.sleep(0.2)
        self.sub_task.cancel()
        await asyncio.gather(self.sub_task, return_exceptions=True)
        seqs = [f[1] for f in self.frames]
        span = (self.last_t - self.first_t) if self.last_t is not None else 0.0
        return {"sent_seconds": span, "expected": int(span * self.svc_rate_hz),
                "produced": produced, "received": len(self.frames),
                "seq_gaps": sum(1 for a, b in zip(seqs, seqs[1:]) if b != a + 1),
                "non_finite": self.non_finite, "reconnects": self.pub.reconnects if self.pub else 0,
                "errors": len(self.pub.errors) if self.pub else 0}

    svc_rate_hz = 90.0


def _reject_constant(name: str):
    raise ValueError(name)


# -- part 1: fuzz ----------------------------------------------------------------------------------

def _tracebacks(log: Path) -> int:
    try:
        return log.read_text(errors="replace").count(TRACEBACK)
    except OSError:
        return 0


async def _recovery(svc: ServiceProcess, session: str, seconds: float, messages: list[tuple[float, dict]],
                    t_offset_s: float, reply_timeout_s: float = 60.0) -> dict:
    """A fresh glove (new connection, its clock ``t_offset_s`` on) streams ``seconds`` of good data in
    real time into an attacked session right after its last bad message. Measured on the source
    clock: how soon after the glove's first data frames come, and the share of the frames due."""
    from clients.client import Publisher
    frames, non_finite, ready = [], [0], asyncio.Event()
    task = asyncio.create_task(_frames_of(svc, session, frames, non_finite, ready))
    await asyncio.wait({asyncio.create_task(ready.wait()), task}, timeout=reply_timeout_s,
                       return_when=asyncio.FIRST_COMPLETED)
    first = len(frames)
    pub = Publisher(svc.url, session, svc.source, source="robustness-recovery")
    t0, src0 = time.perf_counter(), messages[0][0]
    for arrival, m in messages:
        if arrival - src0 > seconds:
            break
        await asyncio.sleep(max(0.0, t0 + arrival - src0 - time.perf_counter()))
        await pub.send(_shift(m, t_offset_s))
    await pub.close()                                       # after the service's sync
    await _wait_drained(svc, session, frames, reply_timeout_s)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    start_t = src0 + t_offset_s
    mine = [f for f in frames[first:] if f[2] >= start_t]
    return {"first_frame_after_last_bad_s": (mine[0][2] - start_t) if mine else None,
            "frames": len(mine), "expected": int(seconds * 90), "errors": len(pub.errors)}


async def _fuzz_life(svc: ServiceProcess, positions: list[int], limits: list[int], workers: int, seed: int,
                     stats: dict, kind_stats: dict, good_speed: float, reply_timeout_s: float, deadline: float, recovery: dict,
                     recovery_seconds: float, recovery_msgs: list, batch: int, tracked: dict) -> dict:
    """Fuzz until every worker reached its limit, the deadline passed, or the service went down. Each
    attacked session's clock is followed (``SessionClock``) to label its time probes; ``tracked`` gets
    the clock's disagreements with the service and every hostile message answered without an error."""
    good = LoopingGlove(svc, "good", good_speed, seed=seed)
    good_task = asyncio.create_task(good.run())
    down: list[str] = []
    machine = {"least_mem_available_mib": None, "highest_load_1min": None}
    sampler = asyncio.create_task(_sample_machine(machine))

    async def worker(k: int):
        binary = k == workers - 1
        attacker = Attacker(svc, f"fuzz-{k}", binary, reply_timeout_s)
        clock = SessionClock()                     # a fresh service: a fresh session
        try:
            while positions[k] < limits[k] and not down and time.monotonic() < deadline:
                todo = range(positions[k], min(limits[k], positions[k] + batch))
                cats, kinds, payloads = zip(*(hostile_message(seed, j * workers + k, binary) for j in todo))
                try:
                    results = await attacker.probe(list(payloads))
                except ServiceDown as err:
                    if not down:                   # the first to notice owns a message of its batch
                        down.append(err.kind)
                        kind = clock.label(payloads[0], binary) if kinds[0] == TIME_PROBE else kinds[0]
                        for st in (stats.setdefault(cats[0], CategoryStats()),
                                   kind_stats.setdefault((cats[0], kind), CategoryStats())):
                            st.sent += 1
                            st.hangs += err.kind == "hang"
                            st.crashes += err.kind == "crash"
                        positions[k] += 1
                    return
                for j, category, kind, payload, (outcome, replies) in zip(todo, cats, kinds, payloads, results):
                    positions[k] += 1
                    if kind == TIME_PROBE:         # labelled before the session takes it, by its replies so far
                        kind = clock.label(payload, binary)
                    before = (clock.newest, clock.pose)
                    clock.update(payload, binary, outcome, replies)
                    for st in (stats.setdefault(category, CategoryStats()),
                               kind_stats.setdefault((category, kind), CategoryStats())):
                        st.count(outcome, replies)
                    if outcome == "replied" and not kind.startswith(VALID) and \
                            not any(m.get("type") == "error" for m in replies) and len(tracked["unanswered"]) < 1000:
                        shown = payload if isinstance(payload, str) else repr(payload)
                        tracked["unanswered"].append({
                            "session": attacker.session, "index": j * workers + k, "category": category, "kind": kind,
                            "replies": json.dumps(replies)[:200], "clock_newest": before[0], "clock_pose": before[1],
                            "message": shown[:300]})
        finally:
            await attacker.close()
            tracked["clock_disagreements"] += clock.disagreements
        if positions[k] >= limits[k] and not down:
            # right after this session's last bad message: a fresh glove, does it stream again?
            # its clock carries on from the fuzz's (message i is at 1 ms x i), half a second later
            recovery[f"fuzz-{k}"] = await _recovery(svc, f"fuzz-{k}", recovery_seconds, recovery_msgs,
                                                    0.001 * limits[k] * workers + 0.5)

    await asyncio.gather(*(worker(k) for k in range(workers)))
    if down:
        good_task.cancel()
        await asyncio.gather(good_task, return_exceptions=True)
        sampler.cancel()
        return {"down": down[0], "good": None, "machine": machine}
    good_result = await good.finish(timeout_s=30)
    good_task.cancel()
    sampler.cancel()
    await asyncio.gather(good_task, sampler, return_exceptions=True)
    return {"down": None, "good": good_result, "machine": machine}


def _mem_available_mib() -> float | None:
    """Memory the machine has available for new work (``MemAvailable``), MiB (Linux; None elsewhere)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


async def _sample_machine(machine: dict, every_s: float = 2.0) -> None:
    """The least memory available and the highest load of the machine while the fuzz runs: a service
    that stops answering on a machine out of memory (its pages evicted and read back again and again)
    is not the service's hang."""
    while True:
        mem, load = _mem_available_mib(), os.getloadavg()[0]
        if mem is not None and (machine["least_mem_available_mib"] is None or mem < machine["least_mem_available_mib"]):
            machine["least_mem_available_mib"] = mem
        if machine["highest_load_1min"] is None or load > machine["highest_load_1min"]:
            machine["highest_load_1min"] = load
        await asyncio.sleep(every_s)


def stop_hung(svc: ServiceProcess, settle_s: float = 0.5, bound_s: float = 10.0) -> dict:
    """A service that stopped answering, before it is killed: the machine's available memory and load,
    the RSS of the web process and of each of its hand workers, and in the service log the stack of
    every thread of each of them (``api/stacks.py``: SIGUSR1; a process that does not run at all, e.g.
    stopped, writes nothing and is passed after ``bound_s``), each after a line naming the process.
    Then every one of them is killed with SIGKILL (a hung process may ignore SIGTERM, and a hand worker
    stuck in a loop would not notice that its web process ended). Returns what was seen."""
    procs = [svc.pid] + descendants(svc.pid)
    seen = {"mem_available_mib": _mem_available_mib(), "load_1min": os.getloadavg()[0],
            "rss_mib": {str(pid): (rss_kib(pid) or 0) / 1024 for pid in procs}, "stacks_written": 0}
    fd = svc.log.fileno() if svc.log is not None and not svc.log.closed else None
    for pid in procs:
        if fd is None:
            break
        what = "web process" if pid == svc.pid else "hand worker"
        # the service's standard error shares this file's offset: the line lands between its own lines
        os.write(fd, f"--- the benchmark asks the {what} (pid {pid}) for its stacks: the service stopped "
                     f"answering ---\n".encode())
        size = os.fstat(fd).st_size
        try:
            os.kill(pid, signal.SIGUSR1)
        except ProcessLookupError:
            continue
        grown, last_change, deadline = size, time.monotonic(), time.monotonic() + bound_s
        while time.monotonic() < deadline:
            time.sleep(0.05)
            now = os.fstat(fd).st_size
            if now != grown:
                grown, last_change = now, time.monotonic()
            elif grown > size and time.monotonic() - last_change >= settle_s:
                break
        seen["stacks_written"] += grown > size
    for pid in procs:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return seen


def run_fuzz(out: Path, messages: int, seed: int, workers: int = 3, good_speed: float = 0.25,
             reply_timeout_s: float = 30.0, max_seconds: float = 3600.0, recovery_seconds: float = 3.0,
             batch: int = 32) -> dict:
    """The bulk fuzz (see the module docstring). ``workers``: connections attacking at once (the last
    one speaks MessagePack), each into its own session, ``batch`` messages in flight on each."""
    from clients.glove import source_messages
    from ..sim.session import SimConfig
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    per = [messages // workers + (1 if k < messages % workers else 0) for k in range(workers)]
    positions = [0] * workers
    stats: dict[str, CategoryStats] = {}
    kind_stats: dict[tuple[str, str], CategoryStats] = {}
    lives, goods, rss, fds = [], [], [], []
    recovery: dict[str, dict] = {}
    deadline = time.monotonic() + max_seconds
    restarts = 0
    t_start = time.perf_counter()
    recovery_msgs = source_messages(SimConfig(motion="sequence", noise="white", seed=seed + 7))
    machine = {"least_mem_available_mib": None, "highest_load_1min": None}
    start_failure = None
    tracked = {"unanswered": [], "clock_disagreements": 0}
    while True:
        log = logs / f"fuzz-{len(lives)}.log"
        with contextlib.ExitStack() as stack:
            try:
                svc = stack.enter_context(service_process(log_path=log))
            except RuntimeError as err:                     # it did not come up: reported, not a lost run
                start_failure = {"log": log.name, "error": str(err)[:300], "mem_available_mib": _mem_available_mib(),
                                 "load_1min": os.getloadavg()[0]}
                break
            rss0, fd0 = svc.rss_kib(), svc.fds()
            life = asyncio.run(_fuzz_life(svc, positions, per, workers, seed, stats, kind_stats, good_speed, reply_timeout_s,
                                          deadline, recovery, recovery_seconds, recovery_msgs, batch, tracked))
            down = None
            if life["down"] is None:
                rss.append((rss0, svc.rss_kib()))
                fds.append((fd0, svc.fds()))
            else:
                down = stop_hung(svc)                       # stacks into the log, then SIGKILL to all of it
        for key, pick in (("least_mem_available_mib", min), ("highest_load_1min", max)):
            seen = [v for v in (machine[key], life["machine"][key]) if v is not None]
            machine[key] = pick(seen) if seen else None
        lives.append({"down": life["down"], "tracebacks": _tracebacks(log), "log": log.name, "when_down": down})
        if life["good"] is not None:
            goods.append(life["good"])
        done = all(p >= n for p, n in zip(positions, per)) or time.monotonic() >= deadline
        if done or life["down"] is None:
            break
        restarts += 1
        if restarts > MAX_RESTARTS:
            break
    total = sum(s.sent for s in stats.values())
    with open(out / "fuzz_unanswered.csv", "w", newline="") as fh:      # hostile, taken without an error reply
        cols = ["session", "index", "category", "kind", "replies", "clock_newest", "clock_pose", "message"]
        w = csv.DictWriter(fh, cols)
        w.writeheader()
        w.writerows(tracked["unanswered"])
    return {"sent": total, "requested": messages, "wall_s": time.perf_counter() - t_start, "stats": stats,
            "kind_stats": kind_stats,
            "stalls": sum(s.stalls for s in stats.values()),
            "hangs": sum(s.hangs for s in stats.values()), "crashes": sum(s.crashes for s in stats.values()),
            "service_restarts": restarts, "tracebacks": sum(x["tracebacks"] for x in lives),
            "good": goods, "recovery": recovery, "rss_kib": rss, "fds": fds,
            "stopped_early": total < messages, "lives": lives, "machine": machine, "start_failure": start_failure,
            "clock_disagreements": tracked["clock_disagreements"], "unanswered": tracked["unanswered"]}


# -- part 2: schema-valid extremes injected into a live stream -------------------------------------

def _extreme_probes() -> list[tuple[str, callable]]:
    """``(name, make(t) -> messages)``: what a glove injects at source time ``t``."""
    def imu(key, value):
        return lambda t: [{"type": "imu", "t": t, "id": "index.1", key: value,
                           **{k: v for k, v in (("gyr", [0.0, 0.0, 0.0]), ("acc", [0.0, 0.0, 9.81])) if k != key}}]

    def pose(position):
        return lambda t: [{"type": "pose", "t": t, "position": position, "orientation": [0, 0, 0, 1]}]

    def calibration(finger):
        return lambda t: [{"type": "calibration", "fingers": {"index": finger}}]

    def huge_time(t0):
        def make(_t):
            def batch(t):
                return {"type": "imu_batch", "samples": [{"t": t, "id": s, "gyr": [0, 0, 0], "acc": [0, 9.81, 0]}
                                                         for s in ("index.1", "index.2")]}
            return [{"type": "pose", "t": t0, "position": [0, 1, 0], "orientation": [0, 0, 0, 1]}, batch(t0),
                    {"type": "pose", "t": t0 + 0.0625, "position": [0, 1, 0], "orientation": [0, 0, 0, 1]},
                    batch(t0 + 0.0625)]
        return make

    return [
        ("imu gyr 1e300 rad/s", imu("gyr", [1e300, 0.0, 0.0])),
        ("imu gyr 1e100 rad/s", imu("gyr", [1e100, 0.0, 0.0])),
        ("imu acc 1e300 m/s2", imu("acc", [0.0, 0.0, 1e300])),
        ("pose position 1e300 m", pose([1e300, 0.0, 0.0])),
        ("pose position 1e10 m", pose([1e10, 0.0, 0.0])),
        ("calibration base position 1e300 m", calibration({"base": {"position": [1e300, 0, 0], "orientation": [0, 0, 0, 1]}})),
        ("calibration lengths 1e-300 m", calibration({"lengths": [1e-300, 1e-300, 1e-300]})),
        ("time 1e300 s", huge_time(1e300)),
        ("time 2**47 s", huge_time(2.0**47)),
    ]


async def _wait_drained(svc: ServiceProcess, session: str, frames: list, timeout_s: float) -> int | None:
    """After the session's source closed: wait (bounded) until the service has handled everything it
    was sent (its source count is 0) and the subscriber holds the session's last frame (``frames``:
    ``(arrival, seq, t)``). Returns the session's frame count, None if that did not happen in time."""
    from clients.client import rest
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status, sessions = await asyncio.to_thread(rest, svc.url, "GET", "/v1/sessions", svc.admin)
        mine = next((x for x in sessions if x["session"] == session), None) if status == 200 else None
        if mine is not None and mine["sources"] == 0:
            if mine["frames_out"] == 0 or (frames and max(f[1] for f in frames) >= mine["frames_out"]):
                return mine["frames_out"]
        await asyncio.sleep(0.2)
    return None


async def _frames_of(svc: ServiceProcess, session: str, frames: list, non_finite: list, ready: asyncio.Event) -> None:
    """A subscriber: ``(arrival, seq, t)`` of every frame; messages with NaN/Infinity counted."""
    from websockets.asyncio.client import connect
    base = svc.url.replace("http://", "ws://")
    async with connect(f"{base}/v1/stream/{session}?token={svc.viewer}", max_size=None) as ws:
        async for data in ws:
            try:
                msg = json.loads(data, parse_constant=_reject_constant)
            except ValueError:
                non_finite[0] += 1
                msg = json.loads(data)
            if msg.get("type") == "hello":
                ready.set()
            elif msg.get("type") == "frame":
                frames.append((time.perf_counter(), msg["seq"], msg["t"]))


async def _extreme_trial(svc: ServiceProcess, session: str, make, seconds: float, inject_at: float,
                         messages: list[tuple[float, dict]], reply_timeout_s: float) -> dict:
    """A glove streams ``seconds`` of good data in real time and injects ``make(t)`` at source time
    ``inject_at``. Measured on the source clock (independent of how busy the machine is): how soon
    after the injection frames resume, and how many of the frames due after it come."""
    from websockets.asyncio.client import connect
    base = svc.url.replace("http://", "ws://")
    frames, non_finite, ready = [], [0], asyncio.Event()
    sub = asyncio.create_task(_frames_of(svc, session, frames, non_finite, ready))
    await asyncio.wait({asyncio.create_task(ready.wait()), sub}, timeout=reply_timeout_s,
                       return_when=asyncio.FIRST_COMPLETED)
    errors_after, inject_t, hung = [], None, False
    synced = asyncio.get_running_loop().create_future()
    src0 = messages[0][0]
    async with connect(f"{base}/v1/ingest/{session}?token={svc.source}", max_size=None, ping_interval=None,
                       close_timeout=2) as ws:
        async def read():
            async for data in ws:
                msg = json.loads(data)
                if msg.get("type") == "error" and inject_t is not None:
                    errors_after.append(msg.get("code"))
                elif msg.get("type") == "sync" and not synced.done():
                    synced.set_result(None)
        reader = asyncio.create_task(read())
        t0 = time.perf_counter()
        for arrival, m in messages:
            if arrival - src0 > seconds:
                break
            await asyncio.sleep(max(0.0, t0 + arrival - src0 - time.perf_counter()))
            if inject_t is None and arrival - src0 >= inject_at:
                for bad in make(arrival):
                    await ws.send(json.dumps(bad))
                inject_t = arrival
            await ws.send(json.dumps(m))
        # everything sent: the service answers sync once it has handled all of it (or never, if hung)
        await ws.send(json.dumps({"type": "sync", "id": 1}))
        try:
            await asyncio.wait_for(asyncio.shield(synced), reply_timeout_s)
        except asyncio.TimeoutError:
            hung = not await _health(svc.url, reply_timeout_s)
        reader.cancel()
        await asyncio.gather(reader, return_exceptions=True)
    produced = None if hung else await _wait_drained(svc, session, frames, reply_timeout_s)
    sub.cancel()
    await asyncio.gather(sub, return_exceptions=True)
    last_t = src0 + seconds
    after = [f for f in frames if inject_t is not None and f[2] > inject_t]
    return {"hung": hung, "produced": produced, "frames_before": len(frames) - len(after), "frames_after": len(after),
            "expected_after": int((last_t - inject_t) * 90) if inject_t is not None else 0,
            "first_frame_after_s": (after[0][2] - inject_t) if after else None,
            "errors_after": len(errors_after), "error_codes": dict(Counter(errors_after)),
            "non_finite_messages": non_finite[0]}


def run_extremes(out: Path, seconds: float, seed: int, reply_timeout_s: float = 30.0,
                 probes: list[str] | None = None) -> list[dict]:
    from clients.glove import source_messages
    from ..sim.session import SimConfig
    msgs = source_messages(SimConfig(motion="sequence", noise="white", seed=seed + 11))
    todo = [p for p in _extreme_probes() if probes is None or p[0] in probes]
    rows, i, life = [], 0, 0
    while i < len(todo) and life <= MAX_RESTARTS:
        log = out / "logs" / f"extremes-{life}.log"
        # every probe streams into a session of its own, all with one source token: above its quota of 8
        with service_process(log_path=log, extra_settings={"max_sessions_per_token": len(todo) + 1}) as svc:
            while i < len(todo):
                name, make = todo[i]
                row = asyncio.run(_extreme_trial(svc, f"extreme-{i}", make, seconds, seconds / 3, msgs, reply_timeout_s))
                row["probe"] = name
                row["service_alive"] = not row["hung"] and svc.alive()
                rows.append(row)
                i += 1
                if row["hung"] or not svc.alive():
                    row["when_down"] = stop_hung(svc)       # stacks into the log, then SIGKILL to all of it
                    break
        tb = _tracebacks(log)
        rows[-1]["tracebacks_in_log"] = tb
        life += 1
    return rows


# -- part 3: never-reading subscribers -------------------------------------------------------------

def _raw_subscriber(url: str, session: str, token: str) -> socket.socket:
    """A WebSocket subscriber that completes the handshake and never reads again."""
    host, port = url.replace("http://", "").split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    sock.sendall((f"GET /v1/stream/{session}?token={token} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                  "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                  "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(1)
        if not chunk:
            raise ConnectionError("the service closed the never-reading subscriber during the handshake")
        head += chunk
    status_line = head.split(b"\r\n")[0]
    if b" 101 " not in status_line:
        raise ConnectionError(f"handshake refused: {status_line!r}")
    return sock


def _send_queue_bytes(port: int) -> int:
    """Bytes the kernel holds in send queues of the service's sockets on ``port`` (``/proc/net/tcp``)."""
    total = 0
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            parts = line.split()
            if int(parts[1].split(":")[1], 16) == port:
                total += int(parts[4].split(":")[0], 16)
    return total


def run_never_readers(out: Path, readers: int, stream_seconds: float, wait_seconds: float, seed: int) -> dict:
    from clients.client import rest
    log = out / "logs" / "never-readers.log"
    with service_process(log_path=log) as svc:
        port = int(svc.url.rsplit(":", 1)[1])
        socks = [_raw_subscriber(svc.url, "slow", svc.viewer) for _ in range(readers)]
        glove = LoopingGlove(svc, "slow", 1.0, seed=seed)

        async def stream():
            task = asyncio.create_task(glove.run())
            await asyncio.sleep(stream_seconds)
            result = await glove.finish(timeout_s=30)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            return result

        normal = asyncio.run(stream())
        t_end = time.monotonic()
        registered = None
        while True:                                          # bounded wait for the service to let them go
            status, sessions = rest(svc.url, "GET", "/v1/sessions", svc.admin)
            s = next((x for x in sessions if x["session"] == "slow"), {}) if status == 200 else {}
            registered = s.get("subscribers")
            queued = _send_queue_bytes(port)                 # let go: unregistered and their buffers freed
            if (registered == 0 and queued == 0) or time.monotonic() - t_end > wait_seconds:
                break
            time.sleep(0.5)
        waited = time.monotonic() - t_end
        fds = svc.fds()
        dropped = s.get("dropped_subscriber_frames")
        for sock in socks:
            sock.close()
    return {"readers": readers, "stream_seconds": stream_seconds, "waited_s": waited,
            "still_registered": registered, "send_queue_bytes": queued, "service_fds": fds,
            "dropped_frames": dropped, "normal": normal, "tracebacks": _tracebacks(log)}


# -- part 4: connection storm ----------------------------------------------------------------------

async def _storm(svc: ServiceProcess, connects: int, concurrency: int) -> Counter:
    from websockets.asyncio.client import connect
    from websockets.exceptions import InvalidStatus
    base = svc.url.replace("http://", "ws://")
    outcomes: Counter = Counter()
    sem = asyncio.Semaphore(concurrency)

    async def one(i: int):
        kind = ("stream", "ingest", "abort", "refused")[i % 4]
        # sources into four sessions in turn: a newer connection of a token takes its session over
        # (the older one is closed), which two concurrent connects into one session would count as failed
        session = f"storm-{i % 4}" if kind != "ingest" else f"storm-in-{(i // 4) % 4}"
        async with sem:
            try:
                if kind == "stream":
                    async with connect(f"{base}/v1/stream/{session}?token={svc.viewer}", open_timeout=30) as ws:
                        await asyncio.wait_for(ws.recv(), 30)
                elif kind == "ingest":
                    async with connect(f"{base}/v1/ingest/{session}?token={svc.source}", open_timeout=30) as ws:
                        await ws.send(json.dumps({"type": "hello", "protocol": 1, "hand": "right"}))
                        await asyncio.wait_for(ws.recv(), 30)
                elif kind == "abort":
                    sock = await asyncio.to_thread(_raw_subscriber, svc.url, session, svc.viewer)
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
                    sock.close()                                # RST instead of a close handshake
                else:
                    try:
                        async with connect(f"{base}/v1/stream/{session}?token=wrong-{i}", open_timeout=30):
                            outcomes["refused_but_opened"] += 1
                            return
                    except InvalidStatus:
                        pass
                outcomes[kind] += 1
            except Exception as err:                            # counted: the storm reports what failed
                outcomes[f"{kind}_failed:{type(err).__name__}"] += 1

    await asyncio.gather(*(one(i) for i in range(connects)))
    return outcomes


async def _viewer_creates(svc: ServiceProcess, names: list[str]) -> int:
    """Subscribe with the viewer token to names no source created; how many sessions that made."""
    from clients.client import rest
    from websockets.asyncio.client import connect
    base = svc.url.replace("http://", "ws://")
    before = len((await asyncio.to_thread(rest, svc.url, "GET", "/v1/sessions", svc.admin))[1])
    for name in names:
        try:
            async with connect(f"{base}/v1/stream/{name}?token={svc.viewer}", open_timeout=30) as ws:
                await asyncio.wait_for(ws.recv(), 30)
        except Exception:                                       # refused: what a hardened service does
            pass
    after = len((await asyncio.to_thread(rest, svc.url, "GET", "/v1/sessions", svc.admin))[1])
    return after - before


def _metric_sum(text: str, name: str) -> float:
    """The value of an unlabelled series in Prometheus exposition text (0 if absent)."""
    line = next((x for x in text.splitlines() if x.startswith(name + " ")), None)
    return 0.0 if line is None else float(line.split()[-1])


def run_storm(out: Path, connects: int, concurrency: int = 8, rounds: int = 4, settle_seconds: float = 30.0,
              after_idle_seconds: float = 3.0) -> dict:
    """``connects`` connects in ``rounds`` equal rounds; after each, once every connection is gone
    (bounded by ``settle_seconds``) and ``after_idle_seconds`` more, the service's RSS and fds: a leak
    grows round after round, memory held only until a collection does not."""
    from clients.client import rest
    log = out / "logs" / "storm.log"
    with service_process(log_path=log) as svc:
        time.sleep(1.0)
        rss0, fd0 = svc.rss_kib(), svc.fds()
        outcomes: Counter = Counter()
        per_round, wall = [], 0.0
        for k in range(rounds):
            n = connects // rounds + (k < connects % rounds)
            t0 = time.perf_counter()
            outcomes += asyncio.run(_storm(svc, n, concurrency))
            wall += time.perf_counter() - t0
            deadline = time.monotonic() + settle_seconds
            while time.monotonic() < deadline:                  # until every connection is gone, bounded
                status, sessions = rest(svc.url, "GET", "/v1/sessions", svc.admin)
                if status == 200 and all(s.get("subscribers", 0) == 0 and s.get("sources", 0) == 0 for s in sessions):
                    break
                time.sleep(0.5)
            time.sleep(after_idle_seconds)
            per_round.append((n, svc.rss_kib(), svc.fds()))
        metrics = rest(svc.url, "GET", "/metrics", svc.admin)[1]
        created = asyncio.run(_viewer_creates(svc, [f"typo-{i}" for i in range(3)]))
    rss1, fd1 = per_round[-1][1], per_round[-1][2]
    return {"connects": connects, "rounds": per_round, "wall_s": wall, "outcomes": dict(outcomes),
            "rss_before_kib": rss0, "rss_after_kib": rss1, "rss_first_round_kib": per_round[0][1],
            "fds_before": fd0, "fds_after": fd1, "fds_max": max(r[2] for r in per_round),
            "gc_collections": int(_metric_sum(metrics, "fingertrack_connection_gc_seconds_count")),
            "gc_seconds": _metric_sum(metrics, "fingertrack_connection_gc_seconds_sum"),
            "viewer_created_sessions": created, "viewer_attempts": 3, "tracebacks": _tracebacks(log)}


# -- part 5: kill -9 while recording ---------------------------------------------------------------

def run_kill9(out: Path, trials: int, min_s: float, max_s: float, seed: int) -> list[dict]:
    rec_root = out / "recordings"
    rng = random.Random(seed)
    rows = []
    for trial in range(trials):
        rec = rec_root / f"kill9-{trial}"
        rec.mkdir(parents=True, exist_ok=True)
        after = rng.uniform(min_s, max_s)
        with service_process(log_path=out / "logs" / f"kill9-{trial}.log",
                             extra_settings={"record_dir": str(rec), "record_all": True}) as svc:
            glove = LoopingGlove(svc, "rec", 1.0, seed=seed + trial)

            async def stream():
                task = asyncio.create_task(glove.run())
                await asyncio.sleep(after)
                os.kill(svc.pid, signal.SIGKILL)
                glove.stop.set()
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
                glove.sub_task.cancel()
                await asyncio.gather(glove.sub_task, return_exceptions=True)

            asyncio.run(stream())
            sent_t = glove.last_t
        files = sorted(rec.glob("*.jsonl"))
        last_t, lines, bad = None, 0, 0
        for f in files:
            for line in f.read_text(encoding="utf-8", errors="replace").splitlines():
                if not line.strip():
                    continue
                lines += 1
                try:
                    msg = json.loads(line)
                except ValueError:
                    bad += 1
                    continue
                ts = [s["t"] for s in msg.get("samples", [])] if msg.get("type") == "imu_batch" else [msg.get("t")]
                ts = [t for t in ts if isinstance(t, (int, float))]
                if ts:
                    last_t = max(ts + ([last_t] if last_t is not None else []))
        replay = None
        if files:
            proc = subprocess.run([sys.executable, "-m", "service.cli", "replay", str(files[0])],
                                  capture_output=True, text=True, timeout=600)
            replay = proc.returncode
        rows.append({"trial": trial, "killed_after_s": after, "files": len(files), "lines": lines, "bad_lines": bad,
                     "lost_s": (sent_t - last_t) if sent_t is not None and last_t is not None else None,
                     "replay_exit": replay})
    return rows


# -- part 6: soak ----------------------------------------------------------------------------------

def run_soak(out: Path, seconds: float, seed: int, samples: int = 20) -> dict:
    log = out / "logs" / "soak.log"
    with service_process(log_path=log) as svc:
        glove = LoopingGlove(svc, "soak", 1.0, seed=seed, seconds=30.0)
        series = []

        async def go():
            task = asyncio.create_task(glove.run())
            t0 = time.perf_counter()
            step = seconds / samples
            for k in range(1, samples + 1):
                await asyncio.sleep(max(0.0, t0 + k * step - time.perf_counter()))
                series.append((time.perf_counter() - t0, svc.rss_kib(), svc.fds()))
            result = await glove.finish(timeout_s=60)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            return result

        good = asyncio.run(go())
    with open(out / "soak.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "rss_kib", "fds"])
        w.writerows(series)
    warm = series[max(1, len(series) // 10) - 1]               # after the first tenth: imports, caches warmed
    return {"seconds": seconds, "series": series, "rss_start_kib": warm[1], "rss_end_kib": series[-1][1],
            "rss_growth": (series[-1][1] - warm[1]) / warm[1] if warm[1] else None,
            "fds_min": min(s[2] for s in series), "fds_max": max(s[2] for s in series),
            "fds_start": warm[2], "fds_end": series[-1][2], "good": good, "tracebacks": _tracebacks(log)}


# -- the campaign ----------------------------------------------------------------------------------

QUICK = {"messages": 1500, "extreme_seconds": 2.0, "probes": ["imu gyr 1e300 rad/s", "calibration lengths 1e-300 m"],
         "readers": 2, "stream_seconds": 2.0, "wait_seconds": 2.0, "connects": 100, "kill_trials": 1,
         "kill_range": (1.5, 2.5), "soak_seconds": 5.0, "recovery_seconds": 1.5}
FULL = {"messages": 100_000, "extreme_seconds": 6.0, "probes": None, "readers": 5, "stream_seconds": 30.0,
        "wait_seconds": 40.0, "connects": 2000, "kill_trials": 3, "kill_range": (8.0, 20.0), "soak_seconds": 600.0,
        "recovery_seconds": 3.0}


def _good_lost(good: dict | None) -> int | None:
    if good is None or good["produced"] is None:
        return None
    return max(0, good["expected"] - FRAME_TOLERANCE - good["produced"]) + (good["produced"] - good["received"])


def run(out_dir: str | Path, quick: bool = False, messages: int | None = None, soak_seconds: float | None = None,
        seed: int = 0, progress: bool = True) -> str:
    p = dict(QUICK if quick else FULL)
    if messages is not None:
        if messages < 1:
            raise ValueError(f"--messages must be at least 1, got {messages}")
        p["messages"] = messages
    if soak_seconds is not None:
        if soak_seconds < 2:
            raise ValueError(f"--soak-seconds must be at least 2, got {soak_seconds}")
        p["soak_seconds"] = soak_seconds
    out = Path(out_dir)
    (out / "logs").mkdir(parents=True, exist_ok=True)

    def say(text):
        if progress:
            print(f"bench robustness: {text}", file=sys.stderr, flush=True)

    walls = {}

    def part(name, fn, *args, **kwargs):
        say(name)
        t0 = time.perf_counter()
        result = fn(*args, **kwargs)
        walls[name.split(",")[0]] = time.perf_counter() - t0
        return result

    fuzz = part(f"fuzz, {p['messages']} messages", run_fuzz, out, p["messages"], seed,
                recovery_seconds=p["recovery_seconds"])
    extremes = part("extremes", run_extremes, out, p["extreme_seconds"], seed, probes=p["probes"])
    never = part("never-readers", run_never_readers, out, p["readers"], p["stream_seconds"], p["wait_seconds"], seed)
    storm = part(f"storm, {p['connects']} connects", run_storm, out, p["connects"])
    kills = part("kill -9", run_kill9, out, p["kill_trials"], *p["kill_range"], seed)
    soak = part(f"soak, {p['soak_seconds']:.0f} s", run_soak, out, p["soak_seconds"], seed)
    return _write(out, p, fuzz, extremes, never, storm, kills, soak, walls)


def _fmt(x, digits=2):
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{digits}f}"
    return str(x)


def _machine_lines(fuzz: dict) -> list[str]:
    """The machine beside the fuzz, and what was seen when the service stopped answering or did not start."""
    machine, lines = fuzz.get("machine") or {}, []
    if machine.get("least_mem_available_mib") is not None:
        lines.append(f"While the fuzz ran the machine had at least {machine['least_mem_available_mib']:.0f} MiB of memory "
                     f"available; its load (1 min) reached {machine['highest_load_1min']:.1f}.")
    for life in fuzz.get("lives", []):
        seen = life.get("when_down")
        if seen:
            rss = ", ".join(f"{v:.0f}" for v in seen["rss_mib"].values())
            lines.append(f"The service of `logs/{life['log']}` {'hung' if life['down'] == 'hang' else 'crashed'}: the "
                         f"machine had {_fmt(seen['mem_available_mib'], 0)} MiB available, load {seen['load_1min']:.1f}; "
                         f"RSS of the web process and its hand workers {rss} MiB; the stacks of {seen['stacks_written']} "
                         f"of {len(seen['rss_mib'])} processes are in that log.")
    failure = fuzz.get("start_failure")
    if failure:
        lines.append(f"A fresh service (`logs/{failure['log']}`) did not start: the machine had "
                     f"{_fmt(failure['mem_available_mib'], 0)} MiB available, load {failure['load_1min']:.1f}; the fuzz "
                     "stopped there.")
    return lines + [""] if lines else []


def _write(out, p, fuzz, extremes, never, storm, kills, soak, walls) -> str:
    st = fuzz["stats"]
    sent = fuzz["sent"]
    kinds = fuzz["kind_stats"]
    hostile = [s for (_, kind), s in kinds.items() if not kind.startswith(VALID)]
    hostile_sent = sum(s.sent for s in hostile)
    hostile_closed = sum(s.closed_by_design for s in hostile)
    hostile_answered = sum(s.error_reply for s in hostile) + hostile_closed
    hostile_silent = sum(s.silent for s in hostile)
    valid = [s for (_, kind), s in kinds.items() if kind.startswith(VALID)]
    abnormal = sum(s.closed_abnormally for s in st.values())
    good_lost = [_good_lost(g) for g in fuzz["good"]]
    good_lost_total = None if not good_lost or None in good_lost else sum(good_lost)
    rec = fuzz["recovery"]
    rec_times = [r["first_frame_after_last_bad_s"] for r in rec.values()]
    worst_recovery = None if not rec_times or None in rec_times else max(rec_times)
    recovered_all = bool(rec) and all(r["first_frame_after_last_bad_s"] is not None
                                      and r["frames"] >= 0.8 * r["expected"] for r in rec.values())
    ext_tracebacks = sum(r.get("tracebacks_in_log", 0) for r in extremes)
    ext_hangs = sum(1 for r in extremes if r["hung"])
    ext_not_recovered = [r["probe"] for r in extremes
                         if r["first_frame_after_s"] is None or r["first_frame_after_s"] > 1.0
                         or r["frames_after"] < 0.8 * r["expected_after"]]
    ext_non_finite = sum(r["non_finite_messages"] for r in extremes)
    kill_lost = [k["lost_s"] for k in kills]
    rows = [  # (part, check, goal, measured, met)
        ("fuzz", "hostile messages sent", f">= {p['messages']}", sent, sent >= p["messages"]),
        ("fuzz", "crashes", "0", fuzz["crashes"], fuzz["crashes"] == 0),
        ("fuzz", "hangs (service restarted)", "0", fuzz["hangs"], fuzz["hangs"] == 0),
        ("fuzz", "stalls (no reply within the reply timeout, /health answering)", "0", fuzz["stalls"],
         fuzz["stalls"] == 0),
        ("fuzz", "tracebacks in the service log", "0", fuzz["tracebacks"], fuzz["tracebacks"] == 0),
        ("fuzz", "connections dropped abnormally", "0", abnormal, abnormal == 0),
        ("fuzz", "hostile messages answered with an error reply, or closed with the reason (1008 for another "
         "protocol, 1009 for a frame over 4 MiB)", f"{hostile_sent}",
         f"{hostile_answered} ({hostile_closed} closed)", hostile_answered == hostile_sent),
        ("fuzz", "hostile messages accepted without a reply", "0", hostile_silent, hostile_silent == 0),
        ("fuzz", "good session: frames lost", "0", good_lost_total, good_lost_total == 0),
        ("fuzz", "attacked sessions: worst time to a frame of a fresh glove's data (source clock), s", "<= 1",
         worst_recovery, recovered_all and worst_recovery is not None and worst_recovery <= 1.0),
        ("extremes", "probes after which frames did not resume within 1 s",
         "0", f"{len(ext_not_recovered)} of {len(extremes)}", not ext_not_recovered),
        ("extremes", "probes that hung the service", "0", ext_hangs, ext_hangs == 0),
        ("extremes", "messages sent with NaN/Infinity", "0", ext_non_finite, ext_non_finite == 0),
        ("extremes", "tracebacks in the service log", "0", ext_tracebacks, ext_tracebacks == 0),
        ("never-readers", f"still registered {_fmt(never['waited_s'], 0)} s after the stream",
         "0", f"{never['still_registered']} of {never['readers']}", never["still_registered"] == 0),
        ("never-readers", "bytes still queued to them by the service", "0", never["send_queue_bytes"],
         never["send_queue_bytes"] == 0),
        ("never-readers", "normal subscriber: frames lost", "0", _good_lost(never["normal"]),
         _good_lost(never["normal"]) == 0),
        ("storm", f"service fds before -> after {storm['connects']} connects", "no growth",
         f"{storm['fds_before']} -> {storm['fds_after']}",
         None not in (storm["fds_before"], storm["fds_after"]) and storm["fds_after"] <= storm["fds_before"]),
        ("storm", "service RSS before -> after, MiB", "<= +5 %",
         f"{storm['rss_before_kib'] / 1024:.0f} -> {storm['rss_after_kib'] / 1024:.0f}",
         storm["rss_after_kib"] <= 1.05 * storm["rss_before_kib"]),
        ("storm", f"service RSS after the first -> the last of {len(storm['rounds'])} rounds, MiB (a leak grows "
         "round after round)", "<= +1 %",
         f"{storm['rss_first_round_kib'] / 1024:.1f} -> {storm['rss_after_kib'] / 1024:.1f}",
         storm["rss_after_kib"] <= 1.01 * storm["rss_first_round_kib"]),
        ("storm", "tracebacks in the service log", "0", storm["tracebacks"], storm["tracebacks"] == 0),
        ("storm", f"sessions a viewer token created ({storm['viewer_attempts']} subscriptions to new names)", "0",
         storm["viewer_created_sessions"], storm["viewer_created_sessions"] == 0),
        ("kill -9", "seconds of sent data missing from the recording (worst trial)", "<= 1",
         None if None in kill_lost or not kill_lost else max(kill_lost),
         bool(kill_lost) and None not in kill_lost and max(kill_lost) <= 1.0),
        ("kill -9", "recordings that `fingertrack replay` reads (exit 0)", f"{len(kills)}",
         sum(1 for k in kills if k["replay_exit"] == 0), all(k["replay_exit"] == 0 for k in kills)),
        ("soak", f"RSS growth over {soak['seconds']:.0f} s (after the first tenth)", "<= 5 %",
         f"{100 * soak['rss_growth']:.1f} %", soak["rss_growth"] is not None and soak["rss_growth"] <= 0.05),
        ("soak", "fd count min / max", "flat", f"{soak['fds_min']} / {soak['fds_max']}",
         soak["fds_max"] <= soak["fds_start"]),
        ("soak", "frames lost (produced vs the glove's data, delivered vs produced)", "0",
         _good_lost(soak["good"]), _good_lost(soak["good"]) == 0),
    ]
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["part", "check", "goal", "measured", "met"])
        w.writerows(rows)
    with open(out / "fuzz.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["category", "sent", "error_reply", "other_reply", "silent", "closed_by_design",
                    "closed_abnormally", "stalls", "hangs", "crashes", "codes", "closes"])
        for name, s in sorted(st.items()):
            w.writerow([name, s.sent, s.error_reply, s.other_reply, s.silent, s.closed_by_design,
                        s.closed_abnormally, s.stalls, s.hangs, s.crashes, " ".join(f"{c}={n}" for c, n in s.codes.most_common()),
                        "; ".join(f"{c}={n}" for c, n in s.closes.most_common())])
    ext_cols = ["probe", "hung", "service_alive", "frames_before", "frames_after", "expected_after",
                "first_frame_after_s", "errors_after", "error_codes", "non_finite_messages"]
    with open(out / "extremes.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(ext_cols)
        for r in extremes:
            w.writerow([json.dumps(r[c]) if isinstance(r[c], dict) else r[c] for c in ext_cols])
    with open(out / "fuzz_kinds.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["category", "kind", "valid", "sent", "error_reply", "other_reply", "silent", "closed_by_design",
                    "closed_abnormally", "stalls", "hangs", "crashes", "codes"])
        for (name, kind), s in sorted(kinds.items()):
            w.writerow([name, kind, kind.startswith(VALID), s.sent, s.error_reply, s.other_reply, s.silent,
                        s.closed_by_design, s.closed_abnormally, s.stalls, s.hangs, s.crashes,
                        " ".join(f"{c}={n}" for c, n in s.codes.most_common())])
    (out / "results.json").write_text(json.dumps({
        "parameters": p, "wall_s": walls, "fuzz": {k: v for k, v in fuzz.items() if k not in ("stats", "kind_stats", "unanswered")},
        "fuzz_categories": {k: vars(v) | {"codes": dict(v.codes)} for k, v in st.items()},
        "fuzz_kinds": {f"{c}: {k}": vars(v) | {"codes": dict(v.codes)} for (c, k), v in kinds.items()},
        "extremes": extremes, "never_readers": never, "storm": storm, "kill9": kills,
        "soak": {k: v for k, v in soak.items()}}, indent=2, default=str))

    met = sum(1 for r in rows if r[4])
    lines = [f"# Robustness campaign: {met} of {len(rows)} checks met", "",
             f"Fuzz: {sent} messages in {fuzz['wall_s']:.0f} s ({'stopped early, ' if fuzz['stopped_early'] else ''}"
             f"{fuzz['service_restarts']} service restarts); soak {soak['seconds']:.0f} s; storm {storm['connects']} connects. "
             "Wall time per part, s: " + ", ".join(f"{k} {v:.0f}" for k, v in walls.items()) + ".",
             ""]
    lines += _machine_lines(fuzz)
    lines += ["| part | check | goal | measured | met |", "|---|---|---|---|---|"]
    lines += [f"| {a} | {b} | {c} | {_fmt(d)} | {'yes' if e else '**no**'} |" for a, b, c, d, e in rows]
    lines += ["", "## Fuzz by category", "",
              "| category | sent | error reply | other reply | silent | closed by design | closed abnormally | stalls | "
              "hangs | most frequent codes |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in sorted(st.items()):
        codes = ", ".join(f"{c} {n}" for c, n in s.codes.most_common(3))
        lines.append(f"| {name} | {s.sent} | {s.error_reply} | {s.other_reply} | {s.silent} | {s.closed_by_design} | "
                     f"{s.closed_abnormally} | {s.stalls} | {s.hangs + s.crashes} | {codes} |")
    lines += ["", "## Fuzz by kind", "",
              f"A kind that starts with \"{VALID.strip()}\" is a message the protocol accepts as it is (an unknown field, a "
              "number within its range such as 5e-324 m, a sample reordered within the clock step, a hello): any "
              f"reply or none is right for it. Valid: {sum(s.sent for s in valid)} messages, "
              f"{sum(s.silent for s in valid)} of them accepted without a reply; hostile: {hostile_sent}, "
              f"{hostile_silent} accepted without a reply (each in `fuzz_unanswered.csv`, the first 1,000). A time "
              "probe is labelled by the attacked session's clock as the documented rule defines it, followed from "
              "the messages sent and the replies (a step beyond 0.5 s from the newest IMU time starts a new clock, "
              f"answered with `clock_step`); messages whose `clock_step` notice differed from that rule's "
              f"prediction: {fuzz['clock_disagreements']}.", "",
              "| category | kind | sent | error reply | other reply | silent | closed by design | most frequent codes |",
              "|---|---|---|---|---|---|---|---|"]
    for (name, kind), s in sorted(kinds.items(), key=lambda x: (x[0][1].startswith(VALID), x[0])):
        codes = ", ".join(f"{c} {n}" for c, n in s.codes.most_common(2))
        lines.append(f"| {name} | {kind} | {s.sent} | {s.error_reply} | {s.other_reply} | {s.silent} | "
                     f"{s.closed_by_design} | {codes} |")
    lines += ["", "Attacked sessions, right after their last bad message a fresh glove (new connection, its clock carrying on "
              "from the fuzz's) streams good data in real time; times on the source clock:", "",
              "| session | first frame after the glove's first data, s | frames / expected | error replies |",
              "|---|---|---|---|"]
    for name, r in sorted(rec.items()):
        lines.append(f"| {name} | {_fmt(r['first_frame_after_last_bad_s'])} | {r['frames']} / {r['expected']} | {r['errors']} |")
    for i, g in enumerate(fuzz["good"]):
        lines.append(f"\nGood session beside the fuzz (service life {i}): {g['sent_seconds']:.1f} s of data sent, "
                     f"{g['produced']} frames produced (expected {g['expected']} from the data, tolerance "
                     f"{FRAME_TOLERANCE}), {g['received']} received, {g['seq_gaps']} seq gaps, {g['reconnects']} "
                     f"reconnects, {g['errors']} error replies.")
    lines += ["", "## Schema-valid extremes injected into a live stream", "",
              "| probe | service | frames after / expected | first frame after, source s | error replies after | codes | "
              "messages with NaN/Infinity |", "|---|---|---|---|---|---|---|"]
    for r in extremes:
        codes = ", ".join(f"{c} {n}" for c, n in sorted(r["error_codes"].items(), key=lambda x: -x[1])[:3])
        lines.append(f"| {r['probe']} | {'hung' if r['hung'] else 'ok' if r['service_alive'] else 'died'} | "
                     f"{r['frames_after']} / {r['expected_after']} | {_fmt(r['first_frame_after_s'])} | "
                     f"{r['errors_after']} | {codes} | {r['non_finite_messages']} |")
    lines += ["", f"Never-reading subscribers: {never['readers']} beside a normal one, {never['stream_seconds']:.0f} s of "
              f"real-time stream; {never['dropped_frames']} frames dropped for them; service fds at the end "
              f"{never['service_fds']}.",
              f"Storm outcomes: {', '.join(f'{k} {v}' for k, v in sorted(storm['outcomes'].items()))} "
              f"in {storm['wall_s']:.1f} s; RSS (MiB) / fds after each round of "
              f"{storm['rounds'][0][0]}: " + ", ".join(f"{r[1] / 1024:.1f} / {r[2]}" for r in storm["rounds"])
              + f" (before: {storm['rss_before_kib'] / 1024:.1f} / {storm['fds_before']}); "
              f"{storm['gc_collections']} collections after connections ended, {storm['gc_seconds']:.2f} s in all.",
              "Kill -9 trials: " + "; ".join(f"after {k['killed_after_s']:.1f} s: {k['lines']} lines, {k['bad_lines']} bad, "
                                            f"lost {_fmt(k['lost_s'])} s, replay exit {k['replay_exit']}" for k in kills),
              f"Soak: RSS {soak['rss_start_kib'] / 1024:.1f} -> {soak['rss_end_kib'] / 1024:.1f} MiB, fds "
              f"{soak['fds_start']} -> {soak['fds_end']}; the glove: {soak['good']['sent_seconds']:.0f} s sent, "
              f"{soak['good']['produced']} frames produced (expected {soak['good']['expected']}), "
              f"{soak['good']['reconnects']} reconnects, {soak['good']['errors']} error replies.",
              "", "Frames lost = expected from the glove's data (90 Hz over the source time it sent, less "
              f"{FRAME_TOLERANCE} for the pipeline's alignment wait at the ends) minus produced, plus produced minus "
              "delivered to the subscriber. The service logs are in `logs/`."]
    text = "\n".join(lines) + "\n"
    (out / "summary.md").write_text(text)
    return text
