"""Dependencies of the routes (FastAPI's ``Depends``/``Security``): who is calling, and which session.

Tokens have roles (``source``, ``viewer``, ``admin``; admin may do everything). A token comes as a
bearer header (``Authorization: Bearer TOKEN``, the declared security scheme) or as ``?token=TOKEN``
(browsers cannot set headers on a WebSocket). A refusal is a 401 (no valid token) or 403 (the role
may not do this) on REST; on a WebSocket the handshake is refused (close 1008 before accepting).
"""
from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, WebSocketException
from fastapi.security import HTTPBearer
from starlette.requests import HTTPConnection

from .config import ServiceSettings
from .metrics import Metrics
from .sessions import LiveSession, SessionFull, Sessions

CAN = {"ingest": ("source", "admin"), "stream": ("viewer", "admin"), "read": ("viewer", "admin"),
       "configure": ("admin",), "metrics": ("source", "viewer", "admin")}
"""Which roles may do what."""
WS_POLICY_VIOLATION = 1008
"""WebSocket close code: refused (token, role, protocol, session name); retrying will not help."""
WS_TRY_AGAIN_LATER = 1013
"""WebSocket close code: the service is full or the client fell behind; it may reconnect."""
WS_GOING_AWAY = 1001
"""WebSocket close code: the service is shutting down."""


class Role(HTTPBearer):
    """``Security(Role("read"))``: the caller's role, if it may do ``action`` (``CAN``)."""

    def __init__(self, action: str):
        super().__init__(scheme_name="token", auto_error=False,
                         description="a token with a role (source, viewer, admin); also accepted as ?token=")
        self.action = action

    async def __call__(self, connection: HTTPConnection) -> str:          # type: ignore[override]
        settings: ServiceSettings = connection.app.state.settings
        token = _token(connection)
        grant = settings.grant_of(token)
        role = None if grant is None else grant.role
        if role is None:
            _refuse(connection, 401, "a valid token is required (Authorization: Bearer TOKEN or ?token=TOKEN)")
        if role not in CAN[self.action]:
            _refuse(connection, 403, f"role {role!r} may not {self.action}; needs one of {list(CAN[self.action])}")
        session = connection.path_params.get("session")
        if not grant.allows(session):
            _refuse(connection, 403, f"this token is not valid for session {session!r}")
        connection.state.grant, connection.state.token = grant, token
        # the key of the token's quotas (sessions created, open connections); an admin has none
        connection.state.quota_key = None if role == "admin" else token
        return role


def _token(connection: HTTPConnection) -> str | None:
    auth = connection.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return connection.query_params.get("token")


def _refuse(connection: HTTPConnection, status: int, detail: str):
    if connection.scope["type"] == "websocket":
        raise WebSocketException(WS_POLICY_VIOLATION, reason=detail[:120])
    raise HTTPException(status, detail)


# dependencies are coroutines: FastAPI runs plain functions in a thread pool, which would lengthen
# every WebSocket handshake (a handshake still open at shutdown is answered with HTTP 500)
async def get_sessions(connection: HTTPConnection) -> Sessions:
    return connection.app.state.sessions


async def get_settings(connection: HTTPConnection) -> ServiceSettings:
    return connection.app.state.settings


async def get_metrics(connection: HTTPConnection) -> Metrics:
    return connection.app.state.metrics


SessionsDep = Annotated[Sessions, Depends(get_sessions)]
SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


async def existing_session(session: str, sessions: SessionsDep) -> LiveSession:
    """The session named in the path; 422 for a bad name, 404 if there is none."""
    try:
        live = sessions.get(session, create=False)
    except ValueError as err:
        raise HTTPException(422, str(err)) from None
    if live is None:
        raise HTTPException(404, f"no session {session!r}")
    return live


def session_or_new(session: str, sessions: Sessions) -> LiveSession:
    """The session named in the path, created if new; 422 for a bad name, 503 when the service is full."""
    try:
        return sessions.get(session, create=True)          # type: ignore[return-value]
    except SessionFull as err:
        raise HTTPException(503, str(err)) from None
    except ValueError as err:
        raise HTTPException(422, str(err)) from None

