"""The FastAPI application: REST health/config/metrics and the two WebSockets of protocol v1.

* ``WS /v1/ingest/{session}`` (role ``source``): ``hello`` first (answered with the server's hello, or
  refused with a clear reason when its protocol is not 1), then ``calibration``, ``pose``, ``imu``,
  ``imu_batch``. Bad input gets an ``error`` reply (code and detail) and is dropped; the connection
  and every other session go on.
* ``WS /v1/stream/{session}`` (role ``viewer``): ``frame`` and ``gesture`` messages.
* JSON text by default; MessagePack binary when the client asks (subprotocol ``fingertrack.msgpack``
  or ``?format=msgpack``).
* Tokens with roles (``source``, ``viewer``, ``admin``; admin may do everything) as a bearer header
  or ``?token=``. Without one no session data is served and no configuration changes.
* ``GET /v1/schema``: the JSON Schema of every message, ``/v1/schema/asyncapi.json`` the AsyncAPI
  document of both WebSockets (no token needed: they describe the protocol, not a session).
* ``GET /viewer/``: the web viewer (``clients/web``), static files that hold no session data; the
  page asks for a session and a viewer token and subscribes like any client. ``GET /``: a page that
  leads to the viewer and the API docs.
"""
from __future__ import annotations

import asyncio
import json
import time
from contextlib import asynccontextmanager
from pathlib import Path

import msgpack
from fastapi import Body, FastAPI, HTTPException, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import ValidationError

from ..protocol import PROTOCOL_VERSION, Hello, ProtocolError, Sync, parse_message
from ..protocol.schema import documents, message_schemas
from .config import ServiceSettings
from .metrics import Metrics
from .outgoing import Outgoing
from .sessions import LiveSession, Subscriber

MSGPACK_SUBPROTOCOL = "fingertrack.msgpack"
WEB_VIEWER = Path(__file__).resolve().parents[2] / "clients" / "web"
"""The web viewer's files (installed with the ``clients`` package)."""
CAN = {"ingest": ("source", "admin"), "stream": ("viewer", "admin"), "read": ("viewer", "admin"),
       "configure": ("admin",), "metrics": ("source", "viewer", "admin")}
SESSION_NAME_MAX = 64
INDEX_PAGE = """<!doctype html><html lang="en"><head><meta charset="utf-8"><title>fingertrack</title>
<link rel="icon" href="data:,"></head><body style="font: 15px system-ui, sans-serif; margin: 2em">
<h1>fingertrack</h1><ul><li><a href="/viewer/">viewer</a>: a live hand, its joint angles and gesture events</li>
<li><a href="/docs">API docs</a> (<a href="/openapi.json">OpenAPI</a>)</li><li><a href="/health">health</a></li></ul>
</body></html>"""


def _token(headers, query) -> str | None:
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return query.get("token")


def _check_name(name: str) -> None:
    if not (1 <= len(name) <= SESSION_NAME_MAX) or not all(c.isalnum() or c in "-_." for c in name):
        raise ValueError(f"session name must be 1-{SESSION_NAME_MAX} characters of letters, digits, '-', '_', '.', got {name!r}")


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


def create_app(settings: ServiceSettings) -> FastAPI:
    settings = settings.with_admin_token()
    metrics = Metrics()
    sessions: dict[str, LiveSession] = {}
    state = {"closing": False, "bus": None}

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        async def flusher():
            while True:
                await asyncio.sleep(settings.flush_interval_s / 2)
                for s in list(sessions.values()):
                    if s.recorder is not None:
                        s.recorder.flush()
        task = asyncio.create_task(flusher())
        if settings.bus is not None:                 # a gateway: sessions run in hand workers
            from ..bus.gateway import GatewayBus
            state["bus"] = await GatewayBus.connect(settings.bus)
        yield
        task.cancel()
        await drain()
        if state["bus"] is not None:
            await state["bus"].close()

    async def drain() -> None:
        """Graceful shutdown: subscribers are closed with 1001 and a reason, recordings flushed and
        closed. Runs before the server closes the remaining connections."""
        if state["closing"]:
            return
        state["closing"] = True
        for s in sessions.values():
            for sub in s.subscribers:
                sub.closed = True
                sub.wake.set()
            s.close()
        await asyncio.sleep(0.1)            # let the stream handlers send their close frames

    app = FastAPI(title="fingertrack", version="0.1.0", lifespan=lifespan,
                  description="Finger tracking for VR hand interaction: protocol v1 over WebSocket, REST config.")
    app.state.drain = drain
    app.state.settings = settings
    app.state.sessions = sessions
    app.state.metrics = metrics

    def require(request_or_ws, action: str) -> str:
        role = settings.role_of(_token(request_or_ws.headers, request_or_ws.query_params))
        if role is None:
            raise HTTPException(401, "a valid token is required (Authorization: Bearer TOKEN or ?token=TOKEN)")
        if role not in CAN[action]:
            raise HTTPException(403, f"role {role!r} may not {action}; needs one of {list(CAN[action])}")
        return role

    def get_session(name: str, create: bool) -> LiveSession:
        _check_name(name)
        s = sessions.get(name)
        if s is None:
            if not create:
                raise HTTPException(404, f"no session {name!r}")
            if len(sessions) >= settings.max_sessions:
                raise HTTPException(503, f"session limit {settings.max_sessions} reached")
            bus = state["bus"]
            s = sessions[name] = LiveSession(name, settings, metrics) if bus is None else bus.session(name, settings, metrics)
            metrics.sessions.set(len(sessions))
        return s

    @app.get("/health")
    def health():
        return {"status": "ok"}

    @app.get("/ready")
    def ready():
        if state["closing"]:
            raise HTTPException(503, "shutting down")
        return {"ready": True, "sessions": len(sessions), "protocol": PROTOCOL_VERSION}

    @app.get("/v1/schema", tags=["protocol"])
    def protocol_schema():
        """JSON Schema (draft 2020-12) of every protocol-v1 message, by file name (as in ``docs/schema/``)."""
        return {"protocol": PROTOCOL_VERSION, "schemas": message_schemas()}

    @app.get("/v1/schema/{name}", tags=["protocol"])
    def protocol_schema_file(name: str):
        """One of the documents of ``/v1/schema``, or the AsyncAPI document ``asyncapi.json``."""
        docs = documents()
        if name not in docs:
            raise HTTPException(404, f"no schema {name!r}; expected one of {sorted(docs)}")
        return docs[name]

    @app.get("/v1/sessions")
    def list_sessions(request: Request):
        require(request, "read")
        return [s.summary() for s in sessions.values()]

    @app.get("/v1/sessions/{session}/config")
    def get_config(session: str, request: Request):
        require(request, "read")
        try:
            return get_session(session, create=False).config.as_dict()
        except ValueError as err:
            raise HTTPException(422, str(err)) from None

    @app.put("/v1/sessions/{session}/config")
    def put_config(session: str, request: Request, change: dict = Body(...)):
        require(request, "configure")
        unknown = set(change) - {"estimator", "estimator_params", "gestures", "record"}
        if unknown:
            raise HTTPException(422, f"unknown config fields {sorted(unknown)}; expected estimator, estimator_params, gestures, record")
        try:
            return get_session(session, create=True).update_config(change)
        except ValidationError as err:
            raise HTTPException(422, json.loads(err.json(include_url=False))) from None
        except ValueError as err:
            raise HTTPException(422, str(err)) from None

    @app.get("/metrics")
    def get_metrics(request: Request):
        require(request, "metrics")
        return Response(metrics.render(), media_type="text/plain; version=0.0.4")

    async def accept(ws: WebSocket, action: str) -> bool:
        binary = MSGPACK_SUBPROTOCOL in ws.scope.get("subprotocols", []) or ws.query_params.get("format") == "msgpack"
        try:
            require(ws, action)
        except HTTPException as err:
            await ws.close(code=1008, reason=str(err.detail)[:120])
            return False
        await ws.accept(subprotocol=MSGPACK_SUBPROTOCOL if MSGPACK_SUBPROTOCOL in ws.scope.get("subprotocols", []) else None)
        ws.state.binary = binary
        return True

    async def open_session(ws: WebSocket, action: str, session: str) -> LiveSession | None:
        """Check the token and the session name; ``None`` (connection refused or closed) if not allowed."""
        if not await accept(ws, action):
            return None
        try:
            return get_session(session, create=True)
        except (HTTPException, ValueError) as err:
            # a full service may take the session later (1013 "try again later"); a bad name will not
            busy = isinstance(err, HTTPException) and err.status_code == 503
            await ws.close(code=1013 if busy else 1008, reason=str(getattr(err, "detail", err))[:120])
            return None

    async def send(ws: WebSocket, message: dict | Outgoing) -> None:
        if isinstance(message, Outgoing):    # encoded once for all subscribers of its session
            if ws.state.binary:
                await ws.send_bytes(message.packed())
            else:
                await ws.send_text(message.text())
        elif ws.state.binary:
            await ws.send_bytes(msgpack.packb(message))
        else:
            await ws.send_text(json.dumps(message, separators=(",", ":")))

    async def send_error(ws: WebSocket, code: str, detail: str) -> None:
        metrics.errors.labels(code).inc()
        await send(ws, {"type": "error", "code": code, "detail": detail})

    @app.websocket("/v1/ingest/{session}")
    async def ingest(ws: WebSocket, session: str):
        live = await open_session(ws, "ingest", session)
        if live is None:
            return
        live.sources += 1
        live.attach_source(lambda code, detail: send_error(ws, code, detail))
        bucket = TokenBucket(settings.rate_limit_msgs_per_s)
        greeted = False
        try:
            while True:
                data = await ws.receive()
                if data["type"] == "websocket.disconnect":
                    break
                raw_bytes = data.get("bytes")
                text = data.get("text")
                size = len(raw_bytes) if raw_bytes is not None else len(text or "")
                if size > settings.max_message_bytes:
                    await send_error(ws, "message_too_large", f"{size} bytes; the limit is {settings.max_message_bytes}")
                    continue
                if not bucket.take():
                    await send_error(ws, "rate_limited", f"more than {settings.rate_limit_msgs_per_s:g} messages/s; message dropped")
                    continue
                try:
                    raw = msgpack.unpackb(raw_bytes) if raw_bytes is not None else json.loads(text, parse_constant=_reject)
                    msg = parse_message(raw)
                except ProtocolError as err:
                    await send_error(ws, err.code, err.detail)
                    continue
                except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as err:
                    await send_error(ws, "invalid_json" if text is not None else "invalid_msgpack", f"cannot decode: {err}")
                    continue
                if isinstance(msg, Hello):
                    if msg.protocol != PROTOCOL_VERSION:
                        await send_error(ws, "unsupported_protocol",
                                         f"protocol {msg.protocol} is not supported; this server speaks protocol {PROTOCOL_VERSION}")
                        await ws.close(code=1008, reason=f"unsupported protocol {msg.protocol}")
                        return
                    greeted = True
                    await send(ws, {"type": "hello", "protocol": PROTOCOL_VERSION, "server": "fingertrack", "session": session})
                elif not greeted:
                    await send_error(ws, "expected_hello", f"the first message must be hello, got {msg.type}")
                    continue
                elif isinstance(msg, Sync):           # everything before it is handled: say so
                    await live.settled()
                    await send(ws, {"type": "sync", "id": msg.id})
                    continue
                counters = live.hand.session.counters
                late, dup = counters.late, counters.duplicate
                try:
                    await live.ingest(raw, msg)
                except ValueError as err:          # e.g. a calibration that does not fit the hand
                    await send_error(ws, "invalid_message", str(err))
                    continue
                if counters.late > late:
                    await send_error(ws, "time_backwards", f"{msg.type} at t={getattr(msg, 't', None)} is older than what "
                                     "was already processed; dropped")
                elif counters.duplicate > dup:
                    await send_error(ws, "duplicate", f"{msg.type} at t={getattr(msg, 't', None)} was already received; dropped")
        except WebSocketDisconnect:
            pass
        finally:
            live.sources -= 1

    @app.websocket("/v1/stream/{session}")
    async def stream(ws: WebSocket, session: str):
        live = await open_session(ws, "stream", session)
        if live is None:
            return
        sub = Subscriber(settings.subscriber_queue_frames, settings.subscriber_queue_events, binary=ws.state.binary)
        live.subscribers.add(sub)
        metrics.subscribers.inc()

        async def watch_disconnect():
            try:
                while True:
                    data = await ws.receive()
                    if data["type"] == "websocket.disconnect":
                        return
            except Exception:
                return

        closer = asyncio.create_task(watch_disconnect())
        try:
            await send(ws, {"type": "hello", "protocol": PROTOCOL_VERSION, "server": "fingertrack", "session": session})
            while not closer.done():
                if not sub.queue:
                    waiter = asyncio.create_task(sub.wake.wait())
                    await asyncio.wait({waiter, closer}, return_when=asyncio.FIRST_COMPLETED)
                    waiter.cancel()
                if state["closing"] or (sub.closed and not sub.queue):
                    reason = "server shutting down" if state["closing"] else "subscriber too slow: gesture events would be lost"
                    # 1013 "try again later": a client that fell behind may reconnect (1008 means refused)
                    await ws.close(code=1001 if state["closing"] else 1013, reason=reason)
                    break
                while sub.queue:
                    msg, t0 = sub.pop()
                    await send(ws, msg)
                    metrics.messages_out.labels(session).inc()
                    metrics.latency.labels(session).observe(time.perf_counter() - t0)
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            closer.cancel()
            live.subscribers.discard(sub)
            metrics.subscribers.dec()

    @app.get("/", include_in_schema=False)
    def index():
        return HTMLResponse(INDEX_PAGE)

    if WEB_VIEWER.is_dir():
        app.mount("/viewer", StaticFiles(directory=WEB_VIEWER, html=True), name="viewer")
    return app


def _reject(name: str):
    raise ValueError(f"non-finite number {name} is not allowed")
