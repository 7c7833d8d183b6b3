"""``WS /v1/ingest/{session}`` (role ``source``): ``hello`` first (answered with the server's hello, or
refused with a clear reason when its protocol is not this server's), then ``calibration``, ``pose``,
``imu``, ``imu_batch``, ``reference_pose`` and ``sync`` barriers. Bad input gets an ``error`` reply
(code and detail) and is dropped; the connection and every other session go on. One source per
session (``claim_source``)."""
from __future__ import annotations

import asyncio
import hmac
import re
import time

import orjson
from fastapi import APIRouter, Security, WebSocket, WebSocketDisconnect

from ...protocol import PROTOCOL_VERSION, Hello, ProtocolError, Sync, decode
from ...protocol.messages import SamplesRefused, dump_message
from ...protocol.outgoing import SyncReplyDict
from ..config import ServiceSettings
from ..deps import WS_POLICY_VIOLATION, WS_TRY_AGAIN_LATER, MetricsDep, Role, SessionsDep, SettingsDep
from ..metrics import Metrics
from ..backlog import DATA_TYPES, IngestBacklog
from ..replies import drop_replies, failure_reply
from ..sessions import LiveSession
from .socket import close_reason, open_session, release, send, send_error, server_hello, write_reply_now

router = APIRouter()


class TokenBucket:
    def __init__(self, rate: float):
        self.rate, self.capacity = rate, rate
        self.tokens, self.t = rate, time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.capacity, self.tokens + (now - self.t) * self.rate)
        self.t = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def give_back(self) -> None:
        """Undo the last ``take`` (its message was not handled after all: it is asked for again)."""
        self.tokens = min(self.capacity, self.tokens + 1.0)


def _size(data: dict) -> int:
    """A received WebSocket message's size in bytes as it came on the wire (a text character takes up
    to 4)."""
    payload = data["bytes"] if data.get("bytes") is not None else data.get("text") or ""
    return len(payload) if isinstance(payload, bytes) or payload.isascii() \
        else len(payload.encode("utf-8", "surrogatepass"))


def _admit(size: int, settings: ServiceSettings, bucket: TokenBucket) -> tuple[str, str] | None:
    """``(code, detail)`` if a received WebSocket message must be refused before decoding."""
    if size > settings.max_message_bytes:
        return "message_too_large", f"{size} bytes; the limit is {settings.max_message_bytes}"
    if not bucket.take():
        return "rate_limited", f"more than {settings.rate_limit_msgs_per_s:g} messages/s; message dropped"
    return None


def _peek(data: dict) -> dict | None:
    """The decoded message, for what the door needs to know (type, time); ``None`` if it is not an object."""
    binary = data.get("bytes") is not None
    try:
        obj = decode(data["bytes"] if binary else data["text"], binary)
    except ProtocolError:
        return None
    return obj if isinstance(obj, dict) else None


def _is_data(data: dict) -> bool:
    return (_peek(data) or {}).get("type") in DATA_TYPES


def _overload_reply(data: dict, backlog: IngestBacklog) -> tuple[str, str]:
    obj = _peek(data) or {}
    kind, t = obj.get("type"), obj.get("t")
    if t is None and kind == "imu_batch" and isinstance(obj.get("samples"), list) and obj["samples"] \
            and isinstance(obj["samples"][0], dict):
        t = obj["samples"][0].get("t")
    what = f"{kind} at t={t}" if isinstance(t, (int, float)) and not isinstance(t, bool) else str(kind)
    return "overloaded", (f"{what}: the service cannot keep up with this source ({len(backlog)} messages wait to be "
                          "processed); dropped. Send less, or wait for the answer to a sync")


class _Say:
    """``await say(send_fn, *args, **fields)``: ``send_fn(ws, *args, **fields)`` unless the connection is gone
    (then nothing more is sent); shared by the processor and the door (``_Door.intake``'s ``sync`` answers)."""

    def __init__(self, ws: WebSocket):
        self.ws, self.gone = ws, False

    async def __call__(self, send_fn, *args, **fields) -> None:
        if not self.gone:
            try:
                await send_fn(self.ws, *args, **fields)
            except (WebSocketDisconnect, RuntimeError, OSError):
                self.gone = True


_SYNC_HEAD = re.compile(r'\{\s*"type"\s*:\s*"sync"\s*[,}]')
_SYNC_ID_MAX = 2 ** 53


def _plain_sync_id(text: str) -> int | None:
    """The ``id`` of a ``sync`` that is exactly ``{"type": "sync", "id": <an integer 0..2**53>}``, which ``Sync``
    takes as it is (decoded once, no model); ``None`` for anything else (then validated the whole way, with its
    error reply)."""
    try:
        raw = orjson.loads(text)
    except orjson.JSONDecodeError:
        return None
    if type(raw) is dict and len(raw) == 2 and raw.get("type") == "sync":
        sync_id = raw.get("id")
        if type(sync_id) is int and 0 <= sync_id <= _SYNC_ID_MAX:
            return sync_id
    return None


class SyncAnswer:
    """A ``sync``'s answer (``LiveSession.answer_in_order``): ``await answer()`` sends it as the processor's
    answer does (``_Say``); ``now()`` writes it at once where the server takes ready-made frames and the
    connection takes them without waiting (``True``: done, or nothing to send to a connection gone), so that a
    session with no reply before it answers without a task of its own (a task per ``sync`` cost more of the web
    process's time than the answer); ``False``: nothing written, await it."""

    __slots__ = ("say", "reply")

    def __init__(self, say: "_Say", reply: SyncReplyDict):
        self.say, self.reply = say, reply

    async def __call__(self) -> None:
        await self.say(send, self.reply)

    def now(self) -> bool:
        say = self.say
        if say.gone:
            return True
        return write_reply_now(say.ws, self.reply)


async def _close_quietly(ws: WebSocket, code: int, reason: str) -> None:
    """Close a connection that may be gone already (its peer left): then there is nothing to close
    (the failed close used to end in a 'Task exception was never retrieved' traceback in the log)."""
    try:
        await ws.close(code=code, reason=reason)
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass


async def claim_source(ws: WebSocket, live: LiveSession, metrics: Metrics) -> bool:
    """Make this connection the session's source. One source per session: a connection of the same
    token takes over (the older one is closed), another token is refused (1008 with the reason)."""
    token = ws.state.token
    old = live.source
    if old is not None:
        if not hmac.compare_digest(token.encode(), (live.source_token or "").encode()):
            release(ws)
            await ws.close(code=WS_POLICY_VIOLATION,
                           reason=close_reason(f"session {live.name!r} already has a source; one source per session"))
            return False
        metrics.disconnects.labels("replaced").inc()
        asyncio.create_task(_close_quietly(old, WS_POLICY_VIOLATION, "replaced by a newer connection of the same token"))
    live.source, live.source_token = ws, token
    live.touch()
    return True


@router.websocket("/v1/ingest/{session}", dependencies=[Security(Role("ingest"))])
async def ingest(ws: WebSocket, session: str, sessions: SessionsDep, settings: SettingsDep, metrics: MetricsDep):
    live = await open_session(ws, sessions, session)
    if live is None:
        return
    if not await claim_source(ws, live, metrics):
        return
    live.attach_source(lambda code, detail, samples=None: send_error(ws, metrics, code, detail, samples=samples))
    backlog = IngestBacklog(settings.ingest_backlog_messages, settings.ingest_backlog_bytes)
    say = _Say(ws)
    processor = asyncio.create_task(_process(ws, session, live, backlog, metrics, say))
    door = _Door(ws, session, live, backlog, processor, settings, metrics, say)
    # the server hands such messages over as they arrive (``_Door.intake``), to a session that takes them so
    wire = getattr(ws.state, "wire", None) if type(live).forward is not LiveSession.forward else None
    if wire is not None:
        wire.intake = door.intake
    try:
        # in a task of its own: each wait for a message suspends and resumes its few frames, not the two dozen
        # of the server's and the framework's layers around this route
        await asyncio.create_task(door.read())
    finally:
        if wire is not None:
            wire.intake = None
        backlog.close()                      # what was received is still processed (its replies go nowhere)
        await asyncio.gather(processor, return_exceptions=True)
        release(ws)
        if live.source is ws:
            live.source = live.source_token = None
            live.touch()


class _Door:
    """The connection's reading side: every received message admitted (size, rate), then handed to the
    session at once (a data message its worker validates, while the processor waits with nothing queued:
    ``LiveSession.forwardable``), or queued for the processor, or refused with a reply in its place.

    ``read`` reads the connection all the time (``backlog.py``: pings and pongs keep passing) until it ends
    or the processor is done. ``intake`` is the server's way in for a text message as it arrives
    (``server.DrainingWebSocket``), taken only while ``read`` waits for the next message with nothing
    received before it left waiting: a message handed on at once then goes there as ``read`` would hand
    it on, without a turn of the loop, a wake of ``read`` and the ASGI layers' receive per message (a
    quarter of the web process's time per glove message). A ``sync`` is taken there too (``answer_sync``):
    its answer put in its place among the session's replies as the processor puts it, without the reader's
    and the processor's wakes (a glove asks one every 64 messages)."""

    def __init__(self, ws: WebSocket, session: str, live: LiveSession, backlog: IngestBacklog, processor: asyncio.Task,
                 settings: ServiceSettings, metrics: Metrics, say: _Say | None = None):
        self.ws, self.session, self.live, self.backlog, self.processor = ws, session, live, backlog, processor
        self.settings, self.metrics = settings, metrics
        self.say = say or _Say(ws)
        self.bucket = TokenBucket(settings.rate_limit_msgs_per_s)
        self.waiting = False
        """``read`` waits for the next message and everything received before was taken"""
        self.closing: asyncio.Task | None = None
        """the close of a connection ``intake`` found overloaded (it takes nothing more then)"""

    async def read(self) -> None:
        ws = self.ws
        try:
            while not self.processor.done():
                self.waiting = True
                try:
                    data = await ws.receive()
                finally:
                    self.waiting = False
                if data["type"] == "websocket.disconnect":
                    break
                if not self.take(data):
                    await self.close_overloaded()
                    break
        except (WebSocketDisconnect, RuntimeError):   # RuntimeError: the processor closed the connection
            pass

    def intake(self, text: str) -> bool:
        """A text message as it arrives: ``True`` if taken here (handed on at once to the session, as ``read``
        would have); ``False``: not now (it goes to ``read`` through the server's queue)."""
        if not self.waiting or self.closing is not None or self.processor.done():
            return False
        size = len(text) if text.isascii() else len(text.encode("utf-8", "surrogatepass"))     # (``_size``'s)
        if not self._may_hand_on(size):
            return False                     # (``answer_sync``'s condition too)
        live = self.live
        msg = live.forwardable_text(text)
        if msg is None:
            return _SYNC_HEAD.match(text) is not None and self.answer_sync(text, size)
        if not self.bucket.take():
            return False                     # (a failed take uses no token: ``read`` asks again)
        if not self.forward(msg):
            self.closing = asyncio.get_running_loop().create_task(self.close_overloaded())
        return True

    def answer_sync(self, text: str, size: int) -> bool:
        """A valid ``sync`` as it arrives: its answer put in its place among the session's replies, as the
        processor puts it (``LiveSession.answer_in_order``), under the same conditions as a data message
        handed on here (``forwardable``'s, the session's source greeted), so it keeps its place in the order;
        ``False`` (not taken, its token given back: the processor handles it) for anything else, an invalid
        one (answered with its error there) or one whose answer cannot wait in its place."""
        if not self._may_hand_on(size):
            return False
        sync_id = _plain_sync_id(text)
        if sync_id is None:
            try:
                _, msg = self.live.parse_input(text, False)
            except ProtocolError:
                return False
            if not isinstance(msg, Sync):
                return False
            sync_id = msg.id
        if not self.bucket.take():
            return False
        if not self.live.answer_in_order(SyncAnswer(self.say, SyncReplyDict(type="sync", id=sync_id))):
            self.bucket.give_back()
            return False
        return True

    def forwardable(self, data: dict, size: int):
        """The message, if it may go to the session at once (within the size limit, the processor waiting
        with nothing queued, the session's source this connection and greeted); else ``None``."""
        return self.live.forwardable(data) if self._may_hand_on(size) else None

    def _may_hand_on(self, size: int) -> bool:
        backlog = self.backlog
        return size <= self.settings.max_message_bytes and backlog.greeted and backlog.idle() \
            and self.live.source is self.ws

    def take(self, data: dict) -> bool:
        """One received message: handed on, queued for the processor, or refused (the reply in its place,
        after the replies to every earlier one). ``False``: the connection must close (overloaded)."""
        size = _size(data)
        msg = self.forwardable(data, size)
        if msg is not None and self.bucket.take():
            return self.forward(msg)
        backlog = self.backlog
        refused = _admit(size, self.settings, self.bucket)
        if refused is None and not backlog.put(data, size, lambda: _is_data(data)):
            self.live.overloaded += 1
            self.metrics.overloaded.labels(self.session).inc()
            refused = _overload_reply(data, backlog)
        return refused is None or self.refuse(refused)

    def forward(self, msg) -> bool:
        """``msg`` to the session (``LiveSession.forward``); a defect is answered in the message's place, as
        the processor does. ``False``: the connection must close (overloaded)."""
        try:
            self.live.forward(msg)
            return True
        except Exception as err:
            return self.refuse(failure_reply(self.session, msg, err))

    def refuse(self, reply: tuple[str, str]) -> bool:
        if self.backlog.put_reply(reply):
            return True
        self.metrics.disconnects.labels("overloaded").inc()
        return False

    async def close_overloaded(self) -> None:
        await _close_quietly(self.ws, WS_TRY_AGAIN_LATER, close_reason(
            f"overloaded: {self.backlog.max_reply_bytes} bytes of replies to refused messages wait; send less"))


async def _process(ws: WebSocket, session: str, live: LiveSession, backlog: IngestBacklog, metrics: Metrics,
                   say: _Say | None = None) -> None:
    """The received messages in order: decoded, validated, answered or handed to the session. After
    the connection ended, the rest of the backlog is still handed to the session, unanswered."""
    say = say or _Say(ws)

    async def reply(code: str, detail: str, **fields) -> None:
        """An error reply about this message, after those about every earlier one (a session whose hand
        runs in a worker process answers its messages later: ``settled``)."""
        await live.settled()
        await say(send_error, metrics, code, detail, **fields)

    greeted = False
    while (data := await backlog.get()) is not None:
        if isinstance(data, tuple):          # the reply to a message refused at the door, in its place
            await reply(*data)
            continue
        binary = data.get("bytes") is not None
        partial = None
        try:
            raw, msg = live.parse_input(data["bytes"] if binary else data["text"], binary)
        except SamplesRefused as err:          # the batch's valid samples go on (answered below)
            partial, msg = err, err.kept
            raw = dump_message(msg)
        except ProtocolError as err:
            await reply(err.code, err.detail)
            continue
        if isinstance(msg, Hello):
            if msg.protocol != PROTOCOL_VERSION:
                shown = str(msg.protocol) if len(str(msg.protocol)) <= 12 else str(msg.protocol)[:12] + "..."
                await reply("unsupported_protocol",
                            f"protocol {shown} is not supported; this server speaks protocol {PROTOCOL_VERSION}")
                if not say.gone:
                    await ws.close(code=WS_POLICY_VIOLATION, reason=close_reason(f"unsupported protocol {shown}"))
                return
            greeted = True
            await live.settled()
            await say(send, server_hello(session))
        elif not greeted:
            await reply("expected_hello", f"the first message must be hello, got {msg.type}")
            continue
        elif isinstance(msg, Sync):           # everything before it is handled: say so
            answer = SyncAnswer(say, SyncReplyDict(type="sync", id=msg.id))
            if not live.answer_in_order(answer):    # (a worker's session: the later messages go on meanwhile)
                await live.settled()
                await answer()
            continue
        if partial is not None:
            await reply(partial.code, partial.detail, samples=partial.refused)
        try:
            dropped = await live.ingest(raw, msg)
        except Exception as err:           # bad input, or a defect (logged); no exception reaches the socket layer
            await reply(*failure_reply(session, msg, err))
            continue
        if isinstance(msg, Hello):
            backlog.greeted = True           # this connection's hello is the session's: the reader may hand on
        for code, detail in drop_replies(msg, dropped):            # a bus session answers from its worker
            await reply(code, detail)
