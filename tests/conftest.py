import threading

import numpy as np
import pytest
from starlette.websockets import WebSocket

from protocol_validation import ServiceMessageCheck


def pytest_addoption(parser):
    parser.addoption("--busy", type=int, default=0, metavar="N",
                     help="run the tests with N CPU-bound processes beside them (tests/busy.py)")


def pytest_configure(config):
    count = config.getoption("busy")
    if count:
        from busy import busy_processes
        config._busy = busy_processes(count)
        pids = config._busy.__enter__()
        print(f"\nbusy: {count} CPU-bound processes beside the tests (pids {pids})")


def pytest_unconfigure(config):
    busy = getattr(config, "_busy", None)
    if busy is not None:
        busy.__exit__(None, None, None)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


_SENT: list = []
_SENT_LOCK = threading.Lock()


@pytest.fixture(scope="session")
def _capture_service_messages():
    """Records every message an in-process service sends on its WebSockets (servers run in threads
    of the test process); the recording costs one list append, validation happens after each test."""
    send_text, send_bytes = WebSocket.send_text, WebSocket.send_bytes

    async def text(self, data):
        with _SENT_LOCK:
            _SENT.append(data)
        await send_text(self, data)

    async def binary(self, data):
        with _SENT_LOCK:
            _SENT.append(bytes(data))
        await send_bytes(self, data)

    WebSocket.send_text, WebSocket.send_bytes = text, binary
    yield ServiceMessageCheck()
    WebSocket.send_text, WebSocket.send_bytes = send_text, send_bytes


@pytest.fixture(autouse=True)
def service_messages_follow_the_schema(_capture_service_messages):
    """Every message the service sent during a test validates against the published JSON Schema
    (docs/schema/service-message.schema.json, checked strictly: no undeclared fields)."""
    yield
    with _SENT_LOCK:
        sent = list(_SENT)
        _SENT.clear()
    check = _capture_service_messages
    for data in sent:
        problems = check.problems(data)
        if problems:
            shown = data if isinstance(data, str) else repr(data)
            pytest.fail(f"the service sent a message that does not follow its schema: {problems[:5]}; "
                        f"message: {shown[:300]}", pytrace=False)
