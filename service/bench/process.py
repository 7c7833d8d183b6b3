"""The service in its own process for the benchmarks: ``fingertrack serve`` on a free localhost port,
as deployed, with tokens written to a temporary settings file."""
from __future__ import annotations

import contextlib
import json
import os
import secrets
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from ..api.server import free_port


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
                    log_path: str | Path | None = None, credentials: tuple[str, str, str] | None = None):
    """Start ``fingertrack serve`` with fresh source/viewer/admin tokens; yields a
    :class:`ServiceProcess`, terminates the service on exit. A service that does not become healthy
    (within ``start_timeout_s``, a bound for a failure only: a start compiles the kernels first when
    their cache is cold, which took over 20 s on a busy machine) raises ``RuntimeError`` with its log.
    ``log_path``: keep the service's stderr there (else it goes with the temporary folder).
    ``credentials``: the (source, viewer, admin) tokens to use (e.g. the same for several gateways)."""
    from clients.client import wait_healthy

    port = free_port()
    source, viewer, admin = credentials or tuple(secrets.token_urlsafe(12) for _ in range(3))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "service.json"
        cfg.write_text(json.dumps({"tokens": {source: "source", viewer: "viewer"}, "admin_token": admin,
                                   **(extra_settings or {})}))
        log = open(log_path or Path(tmp) / "service.log", "w+")         # a file, not a pipe: a full pipe would stall the service
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--config", str(cfg)],
                                stdout=subprocess.DEVNULL, stderr=log)
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
