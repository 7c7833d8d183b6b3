"""The service in its own process for the benchmarks: ``fingertrack serve`` on a free localhost port,
as deployed, with tokens written to a temporary settings file; and what makes a benchmark's child
processes end with it (``torn_down_on_signal``, ``bound_to_this_process``)."""
from __future__ import annotations

import contextlib
import functools
import json
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from ..api.server import free_port


PR_SET_PDEATHSIG = 1
"""``prctl`` option: the signal a process gets when the thread that started it ends (Linux, ``<linux/prctl.h>``)"""


def _prctl():
    """libc's ``prctl`` (Linux), looked up before any fork: after it, a child only calls it."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


def _end_with(prctl, parent: int) -> None:
    prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:                       # the parent ended before the request: no signal comes
        os._exit(1)


def bound_to_this_process():
    """A ``preexec_fn`` for a child process (a service, a NATS server or worker, a load generator) that
    has the kernel SIGKILL it when this process ends, however it ends (a SIGKILL included: then no
    teardown runs here). ``None`` where that cannot be had: not Linux, or called from a thread other
    than the main one (the signal comes when the starting *thread* ends, and a benchmark's helper
    threads end long before it)."""
    prctl = _prctl() if threading.current_thread() is threading.main_thread() else None
    return None if prctl is None else functools.partial(_end_with, prctl, os.getpid())


def end_with_parent(parent: int) -> None:
    """In a child started without a ``preexec_fn`` (``multiprocessing``): SIGKILL this process when
    ``parent``, the process (main thread) that started it, ends (Linux; elsewhere nothing)."""
    if (prctl := _prctl()) is not None:
        _end_with(prctl, parent)


@contextlib.contextmanager
def torn_down_on_signal():
    """While the block runs, SIGTERM and SIGHUP end it as Ctrl-C does (``KeyboardInterrupt`` in the main
    thread), so that every ``with`` and ``finally`` on the way out stops the child processes it started;
    a second signal during that teardown is ignored. Without it, a SIGTERM ended the benchmark at once
    and left its service (and that service's hand workers, or the NATS server, workers and gateways)
    running. Only in the main thread (elsewhere the block runs as it is)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = (signal.SIGTERM, signal.SIGHUP)

    def stop(signum, _frame):
        for sig in signals:
            signal.signal(sig, signal.SIG_IGN)
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")
    before = {sig: signal.signal(sig, stop) for sig in signals}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def _stat(pid: int | str) -> list[str] | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


def _descendants(pid: int) -> dict[int, list[str]] | None:
    """The running descendants of process ``pid`` (its children, theirs, ...) with their ``/proc/PID/stat``
    fields after the name (Linux ``/proc``; None elsewhere)."""
    if not Path("/proc").is_dir():
        return None
    stats = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit() and (fields := _stat(entry)) is not None:
            stats[int(entry)] = fields
    found, frontier = {}, {pid}
    while frontier:
        children = {p: f for p, f in stats.items() if int(f[1]) in frontier and p not in found}
        found.update(children)
        frontier = set(children)
    return found


def rss_kib(pid: int) -> int | None:
    """Resident memory of process ``pid``, KiB (Linux ``/proc``; None elsewhere or once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def descendants(pid: int) -> list[int]:
    """The pids of the running descendants of process ``pid`` (Linux ``/proc``; empty elsewhere)."""
    return sorted(_descendants(pid) or ())


def descendants_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of the running descendants of process ``pid`` (Linux ``/proc``; None
    elsewhere)."""
    tree = _descendants(pid)
    if tree is None:
        return None
    return sum((int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK") for f in tree.values())


@dataclass
class ServiceProcess:
    url: str
    pid: int
    source: str
    viewer: str
    admin: str
    log: IO | None = None
    """the service's log (its standard error), open; lines written here land between the service's own"""

    def cpu_seconds(self) -> float | None:
        """User + system CPU time the service process has used so far (Linux ``/proc``; None elsewhere)."""
        try:
            fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return None
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")   # utime, stime

    def children_cpu_seconds(self) -> float | None:
        """User + system CPU time the service's running child processes (its hand workers, and theirs)
        have used so far (Linux ``/proc``; None elsewhere)."""
        return descendants_cpu_seconds(self.pid)

    def alive(self) -> bool:
        """The process exists and has not exited (a zombie, killed but not yet reaped, is not alive)."""
        try:
            return Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    def rss_kib(self) -> int | None:
        """Resident memory, KiB (Linux ``/proc``; None elsewhere or once the process is gone)."""
        return rss_kib(self.pid)

    def fds(self) -> int | None:
        """Open file descriptors (Linux ``/proc``; None elsewhere or once the process is gone)."""
        try:
            return len(os.listdir(f"/proc/{self.pid}/fd"))
        except OSError:
            return None


@contextlib.contextmanager
def service_process(start_timeout_s: float = 300.0, extra_settings: dict | None = None,
                    log_path: str | Path | None = None, credentials: tuple[str, str, str] | None = None,
                    env: dict | None = None):
    """Start ``fingertrack serve`` with fresh source/viewer/admin tokens; yields a
    :class:`ServiceProcess`, terminates the service on exit. A service that does not become healthy
    (within ``start_timeout_s``, a bound for a failure only: a start compiles the kernels first when
    their cache is cold, which took over 20 s on a busy machine) raises ``RuntimeError`` with its log.
    ``log_path``: keep the service's stderr there (else it goes with the temporary folder).
    ``credentials``: the (source, viewer, admin) tokens to use (e.g. the same for several gateways).
    ``env``: variables set for the service on top of this process's (e.g. another kernel cache)."""
    from clients.client import wait_healthy

    port = free_port()
    source, viewer, admin = credentials or tuple(secrets.token_urlsafe(12) for _ in range(3))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "service.json"
        cfg.write_text(json.dumps({"tokens": {source: "source", viewer: "viewer"}, "admin_token": admin,
                                   **(extra_settings or {})}))
        log = open(log_path or Path(tmp) / "service.log", "w+")         # a file, not a pipe: a full pipe would stall the service
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--config", str(cfg)],
                                stdout=subprocess.DEVNULL, stderr=log, preexec_fn=bound_to_this_process(),
                                env=None if env is None else {**os.environ, **env})
        url = f"http://127.0.0.1:{port}"
        try:
            try:
                wait_healthy(url, start_timeout_s, alive=lambda: proc.poll() is None)
            except RuntimeError:
                log.seek(0)
                raise RuntimeError("the service did not start: " + log.read()) from None
            yield ServiceProcess(url, proc.pid, source, viewer, admin, log)
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:                # it ignored SIGTERM: do not leave it running
                proc.kill()
                proc.wait()
            log.close()
