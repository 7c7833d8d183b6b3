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
