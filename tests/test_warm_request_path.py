"""The request path warmed before serving (``app.warm_request_path``): the first REST request a running service
answers imports nothing (the framework's lazy set-up was done in the lifespan, not on the event loop while
sessions stream), and a warm-up that fails is logged without stopping the start."""
from __future__ import annotations

import asyncio
import logging

from fastapi import FastAPI

from clients.client import rest
from service.api.app import WARM_PATH, warm_request_path


def _imports(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("import time:")]


def test_the_first_rest_request_of_a_serving_service_imports_nothing(tmp_path):
    from service.bench.process import service_process

    log = tmp_path / "service.log"
    # every import of the service process goes to its log as it happens (the interpreter's -X importtime)
    with service_process(log_path=log, extra_settings={"hand_workers": 0},
                         env={"PYTHONPROFILEIMPORTTIME": "1"}) as svc:
        assert _imports(log.read_text())           # the switch works: start-up imports are listed
        before = log.stat().st_size
        status, body = rest(svc.url, "GET", "/v1/sessions", svc.admin)       # a plain function's route, a token
        assert status == 200 and body == []
        status, _ = rest(svc.url, "PUT", "/v1/sessions/bad%20name!/config", svc.admin, {"estimator": "chain"})
        assert status == 422                        # a body, a dependency refusing it
        with open(log) as f:
            f.seek(before)
            assert _imports(f.read()) == []


def test_a_warm_up_that_fails_is_logged_and_the_start_goes_on(caplog):
    app = FastAPI()

    @app.get(WARM_PATH)
    def ready():
        raise RuntimeError("not today")

    with caplog.at_level(logging.WARNING, logger="service.api.app"):
        asyncio.run(warm_request_path(app))         # returns: the service would start
    assert any("warming the request path" in r.getMessage() and "not today" in r.getMessage() for r in caplog.records)


def test_a_warm_up_answered_otherwise_is_logged(caplog):
    from fastapi.responses import JSONResponse

    app = FastAPI()

    @app.get(WARM_PATH)
    def ready():
        return JSONResponse({"ready": False}, status_code=503)

    with caplog.at_level(logging.WARNING, logger="service.api.app"):
        asyncio.run(warm_request_path(app))
    said = [r.getMessage() for r in caplog.records]
    assert said == [f"warming the request path: GET {WARM_PATH} answered 503"]   # (the unrouted path's 404 is expected)


def _request(path: str, token: str) -> dict:
    return {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET", "scheme": "http",
            "path": path, "raw_path": path.encode(), "root_path": "", "query_string": b"",
            "headers": [(b"host", b"localhost"), (b"authorization", f"Bearer {token}".encode())],
            "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80), "state": {}}


def test_the_routers_are_set_up_before_the_first_request():
    """Python calls made on the event loop's thread by a request (a count, not a time: the same on a busy machine).
    After the warm-up, the first request no route matches makes as many as the next one (without it: about 19
    times as many, every router's set-up), and the first ``GET /v1/sessions`` fewer than three times as many as
    the next (its own dependencies are still classified at its first call: 2.4 times; with only the thread pool
    started ahead, 3.6 times; with nothing, 12 times)."""
    import sys

    from service.api.app import create_app
    from service.api.config import ServiceSettings

    token = "adm-" + "x" * 28
    app = create_app(ServiceSettings(port=0, hand_workers=0, admin_token=token))

    async def calls(path: str) -> int:
        n = 0

        def count(frame, event, arg):
            nonlocal n
            n += event == "call"

        async def receive() -> dict:
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(message: dict) -> None:
            pass

        sys.setprofile(count)
        try:
            await app(_request(path, token), receive, send)
        finally:
            sys.setprofile(None)
        return n

    async def main() -> tuple[list[int], list[int]]:
        await warm_request_path(app)
        return [await calls("/no-such-path") for _ in range(2)], [await calls("/v1/sessions") for _ in range(2)]

    unrouted, sessions = asyncio.run(main())
    assert unrouted[0] == unrouted[1] > 0
    assert sessions[1] > 0 and sessions[0] < 3 * sessions[1]


_TELEMETRY_PROBE = '''
import asyncio, contextlib
from opentelemetry import trace
from opentelemetry.trace import INVALID_SPAN_CONTEXT, NonRecordingSpan
from service.api.app import create_app, warm_request_path
from service.api.config import ServiceSettings
spans = []
class Tracer(trace.Tracer):
    def start_span(self, name, context=None, kind=None, attributes=None, *a, **k):
        spans.append(name)
        return NonRecordingSpan(INVALID_SPAN_CONTEXT)
    def start_as_current_span(self, name, *a, **k):
        spans.append(name)
        return contextlib.nullcontext(NonRecordingSpan(INVALID_SPAN_CONTEXT))
class Provider(trace.TracerProvider):
    def get_tracer(self, *a, **k):
        return Tracer()
trace.set_tracer_provider(Provider())
app = create_app(ServiceSettings(port=0, hand_workers=0, admin_token="adm-" + "x" * 28))
async def main():
    await warm_request_path(app)
    print(len(spans))
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET", "scheme": "http",
             "path": "/ready", "raw_path": b"/ready", "root_path": "", "query_string": b"",
             "headers": [(b"host", b"localhost")], "client": None, "server": None, "state": {}}
    async def receive(): return {"type": "http.request", "body": b"", "more_body": False}
    async def send(m): pass
    await app(scope, receive, send)
    print(len(spans))
asyncio.run(main())
'''


def test_a_configured_tracer_sees_no_request_at_start():
    """With a tracer provider set (an operator's OpenTelemetry set-up; global to a process, so in a process of its
    own), the warm-up records no span, and a real request after it does (the tracer is live)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _TELEMETRY_PROBE], capture_output=True, text=True, timeout=120,
                         check=True).stdout.split()
    assert out[0] == "0" and int(out[1]) > 0
