"""REST: the index page, health and readiness, the sessions, a session's configuration and gesture
enrolment, Prometheus metrics."""
from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Request, Security
from fastapi.responses import HTMLResponse, JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ...protocol import PROTOCOL_VERSION
from ..deps import MetricsDep, Role, SessionsDep, existing_session, session_or_new
from ..metrics import Metrics
from ..sessions import LiveSession, SessionConfig, SessionConfigChange

router = APIRouter()
INDEX_PAGE = """<!doctype html><html lang="en"><head><meta charset="utf-8"><title>fingertrack</title>
<link rel="icon" href="data:,"></head><body style="font: 15px system-ui, sans-serif; margin: 2em">
<h1>fingertrack</h1><ul><li><a href="/viewer/">viewer</a>: a live hand, its joint angles and gesture events</li>
<li><a href="/docs">API docs</a> (<a href="/openapi.json">OpenAPI</a>)</li><li><a href="/health">health</a></li></ul>
</body></html>"""


@router.get("/", include_in_schema=False)
def index():
    """A page that leads to the viewer and the API docs."""
    return HTMLResponse(INDEX_PAGE)


# health and metrics are coroutines: answered on the event loop at once, not after a hop through the
# thread pool, whose thread has to win the interpreter lock from a busy loop first

@router.get("/health")
async def health():
    return {"status": "ok"}


@router.get("/ready")
def ready(sessions: SessionsDep):
    if sessions.closing:
        raise HTTPException(503, "shutting down")
    if len(sessions) >= sessions.settings.max_sessions:     # a new session would be refused
        return JSONResponse({"ready": False, "reason": f"session table full ({len(sessions)} of "
                             f"{sessions.settings.max_sessions})", "sessions": len(sessions)}, status_code=503)
    return {"ready": True, "sessions": len(sessions), "protocol": PROTOCOL_VERSION}


@router.get("/v1/sessions")
def list_sessions(request: Request, sessions: SessionsDep, role: Annotated[str, Security(Role("read"))]):
    """Every live session the token may see; where its recording is only to an admin (others see
    whether it records)."""
    out = [live.summary() for live in sessions if request.state.grant.allows(live.name)]
    if role != "admin":
        for summary in out:
            summary["recording"] = summary["recording"] is not None
    return out


@router.get("/v1/sessions/{session}/config", dependencies=[Security(Role("read"))], response_model=SessionConfig)
def get_config(live: Annotated[LiveSession, Depends(existing_session)]):
    return live.config


@router.put("/v1/sessions/{session}/config", dependencies=[Security(Role("configure"))], response_model=SessionConfig)
def put_config(session: str, change: SessionConfigChange, sessions: SessionsDep):
    # a plain function (FastAPI's thread pool), as before: a bus session's change waits for its worker
    live = session_or_new(session, sessions)
    values = change.model_dump(exclude_unset=True, exclude_none=True)
    try:
        return live.update_config(values)
    except ValidationError as err:
        raise HTTPException(422, json.loads(err.json(include_url=False))) from None
    except ValueError as err:
        raise HTTPException(422, str(err)) from None


class EnrolmentRequest(BaseModel):
    """Body of ``POST /v1/sessions/{session}/enrolment``."""

    model_config = ConfigDict(extra="forbid")

    segments: list[dict[str, Any]] = Field(..., min_length=1, description="labelled segments of the session's recent "
                                           "frames: ``{label: point|grasp|pinch|open|rest, start_s, end_s}`` (source clock, s)")


@router.post("/v1/sessions/{session}/enrolment", dependencies=[Security(Role("configure"))])
def post_enrolment(body: EnrolmentRequest, live: Annotated[LiveSession, Depends(existing_session)]):
    """Fit the session's gesture thresholds to the user (``gestures.enrolment``) and apply them."""
    try:
        return live.enrol(body.segments)
    except ValueError as err:
        raise HTTPException(422, str(err)) from None


METRICS_ROLE = Role("metrics")


@router.get("/metrics")
async def get_metrics(metrics: MetricsDep, role: Annotated[str, Security(METRICS_ROLE)]):
    """Prometheus text; series labelled by session to admins only."""
    return metrics_response(metrics, role)


def metrics_response(metrics: Metrics, role: str) -> Response:
    return Response(metrics.render(admin=role == "admin"), media_type="text/plain; version=0.0.4")


# ``GET /health`` and ``GET /metrics`` answered as the routes above answer them, without the framework's
# layers between the server and the route (``app.ProbePaths``): a monitoring system asks them many times a
# second, and those layers took more of the web process's time than the answers

async def answer_health(app, scope, receive) -> Response:
    return JSONResponse({"status": "ok"})


async def answer_metrics(app, scope, receive) -> Response:
    """The route's answer: the same token check (``Role``), the same refusal (the app's handler of an
    ``HTTPException``: 401 or 403 with a JSON ``detail``), the same text and headers."""
    request = Request(scope, receive)
    try:
        return metrics_response(app.state.metrics, await METRICS_ROLE(request))
    except StarletteHTTPException as exc:
        return await app.exception_handlers[StarletteHTTPException](request, exc)


PROBES = {"/health": answer_health, "/metrics": answer_metrics}
"""``GET`` paths answered without the framework's layers (``app.ProbePaths``): ``answer(app, scope, receive)``
gives the response"""
