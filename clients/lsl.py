"""Lab Streaming Layer bridge: subscribes to fingertrack sessions and republishes them as LSL streams,
so any LSL recorder (LabRecorder, XDF) or online analysis gets the hand beside EEG, EMG or body data.

Per session (``fingertrack lsl --session NAME[:HAND]``):

* ``fingertrack <session> <hand>``, type ``MoCap``: one float32 channel per joint angle (thumb
  ``mcp, ip``; index, middle, ring, little ``mcp, pip, dip``: 14 channels), radians, flexion
  positive. The stream description lists every channel (``label`` ``<finger>_<joint>``, ``unit``
  ``radians``, ``type`` ``JointAngle``), the hand, the session, the service and the clock mapping.
  Nominal rate: the service's frame rate (90 Hz unless configured otherwise).
* ``fingertrack <session> gestures``, type ``Markers``: one string channel, irregular rate; each
  gesture event as JSON text (``{"gesture": "point", "event": "start", "confidence": 0.8, ...}``).

``source_id`` is ``fingertrack/<host:port>/<session>/<hand>`` (``.../gestures`` for the markers): the
same across restarts of the bridge or the service, so a recorder that lost a stream picks it up again.
Streams are created when the bridge starts (an inlet can connect before the first frame); a session
whose source turns out to be the other hand gets a second hand stream.

Time: a frame's ``t`` is on the source's clock. Its LSL timestamp is ``t + offset``:

* ``source_clock="lsl"``: the source stamps ``t`` with this machine's monotonic clock, which is the
  LSL clock (``pylsl.local_clock()``); the offset is 0 and the timestamp is the source's own time.
* ``source_clock="estimate"`` (default, any other source): the offset is the smallest ``arrival - t``
  seen so far in the source's run (``arrival`` = ``local_clock()`` when the frame reaches the bridge),
  the usual minimum-delay estimate: the source's sample spacing is kept exactly, timestamps are
  never later than the arrival, and they are late by the smallest end-to-end delay seen (the
  service's reorder window, 20 ms by default, plus transport). A new run of the source clock (time
  going backwards, or a clock step the service reports) starts a new estimate. Drift between the two
  clocks is followed only when it lowers the offset.

Gesture events carry the ``t`` of the frame that caused them and get the same mapping.
"""
from __future__ import annotations

import asyncio
import json
import math
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from service.protocol.messages import FINGER_JOINTS

from .client import Subscription

CHANNELS: tuple[tuple[str, str], ...] = tuple((f, j) for f, joints in FINGER_JOINTS.items() for j in joints)
"""(finger, joint) of every channel of a hand stream, in channel order."""
SOURCE_CLOCKS = ("estimate", "lsl")


def load_pylsl():
    """``pylsl``, or a ``RuntimeError`` saying how to get it (it ships liblsl in its wheel)."""
    try:
        import pylsl
    except ImportError:
        raise RuntimeError("the LSL bridge needs pylsl: pip install 'fingertrack[lsl]'") from None
    except (RuntimeError, OSError) as err:          # pylsl without a loadable liblsl
        raise RuntimeError(f"pylsl cannot load liblsl: {err}") from None
    return pylsl


class ClockMap:
    """Source clock -> LSL clock for one session (module docstring, "Time")."""

    def __init__(self, source_clock: str = "estimate"):
        if source_clock not in SOURCE_CLOCKS:
            raise ValueError(f"source clock must be one of {list(SOURCE_CLOCKS)}, got {source_clock!r}")
        self.source_clock = source_clock
        self.offset: float | None = 0.0 if source_clock == "lsl" else None
        self._last_t: float | None = None
        self._clock_steps: int | None = None
        self.runs = 0

    def frame_time(self, t: float, arrival: float, clock_steps: int | None = None) -> float:
        """The LSL time of a frame at source time ``t`` that arrived at LSL time ``arrival``."""
        if self.source_clock == "lsl":
            return t
        new_run = self._last_t is None or t < self._last_t or (
            clock_steps is not None and self._clock_steps is not None and clock_steps != self._clock_steps)
        if new_run:
            self.offset = None
            self.runs += 1
        self._last_t, self._clock_steps = t, clock_steps
        delay = arrival - t
        if self.offset is None or delay < self.offset:
            self.offset = delay
        return t + self.offset

    def event_time(self, t: float) -> float:
        """The LSL time of a gesture event at source time ``t`` (its frame has been mapped already)."""
        return t + (self.offset or 0.0)


@dataclass
class SessionStreams:
    """The LSL outlets of one session."""

    session: str
    declared_hand: str
    clock: ClockMap
    hands: dict = field(default_factory=dict)          # hand -> StreamOutlet
    markers: object | None = None
    frames: int = 0
    events: int = 0


class LslBridge:
    """Subscribes to sessions of a fingertrack service and republishes them on LSL (module docstring).

    ``sessions``: ``(name, hand)`` pairs; ``hand`` is what the session's source is expected to be
    (``right``/``left``), used to create the hand stream before the first frame."""

    def __init__(self, url: str, token: str, sessions: list[tuple[str, str]], source_clock: str = "estimate",
                 rate_hz: float = 90.0, binary: bool = False):
        self.pylsl = load_pylsl()
        if not sessions:
            raise ValueError("name at least one session")
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate must be a positive number of Hz, got {rate_hz}")
        self.url, self.token, self.binary, self.rate_hz = url, token, binary, rate_hz
        self.source_clock = ClockMap(source_clock).source_clock     # validated
        self.service = urlsplit(url).netloc or url
        self.streams: dict[str, SessionStreams] = {}
        self.subscriptions: list[Subscription] = []
        for name, hand in sessions:
            if hand not in ("right", "left"):
                raise ValueError(f"session {name!r}: hand must be right or left, got {hand!r}")
            s = SessionStreams(name, hand, ClockMap(source_clock))
            s.markers = self.pylsl.StreamOutlet(self._marker_info(name))
            self._hand_outlet(s, hand)
            self.streams[name] = s

    # -- stream descriptions ------------------------------------------------------------------------
    def source_id(self, session: str, what: str) -> str:
        return f"fingertrack/{self.service}/{session}/{what}"

    def _describe(self, info, session: str) -> None:
        desc = info.desc()
        desc.append_child_value("manufacturer", "fingertrack")
        desc.append_child_value("session", session)
        desc.append_child_value("service", self.service)
        clock = desc.append_child("clock")
        clock.append_child_value("source_clock", self.source_clock)
        clock.append_child_value("mapping", "lsl_time = t + 0 (the source stamps with the LSL clock)"
                                 if self.source_clock == "lsl" else
                                 "lsl_time = t + min(arrival - t) over the source's run (minimum-delay estimate)")

    def hand_info(self, session: str, hand: str):
        pylsl = self.pylsl
        info = pylsl.StreamInfo(f"fingertrack {session} {hand}", "MoCap", len(CHANNELS), self.rate_hz,
                                pylsl.cf_float32, self.source_id(session, hand))
        self._describe(info, session)
        info.desc().append_child_value("hand", hand)
        channels = info.desc().append_child("channels")
        for finger, joint in CHANNELS:
            ch = channels.append_child("channel")
            ch.append_child_value("label", f"{finger}_{joint}")
            ch.append_child_value("unit", "radians")
            ch.append_child_value("type", "JointAngle")
            ch.append_child_value("finger", finger)
            ch.append_child_value("joint", joint)
        return info

    def _marker_info(self, session: str):
        pylsl = self.pylsl
        info = pylsl.StreamInfo(f"fingertrack {session} gestures", "Markers", 1, pylsl.IRREGULAR_RATE,
                                pylsl.cf_string, self.source_id(session, "gestures"))
        self._describe(info, session)
        info.desc().append_child_value("format", "JSON text of each gesture event: gesture, event, confidence, ray")
        return info

    def _hand_outlet(self, s: SessionStreams, hand: str):
        if hand not in s.hands:
            s.hands[hand] = self.pylsl.StreamOutlet(self.hand_info(s.session, hand))
        return s.hands[hand]

    # -- republishing -------------------------------------------------------------------------------
    def handle(self, session: str, message: dict, arrival: float | None = None) -> None:
        """Push one message of ``session`` (a ``frame`` or a ``gesture``; others are ignored)."""
        s = self.streams[session]
        arrival = self.pylsl.local_clock() if arrival is None else arrival
        if message["type"] == "frame":
            stamp = s.clock.frame_time(message["t"], arrival, message.get("status", {}).get("clock_steps"))
            fingers = message["fingers"]
            sample = [fingers.get(f, {}).get(j, math.nan) for f, j in CHANNELS]
            self._hand_outlet(s, message["hand"]).push_sample([math.nan if v is None else v for v in sample], stamp)
            s.frames += 1
        elif message["type"] == "gesture":
            event = {k: v for k, v in message.items() if k != "type"}
            s.markers.push_sample([json.dumps(event, separators=(",", ":"))], s.clock.event_time(message["t"]))
            s.events += 1

    async def _follow(self, session: str) -> None:
        sub = Subscription(self.url, session, self.token, binary=self.binary)
        self.subscriptions.append(sub)
        async for message in sub:
            self.handle(session, message)

    async def run(self) -> None:
        """Follow every session until ``close()`` (a refused token or role raises)."""
        await asyncio.gather(*(self._follow(name) for name in self.streams))

    async def close(self) -> None:
        for sub in self.subscriptions:
            await sub.close()
