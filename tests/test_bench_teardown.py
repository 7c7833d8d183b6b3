"""A benchmark's child processes end with it: a SIGTERM to ``fingertrack bench load`` stops its service
(and that service's hand workers) and its load generator on the way out, and a child started with
``bound_to_this_process`` is killed by the kernel when its parent is SIGKILLed (no teardown runs then).
Waits are for processes to appear and go; the timeouts only bound a failure."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.bench.process import descendants

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux /proc and prctl")


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _started(pid: int) -> str | None:
    """The process's start time (``/proc/PID/stat`` field 22), None once it is gone or a zombie: with the
    pid it names one process, not a later one given the same pid."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return None if fields[0] == "Z" else fields[19]


def _wait_gone(procs: dict[int, str], timeout_s: float = 120.0) -> list[str]:
    """Wait until none of ``procs`` (pid -> start time) runs; returns the command lines of those that still do."""
    deadline = time.monotonic() + timeout_s
    while True:
        left = [pid for pid, started in procs.items() if _started(pid) == started]
        if not left or time.monotonic() > deadline:
            return [f"{pid}: {_cmdline(pid)}" for pid in left]
        time.sleep(0.1)


def test_sigterm_to_bench_load_stops_its_service_hand_workers_and_generator(tmp_path):
    log = open(tmp_path / "bench.log", "w+")
    bench = subprocess.Popen([sys.executable, "-m", "service.cli", "bench", "load", "--hands", "1", "--seconds", "60",
                              "--out", str(tmp_path / "out")], stdout=log, stderr=subprocess.STDOUT)
    try:
        # the level has begun once its load generator runs: the service and its two hand workers are up
        deadline = time.monotonic() + 300.0
        while True:
            commands = [_cmdline(pid) for pid in descendants(bench.pid)]
            if any("service.bench.load" in c for c in commands) \
                    and sum("service.api.hands.worker" in c for c in commands) == 2:
                break
            assert bench.poll() is None, "the benchmark ended before its level began"
            assert time.monotonic() < deadline, f"the level did not begin: {commands}"
            time.sleep(0.1)
        children = {pid: _started(pid) for pid in descendants(bench.pid)}
        kinds = [_cmdline(pid) for pid in children]
        assert any(" serve " in c for c in kinds) and any("service.bench.load" in c for c in kinds), kinds
        bench.send_signal(signal.SIGTERM)
        assert bench.wait(timeout=120) == 130           # as after Ctrl-C
        assert _wait_gone(children) == []
        log.seek(0)
        assert "Traceback" not in log.read()
    finally:
        if bench.poll() is None:
            bench.kill()
        log.close()


PARENT = """
import subprocess, sys, time
from service.bench.process import bound_to_this_process
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"], preexec_fn=bound_to_this_process())
print(child.pid, flush=True)
time.sleep(600)
"""


def test_a_child_bound_to_its_parent_is_killed_when_the_parent_is_sigkilled():
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True,
                              cwd=Path(__file__).resolve().parents[1])
    try:
        child = int(parent.stdout.readline())
        started = _started(child)
        assert started is not None
        parent.kill()                                   # no teardown can run: only the kernel stops the child
        parent.wait()
        assert _wait_gone({child: started}) == []
    finally:
        if parent.poll() is None:
            parent.kill()
