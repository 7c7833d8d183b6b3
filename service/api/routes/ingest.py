"""``WS /v1/ingest/{session}`` (role ``source``): ``hello`` first (answered with the server's hello, or
refused with a clear reason when its protocol is not this server's), then ``calibration``, ``pose``,
``imu``, ``imu_batch``, ``reference_pose`` and ``sync`` barriers. Bad input gets an ``error`` reply
(code and detail) and is dropped; the connection and every other session go on. One source per
session (``claim_source``)."""
from __future__ import annotations

import asyncio
import hmac
import time

from fastapi import APIRouter, Security, WebSocket, WebSocketDisconnect

from ...protocol import PROTOCOL_VERSION, Hello, ProtocolError, Sync, parse_input
from ...protocol.messages import SamplesRefused, dump_message
from ...protocol.outgoing import SyncReplyDict
from ..config import ServiceSettings
from ..deps import WS_POLICY_VIOLATION, MetricsDep, Role, SessionsDep, SettingsDep
from ..metrics import Metrics
from ..replies import drop_replies, failure_reply
from ..sessions import LiveSession
from .socket import close_reason, open_session, release, send, send_error, server_hello

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


def _admit(data: dict, settings: ServiceSettings, bucket: TokenBucket) -> tuple[str, str] | None:
    """``(code, detail)`` if a received WebSocket message must be refused before decoding."""
    payload = data["bytes"] if data.get("bytes") is not None else data.get("text") or ""
    # bytes as they came on the wire (a text character takes up to 4)
    size = len(payload) if isinstance(payload, bytes) or payload.isascii() \
        else len(payload.encode("utf-8", "surrogatepass"))
    if size > settings.max_message_bytes:
        return "message_too_large", f"{size} bytes; the limit is {settings.max_message_bytes}"
    if not bucket.take():
        return "rate_limited", f"more than {settings.rate_limit_msgs_per_s:g} messages/s; message dropped"
    return None


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
        asyncio.create_task(old.close(code=WS_POLICY_VIOLATION, reason="replaced by a newer connection of the same token"))
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
    live.attach_source(lambda code, detail: send_error(ws, metrics, code, detail))
    bucket = TokenBucket(settings.rate_limit_msgs_per_s)
    greeted = False
    try:
        while True:
            data = await ws.receive()
            if data["type"] == "websocket.disconnect":
                break
            refused = _admit(data, settings, bucket)
            if refused:
                await send_error(ws, metrics, *refused)
                continue
            binary = data.get("bytes") is not None
            partial = None
            try:
                raw, msg = parse_input(data["bytes"] if binary else data["text"], binary)
            except SamplesRefused as err:          # the batch's valid samples go on (answered below)
                partial, msg = err, err.kept
                raw = dump_message(msg)
            except ProtocolError as err:
                await send_error(ws, metrics, err.code, err.detail)
                continue
            if isinstance(msg, Hello):
                if msg.protocol != PROTOCOL_VERSION:
                    shown = str(msg.protocol) if len(str(msg.protocol)) <= 12 else str(msg.protocol)[:12] + "..."
                    await send_error(ws, metrics, "unsupported_protocol",
                                     f"protocol {shown} is not supported; this server speaks protocol {PROTOCOL_VERSION}")
                    await ws.close(code=WS_POLICY_VIOLATION, reason=close_reason(f"unsupported protocol {shown}"))
                    return
                greeted = True
                await send(ws, server_hello(session))
            elif not greeted:
                await send_error(ws, metrics, "expected_hello", f"the first message must be hello, got {msg.type}")
                continue
            elif isinstance(msg, Sync):           # everything before it is handled: say so
                await live.settled()
                await send(ws, SyncReplyDict(type="sync", id=msg.id))
                continue
            if partial is not None:
                await send_error(ws, metrics, partial.code, partial.detail, samples=partial.refused)
            try:
                dropped = await live.ingest(raw, msg)
            except Exception as err:           # bad input, or a defect (logged); no exception reaches the socket layer
                await send_error(ws, metrics, *failure_reply(session, msg, err))
                continue
            for reply in drop_replies(msg, dropped):            # a bus session answers from its worker
                await send_error(ws, metrics, *reply)
    except WebSocketDisconnect:
        pass
    finally:
        release(ws)
        if live.source is ws:
            live.source = live.source_token = None
            live.touch()
