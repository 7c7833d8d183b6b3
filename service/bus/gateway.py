"""The gateway side of the bus: a session proxy that looks like a ``LiveSession`` to the API.

``fingertrack serve --bus nats://...`` keeps the whole API (tokens, validation, rate limits,
subscribers' bounded queues, sync barriers) and swaps the session: ``BusSession.ingest`` sends the
validated source message to the session's owning worker as a request and returns once the worker
has handled it (its frames are out, its late/duplicate counts and errors come back in the reply);
frames and gesture events of ``ft.out.<s>`` go to this gateway's subscribers of the session. When no
worker listens (the owner died), the gateway asks ``ft.assign``; until a worker has taken the session
over, messages are dropped and counted (``lost_to_failover`` in the session summary).
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
    """A session whose hand runs in a worker (module docstring)."""

    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics, bus: GatewayBus):
        super().__init__(name, settings, metrics)
        self.bus = bus
        self.lost_to_failover = 0
        self.unconfirmed = 0                        # handed to a live owner that did not answer in time
        self.hand_side: str | None = None
        self._subscribed = asyncio.Event()
        self._subscription = None
        bus.loop.call_soon_threadsafe(lambda: bus.loop.create_task(self._subscribe()))

    async def _subscribe(self) -> None:
        self._subscription = await self.bus.nc.subscribe(output_subject(self.name), cb=self._on_output)
        await self.bus.nc.flush()
        self._subscribed.set()

    async def _on_output(self, msg) -> None:
        out = unpack(msg.data)
        if out.get("type") == "frame":
            self.hand_side = out.get("hand")
        self._fan_out([out], time.perf_counter())

    async def ingest(self, raw: dict, parsed) -> None:
        await self._subscribed.wait()
        self.metrics.messages_in.labels(self.name).inc()
        reply = await self.bus.request(source_subject(self.name), {"raw": raw}, self.name)
        if reply is None:
            self.lost_to_failover += 1
            return
        self.unconfirmed += int(reply.get("unconfirmed", False))
        counters = self.hand.session.counters       # the API compares them around this call
        counters.late += reply["late"]
        counters.duplicate += reply["duplicate"]
        if reply["error"]:
            raise ValueError(reply["error"])

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
        return out

    def close(self) -> None:
        super().close()
        if self._subscription is not None:
            self.bus.loop.call_soon_threadsafe(lambda: self.bus.loop.create_task(self._subscription.unsubscribe()))
