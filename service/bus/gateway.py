"""The gateway side of the bus: a session proxy that looks like a ``LiveSession`` to the API.

``fingertrack serve --bus nats://...`` keeps the whole API (tokens, validation, rate limits,
subscribers' bounded queues, sync barriers) and swaps the session: ``BusSession.ingest`` sends the
validated source message to the session's owning worker (pipelined: it does not wait for the
reply; the reply's late/duplicate counts and errors become the usual error replies to the source, and
a ``sync`` is answered once every earlier message was answered);
frames and gesture events of ``ft.out.<s>`` go to this gateway's subscribers of the session. When no
worker listens (the owner died), the gateway asks ``ft.assign`` until a worker has taken the session
over, holding the source's next message meanwhile; messages the server reported undeliverable are
counted as ``lost_to_failover``, messages the dead owner never answered as ``unconfirmed`` (session
summary).
"""
from __future__ import annotations

import asyncio
import time

from nats.errors import NoRespondersError
from nats.errors import TimeoutError as NatsTimeout

from ..api.config import ServiceSettings
from ..api.metrics import Metrics
from ..api.sessions import LiveSession
from .subjects import (ASSIGN, REPLY_WAIT_S, close, config_subject, connect, output_subject, pack, source_subject,
                       unpack)

ASSIGN_TIMEOUT_S = 1.0
"""how long a gateway waits for a worker to answer ``ft.assign``, s"""
WINDOW = 256
"""source messages of one session on their way to its worker at once (more: the source waits)"""
UNCONFIRMED = {"late": 0, "duplicate": 0, "error": None, "unconfirmed": True}


class GatewayBus:
    """One NATS connection of a gateway process."""

    def __init__(self, nc, loop: asyncio.AbstractEventLoop):
        self.nc = nc
        self.loop = loop

    @staticmethod
    async def connect(url: str) -> "GatewayBus":
        nc = await connect(url, "fingertrack-gateway")
        return GatewayBus(nc, asyncio.get_running_loop())

    async def close(self) -> None:
        await close(self.nc)

    async def assign(self, name: str) -> dict:
        """Ask the workers to make sure the session has an live owner: ``{"owner", "by", "claimed"}``
        (``claimed``: the answering worker took the session just now), ``{}`` if no worker answered."""
        try:
            return unpack((await self.nc.request(ASSIGN, pack({"session": name}), timeout=ASSIGN_TIMEOUT_S)).data)
        except (NoRespondersError, NatsTimeout):
            return {}

    async def request(self, subject: str, payload: dict, name: str) -> dict | None:
        """A request to the session's owner; ``None``: no worker owns the session now (the message is
        lost), ``UNCONFIRMED``: the owner is there but did not answer in time."""
        data = pack(payload)
        for _ in range(2):
            try:
                return unpack((await self.nc.request(subject, data, timeout=REPLY_WAIT_S)).data)
            except NoRespondersError:               # nobody listens: the owner is gone, or there is none yet
                answer = await self.assign(name)
                if not answer or answer.get("owner") != answer.get("by"):
                    return None                     # its lease has not lapsed yet: lost
            except NatsTimeout:                     # the owner may have died holding it
                if not (await self.assign(name)).get("claimed"):
                    return UNCONFIRMED
        return None

    def session(self, name: str, settings: ServiceSettings, metrics: Metrics) -> "BusSession":
        return BusSession(name, settings, metrics, self)


class BusSession(LiveSession):
    """A session whose hand runs in a worker (module docstring). Source messages are pipelined: up to
    ``WINDOW`` wait for their reply at once, each with its own reply subject, so a reply (or the
    server's "no responders" status) belongs to exactly one message."""

    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics, bus: GatewayBus):
        super().__init__(name, settings, metrics)
        self.bus = bus
        self.lost_to_failover = 0                   # sent while no worker owned the session
        self.unconfirmed = 0                        # handed to an owner that never answered (it died holding them)
        self.stale_frames = 0                       # frames of a former owner, dropped
        self._last_seq = 0
        self.hand_side: str | None = None
        self._inbox = f"{bus.nc.new_inbox()}.ft"
        self._n = 0
        self._pending: dict[int, tuple[str, float | None]] = {}
        self._replied = asyncio.Event()
        self._owner_ok = False
        self._assigning: asyncio.Task | None = None
        self._source_error = None
        self._subscribed = asyncio.Event()
        self._subscriptions: list = []
        bus.loop.call_soon_threadsafe(lambda: bus.loop.create_task(self._subscribe()))

    async def _subscribe(self) -> None:
        self._subscriptions = [await self.bus.nc.subscribe(output_subject(self.name), cb=self._on_output),
                               await self.bus.nc.subscribe(f"{self._inbox}.*", cb=self._on_reply)]
        await self.bus.nc.flush()
        self._subscribed.set()

    def attach_source(self, send_error) -> None:
        self._source_error = send_error

    async def _on_output(self, msg) -> None:
        out = unpack(msg.data)
        if out.get("type") == "frame":
            if out["seq"] <= self._last_seq:        # from a former owner that has not noticed yet
                self.stale_frames += 1
                return
            self._last_seq = out["seq"]
            self.hand_side = out.get("hand")
        self._fan_out([out], time.perf_counter())

    async def _on_reply(self, msg) -> None:
        n = int(msg.subject.rsplit(".", 1)[1])
        entry = self._pending.get(n)
        try:
            if entry is not None:                   # else written off already
                await self._answer(msg, *entry)
        finally:                                    # answered (its error sent) before a sync can see it gone
            self._pending.pop(n, None)
            self._replied.set()

    async def _answer(self, msg, kind: str, t: float | None) -> None:
        if msg.headers and msg.headers.get("Status") == "503":     # nobody listens: the owner is gone
            self.lost_to_failover += 1
            self._owner_ok = False
            return
        reply = unpack(msg.data)
        if self._source_error is None:
            return
        if reply["error"]:
            await self._source_error("invalid_message", reply["error"])
        elif reply["late"]:
            await self._source_error("time_backwards", f"{kind} at t={t} is older than what was already processed; dropped")
        elif reply["duplicate"]:
            await self._source_error("duplicate", f"{kind} at t={t} was already received; dropped")

    async def _ensure_owner(self) -> None:
        """Until a live worker owns the session (a takeover needs the old owner gone or its lease
        lapsed); messages wait meanwhile instead of being lost."""
        while not self._owner_ok:
            answer = await self.bus.assign(self.name)
            if answer and answer.get("owner") == answer.get("by"):
                self._owner_ok = True
            else:
                await asyncio.sleep(0.05)

    async def ingest(self, raw: dict, parsed) -> None:
        await self._subscribed.wait()
        if not self._owner_ok:
            self._write_off()
            await self._ensure_owner()
        while len(self._pending) >= WINDOW:         # backpressure: the source waits for the worker
            if not await self._wait_replies():
                self._write_off()
        self.metrics.messages_in.labels(self.name).inc()
        self._n += 1
        self._pending[self._n] = (parsed.type, getattr(parsed, "t", None))
        await self.bus.nc.publish(source_subject(self.name), pack({"raw": raw}), reply=f"{self._inbox}.{self._n}")

    async def _wait_replies(self) -> bool:
        """Wait for a reply. None for ``REPLY_WAIT_S``: the workers check the owner; False when it was
        gone and the session has a new owner now (the pending messages will never be answered)."""
        self._replied.clear()
        try:
            await asyncio.wait_for(self._replied.wait(), REPLY_WAIT_S)
            return True
        except asyncio.TimeoutError:
            return not (await self.bus.assign(self.name)).get("claimed")

    def _write_off(self) -> None:
        """Messages sent to an owner that is gone will not be answered."""
        self.unconfirmed += len(self._pending)
        self._pending.clear()

    async def settled(self) -> None:
        """Every message sent so far was answered (or written off): what ``sync`` waits for."""
        while self._pending:
            if not await self._wait_replies():
                self._write_off()

    def update_config(self, change: dict) -> dict:
        """Validated here (a bad change changes nothing), then applied by the owner, which keeps it in
        the session's state so it survives a change of owner. Called from a worker thread of the API."""
        config = super().update_config(change)
        future = asyncio.run_coroutine_threadsafe(
            self.bus.request(config_subject(self.name), {"change": change}, self.name), self.bus.loop)
        reply = future.result(timeout=2 * (REPLY_WAIT_S + ASSIGN_TIMEOUT_S) + 1.0)
        if reply is None or reply.get("unconfirmed"):
            raise ValueError("no hand worker answered; the change is kept here and was not applied")
        if "error" in reply:
            raise ValueError(reply["error"])
        return config

    def summary(self) -> dict:
        out = super().summary()
        out["hand"] = self.hand_side or out["hand"]
        out["lost_to_failover"] = self.lost_to_failover
        out["unconfirmed"] = self.unconfirmed
        out["stale_frames"] = self.stale_frames
        return out

    def close(self) -> None:
        super().close()
        for sub in self._subscriptions:
            self.bus.loop.call_soon_threadsafe(lambda sub=sub: self.bus.loop.create_task(sub.unsubscribe()))
