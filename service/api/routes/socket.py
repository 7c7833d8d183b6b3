"""What the two WebSockets share: the accepted connection's encoding, sending, error replies and
the session lookup after the handshake.

Every send is watched (``Sessions.sending``): a connection whose peer stopped reading blocks in a send
once its socket buffers are full, and a closing handshake cannot pass it either; ``drop_stuck`` (run
by the app's housekeeping) aborts the transport of a connection stuck longer than
``subscriber_send_timeout_s``, so the connection ends and its buffers are freed."""
from __future__ import annotations

import contextlib
import logging
import socket
import struct
import time

from fastapi import WebSocket
from fastapi.responses import JSONResponse
from starlette.websockets import WebSocketState

from ...protocol import MSGPACK_SUBPROTOCOL, PROTOCOL_VERSION, encode
from ...protocol.outgoing import ErrorMessageDict, ServerHelloDict, SyncReplyDict
from ..deps import WS_POLICY_VIOLATION, WS_TRY_AGAIN_LATER
from ..metrics import Metrics
from ..outgoing import WIRE_EXTENSION, Outgoing, joined_frames, ws_frame
from ..sessions import LiveSession, SessionFull, Sessions

log = logging.getLogger("fingertrack")


async def accept(ws: WebSocket) -> bool:
    """Accept the handshake (the token was checked by the route's ``Security`` dependency) unless the
    token has ``max_connections_per_token`` open already (then HTTP 429 with a JSON ``detail``,
    ``False``); a connection counted here is ``release``d by its route. It speaks MessagePack when
    the client asks with the subprotocol or ``?format=msgpack``."""
    sessions: Sessions = ws.app.state.sessions
    key, limit = getattr(ws.state, "quota_key", None), sessions.settings.max_connections_per_token
    if key is not None and sessions.connections.get(key, 0) >= limit:
        await ws.send_denial_response(JSONResponse(
            {"detail": f"this token already has {limit} open connections (the limit per token)"}, status_code=429))
        return False
    offered = MSGPACK_SUBPROTOCOL in ws.scope.get("subprotocols", [])
    await ws.accept(subprotocol=MSGPACK_SUBPROTOCOL if offered else None)
    ws.state.binary = offered or ws.query_params.get("format") == "msgpack"
    wire = ws.scope.get("extensions", {}).get(WIRE_EXTENSION)              # (``send_outputs``)
    # with an extension negotiated (per-message deflate) the server takes no ready-made frames: none built
    ws.state.wire = None if wire is None or wire.conn.extensions else wire
    if key is not None:
        sessions.connections[key] = sessions.connections.get(key, 0) + 1
    return True


def release(ws: WebSocket) -> None:
    """The end of a connection ``accept`` counted."""
    key, connections = getattr(ws.state, "quota_key", None), ws.app.state.sessions.connections
    if key is not None and key in connections:
        connections[key] -= 1
        if not connections[key]:
            del connections[key]


async def open_session(ws: WebSocket, sessions: Sessions, name: str) -> LiveSession | None:
    """Accept and find (or create, owned by the caller's token) the session; ``None`` if refused: HTTP
    429 over the token's connection quota, or after closing the connection with the reason: 1013
    (try again later) when the service or the token's session quota is full, 1008 for a bad name."""
    if not await accept(ws):
        return None
    try:
        return sessions.get(name, create=True, owner=getattr(ws.state, "quota_key", None))
    except (SessionFull, ValueError) as err:
        # a full service may take the session later (1013 "try again later"); a bad name will not
        release(ws)
        code = WS_TRY_AGAIN_LATER if isinstance(err, SessionFull) else WS_POLICY_VIOLATION
        await ws.close(code=code, reason=close_reason(str(err)))
        return None


def close_reason(text: str) -> str:
    """A WebSocket close reason fits in 123 bytes: cut at 120 UTF-8 bytes, on a character boundary."""
    return text.encode()[:120].decode("utf-8", "ignore")


async def send(ws: WebSocket, message: ServerHelloDict | SyncReplyDict | ErrorMessageDict | Outgoing) -> None:
    """One message in the connection's encoding (an ``Outgoing`` one is encoded once for everyone): written as
    its ready-made frame where the server takes those (``_write_frames``: a source's error and ``sync``
    replies, the hellos), else through ASGI."""
    binary = ws.state.binary
    if isinstance(message, Outgoing):
        if await _write_frames(ws, message.wire(binary)):
            return
        data = message.packed() if binary else message.text()
    else:
        data = encode(message, binary)
        if await _write_frames(ws, _frame_of(data, binary)):
            return
    sending = ws.app.state.sessions.sending
    sending[ws] = time.monotonic()
    try:
        if isinstance(data, bytes):
            await ws.send_bytes(data)
        else:
            await ws.send_text(data)
    finally:
        sending.pop(ws, None)


async def send_outputs(ws: WebSocket, messages: list[Outgoing]) -> None:
    """Outputs of a session (frames, gesture events) in the connection's encoding, in order: in one write of
    the frames each message built once for every subscriber (``_write_frames``), else one by one (``send``)."""
    if not await _write_frames(ws, joined_frames(messages, ws.state.binary)):
        for message in messages:
            await send(ws, message)


def _frame_of(data: str | bytes, binary: bool) -> bytes:
    return ws_frame(data if binary else data.encode(), binary)


def reply_frame(message: SyncReplyDict | ErrorMessageDict, binary: bool) -> bytes:
    """``message`` as the whole WebSocket frame ``send`` writes of it in the connection's encoding ``binary``."""
    return _frame_of(encode(message, binary), binary)


def write_reply_now(ws: WebSocket, message: SyncReplyDict | ErrorMessageDict) -> bool:
    """``send``'s ready-made frame of ``message`` without waiting: written at once where the server takes such
    frames, its buffers are not full and the connection is open; ``False``: nothing written, the caller sends it
    the awaited way."""
    wire = getattr(ws.state, "wire", None)
    if wire is None or not wire.writable.is_set() or ws.application_state is not WebSocketState.CONNECTED:
        return False
    return wire.write_frames(reply_frame(message, ws.state.binary))


async def _write_frames(ws: WebSocket, data: bytes) -> bool:
    """``data``, whole WebSocket frames (``outgoing.ws_frame``), written as they are where the server takes
    ready-made frames (``server.DrainingWebSocket.write_frames``), after waiting while its buffers are full as
    the ASGI send waits, watched as any send (``drop_stuck``). ``False``, nothing written: the caller sends
    through ASGI (another server, per-message deflate negotiated, the connection closing or closed: that
    send raises or does what it would)."""
    wire = getattr(ws.state, "wire", None)
    if wire is None:
        return False
    sending = ws.app.state.sessions.sending
    sending[ws] = time.monotonic()
    try:
        if not wire.writable.is_set():
            await wire.writable.wait()
        return ws.application_state is WebSocketState.CONNECTED and wire.write_frames(data)
    finally:
        sending.pop(ws, None)


def drop_stuck(sessions: Sessions, metrics: Metrics, timeout_s: float, now: float) -> None:
    """Abort every connection that has been in one send for more than ``timeout_s``."""
    for ws, since in list(sessions.sending.items()):
        if now - since > timeout_s:
            sessions.sending.pop(ws, None)
            metrics.disconnects.labels("send_timeout").inc()
            _abort(ws)


def _abort(ws: WebSocket) -> bool:
    """Drop the connection at once (TCP reset), without waiting for buffered data to drain (ASGI has no
    message for this). The server's protocol object, which owns the transport, is the owner of the
    ASGI ``send`` callable, possibly behind wrappers (Starlette wraps it in a closure)."""
    stack, looked = [getattr(ws, "_send", None)], 0
    while stack and looked < 16:
        fn = stack.pop()
        looked += 1
        transport = getattr(getattr(fn, "__self__", None), "transport", None)
        if transport is not None:
            sock = transport.get_extra_info("socket")
            if sock is not None:             # a reset discards what the kernel still queues for the peer
                with contextlib.suppress(OSError):  # (a plain close leaves it queued to a peer that never reads)
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            transport.abort()
            return True
        for cell in getattr(fn, "__closure__", None) or ():
            try:
                inner = cell.cell_contents
            except ValueError:
                continue
            if callable(inner):
                stack.append(inner)
    log.warning("cannot drop a stalled connection: no transport found behind the ASGI send")
    return False


async def send_error(ws: WebSocket, metrics: Metrics, code: str, detail: str, samples: list[int] | None = None) -> None:
    """An ``error`` reply (``ErrorMessage``); ``samples``: the indexes of the samples an ``invalid_samples``
    reply refuses."""
    metrics.errors.labels(code).inc()
    reply = ErrorMessageDict(type="error", code=code, detail=detail)
    if samples is not None:
        reply["samples"] = samples
    await send(ws, reply)


def server_hello(session: str, waiting: bool | None = None) -> ServerHelloDict:
    """The service's hello; ``waiting`` (on ``/v1/stream`` only) says whether the session still waits
    for its source."""
    hello = ServerHelloDict(type="hello", protocol=PROTOCOL_VERSION, server="fingertrack", session=session)
    if waiting is not None:
        hello["waiting"] = waiting
    return hello
