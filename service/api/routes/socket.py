"""What the two WebSockets share: the accepted connection's encoding, sending, error replies and
the session lookup after the handshake."""
from __future__ import annotations

from fastapi import WebSocket

from ...protocol import MSGPACK_SUBPROTOCOL, PROTOCOL_VERSION, encode
from ..deps import WS_POLICY_VIOLATION, WS_TRY_AGAIN_LATER
from ..metrics import Metrics
from ..outgoing import Outgoing
from ..sessions import LiveSession, SessionFull, Sessions


async def accept(ws: WebSocket) -> None:
    """Accept the handshake (the token was checked by the route's ``Security`` dependency); the
    connection speaks MessagePack when the client asks with the subprotocol or ``?format=msgpack``."""
    offered = MSGPACK_SUBPROTOCOL in ws.scope.get("subprotocols", [])
    await ws.accept(subprotocol=MSGPACK_SUBPROTOCOL if offered else None)
    ws.state.binary = offered or ws.query_params.get("format") == "msgpack"


async def open_session(ws: WebSocket, sessions: Sessions, name: str) -> LiveSession | None:
    """Accept and find (or create) the session; ``None`` after closing the connection with the reason:
    1013 (try again later) when the service is full, 1008 for a bad name."""
    await accept(ws)
    try:
        return sessions.get(name, create=True)
    except (SessionFull, ValueError) as err:
        # a full service may take the session later (1013 "try again later"); a bad name will not
        code = WS_TRY_AGAIN_LATER if isinstance(err, SessionFull) else WS_POLICY_VIOLATION
        await ws.close(code=code, reason=str(err)[:120])
        return None


async def send(ws: WebSocket, message: dict | Outgoing) -> None:
    """One message in the connection's encoding (an ``Outgoing`` one is encoded once for everyone)."""
    binary = ws.state.binary
    if isinstance(message, Outgoing):
        data = message.packed() if binary else message.text()
    else:
        data = encode(message, binary)
    if isinstance(data, bytes):
        await ws.send_bytes(data)
    else:
        await ws.send_text(data)


async def send_error(ws: WebSocket, metrics: Metrics, code: str, detail: str) -> None:
    metrics.errors.labels(code).inc()
    await send(ws, {"type": "error", "code": code, "detail": detail})


def server_hello(session: str) -> dict:
    return {"type": "hello", "protocol": PROTOCOL_VERSION, "server": "fingertrack", "session": session}
