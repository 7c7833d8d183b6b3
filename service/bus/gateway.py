"""The gateway side of the bus: a session proxy that looks like a ``LiveSession`` to the API.

``fingertrack serve --bus nats://...`` keeps the whole API (tokens, validation, rate limits,
subscribers' bounded queues, sync barriers) and swaps the session: ``BusSession.ingest`` sends the
validated source message to the session's owning worker (pipelined: it does not wait for the
reply; the reply's errors, as the embedded service would give them, go to the source, and
a ``sync`` is answered once every earlier message was answered);
frames and gesture events of ``ft.out.<s>`` go to this gateway's subscribers of the session. When no
worker listens (the owner died), the gateway asks ``ft.assign`` until a worker has taken the session
over, holding the source's next message meanwhile, and sends the new owner, in order, every message
the old one never answered (``resent_after_failover``; beyond ``RESEND_MAX`` they are lost and
counted as ``lost_to_failover``; session summary). With no worker at all, sources wait.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field

from nats.errors import Error as NatsError
from nats.errors import NoRespondersError
from nats.errors import TimeoutError as NatsTimeout

from ..api.config import ServiceSettings
from ..api.metrics import Metrics
from ..api.sessions import LiveSession, SessionConfig, SessionFull
from .subjects import (ASSIGN, CONFIG_WAIT_S, PROBE_EVERY_S, REPLY_WAIT_S, Liveness, close, config_subject, connect,
                       output_subject, pack, probe_worker, source_subject, unpack)

log = logging.getLogger("fingertrack.bus")

ASSIGN_TIMEOUT_S = 1.0
"""how long a gateway waits for a worker to answer ``ft.assign``, s"""
WINDOW = 256
"""source messages of one session on their way to its worker at once (more: the source waits)"""
RESEND_MAX = 4 * WINDOW
"""source messages kept for a new owner while a session has none (more are lost and counted)"""
UNCONFIRMED = {"errors": [], "unconfirmed": True}
ASSIGN_BACKOFF_MAX_S = 0.3
"""a session whose ``ft.assign`` answer came from another worker than the owner it names (that worker
checked the owner and found it there, or could not tell: its lease decides), an owner this gateway has
not found gone, asks again after ``PROBE_EVERY_S``, doubled after each such answer up to this, s (each
such check holds back the answering worker's own sessions). Not while the owner named is one this
gateway found gone: a takeover is due then, and waiting longer between the requests made it later
(10 hands, a worker killed: the slowest moved session 0.56-0.88 s after the kill with the backoff
there too, 0.28-0.60 s without, in three interleaved pairs at load 4.7-9)"""
OWNER_FORGOTTEN_S = 30.0
"""a worker this gateway has not probed for this long is forgotten (``GatewayBus.owner_gone``), s"""


@dataclass
class ProbedOwner:
    """What a gateway's probes found of one session owner (``GatewayBus.owner_gone``)."""
    gone: asyncio.Event = field(default_factory=asyncio.Event)
    """set once a probe found the worker gone"""
    probed_at: float = float("-inf")
    """when the last probe started, monotonic s"""
    gone_at: float = float("inf")
    """when a probe last found it gone, monotonic s"""


class GatewayBus:
    """One NATS connection of a gateway process."""

    def __init__(self, nc, loop: asyncio.AbstractEventLoop):
        self.nc = nc
        self.loop = loop
        self._watching: set[str] = set()
        self._owners: dict[str, ProbedOwner] = {}   # by worker id, those probed within OWNER_FORGOTTEN_S
        self._probes: set[asyncio.Task] = set()

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

    def owner_gone(self, owner: str) -> asyncio.Event:
        """An event set once the worker ``owner`` is found gone (nobody answers its liveness subject);
        asks the server, at most every ``PROBE_EVERY_S`` for all of this gateway's sessions of that owner.
        A probe does not wait for the one before: a live owner behind with its sessions may take the
        whole ``PROBE_TIMEOUT_S`` to answer, and if it dies meanwhile that probe gets no answer at all
        (a 10-hand run found the dead owner 0.22-0.26 s after the kill so)."""
        now = time.monotonic()
        entry = self._owners.get(owner)
        if entry is None:                           # a new one: the workers not probed for long are forgotten
            for worker in [w for w, known in self._owners.items() if now - known.probed_at > OWNER_FORGOTTEN_S]:
                del self._owners[worker]
            entry = self._owners[owner] = ProbedOwner()
        if now - entry.probed_at >= PROBE_EVERY_S:
            entry.probed_at = now
            probe = self.loop.create_task(self._probe(owner, entry))
            self._probes.add(probe)
            probe.add_done_callback(self._probes.discard)
        return entry.gone

    def found_gone(self, owner: str) -> bool:
        """Whether a probe of this gateway found ``owner`` gone (and no later one found it there again)."""
        entry = self._owners.get(owner)
        return entry is not None and entry.gone.is_set()

    async def until_gone(self, owner: str) -> None:
        """Probe ``owner`` (``owner_gone``) until it is found gone."""
        while not (gone := self.owner_gone(owner)).is_set():
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(gone.wait(), PROBE_EVERY_S)

    async def _probe(self, owner: str, entry: ProbedOwner) -> None:
        started = time.monotonic()
        try:
            found = await probe_worker(self.nc, owner)
        except (NatsError, OSError):                # reconnecting: the reply wait decides
            return
        except Exception:                           # a defect: logged, and the reply wait decides
            log.exception("gateway: the liveness probe of worker %s failed", owner)
            return
        if found is Liveness.GONE:
            entry.gone.set()
            entry.gone_at = time.monotonic()
        elif found is Liveness.ANSWERED and entry.gone.is_set() and started > entry.gone_at:
            entry.gone = asyncio.Event()            # there again (a worker restarted under its name)
        # Liveness.NO_ANSWER says nothing: what an earlier probe found stands

    async def request(self, subject: str, payload: dict, name: str, timeout_s: float = REPLY_WAIT_S) -> dict | None:
        """A request to the session's owner; ``None``: no worker owns the session now (the message is
        lost), ``UNCONFIRMED``: the owner is there but did not answer within ``timeout_s``."""
        data = pack(payload)
        for _ in range(2):
            try:
                return unpack((await self.nc.request(subject, data, timeout=timeout_s)).data)
            except NoRespondersError:               # nobody listens: the owner is gone, or there is none yet
                answer = await self.assign(name)
                if not answer or answer.get("owner") != answer.get("by"):
                    return None                     # its lease has not lapsed yet: lost
            except NatsTimeout:                     # the owner may have died holding it
                if not (await self.assign(name)).get("claimed"):
                    return UNCONFIRMED
        return None

    def watch(self, sessions, name: str) -> None:
        """Viewers wait here for a session no source of this gateway has created: its source may stream
        into another gateway. Its first output on ``ft.out.<s>`` creates the session here (the waiting
        viewers join it, ``Sessions.get``); outputs are passed on until the session's own subscription
        is in place (a frame seen twice is dropped by its ``seq``). The watch ends with it, or when
        nobody waits any more."""
        if name in self._watching:
            return
        self._watching.add(name)

        async def on_output(msg) -> None:
            live = sessions.by_name.get(name)
            if live is None:
                if not sessions.waiting.get(name):
                    await end()                     # every waiting viewer left
                    return
                try:
                    live = sessions.get(name, create=True)
                except (SessionFull, ValueError):   # a full table: the viewers go on waiting
                    return
            if not isinstance(live, BusSession) or live._subscribed.is_set():
                await end()                         # its own subscription has this message and the next
                return
            await live._on_output(msg)

        async def end() -> None:
            sub = subscription.pop(0) if subscription else None
            self._watching.discard(name)
            if sub is not None:
                await sub.unsubscribe()

        subscription: list = []

        async def start() -> None:
            subscription.append(await self.nc.subscribe(output_subject(name), cb=on_output))
        self.loop.create_task(start())

    def session(self, name: str, settings: ServiceSettings, metrics: Metrics) -> "BusSession":
        return BusSession(name, settings, metrics, self)


class BusSession(LiveSession):
    """A session whose hand runs in a worker (module docstring). Source messages are pipelined: up to
    ``WINDOW`` wait for their reply at once, each with its own reply subject, so a reply (or the
    server's "no responders" status) belongs to exactly one message."""

    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics, bus: GatewayBus):
        super().__init__(name, settings, metrics)
        self.bus = bus
        self.lost_to_failover = 0                   # could not be kept for the next owner (RESEND_MAX)
        self.resent = 0                             # sent again to a new owner (the old one died holding them)
        self.stale_frames = 0                       # frames of a former owner, dropped
        self._last_seq = 0
        self.hand_side: str | None = None
        self._inbox = f"{bus.nc.new_inbox()}.ft"
        self._n = 0
        self._pending: dict[int, tuple[str, float | None, bytes]] = {}
        self._resend: dict[int, tuple[str, float | None, bytes]] = {}
        self._replied = asyncio.Event()
        self._owner_ok = False
        self._owner: str | None = None              # the worker that owned the session when it was last asked
        self._assign_gap = PROBE_EVERY_S            # ft.assign asked again after this at the soonest (ASSIGN_BACKOFF_MAX_S)
        self._assign_after = float("-inf")          # ... from then on (monotonic s)
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
                await self._answer(msg, n, entry)
        finally:                                    # answered (its error sent) before a sync can see it gone
            self._pending.pop(n, None)
            self._replied.set()

    def _keep_for_next_owner(self, n: int, entry) -> None:
        if len(self._resend) < RESEND_MAX:
            self._resend[n] = entry
        else:
            self.lost_to_failover += 1

    async def _answer(self, msg, n: int, entry) -> None:
        if msg.headers and msg.headers.get("Status") == "503":     # nobody listens: the owner is gone
            self._keep_for_next_owner(n, entry)
            self._owner_ok = False
            if self._owner is not None:
                self.bus.owner_gone(self._owner)    # probed: a found-gone owner's takeover is asked for without a pause
            return
        if self._source_error is None:
            return
        for code, detail in unpack(msg.data)["errors"]:     # as the embedded service answers (api.replies)
            await self._source_error(code, detail)

    async def _recover(self) -> None:
        """Until a live worker owns the session (a takeover needs the old owner gone or its lease
        lapsed), the source waits; then what the old owner never answered goes to the new one, in order."""
        self._write_off()
        while not self._owner_ok:
            answer = await self._assign()
            if answer and answer.get("owner") == answer.get("by"):
                self._owner_ok, self._owner = True, answer["owner"]
            else:
                await asyncio.sleep(max(0.05, self._assign_after - time.monotonic()))
        kept, self._resend = self._resend, {}
        for n in sorted(kept):
            self.resent += 1
            await self._publish(kept[n])

    async def _assign(self) -> dict:
        """``ft.assign`` for this session (``GatewayBus.assign``). An answer from another worker than the
        owner it names, an owner not found gone, means that worker checked the owner for nothing: the next
        request waits (``ASSIGN_BACKOFF_MAX_S``)."""
        answer = await self.bus.assign(self.name)
        named = answer.get("owner") if answer else None
        if named is not None and named != answer.get("by") and not self.bus.found_gone(named):
            self._assign_after = time.monotonic() + self._assign_gap
            self._assign_gap = min(2 * self._assign_gap, ASSIGN_BACKOFF_MAX_S)
        else:
            self._assign_gap, self._assign_after = PROBE_EVERY_S, float("-inf")
        return answer

    async def _publish(self, entry) -> None:
        self._n += 1
        self._pending[self._n] = entry
        await self.bus.nc.publish(source_subject(self.name), entry[2], reply=f"{self._inbox}.{self._n}")

    async def ingest(self, raw: dict, parsed) -> None:
        await self._subscribed.wait()
        if not self._owner_ok:
            await self._recover()
        while len(self._pending) >= WINDOW:         # backpressure: the source waits for the worker
            if not await self._wait_replies():
                await self._recover()
        self.metrics.messages_in.labels(self.name).inc()
        await self._publish((parsed.type, getattr(parsed, "t", None), pack({"raw": raw})))

    async def _wait_replies(self) -> bool:
        """Wait for a reply. None for ``REPLY_WAIT_S``, or the owner found gone meanwhile
        (``GatewayBus.until_gone``): the workers check the owner; False when it was
        gone and the session has a new owner now (the pending messages will never be answered). The new
        owner is known by its name, not only by the answer that claimed it: that answer may have been
        lost (a worker taking several sessions over answers late), and every later answer says "not
        claimed just now"; the session's source then waited for ever on a full window."""
        self._replied.clear()
        replied = asyncio.ensure_future(self._replied.wait())
        deadline = time.monotonic() + REPLY_WAIT_S
        gone = None
        try:
            await asyncio.wait({replied}, timeout=min(PROBE_EVERY_S, REPLY_WAIT_S))
            if not replied.done() and self._owner is not None:
                # a reply is late: is the owner still there? A session whose window is full publishes
                # nothing, so only a probe finds a dead owner before the wait runs out (a gateway noticed
                # one 0.77 s after a kill at 10 hands). Not while replies come in time: a backlog waits
                # here at every reply, and a probe task each time would be work for nothing
                gone = asyncio.ensure_future(self.bus.until_gone(self._owner))
                await asyncio.wait({replied, gone}, timeout=max(0.0, deadline - time.monotonic()),
                                   return_when=asyncio.FIRST_COMPLETED)
            if (not replied.done() and (gone is None or not gone.done())
                    and (left := self._assign_after - time.monotonic()) > 0):
                await asyncio.wait({replied}, timeout=left)     # not ft.assign again yet (``_assign``)
        finally:
            for wait in (replied, gone):
                if wait is not None and not wait.done():
                    wait.cancel()
        if self._replied.is_set():
            return True
        # a dead owner's sessions ask at most once per PROBE_EVERY_S each (a live one's less often, ``_assign``):
        # an answer lost (a busy new owner answering after ASSIGN_TIMEOUT_S) is asked again then, and
        # without any worker nothing spins
        answer = await self._assign()
        if answer.get("claimed") or (answer.get("owner") is not None and self._owner is not None
                                     and answer["owner"] != self._owner):
            # moved: the caller's ``_recover`` sends the new owner what the old one never answered, and
            # need not ask ``ft.assign`` once more when this answer already names a live owner (that
            # second round trip to a busy new owner took 0.3-0.4 s of a 2 s takeover)
            self._owner_ok = answer.get("owner") == answer.get("by")
            self._owner = answer["owner"] if self._owner_ok else self._owner
            return False
        return True

    def _write_off(self) -> None:
        """Messages sent to an owner that is gone will not be answered: kept for the next owner."""
        for n, entry in self._pending.items():
            self._keep_for_next_owner(n, entry)
        self._pending.clear()

    async def settled(self) -> None:
        """Every message sent so far was answered: what ``sync`` waits for."""
        while self._pending or self._resend or not self._owner_ok:
            if not self._owner_ok or self._resend:
                await self._recover()
            elif not await self._wait_replies():
                await self._recover()

    def enrol(self, segments: list) -> dict:
        """Enrolment needs the recent frames, which the worker holds: refused with a reason."""
        raise ValueError("enrolment: this session's hand runs on a bus worker, which holds its recent frames; "
                         "enrolment is available for sessions served in process")

    def update_config(self, change: dict) -> dict:
        """Validated and kept here (a bad change changes nothing; the gateway's hand runs nothing, so it
        loads no estimator), then applied by the owner, which keeps it in the session's state so it
        survives a change of owner. Called from a worker thread of the API."""
        spec, params, gestures, record = self.checked_config(change)
        self.config = SessionConfig(estimator=spec.name, estimator_params=params, gestures=gestures, record=record)
        self._apply_recording()
        config = self.config.model_dump()
        future = asyncio.run_coroutine_threadsafe(
            self.bus.request(config_subject(self.name), {"change": change}, self.name, CONFIG_WAIT_S), self.bus.loop)
        reply = future.result(timeout=2 * (CONFIG_WAIT_S + ASSIGN_TIMEOUT_S) + 1.0)
        if reply is None or reply.get("unconfirmed"):
            raise ValueError("no hand worker answered; the change is kept here and was not applied")
        if "error" in reply:
            raise ValueError(reply["error"])
        return config

    def summary(self) -> dict:
        out = super().summary()
        out["hand"] = self.hand_side or out["hand"]
        out["lost_to_failover"] = self.lost_to_failover
        out["resent_after_failover"] = self.resent
        out["stale_frames"] = self.stale_frames
        return out

    def close(self) -> None:
        super().close()
        for sub in self._subscriptions:
            self.bus.loop.call_soon_threadsafe(lambda sub=sub: self.bus.loop.create_task(sub.unsubscribe()))
