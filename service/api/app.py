"""The FastAPI application, assembled: settings, sessions and metrics on ``app.state``, the routes
(``routes/``: ``rest``, ``ingest``, ``stream``), the lifespan (recordings flushed periodically,
idle sessions removed, connections stuck in a send dropped, a graceful drain at shutdown; the
memory of ended connections collected soon after they end, ``churn``; the hand
worker processes, ``hands.pool`` and ``settings.hand_workers``, or with ``settings.bus`` the
connection to the bus's hand workers) and the web viewer.

Endpoints:

* ``WS /v1/ingest/{session}`` (role ``source``) and ``WS /v1/stream/{session}`` (role ``viewer``):
  protocol v1, JSON text by default, MessagePack binary when the client asks (subprotocol
  ``fingertrack.msgpack`` or ``?format=msgpack``);
* ``GET /health``, ``GET /ready``, ``GET /v1/sessions``, ``GET|PUT /v1/sessions/{session}/config``,
  ``GET /metrics``;
* ``GET /v1/schema``: the JSON Schema of every message, ``/v1/schema/asyncapi.json`` the AsyncAPI
  document of both WebSockets (no token needed: they describe the protocol, not a session);
* ``GET /viewer/``: the web viewer (``clients/web``), static files that hold no session data; the
  page asks for a session and a viewer token and subscribes like any client. ``GET /``: a page that
  leads to the viewer and the API docs.

Tokens with roles (``deps``): without one no session data is served and no configuration changes.
"""
from __future__ import annotations

import asyncio
import logging
import time
from contextlib import asynccontextmanager
from importlib.resources import files

from fastapi import FastAPI
from fastapi_offline import FastAPIOffline
from fastapi.staticfiles import StaticFiles
from starlette.applications import Starlette

from ..estimators.warm import warm_off_loop
from .churn import ChurnCollector, CollectAfterConnections
from .config import ServiceSettings
from .hands.pool import HandPool
from .metrics import Metrics
from .routes import ingest, rest, schema, stream
from .routes.socket import drop_stuck
from .sessions import Sessions

log = logging.getLogger(__name__)
WEB_VIEWER = files("clients") / "web"
"""The web viewer's files (package data of ``clients``)."""


def create_app(settings: ServiceSettings) -> FastAPI:
    settings = settings.with_admin_token()
    metrics = Metrics()
    sessions = Sessions(settings, metrics)
    churn = ChurnCollector(settings.connection_gc_delay_s, metrics.connection_gc.observe)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.loop = asyncio.get_running_loop()     # the event loop serving it (``settings.event_loop``)
        async def housekeeping():
            """Flush recordings, remove idle sessions, drop connections stuck in a send
            (``routes.socket.drop_stuck``)."""
            period = min(settings.flush_interval_s / 2, settings.subscriber_send_timeout_s / 4,
                         settings.idle_timeout_s / 4)
            while True:
                await asyncio.sleep(period)
                sessions.flush_recordings()
                sessions.evict_idle(time.monotonic())
                drop_stuck(sessions, metrics, settings.subscriber_send_timeout_s, time.monotonic())
        if settings.bus is not None:                 # a gateway: sessions run in hand workers
            from ..bus.gateway import GatewayBus
            sessions.bus = await GatewayBus.connect(settings.bus)
        elif settings.hand_workers:                  # hands in worker processes of this machine
            sessions.pool = HandPool(settings, metrics)
            await sessions.pool.start()
            await sessions.pool.wait_ready()         # each has the default estimator's kernels loaded
        else:
            await warm_off_loop(settings.estimator)  # the default estimator's kernels, before serving
        await warm_request_path(app)
        task = asyncio.create_task(housekeeping())
        yield
        task.cancel()
        churn.cancel()
        await sessions.drain()
        if sessions.bus is not None:
            await sessions.bus.close()
        if sessions.pool is not None:
            await sessions.pool.close()

    app = FastAPIOffline(title="fingertrack", version="0.1.0", lifespan=lifespan,
                  description="Finger tracking for VR hand interaction: protocol v1 over WebSocket, REST config.")
    app.state.settings, app.state.sessions, app.state.metrics = settings, sessions, metrics
    app.state.drain = sessions.drain
    app.state.churn = churn
    app.add_middleware(CollectAfterConnections, collector=churn)
    for module in (rest, schema, ingest, stream):
        app.include_router(module.router)
    built = app.build_middleware_stack
    app.build_middleware_stack = lambda: ProbePaths(built(), app)   # (built when the server first calls it)
    if WEB_VIEWER.is_dir():
        app.mount("/viewer", StaticFiles(directory=str(WEB_VIEWER), html=True), name="viewer")
    return app


WARM_PATH = "/ready"
"""the request ``warm_request_path`` sends through the app: a plain function's route (the thread pool), no token"""
WARM_UNROUTED = "/-warm-up"
"""the second one: a path no route matches, so that every router is walked (404)"""


async def warm_request_path(app: FastAPI) -> None:
    """Two requests through the app's stack before serving (from the lifespan, where the server has built it):
    ``GET /ready``, then a ``GET`` of a path no route matches. The first request that goes past ``ProbePaths``
    pays the framework's lazy set-up on the event loop: the routers' route contexts built, the thread pool's
    backend module imported and its first thread started, 15 ms of the loop's CPU here against 2 ms for the
    next request. It fell on the first REST call made while sessions stream, the first estimator switch in
    ``bench switch``, and every session's frames waited for it (the others' largest stall at that switch,
    10-20 ms). ``/ready`` sets up the thread pool and the REST router; the unrouted path walks the others (the
    sockets' routers, the viewer's mount: 1.4 ms of the loop's CPU at their first request otherwise). They are
    sent below the framework's telemetry (``Starlette.__call__``, as FastAPI's own entry calls it when telemetry
    is off): a configured tracer sees no request at start. A failure here is logged; the service starts anyway."""
    for path, expected in ((WARM_PATH, 200), (WARM_UNROUTED, 404)):
        scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.3"}, "http_version": "1.1",
                 "method": "GET", "scheme": "http", "path": path, "raw_path": path.encode(), "root_path": "",
                 "query_string": b"", "headers": [(b"host", b"localhost")], "client": None, "server": None,
                 "state": {}}
        sent: list[dict] = []

        async def receive() -> dict:
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(message: dict) -> None:
            sent.append(message)

        try:
            await Starlette.__call__(app, scope, receive, send)
        except Exception as err:                    # a defect: the first request pays it instead
            log.warning("warming the request path (GET %s) failed: %s: %s", path, type(err).__name__, err,
                        exc_info=True)
            return
        status = next((m.get("status") for m in sent if m["type"] == "http.response.start"), None)
        if status != expected:
            log.warning("warming the request path: GET %s answered %s", path, status)


class ProbePaths:
    """The app's outermost layer (inside the framework's own entry, so its telemetry, when configured, still
    sees every request): ``GET`` of a path in ``rest.PROBES`` (``/health``, ``/metrics``) answered there, as
    its route answers it (the same token check, body, headers and refusals; the OpenAPI schema keeps the
    routes), without the dozen layers of middleware, routing and dependency solving a request passes
    otherwise. They took more of the web process's time than the answers (a probe asking both 20 times a
    second at 50 hands: about a tenth of the process's busy time). Anything else, a ``root_path``, dependency
    overrides or middleware other than the app's own take the whole way; so does a request whose answer
    failed here (a defect), answered there as on any route (500)."""

    def __init__(self, stack, app: FastAPI):
        self.stack, self.app = stack, app
        self.probes = rest.PROBES if all(m.cls is CollectAfterConnections for m in app.user_middleware) else {}

    async def __call__(self, scope, receive, send) -> None:
        answer = self.probes.get(scope["path"]) if scope["type"] == "http" else None
        if answer is None or scope["method"] != "GET" or scope.get("root_path") or self.app.dependency_overrides:
            return await self.stack(scope, receive, send)
        try:
            response = await answer(self.app, scope, receive)
        except Exception:                           # a defect: logged, and answered the whole way
            log.exception("answering %s at the app's entry failed; it is answered the whole way", scope["path"])
            return await self.stack(scope, receive, send)
        await response(scope, receive, send)
