import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest
from starlette.websockets import WebSocket

from protocol_validation import SentRecords, ServiceMessageCheck

SENT_CAPTURE = Path(__file__).resolve().parent / "sent_capture"

# A REST call's answer is waited for as long as a busy machine needs (the client's 10 s default is for
# people at a terminal; a switch's PUT answers after the session's new estimator is built, which took
# more than 10 s on a 2-core machine at load 6-8). Patched before the test modules import ``rest``; a
# test that means a shorter bound passes ``timeout_s`` itself.
import clients.client as _client                          # noqa: E402

_rest = _client.rest


def _patient_rest(*args, timeout_s: float = 120.0, **kwargs):
    return _rest(*args, timeout_s=timeout_s, **kwargs)


_patient_rest.__doc__ = _rest.__doc__
_client.rest = _patient_rest


def pytest_addoption(parser):
    parser.addoption("--busy", type=int, default=0, metavar="N",
                     help="run the tests with N CPU-bound processes beside them (tests/busy.py)")


def pytest_configure(config):
    # service processes the tests start record what they send (sent_capture/sitecustomize.py)
    config._sent_dir = tempfile.mkdtemp(prefix="fingertrack-sent-")
    os.environ["FINGERTRACK_TEST_SENT_DIR"] = config._sent_dir
    # no spare hand worker (a process started ahead beside every service a test starts: seconds of CPU
    # each); the tests of the spare turn it on
    os.environ.setdefault("FINGERTRACK_HAND_WORKER_SPARE", "false")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(SENT_CAPTURE), *filter(None, [os.environ.get("PYTHONPATH")])])
    if not hasattr(config, "workerinput"):              # with pytest-xdist, once, in the controlling process
        _compile_kernels_once()
    count = config.getoption("busy")
    if count and not hasattr(config, "workerinput"):
        from busy import busy_processes
        config._busy = busy_processes(count)
        pids = config._busy.__enter__()
        print(f"\nbusy: {count} CPU-bound processes beside the tests (pids {pids})")


def _compile_kernels_once() -> None:
    """Kernels not yet in the on-disk cache (a fresh checkout) are compiled here once, before the test
    processes start, in two processes side by side (chain's, and the pipeline's with inertial's: 35-40 s
    of a core each). Else each test process, and each service a test starts, finds the cache empty and
    compiles the same kernels at the same time (the first tests to touch them took minutes). Tests of a
    cold cache use caches of their own."""
    import subprocess
    import sys
    from service.estimators.warm import PIPELINE, _kernels, _on_disk
    cold = [name for name in ("chain", PIPELINE, "inertial") if not _on_disk(_kernels(name))]
    groups = [[n for n in cold if n == "chain"], [n for n in cold if n != "chain"]]
    procs = [subprocess.Popen([sys.executable, "-c", f"from service.estimators.warm import warm\nfor n in {g!r}: warm(n)"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT) for g in groups if g]
    for proc in procs:
        out = proc.communicate()[0]
        if proc.returncode:                 # the tests that use the kernels compile them again, and fail or pass
            print(f"\ncompiling kernels before the tests failed ({proc.returncode}):\n{out.decode(errors='replace')}")


LONGEST_FIRST = ("test_hardening.py", "test_bench_robustness.py", "test_bench_gestures.py", "test_hand_workers.py",
                 "test_service.py", "test_read_only_root.py", "test_bus.py", "test_bench_paper.py", "test_estimators.py",
                 "test_hand_pool.py", "test_bench_accuracy.py", "test_schema.py", "test_rigid_cores.py", "test_cli.py",
                 "test_viewer_token.py", "test_pipeline.py", "test_load.py")
"""The test files that take longest (wall time in a test worker, the mean share of two whole runs at load
6-8), longest first; every other file takes under a minute. Each file runs in one worker
(``--dist loadfile``) and the workers are handed files in the order of collection (``--no-loadscope-reorder``
in ``pyproject.toml``: pytest-xdist's own order, by number of tests, handed out the two-test read-only-root
file, over a minute, among the last), so one worker no longer goes on alone with a long file at the end."""


def pytest_collection_modifyitems(config, items):
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))       # stable: the others as collected


def pytest_unconfigure(config):
    busy = getattr(config, "_busy", None)
    if busy is not None:
        busy.__exit__(None, None, None)
    sent_dir = getattr(config, "_sent_dir", None)
    if sent_dir:
        shutil.rmtree(sent_dir, ignore_errors=True)


_HANDLED = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@pytest.fixture(autouse=True)
def signal_handlers_are_left_as_found():
    """A test that runs service code in the test process's main thread (a hand worker's ``main``, a
    bus worker, a benchmark's teardown) may change how the process takes SIGINT, SIGTERM or SIGHUP. Left
    so, every later child process would inherit it: a ``fingertrack serve`` started with SIGINT ignored
    still stops on Ctrl-C (uvicorn catches it) but exits 0 instead of 130. The handlers are put back
    after each test, with a warning naming the test that changed them."""
    before = {sig: signal.getsignal(sig) for sig in _HANDLED}
    yield
    for sig, handler in before.items():
        now = signal.getsignal(sig)
        if now is not handler and handler is not None:   # None: installed from C, cannot be put back
            signal.signal(sig, handler)
            import warnings
            warnings.warn(f"the test left the {signal.Signals(sig).name} handler changed ({handler!r} -> {now!r}); "
                          "put back", RuntimeWarning, stacklevel=1)


@pytest.fixture(scope="module")
def one_hand_worker():
    """For a test module whose services (in-process ``ServerThread``s and the service processes its tests
    start) run one session at a time, or several that need not be on different processes: one hand worker
    per service instead of the default two (``FINGERTRACK_HAND_WORKERS=1``; settings a test gives
    explicitly still win). The second worker started with every service, loaded the default estimator
    (about 3 s of CPU) and got no session. Several workers, sessions spread over them and moved between
    them are the subject of the hand worker tests, which ask for the workers they need."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FINGERTRACK_HAND_WORKERS", "1")
        yield


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

    # ready-made frames written past Starlette (``DrainingWebSocket.write_frames``): each frame's payload
    from sent_capture.ws_frames import payloads
    from service.api.server import DrainingWebSocket
    write_frames = DrainingWebSocket.write_frames

    def written(self, data):
        done = write_frames(self, data)
        if done:
            with _SENT_LOCK:
                _SENT.extend(payloads(data))
        return done

    WebSocket.send_text, WebSocket.send_bytes = text, binary
    DrainingWebSocket.write_frames = written
    yield ServiceMessageCheck()
    WebSocket.send_text, WebSocket.send_bytes = send_text, send_bytes
    DrainingWebSocket.write_frames = write_frames


@pytest.fixture(scope="session")
def _service_process_messages(pytestconfig):
    """What service processes started by the tests sent (their own Python processes, recorded by
    sent_capture/sitecustomize.py into the folder pytest_configure names)."""
    return SentRecords(pytestconfig._sent_dir)


@pytest.fixture(autouse=True)
def service_messages_follow_the_schema(_capture_service_messages, _service_process_messages):
    """Every message the service sent during a test validates against the published JSON Schema
    (docs/schema/service-message.schema.json, checked strictly: no undeclared fields): services in
    threads of the test process and service processes the tests started alike."""
    yield
    with _SENT_LOCK:
        sent = [("this process", data) for data in _SENT]
        _SENT.clear()
    sent += [(f"process {pid}", data) for pid, data in _service_process_messages.take()]
    check = _capture_service_messages
    for where, data in sent:
        problems = check.problems(data)
        if problems:
            shown = data if isinstance(data, str) else repr(data)
            pytest.fail(f"the service ({where}) sent a message that does not follow its schema: {problems[:5]}; "
                        f"message: {shown[:300]}", pytrace=False)
