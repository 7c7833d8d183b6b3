"""``WS /v1/stream/{session}`` (role ``viewer``): the server's hello (``"waiting": true`` while no
source has created the session: the viewer waits for it and creates nothing), then ``frame`` and
``gesture`` messages from the subscriber's own bounded queue (``sessions.Subscriber``). A subscriber
that fell too far behind is closed with 1013 (it may reconnect); one whose connection takes no data
for ``subscriber_send_timeout_s`` is dropped (``socket.drop_stuck``); shutdown closes with 1001."""
from __future__ import annotations

import asyncio
import itertools
import time

from fastapi import APIRouter, Security, WebSocket, WebSocketDisconnect
from starlette.websockets import WebSocketState

from ..deps import WS_GOING_AWAY, WS_POLICY_VIOLATION, WS_TRY_AGAIN_LATER, MetricsDep, Role, SessionsDep, SettingsDep
from ..metrics import Metrics
from ..outgoing import joined_frames
from ..sessions import Sessions, Subscriber
from .socket import accept, close_reason, release, send, send_outputs, server_hello

router = APIRouter()
SEND_BATCH = 16
"""queued messages a subscriber's sender writes at once (one write of their ready-made frames: fewer system
calls and turns; 16 frames of about 4 KB fill the transport's default high-water mark once)"""


async def _until_disconnect(ws: WebSocket) -> None:
    try:
        while True:
            data = await ws.receive()
            if data["type"] == "websocket.disconnect":
                return
    except Exception:
        return


async def _send_all(ws: WebSocket, session: str, waiting: bool, sub: Subscriber, closer: asyncio.Task,
                    sessions: Sessions, metrics: Metrics) -> None:
    """The server's hello, then the subscriber's queue as it fills, until the peer leaves, the subscriber
    is closed (too slow) or the server shuts down."""
    def counted(since: list[float]) -> None:
        metrics.of_session(session).sent(since, time.perf_counter())     # (published at the next scrape)

    connected = WebSocketState.CONNECTED

    wire, binary = getattr(ws.state, "wire", None), ws.state.binary     # (set once accepted: ``socket.accept``)

    def write_queued() -> None:
        """While the sender waits with nothing queued: what was queued since, written at once as the sender
        would write it (``send_outputs``' ready-made frames) while the connection takes them so; else the
        sender is woken and sends them (it waits while the buffers are full, or sends through ASGI)."""
        queue = sub.queue
        while queue:
            if wire is None or closer.done() or sessions.closing or sub.closed or not wire.writable.is_set() \
                    or ws.application_state is not connected:
                sub.wake.set()
                return
            if len(queue) == 1:                     # (the usual: one frame due)
                _, msg, t0 = queue[0]
                if not wire.write_frames(msg.wire(binary)):
                    sub.wake.set()
                    return
                sub.pop()                           # (taken before anything else can fail: written once)
                metrics.of_session(session).sent_one(time.perf_counter() - t0)
                return
            batch = list(itertools.islice(queue, SEND_BATCH))
            if not wire.write_frames(joined_frames([m for _, m, _ in batch], binary)):
                sub.wake.set()
                return
            for _ in batch:                         # (taken before anything else can fail: written once)
                sub.pop()
            counted([t0 for _, _, t0 in batch])

    try:
        await send(ws, server_hello(session, waiting=waiting))
        while not closer.done():
            if not sub.queue:
                sub.writer = None if sub.writer_failed else write_queued
                try:
                    await sub.wake.wait()
                finally:
                    sub.writer = None
            if sessions.closing or (sub.closed and not sub.queue):
                reason = "server shutting down" if sessions.closing else "subscriber too slow: gesture events would be lost"
                # 1013 "try again later": a client that fell behind may reconnect (1008 means refused)
                await ws.close(code=WS_GOING_AWAY if sessions.closing else WS_TRY_AGAIN_LATER, reason=reason)
                break
            while sub.queue:
                batch, since = [], []
                while sub.queue and len(batch) < SEND_BATCH:
                    msg, t0 = sub.pop()
                    batch.append(msg)
                    since.append(t0)
                await send_outputs(ws, batch)
                counted(since)
    except (WebSocketDisconnect, RuntimeError):
        pass


@router.websocket("/v1/stream/{session}", dependencies=[Security(Role("stream"))])
async def stream(ws: WebSocket, session: str, sessions: SessionsDep, settings: SettingsDep, metrics: MetricsDep):
    if not await accept(ws):                          # over the token's connection quota (HTTP 429)
        return
    sub = Subscriber(settings.subscriber_queue_frames, settings.subscriber_queue_events, binary=ws.state.binary)
    try:
        live = sessions.subscribe(session, sub)       # None: no source has created it yet; the viewer waits
    except ValueError as err:                         # a bad name
        release(ws)
        await ws.close(code=WS_POLICY_VIOLATION, reason=close_reason(str(err)))
        return
    metrics.subscribers.inc()
    closer = asyncio.create_task(_until_disconnect(ws))
    closer.add_done_callback(lambda _: sub.wake.set())   # the peer left: stop waiting (no task per wait)
    try:
        # in a task of its own: each wait for a frame suspends and resumes its few frames, not the two dozen of
        # the server's and the framework's layers around this route
        await asyncio.create_task(_send_all(ws, session, live is None, sub, closer, sessions, metrics))
    finally:
        closer.cancel()
        sessions.unsubscribe(session, sub)
        metrics.subscribers.dec()
        release(ws)
