"""A hand worker: owns sessions through a lease in NATS JetStream key-value and runs their pipelines.

It keeps two connections to the NATS server: one for its sessions' traffic (source messages in, frames
out) and one for ownership (``ft.assign``, the liveness probe, the lease bucket). A worker that takes a
dead worker's sessions over is usually behind with its own sessions: the bytes of their source messages
wait in its data connection's socket, read one chunk per turn of its loop, and any answer on that
connection waits behind them. Measured at 10 hands on a machine at load average 9, every round trip of
a takeover (the ``ft.assign`` request, the lease read, the probe, the lease write) took 0.13-0.4 s on
the one connection, and the five moved sessions' first frames reached their subscribers 1.9-2.3 s after
the kill; the ownership connection carries only those few messages. Such a worker's loop is still
busy: each of those round trips waited for a turn of every session (0.1-0.4 s at that load). So while a
worker checks or takes the ownership of a session it does not own, its sessions' source messages wait
(``HOLD_MAX_S`` at most; a check is a few round trips on an idle loop), and a session it took over
handles its backlog without yielding until its first frame.

Each owned session is an ordinary ``LiveSession`` (the embedded service's code) whose only
"subscriber" publishes to ``ft.out.<s>``. Every ``RENEW_S`` the worker rewrites each session's lease
with its compact state (``subjects.py``). When a worker takes a session over from one that stopped
renewing, it rebuilds the session from that state: the source's ``hello`` and last ``calibration``,
the session configuration, and the last published joint angles, applied as a ``reference_pose`` at the
first sample it handles (so the filters restart from the last estimate, known to
``reference_pose_std_rad``). What does not survive: the filters' covariances and learned sensor
offsets, the optical track, the gesture recogniser's state, and whatever the source sent between the
last renewal and the takeover (those messages are lost and the frames' ``seq`` jumps over them).
"""
from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
import uuid

from nats.errors import Error as NatsError
from nats.js.api import KeyValueConfig, StorageType
from nats.js.errors import KeyNotFoundError, KeyWrongLastSequenceError

from ..api.config import ServiceSettings, redacted_url
from ..api.metrics import Metrics
from ..api.hands.owner import OutputSink, first_time as _first_time
from ..api.replies import drop_replies, failure_reply
from ..api.sessions import LiveSession
from ..estimators.warm import is_warm, warm_off_loop
from ..pipeline.gc_policy import serving_gc
from ..protocol import PROTOCOL_VERSION, ProtocolError, parse_message

from .subjects import (ASSIGN, BUCKET, LEASE_S, RENEW_S, WORKERS_QUEUE, close, config_subject, connect, output_subject,
                       Liveness, pack, probe_worker, session_token, source_subject, unpack, worker_subject)

log = logging.getLogger("fingertrack.bus")
HOLD_MAX_S = 0.5
"""longest a worker's source messages wait while it checks or takes sessions' ownership (a takeover
that must first load an estimator's kernels takes longer: its sessions go on after this), s"""
STATE_MAX_AGE_S = 3600.0
"""a session nobody has renewed for this long leaves the key-value bucket, s"""


class OwnedSession:
    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics, revision: int):
        self.name = name
        self.live = LiveSession(name, settings, metrics)
        self.sink = OutputSink(settings.output_rate_hz)
        self.live.subscribers.add(self.sink)
        self.revision = revision
        self.hello: dict | None = None
        self.calibration: dict | None = None
        self.resume_angles: dict | None = None      # applied at the first timed message after a takeover
        self.restoring: dict | None = None          # a taken-over session's previous state until it is rebuilt
        self.restore_errors: list[list[str]] = []   # what a rebuild could not restore: sent with the next reply
        self.ready = asyncio.Event()                # rebuilt (at once for a new session): its messages may go in
        self.subscriptions: list = []
        self.lock = asyncio.Lock()
        self.renew_lock = asyncio.Lock()
        self.renewed_at = time.monotonic()

    def state(self, worker: str | None) -> bytes:
        if self.restoring is not None:              # taken over, not rebuilt yet: the previous state, ours now
            return pack({**self.restoring, "worker": worker})
        seq = self.sink.last_seq
        t = self.sink.last_t
        if self.sink.resume_after is not None:       # taken over, no frame yet: keep the previous state
            seq, t = self.sink.resume_after
        return pack({"session": self.name, "worker": worker, "seq": seq, "t": t,
                     "angles": self.sink.last_angles or self.resume_angles, "hello": self.hello,
                     "calibration": self.calibration, "config": self.live.config.model_dump()})


class Worker:
    def __init__(self, url: str, settings: ServiceSettings, worker_id: str | None = None):
        self.url = url
        self.settings = settings
        self.id = worker_id or f"worker-{uuid.uuid4().hex[:8]}"
        self.metrics = Metrics()
        self.owned: dict[str, OwnedSession] = {}
        self.seen: dict[str, tuple[int, float]] = {}   # key -> (revision, when first seen): lapsed leases
        self.nc = None
        """the sessions' traffic: ``ft.src``/``ft.cfg`` in, ``ft.out`` out"""
        self.ctl = None
        """ownership: ``ft.assign``, ``ft.worker.<id>`` and the lease bucket (module docstring)"""
        self.kv = None
        self._tasks: list[asyncio.Task] = []
        self._assigning: dict[str, list] = {}     # session -> [lock, requests using it]: its answers one at a time
        self._answers: set[asyncio.Task] = set()    # ft.assign answers and rebuilds under way
        self._checking = 0                          # ownership checks under way: source messages wait meanwhile
        self._traffic = asyncio.Event()
        self._traffic.set()
        self._held_until = 0.0                      # ... until then at most (monotonic s)
        self._rebuilds: list[OwnedSession] = []     # sessions taken over, claimed, waiting to be rebuilt, in order
        self._rebuild_due = asyncio.Event()

    async def start(self) -> None:
        """Load (or, with a cold cache, compile in a separate process) the hand pipeline's and the
        default estimator's kernels, then connect and take sessions."""
        await warm_off_loop(self.settings.estimator)
        self.nc = await connect(self.url, self.id)
        self.ctl = await connect(self.url, f"{self.id}-ownership")
        js = self.ctl.jetstream()
        self.kv = await js.create_key_value(KeyValueConfig(bucket=BUCKET, history=1, ttl=STATE_MAX_AGE_S,
                                                           storage=StorageType.MEMORY))
        await self.ctl.subscribe(ASSIGN, queue=WORKERS_QUEUE, cb=self._on_assign)
        await self.ctl.subscribe(worker_subject(self.id), cb=self._on_probe)
        await self.ctl.flush()
        self._tasks += [asyncio.create_task(self._renew_forever()), asyncio.create_task(self._rebuild_forever())]

    async def stop(self, release: bool = True) -> None:
        """Stop; with ``release`` the sessions' leases say 'no owner' so another worker takes them at once."""
        background = [*self._tasks, *self._answers]    # renewals, rebuilds, ft.assign answers under way
        for task in background:
            task.cancel()
        await asyncio.gather(*background, return_exceptions=True)
        for owned in list(self.owned.values()):
            for sub in owned.subscriptions:
                await sub.unsubscribe()
            if release:
                try:
                    await self.kv.update(session_token(owned.name), owned.state(None), last=owned.revision)
                except KeyWrongLastSequenceError:
                    pass
            owned.live.close()
        self.owned.clear()
        for nc in (self.ctl, self.nc):
            if nc is not None:
                await close(nc)

    # -- ownership -------------------------------------------------------------------------------
    async def _on_probe(self, msg) -> None:
        if self.nc.is_connected:                    # cut off from its sessions' traffic: not answering lets the lease decide
            await msg.respond(b"")

    async def _on_assign(self, msg) -> None:
        """Each request answered in a task of its own: a worker taking over a dead worker's sessions claims
        them at once (one after the other, each waiting for its bus round trips behind the sessions it
        serves, took 0.3-0.6 s per session at 10 hands); requests for one session wait for each other."""
        task = asyncio.create_task(self._answer_assign(msg))
        self._answers.add(task)
        task.add_done_callback(self._answers.discard)

    async def _answer_assign(self, msg) -> None:
        name = unpack(msg.data)["session"]
        entry = self._assigning.setdefault(name, [asyncio.Lock(), 0])
        entry[1] += 1
        try:
            async with entry[0]:
                claimed_before = name in self.owned
                if claimed_before:
                    owner = self.id
                else:
                    with self._traffic_held():
                        owner = await self.ensure_owner(name)
            await msg.respond(pack({"owner": owner, "by": self.id, "claimed": owner == self.id and not claimed_before}))
        except (NatsError, OSError) as err:         # reconnecting: unanswered, the gateway asks again
            log.warning("worker %s: the ownership of session %r not checked: %s: %s", self.id, name,
                        type(err).__name__, err)
        finally:
            entry[1] -= 1
            if entry[1] == 0:
                del self._assigning[name]           # nobody else waits for it

    @contextlib.contextmanager
    def _traffic_held(self):
        """The sessions' source messages wait while the block runs (module docstring)."""
        self._checking += 1
        if self._checking == 1:
            self._held_until = time.monotonic() + HOLD_MAX_S
            self._traffic.clear()
        try:
            yield
        finally:
            self._checking -= 1
            if not self._checking:
                self._traffic.set()

    async def _after_checks(self) -> None:
        """Wait while ownership checks are under way (``_traffic_held``: ``HOLD_MAX_S`` at most)."""
        if not self._traffic.is_set() and (left := self._held_until - time.monotonic()) > 0:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._traffic.wait(), left)

    async def ensure_owner(self, name: str) -> str | None:
        """The session's owner after claiming it if it has none, its owner is gone, or its owner's
        lease lapsed."""
        if name in self.owned:
            return self.id
        key = session_token(name)
        try:
            entry = await self.kv.get(key)
            state = unpack(entry.value) if entry.value else None
        except KeyNotFoundError:
            entry, state = None, None
        if entry is None or state is None:
            return self.id if await self._claim(name, None, None) else await self._owner_of(key)
        if state.get("worker") in (None, self.id):  # released by a worker that stopped, or ours before a restart
            return self.id if await self._claim(name, entry.revision, state) else await self._owner_of(key)
        if state["worker"] != self.id and await probe_worker(self.ctl, state["worker"]) is Liveness.GONE:
            return self.id if await self._claim(name, entry.revision, state) else await self._owner_of(key)
        now = time.monotonic()
        seen = self.seen.get(key)
        if seen is None or seen[0] != entry.revision:
            self.seen[key] = (entry.revision, now)
            return state["worker"]
        if now - seen[1] < LEASE_S:
            return state["worker"]
        # the owner has not renewed for longer than the lease: take the session over
        return self.id if await self._claim(name, entry.revision, state) else await self._owner_of(key)

    async def _owner_of(self, key: str) -> str | None:
        try:
            entry = await self.kv.get(key)
            return unpack(entry.value).get("worker") if entry.value else None
        except KeyNotFoundError:
            return None

    async def _claim(self, name: str, revision: int | None, previous: dict | None) -> bool:
        """Compare-and-set the lease, once subscribed to the session's subjects. The subscriptions go on
        the data connection and the lease on the other, without waiting for the server to confirm the
        former (a round trip behind the data connection's backlog, 0.1 s in the measurement above): a
        source message that still found nobody listening gets "no responders" at its gateway, which asks
        ``ft.assign`` again, hears this worker named, and sends the message again.

        A session taken over is claimed with its previous state as it was and rebuilt afterwards
        (``_rebuild_forever``): its source messages wait for that, and the claim, so the ``ft.assign``
        answer, does not. Rebuilding a hand (its calibration) takes 10 ms of CPU on an idle core and
        0.06-0.15 s on a busy worker at load 10; rebuilt inside their claims, a takeover of five sessions
        wrote its first lease only after every rebuild (0.78 s after the kill)."""
        owned = OwnedSession(name, self.settings, self.metrics, revision=0)
        owned.restoring = previous
        owned.subscriptions = [
            await self.nc.subscribe(source_subject(name), cb=functools.partial(self._on_source, owned)),
            await self.nc.subscribe(config_subject(name), cb=functools.partial(self._on_config, owned)),
        ]
        try:
            if revision is None:
                owned.revision = await self.kv.create(session_token(name), owned.state(self.id))
            else:
                owned.revision = await self.kv.update(session_token(name), owned.state(self.id), last=revision)
        except KeyWrongLastSequenceError:           # another worker was quicker
            for sub in owned.subscriptions:
                await sub.unsubscribe()
            owned.live.close()
            return False
        self.owned[name] = owned
        if previous is None:
            owned.ready.set()
        else:
            self._rebuilds.append(owned)
            self._rebuild_due.set()
            log.info("worker %s took session %r over from %s (its last state: frame %s)", self.id, name,
                     previous.get("worker") or "a stopped worker", previous.get("seq"))
        return True

    async def _rebuild_forever(self) -> None:
        """Rebuild the sessions taken over, one after the other in the order they were claimed, each on
        the loop and each going on at once: its waiting source messages run (without yielding, until its
        first frame) before the next session is rebuilt. A rebuild waits while ownership checks are under
        way (``HOLD_MAX_S`` at most), so that every session of a dead worker is claimed, and its gateways
        answered, first. A session on an estimator whose kernels this worker has not loaded is rebuilt
        beside the others (loading them takes seconds, in a thread or a separate process)."""
        while True:
            await self._rebuild_due.wait()
            self._rebuild_due.clear()
            while self._rebuilds:
                await self._after_checks()
                owned = self._rebuilds.pop(0)
                try:
                    loaded = is_warm((owned.restoring.get("config") or {}).get("estimator") or self.settings.estimator)
                except Exception:                   # a defect: rebuilt here, never left waiting for ever
                    log.exception("worker %s: session %r: its estimator's kernels not looked up", self.id, owned.name)
                    loaded = True
                if loaded:
                    await self._rebuild(owned)
                    await asyncio.sleep(0)          # its waiting messages first (their callbacks are due now)
                else:
                    task = asyncio.create_task(self._rebuild(owned))
                    self._answers.add(task)
                    task.add_done_callback(self._answers.discard)

    async def _rebuild(self, owned: OwnedSession) -> None:
        try:
            if self.owned.get(owned.name) is owned:     # else given up meanwhile
                await self._restore(owned, owned.restoring)
        except asyncio.CancelledError:              # stopped: its lease is released with the previous state as it
            owned.ready.set()                       # was (``restoring`` kept), its waiting messages find it gone
            raise
        except Exception:                           # a defect: the session goes on with what was restored
            log.exception("worker %s: session %r not rebuilt from its state", self.id, owned.name)
        owned.restoring = None
        owned.ready.set()

    async def _restore(self, owned: OwnedSession, state: dict) -> None:
        """Rebuild a session from the previous owner's last state (module docstring: what survives). The
        frame counter and the last angles first: whatever part of the state this worker cannot rebuild
        (a stored message or configuration it refuses, e.g. of another version), the session's ``seq``
        goes on from the previous owner's. What it could not rebuild is said in one log line, and a stored
        message also in an error reply to the next source message (``OwnedSession.restore_errors``)."""
        if state.get("seq"):
            owned.sink.resume_after = (int(state["seq"]), float(state["t"]))
        owned.resume_angles = state.get("angles") or None
        for kind in ("hello", "calibration"):
            if (raw := state.get(kind)) is None:
                continue
            errors = (await self._handle(owned, raw))["errors"]
            if errors and kind == "hello" and raw.get("hand") in ("left", "right"):
                # the hand at least: its calibration and angles are of that hand, and so must its frames be
                await self._handle(owned, {"type": "hello", "protocol": PROTOCOL_VERSION, "hand": raw["hand"]})
            for code, detail, *_ in errors:
                self._not_restored(owned, code, f"its {kind}: {detail}; send the {kind} again")
            setattr(owned, kind, raw)               # kept as stored, for a worker that can rebuild it
        config = dict(state.get("config") or {})
        if config:
            if self.settings.record_dir is None:
                config.pop("record", None)
            try:
                await self._switch(owned, config)
            except ValueError as err:               # e.g. an estimator this worker does not know: defaults
                log.warning("session %r moved to worker %s, which could not restore its configuration %s: %s; "
                            "the defaults apply", owned.name, self.id, config, err)

    def _not_restored(self, owned: OwnedSession, code: str, what: str) -> None:
        detail = f"the session moved to worker {self.id}, which could not restore {what}"
        log.warning("%s (session %r)", detail, owned.name)
        owned.restore_errors.append([code, detail])

    async def _renew(self, owned: OwnedSession) -> bool:
        """Rewrite the lease with the current state; False (and the session given up) if another
        worker took it over meanwhile. One renewal of a session at a time (the periodic one and the
        fence before publishing would otherwise race each other's compare-and-set)."""
        async with owned.renew_lock:
            return await self._renew_now(owned)

    async def _renew_now(self, owned: OwnedSession) -> bool:
        if not self.nc.is_connected:                # cut off from the session's traffic: let the lease lapse
            return True
        try:
            owned.revision = await self.kv.update(session_token(owned.name), owned.state(self.id), last=owned.revision)
            owned.renewed_at = time.monotonic()
            return True
        except KeyWrongLastSequenceError:           # taken over while we were away: give it up
            if await self._owner_of(session_token(owned.name)) == self.id:    # still ours: a stale revision
                owned.revision = (await self.kv.get(session_token(owned.name))).revision
                return True
            if self.owned.get(owned.name) is owned:
                del self.owned[owned.name]
                for sub in owned.subscriptions:
                    await sub.unsubscribe()
                owned.live.close()
                log.warning("worker %s gave session %r up: another worker took it over", self.id, owned.name)
            return False
        except Exception:                           # NATS reconnecting: the next round tries again
            return True

    async def _renew_forever(self) -> None:
        while True:
            await asyncio.sleep(RENEW_S)
            for owned in list(self.owned.values()):
                await self._renew(owned)

    # -- session traffic -------------------------------------------------------------------------
    async def _handle(self, owned: OwnedSession, raw: dict) -> dict:
        """Process one source message; the reply lists its error replies, ``(code, detail)`` as the
        embedded service gives them (``api.replies``), which the gateway passes on to the source."""
        try:
            parsed = parse_message(raw)
        except ProtocolError as err:                # the gateway validated it: only a version skew gets here
            return {"errors": [[err.code, err.detail]]}
        try:
            errors = [list(reply) for reply in drop_replies(parsed, await owned.live.ingest(raw, parsed))]
        except Exception as err:                    # bad input, or a defect (logged in one line)
            errors = [list(failure_reply(owned.name, parsed, err))]
        if parsed.type == "hello":
            owned.hello = raw
        elif parsed.type == "calibration" and not errors:
            owned.calibration = raw
        return {"errors": errors}

    async def _on_source(self, owned: OwnedSession, msg) -> None:
        if not owned.ready.is_set():                # taken over, being rebuilt (``_claim``)
            await owned.ready.wait()
            if self.owned.get(owned.name) is not owned:
                return                              # given up meanwhile: unanswered, its gateway asks again
        elif owned.sink.resume_after is None and not self._traffic.is_set():
            await self._after_checks()              # an ownership check first (module docstring)
        raw = unpack(msg.data)["raw"]
        async with owned.lock:
            if owned.resume_angles is not None and (t := _first_time(raw)) is not None:
                ref = {"type": "reference_pose", "t0": t, "t1": t, "pose": owned.resume_angles}
                owned.resume_angles = None
                await self._handle(owned, ref)      # angles the protocol refuses: it starts as a new session
            reply = await self._handle(owned, raw)
            if owned.restore_errors:                # first what its rebuild after a move could not restore
                reply["errors"] = owned.restore_errors + reply["errors"]
                owned.restore_errors = []
            # fence: after a long stall, make sure the session is still ours before publishing
            if time.monotonic() - owned.renewed_at > LEASE_S / 2 and not await self._renew(owned):
                owned.sink.pending.clear()
                return
            for data in owned.sink.pending:
                await self.nc.publish(output_subject(owned.name), data)
            owned.sink.pending.clear()
        if msg.reply:
            await msg.respond(pack(reply))
        # one message per turn of the loop: a session with a backlog would otherwise handle message after
        # message (its subscription's next one is taken without a wait) until one yields a frame, and every
        # round trip of an ownership check waits for such a turn of every session (module docstring); a
        # session taken over goes on without a turn until its first frame
        if owned.sink.resume_after is None:
            await asyncio.sleep(0)

    @staticmethod
    async def _switch(owned: OwnedSession, change: dict) -> dict:
        """Apply a configuration change; an estimator whose kernels this process has not loaded is
        compiled (in a separate process) and loaded (in a thread) first, while every session, this one
        on its old estimator, goes on. ``ValueError`` for a bad change, which changes nothing."""
        spec, params, _, _ = owned.live.checked_config(change)
        await warm_off_loop(spec.name, params)
        return owned.live.update_config(change)

    async def _on_config(self, owned: OwnedSession, msg) -> None:
        await owned.ready.wait()                    # a rebuild applies the previous configuration first
        change = unpack(msg.data)["change"]
        try:
            reply = {"config": await self._switch(owned, change)}
        except ValueError as err:
            reply = {"error": str(err)}
        await msg.respond(pack(reply))


async def run_worker(url: str, settings: ServiceSettings, worker_id: str | None = None,
                     started: asyncio.Event | None = None) -> None:
    """Run one worker until cancelled (SIGINT/SIGTERM): its sessions' leases are released on the way out.
    The process's SIGINT and SIGTERM handlers are given back as found (asyncio's removal of a loop's
    handler sets SIGINT to Python's default, whatever it was before)."""
    import signal

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    worker = Worker(url, settings, worker_id)
    await worker.start()
    log.info("fingertrack worker %s on %s", worker.id, redacted_url(url))
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in before:
        loop.add_signal_handler(sig, stop.set)
    try:
        if started is not None:
            started.set()
        with serving_gc():                          # as the embedded service's processes: kernels loaded, heap frozen
            await stop.wait()
        await worker.stop(release=True)
    finally:
        for sig, handler in before.items():
            loop.remove_signal_handler(sig)
            if handler is not None:                 # None: installed from C, cannot be put back
                signal.signal(sig, handler)
