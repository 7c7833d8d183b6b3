"""NATS subjects, the messages on them and the session lease (documented in docs/bus.md).

Every payload is MessagePack. ``<s>`` is the session's subject token (``session_token``).

* ``ft.assign`` (request, queue group ``ft-workers``): ``{"session": name}`` from a gateway that has
  data for a session; a worker answers ``{"owner": worker_id}`` once some worker owns it (it claims
  it if nobody does, or if its owner's lease has lapsed).
* ``ft.src.<s>`` (request, only the owner subscribes): ``{"raw": source message}``, one protocol-v1
  source message the gateway validated; the reply ``{"errors": [[code, detail], ...]}`` (the error
  replies the embedded service would give, ``api.replies``) comes once the worker has handled it (its frames are published before the reply), so ``sync`` keeps
  its meaning across the bus. No reply within ``REPLY_WAIT_S``: the gateway asks ``ft.assign`` again;
  if that moved the session (its owner was gone) the unanswered messages go to the new owner.
* ``ft.worker.<id>`` (request, the worker itself): an empty liveness probe, answered at once. A
  worker's subscriptions end with its connection, so "no responders" means the process is gone: its
  sessions are taken over at once instead of after the lease. Workers probe a session's owner before
  they take it over; a gateway waiting for an owner's replies probes it every ``PROBE_EVERY_S``.
* ``ft.cfg.<s>`` (request, owner): ``{"change": {...}}`` a configuration change; reply
  ``{"config": {...}}`` or ``{"error": str}``, once applied: an estimator whose kernels the worker has
  not loaded is compiled in a separate process and loaded first (up to ``CONFIG_WAIT_S``), while
  the worker's sessions, this one on its old estimator, go on.
* ``ft.out.<s>`` (publish, owner -> every gateway with subscribers): a ``frame`` or ``gesture``
  message exactly as the embedded service sends it; ``seq`` increases across a change of owner.
* Key-value bucket ``ft_sessions`` (JetStream, memory storage), key ``<s>``: the lease and the
  session's compact state ``{"session", "worker", "seq", "t", "angles", "hello", "calibration",
  "config"}``, rewritten by the owner every ``RENEW_S`` with a compare-and-set on the revision it
  last wrote. A worker that saw the same revision for longer than ``LEASE_S`` may take the session
  over with a compare-and-set on that revision: exactly one succeeds, and a former owner whose
  renewal fails gives the session up. An owner whose last renewal is older than ``LEASE_S / 2``
  renews before it publishes anything more (a fence), and gateways drop a frame whose ``seq`` is not
  above the last one they passed on.
"""
from __future__ import annotations

import asyncio
import enum
import logging
import re

import msgpack
import nats

from ..api.config import redacted_url

log = logging.getLogger("fingertrack.bus")

ASSIGN = "ft.assign"
WORKERS_QUEUE = "ft-workers"
BUCKET = "ft_sessions"
RENEW_S = 0.15
"""how often an owner rewrites its sessions' lease and state, s"""
LEASE_S = 3.0
"""a lease not renewed for this long (as seen by another worker) may be taken over, s. Only for an
owner that is alive but stuck or cut off: a dead owner is found at once by the liveness probe. Long
enough that a worker starved of CPU on a busy machine keeps its sessions."""
REPLY_WAIT_S = 0.3
"""how long a gateway waits for a worker's reply to one source message before it checks the owner, s"""
CONFIG_WAIT_S = 300.0
"""how long a gateway waits for the owner to apply a configuration change (it may compile an
estimator's kernels first, in a separate process, while its sessions go on), s"""
CONNECT_TIMEOUT_S = 10.0
"""how long a worker or gateway tries to reach the NATS server at start, s (later: for ever)"""
PROBE_TIMEOUT_S = 0.2
"""how long a worker waits for another worker's liveness answer before it relies on the lease, s"""
PROBE_EVERY_S = 0.1
"""while a gateway waits for a worker's replies (a session's window full), how often it asks whether
that worker is still there, s"""
_SAFE = re.compile(r"[A-Za-z0-9_-]+")


def session_token(name: str) -> str:
    """A subject token and key for a session name: ``s<name>`` for ASCII letters, digits, ``-``,
    ``_``; else ``h<hex of UTF-8>`` (dots and other letters would split or break subjects)."""
    return "s" + name if _SAFE.fullmatch(name) else "h" + name.encode().hex()


def source_subject(name: str) -> str:
    return f"ft.src.{session_token(name)}"


def worker_subject(worker_id: str) -> str:
    return f"ft.worker.{worker_id}"


def config_subject(name: str) -> str:
    return f"ft.cfg.{session_token(name)}"


def output_subject(name: str) -> str:
    return f"ft.out.{session_token(name)}"


def pack(obj) -> bytes:
    return msgpack.packb(obj)


def unpack(data: bytes):
    return msgpack.unpackb(data)


class Liveness(enum.Enum):
    """What a liveness probe of a worker (``probe_worker``) found."""
    ANSWERED = "answered"
    """the worker answered: it is there"""
    NO_ANSWER = "no answer"
    """no answer within ``PROBE_TIMEOUT_S``: alive but slow, stuck or cut off, or the prober's own loop was
    too busy to read the answer in time; says nothing either way (a worker's lease decides)"""
    GONE = "gone"
    """nobody listens on its liveness subject: its process (or its connection) is gone, the server says so at once"""


async def probe_worker(nc, worker_id: str) -> Liveness:
    """Probe the worker's liveness subject (``Liveness``). NATS and socket errors (reconnecting) are the
    caller's to handle."""
    try:
        await nc.request(worker_subject(worker_id), b"", timeout=PROBE_TIMEOUT_S)
        return Liveness.ANSWERED
    except nats.errors.NoRespondersError:
        return Liveness.GONE
    except nats.errors.TimeoutError:
        return Liveness.NO_ANSWER


async def connect(url: str, name: str):
    """A NATS connection that reconnects for ever and reports trouble in one log line, not a traceback."""
    shown = redacted_url(url)

    async def on_error(err):
        log.warning("nats %s: %s", shown, err)

    async def on_disconnect():
        log.warning("nats %s: disconnected; reconnecting", shown)

    try:
        return await asyncio.wait_for(nats.connect(url, name=name, max_reconnect_attempts=-1, reconnect_time_wait=0.2,
                                                   error_cb=on_error, disconnected_cb=on_disconnect),
                                      CONNECT_TIMEOUT_S)
    except asyncio.TimeoutError:
        raise ConnectionError(f"cannot reach the NATS server at {url} within {CONNECT_TIMEOUT_S:g} s "
                              "(is nats-server running, with -js?)") from None


async def close(nc) -> None:
    """Drain (finish what is in flight) if connected, else just close."""
    try:
        await nc.drain()
    except nats.errors.Error:
        await nc.close()
