"""Live sessions: one tracked hand per session name, its subscribers and its recording.

One source per session: a new connection of the same token takes over (the older one is closed with
1008, e.g. after a network change left it half-open); another token is refused with 1008.

Lifecycle (``Sessions``): only a source (or an admin changing a session's configuration) creates a
session; a viewer subscribing to a name that does not exist yet waits for it without creating
anything (its subscriber joins the session the moment a source creates it, before any frame). A
session with no source and no output for ``idle_timeout_s`` is removed and its recording closed, whether
viewers watch it or not: a viewer neither creates nor keeps a table entry. Its viewers stay connected
and wait for the session's next source as for a new session.

Backpressure: every subscriber has its own bounded queue. Frames beyond ``subscriber_queue_frames``
push out the subscriber's oldest frame (counted per session and in the metrics); gesture events are
kept in order and never dropped (a subscriber more than ``subscriber_queue_events`` events behind is
closed instead). Ingest only appends to queues, so a slow subscriber never slows ingest or the others.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from pydantic import BaseModel, ConfigDict, Field

from gestures.recognizer import GestureSettings
from ..estimators.registry import EstimatorSpec
from ..estimators.warm import warm_ahead
from ..pipeline.hand import Dropped, PipelineSettings
from ..pipeline.tracked import TrackedHand
from ..protocol.messages import dump_message
from ..protocol.wire import parse_input
from ..protocol.outgoing import FrameDict, FrameStatusDict, GestureDict
from .config import ServiceSettings
from .metrics import Metrics
from .outgoing import Outgoing

log = logging.getLogger(__name__)

SESSION_NAME_MAX = 64


class SubscriberTooSlow(Exception):
    pass


_due: dict[asyncio.AbstractEventLoop, list] = {}
"""per event loop: the subscribers whose ``writer`` runs at the end of the current turn (``_write_at_turns_end``)"""


def _write_at_turns_end(sub: "Subscriber") -> None:
    """``sub._write_soon()`` at the end of this turn of the loop, in one callback for every subscriber queued to
    in the turn (a callback each, with the running loop looked up each time, cost more than a frame's write)."""
    loop = sub._loop
    if loop is None:
        loop = sub._loop = asyncio.get_running_loop()
    due = _due.get(loop)
    if due is None:
        due = _due[loop] = []
        loop.call_soon(_write_due, loop)
    due.append(sub)


def _write_due(loop: asyncio.AbstractEventLoop) -> None:
    for sub in _due.pop(loop, ()):
        sub._write_soon()


@dataclass(eq=False)
class Subscriber:
    frames_max: int
    events_max: int
    binary: bool = False
    queue: deque = field(default_factory=deque)      # (kind, Outgoing, t_ingest) in order
    frames_queued: int = 0
    dropped: int = 0
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    closed: bool = False
    writer: Callable[[], None] | None = None
    """set by the subscriber's sender while it waits with nothing queued (``routes.stream``): called once per
    turn of the loop after messages were queued, to write them there and then, in place of a wake of the
    sender (its task's turn and its wait's future cost the web process more than the write of a frame)"""
    _writing_soon: bool = False
    _loop: asyncio.AbstractEventLoop | None = None
    writer_failed: bool = False
    """``writer`` raised once (a defect, logged): the sender no longer sets it"""

    def put(self, message: Outgoing, t_ingest: float) -> int:
        """Queue a message; returns how many frames were dropped to make room."""
        dropped = 0
        if message.type == "frame":
            if self.frames_queued >= self.frames_max:
                for i, (kind, _, _) in enumerate(self.queue):
                    if kind == "frame":
                        del self.queue[i]
                        self.frames_queued -= 1
                        dropped = 1
                        break
            self.frames_queued += 1
        elif sum(1 for k, _, _ in self.queue if k != "frame") >= self.events_max:
            self.closed = True
            raise SubscriberTooSlow()
        self.queue.append((message.type, message, t_ingest))
        if dropped:
            self.dropped += dropped
        if self.writer is None:
            self.wake.set()
        elif not self._writing_soon:
            self._writing_soon = True
            _write_at_turns_end(self)
        return dropped

    def _write_soon(self) -> None:
        self._writing_soon = False
        if self.writer is not None and self.queue:      # (else the sender woke meanwhile: it sends them)
            try:
                self.writer()
            except Exception:                           # a defect: logged once; from now on the sender sends
                log.exception("writing a subscriber's queued outputs at the end of the turn failed; its sender "
                              "sends them from now on")
                self.writer_failed, self.writer = True, None
                self.wake.set()

    def pop(self):
        kind, msg, t = self.queue.popleft()
        if kind == "frame":
            self.frames_queued -= 1
        if not self.queue:
            self.wake.clear()
        return msg, t

    def close(self) -> None:
        """Ask the subscriber's sender to finish (it sends the close frame)."""
        self.closed = True
        self.wake.set()


class Recorder:
    """Appends source messages to a JSON Lines file, flushed at least every ``flush_interval_s``."""

    def __init__(self, path: Path, flush_interval_s: float):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._fh = open(path, "a", encoding="utf-8")
        self._interval = flush_interval_s
        self._last_flush = time.monotonic()

    def write(self, message: dict) -> None:
        self._fh.write(json.dumps(message, separators=(",", ":")) + "\n")
        if time.monotonic() - self._last_flush >= self._interval:
            self.flush()

    def flush(self) -> None:
        if not self._fh.closed:
            self._fh.flush()
            self._last_flush = time.monotonic()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.flush()
            self._fh.close()


class SessionConfig(BaseModel):
    """What ``GET/PUT /v1/sessions/{session}/config`` reads and changes (``LiveSession.update_config``
    validates a change whole, then replaces the configuration)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    estimator: str = Field(description="estimator name (``fingertrack estimate --list``)")
    estimator_params: dict[str, Any] = Field(default_factory=dict, description="the estimator's settings as given "
                                             "(its defaults for the others)")
    gestures: GestureSettings = Field(default_factory=GestureSettings, description="gesture recogniser thresholds")
    record: bool = Field(description="the session's source messages are recorded (needs the service's record_dir)")


class SessionConfigChange(BaseModel):
    """Body of ``PUT /v1/sessions/{session}/config``: the fields to change; the others (omitted or
    null) stay."""

    model_config = ConfigDict(extra="forbid")

    estimator: str | None = Field(None, description="estimator name (``fingertrack estimate --list``)")
    estimator_params: dict[str, Any] | None = Field(None, description="the estimator's settings; omitted: kept if the estimator stays, else its defaults")
    gestures: dict[str, Any] | None = Field(None, description="gesture recogniser settings to change")
    record: bool | None = Field(None, description="record the session's source messages (needs the service's record_dir)")


class LiveSession:
    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics):
        self.name = name
        self.settings = settings
        self.metrics = metrics
        self.config = SessionConfig(estimator=settings.estimator, record=settings.record_all)
        self.hand: TrackedHand | None = self._make_hand()
        self.subscribers: set[Subscriber] = set()
        self.recorder: Recorder | None = None
        self.source: Any = None
        """The connection feeding the session (one at a time), and its token."""
        self.source_token: str | None = None
        self._last_status: FrameStatusDict | dict = {}
        self.frames_out = 0
        self.dropped_frames = 0
        self.overloaded = 0
        """Source messages refused because the service could not keep up (``backlog.py``)."""
        self.created = time.time()
        self.owner: str | None = None
        """The token that created it (its quota key; ``None``: an admin)."""
        self.idle_since: float | None = time.monotonic()
        """Since when the session has had no source and no output; ``None`` while a source is connected.
        Subscribers do not count (a viewer does not keep a session alive)."""
        self._lock = asyncio.Lock()
        self._apply_recording()

    def _make_hand(self) -> TrackedHand | None:
        """The session's hand, run here (``None`` in a session whose hand runs in another process)."""
        return TrackedHand(settings=PipelineSettings(estimator=self.settings.estimator,
                                                     output_rate_hz=self.settings.output_rate_hz))

    @property
    def sources(self) -> int:
        return int(self.source is not None)

    def touch(self) -> None:
        """Note a connection coming or going: idle from now if no source is left."""
        self.idle_since = None if self.sources else time.monotonic()

    def _apply_recording(self) -> None:
        want = self.config.record and self.settings.record_dir is not None
        if want and self.recorder is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            self.recorder = Recorder(Path(self.settings.record_dir) / f"{self.name}-{stamp}.jsonl", self.settings.flush_interval_s)  # type: ignore[arg-type]
        elif not want and self.recorder is not None:
            self.recorder.close()
            self.recorder = None

    def checked_config(self, change: SessionConfigChange | dict) -> tuple[EstimatorSpec, dict, GestureSettings, bool]:
        """A configuration change (a dict as a ``SessionConfigChange``) validated against the current
        configuration: the estimator, its parameters, the gesture settings and whether to record, as
        they would be after it (nothing changes here; ``ValueError``/``ValidationError`` naming what
        is wrong)."""
        change = SessionConfigChange.model_validate(change)
        current = self.config
        estimator = current.estimator if change.estimator is None else change.estimator
        params = change.estimator_params
        if params is None:
            params = current.estimator_params if estimator == current.estimator else {}
        gestures = current.gestures
        if change.gestures is not None:
            gestures = GestureSettings(**{**current.gestures.model_dump(), **change.gestures})
        spec = EstimatorSpec.of(estimator, params)
        record = current.record if change.record is None else change.record
        if record and self.settings.record_dir is None:
            raise ValueError("record: the service has no record_dir; start it with one to record sessions")
        return spec, params, gestures, record

    def update_config(self, change: SessionConfigChange | dict) -> dict:
        """Validate everything first (a dict as a ``SessionConfigChange``), then apply: a bad change
        changes nothing."""
        spec, params, gestures, record = self.checked_config(change)
        if (spec.name, params) != (self.config.estimator, self.config.estimator_params):
            # the estimator's kernels are compiled in another process before the hand switches to it
            warm_ahead(spec.name, params)
            self.hand.set_estimator(spec)
        self.config = SessionConfig(estimator=spec.name, estimator_params=params, gestures=gestures, record=record)
        self.hand.set_gesture_settings(gestures)
        self._apply_recording()
        return self.config.model_dump()

    def enrol(self, segments: list) -> dict:
        """Fit the gesture thresholds to labelled segments of the recent frames and apply them
        (``gestures.enrolment``); raises ``EnrolmentError`` naming what was wrong."""
        from gestures.enrolment import enrol
        fitted, report = enrol(self.hand.recognizer, segments, self.config.gestures)
        config = self.update_config({"gestures": fitted.model_dump()})
        return {"gestures": config["gestures"], "changes": report}

    def parse_input(self, data: str | bytes, binary: bool):
        """``(decoded value, validated message)`` of a received message (``protocol.parse_input``; a
        session whose hand runs in a worker process leaves data messages to the worker to validate)."""
        return parse_input(data, binary)

    def forwardable(self, data: dict):
        """The message of a received WebSocket message the ingest route's reader may hand to ``ingest``
        itself (a greeted connection's, nothing queued before it) because nothing is to be answered or
        waited for before it goes on: ``None`` here (a session whose hand runs here does the work then)."""
        return None

    def forwardable_text(self, text: str):
        """``forwardable`` of a received text message."""
        return self.forwardable({"type": "websocket.receive", "text": text})

    def forward(self, msg) -> None:
        """Hand on a message ``forwardable`` gave, at once (never called here: it gives none)."""
        raise NotImplementedError

    async def ingest(self, raw: dict, parsed) -> Dropped | None:
        """Run one validated source message through the hand and fan the outputs out; after each
        frame it yields to the event loop so the subscribers' senders go out before the next tick.
        Returns what the message dropped and why (``None``: a session whose hand runs elsewhere
        answers later, through ``attach_source``)."""
        t0 = time.perf_counter()
        async with self._lock:          # several sources (glove, tracker) may feed one hand: one at a time
            self.metrics.of_session(self.name).received()
            if self.recorder is not None:
                self.recorder.write(dump_message(parsed))     # as validated: unknown fields dropped
            dropped = self.hand.accept(parsed)
            for group in self.hand.outputs():
                self._fan_out(group, t0)
                await asyncio.sleep(0)
        return dropped

    def attach_source(self, send_error) -> None:
        """``send_error(code, detail)`` (async) answers the connected source. Errors are found while
        ingesting here, so the embedded session needs it not; a bus session answers from its replies."""

    async def settled(self) -> None:
        """Every message ingested so far has been handled (here: as soon as ``ingest`` returned)."""

    def answer_in_order(self, answer) -> bool:
        """Have ``answer()`` (an async reply to the source, e.g. ``sync``'s, due once every message ingested so
        far is handled and its error replies are out: ``settled``) sent in its place among the error replies,
        without holding back the messages after it; ``False`` where the session does not (the caller waits
        for ``settled``, then answers)."""
        return False

    def _fan_out(self, group: list[FrameDict | GestureDict], t0: float) -> None:
        for out in group:
            if out["type"] == "frame":
                self._last_status = out["status"]
                out["status"]["dropped"]["subscriber_frames"] = self.dropped_frames
                out["status"]["dropped"]["overloaded"] = self.overloaded
            self._deliver(Outgoing(out), t0)  # serialised once, on first send, for every subscriber

    def _deliver(self, encoded: Outgoing, t0: float) -> None:
        """One output message to every subscriber's queue."""
        if self.idle_since is not None:       # output with no source here (its tail; on a bus, another gateway's source)
            self.idle_since = time.monotonic()
        if encoded.type == "frame":
            self.frames_out += 1
        for sub in list(self.subscribers):
            try:
                dropped = sub.put(encoded, t0)
            except SubscriberTooSlow:
                self.subscribers.discard(sub)
                continue
            if dropped:
                self.dropped_frames += dropped
                self.metrics.dropped_frames.labels(self.name).inc(dropped)

    @property
    def last_status(self) -> FrameStatusDict | dict:
        """The status of the last frame sent (``{}`` before the first)."""
        return self._last_status

    def summary(self) -> dict:
        return {"session": self.name, "hand": self.hand.hand if self.hand is not None else None, "sources": self.sources,
                "subscribers": len(self.subscribers), "frames_out": self.frames_out,
                "dropped_subscriber_frames": self.dropped_frames, "overloaded": self.overloaded,
                "config": self.config.model_dump(),
                "status": self.last_status, "recording": str(self.recorder.path) if self.recorder else None}

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()


class SessionFull(Exception):
    """The service holds ``max_sessions`` sessions; a new one may fit later."""


def check_session_name(name: str) -> None:
    if not (1 <= len(name) <= SESSION_NAME_MAX) or not all(c.isalnum() or c in "-_." for c in name):
        raise ValueError(f"session name must be 1-{SESSION_NAME_MAX} characters of letters, digits, '-', '_', '.', got {name!r}")


class Sessions:
    """The service's live sessions by name, at most ``settings.max_sessions``, and its shutdown."""

    def __init__(self, settings: ServiceSettings, metrics: Metrics):
        self.settings = settings
        self.metrics = metrics
        self.by_name: dict[str, LiveSession] = {}
        self.closing = False
        self.bus = None
        """A ``bus.gateway.GatewayBus`` when the hands run in workers (``settings.bus``), else None."""
        self.pool = None
        """A ``hands.pool.HandPool`` when the hands run in this machine's worker processes
        (``settings.hand_workers``), else None (every hand on the event loop)."""
        self.connections: dict[str, int] = {}
        """Open WebSockets per (non-admin) token."""
        self.waiting: dict[str, set[Subscriber]] = {}
        """Subscribers of sessions no source has created yet, by name."""
        self.sending: dict[Any, float] = {}
        """Connections in a send, since when (monotonic s): ``routes.socket.drop_stuck`` aborts the
        ones stuck longer than ``subscriber_send_timeout_s``."""

    def __len__(self) -> int:
        return len(self.by_name)

    def __iter__(self):
        return iter(list(self.by_name.values()))

    def get(self, name: str, create: bool, owner: str | None = None) -> LiveSession | None:
        """The session ``name``; a new one when ``create``, created by ``owner`` (a token; ``None``: an
        admin), else ``None`` if there is none. ``SessionFull`` at the limit of the service or of the
        owner (``max_sessions_per_token``); a bad name raises ``ValueError``."""
        check_session_name(name)
        live = self.by_name.get(name)
        if live is None and create:
            if len(self.by_name) >= self.settings.max_sessions:
                raise SessionFull(f"session limit {self.settings.max_sessions} reached")
            mine = 0 if owner is None else sum(1 for x in self.by_name.values() if x.owner == owner)
            if mine >= self.settings.max_sessions_per_token:
                raise SessionFull(f"this token already has {mine} live sessions (the limit per token)")
            backend = self.bus or self.pool
            live = self.by_name[name] = (LiveSession(name, self.settings, self.metrics) if backend is None
                                         else backend.session(name, self.settings, self.metrics))
            live.owner = owner
            live.subscribers.update(self.waiting.pop(name, ()))   # its waiting viewers, before any frame
            live.touch()
            self.metrics.sessions.set(len(self.by_name))
        return live

    def subscribe(self, name: str, sub: Subscriber) -> LiveSession | None:
        """Add a subscriber to the session ``name``; ``None`` if there is none yet: then it waits (it
        joins the session when a source creates it, here or, on the bus, when the session's first
        output reaches this gateway). A bad name raises ``ValueError``."""
        live = self.get(name, create=False)
        if live is None:
            self.waiting.setdefault(name, set()).add(sub)
            if self.bus is not None:          # its source may stream into another gateway
                self.bus.watch(self, name)
        else:
            live.subscribers.add(sub)
            live.touch()
        return live

    def unsubscribe(self, name: str, sub: Subscriber) -> None:
        live = self.by_name.get(name)
        if live is not None and sub in live.subscribers:
            live.subscribers.discard(sub)
            live.touch()
        waiting = self.waiting.get(name)
        if waiting is not None:
            waiting.discard(sub)
            if not waiting:
                del self.waiting[name]

    def evict_idle(self, now: float) -> list[str]:
        """Remove the sessions idle (no source, no output) for ``idle_timeout_s``, closing their
        recordings; their subscribers wait for the name's next session. Returns their names."""
        gone = [name for name, live in self.by_name.items()
                if live.idle_since is not None and now - live.idle_since >= self.settings.idle_timeout_s]
        for name in gone:
            live = self.by_name.pop(name)
            live.close()
            self.metrics.forget_session(name)
            if live.subscribers:
                self.waiting.setdefault(name, set()).update(live.subscribers)
                live.subscribers.clear()
                if self.bus is not None:
                    self.bus.watch(self, name)
        if gone:
            self.metrics.sessions.set(len(self.by_name))
        return gone

    def flush_recordings(self) -> None:
        for live in self:
            if live.recorder is not None:
                live.recorder.flush()

    async def drain(self) -> None:
        """Graceful shutdown: subscribers are asked to close (1001 with a reason), recordings flushed
        and closed. Runs before the server closes the remaining connections."""
        if self.closing:
            return
        self.closing = True
        for live in self:
            for sub in live.subscribers:
                sub.close()
            live.close()
        for waiting in self.waiting.values():
            for sub in waiting:
                sub.close()
        await asyncio.sleep(0.1)            # let the stream handlers send their close frames
