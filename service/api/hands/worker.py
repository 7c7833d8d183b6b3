"""A hand worker process of the embedded service (``python -m service.api.hands.worker FD SETTINGS [PARENT]``).

It owns the sessions the web process opens on it and runs their hands (``TrackedHand``, through the
same ``LiveSession`` the in-process service uses). It talks to the web process over one stream socket
(file descriptor ``FD``): frames of 4-byte big-endian length + MessagePack, each frame a list of
messages (a batch: everything that came in at once is handled before the outputs go back in one write,
at the latest every ``FLUSH_S`` of processing; the frames of a small batch's messages, and of any
batch's last message, go back as soon as each is made, before the later ticks, unless the worker has
``GROUP_SESSIONS`` sessions or more). ``SETTINGS`` is a JSON object of the few service
settings a hand needs (no secrets).

Web process -> worker (the bus's message shapes, ``bus/subjects.py``, with a session number ``sid``):

* ``["open", sid, name, state]``: own the session; ``state`` is the compact session state of
  ``hands.owner`` (``None`` for a new session; after a restart of a worker, or when the session moves
  between workers, its last state, so the hand continues from its last estimate). Its hand is built by
  a thread while the worker goes on serving its other sessions (building a hand takes 10-20 ms of the
  interpreter; ``warm.sharing_the_interpreter``); the session's messages that come meanwhile wait for it,
  in order;
* ``["src", sid, n, raw]``: a validated source message (packed once more, as MessagePack bytes, so
  that the web process packs it once and can send it again as it is), numbered ``n`` per session;
* ``["chk", sid, n, data, binary]``: a source data message (``imu``, ``imu_batch``, ``pose`` with only
  their fields) as it arrived, JSON text or MessagePack bytes (``binary``), validated here: its
  error replies, e.g. an ``imu_batch``'s refused samples, come back in its ``rep``;
* ``["cfg", sid, n, change]`` / ``["enrol", sid, n, segments]``: a configuration change / a gesture
  enrolment; an estimator whose kernels this process has not loaded is first compiled into the cache
  by a separate process at a lower priority (unless they are in it), then loaded here by a thread,
  while the worker goes on serving (the session keeps its old estimator until then), then applied;
* ``["fmt", sid, binary]``: whether a subscriber of the session reads MessagePack (``binary``), so
  that its outputs are encoded as that too;
* ``["drops", sid, subscriber_frames, overloaded]``: the session's counts for its frames'
  ``status.dropped`` (frames dropped for slow subscribers, source messages refused as overload), sent
  when they change;
* ``["close", sid]``.

Worker -> web process:

* ``["out", sid, n, head, text, packed]``: a ``frame`` or ``gesture`` message caused by source message
  ``n`` (``seq`` continued across a restart), always before the reply to ``n``, encoded here once for
  every subscriber: ``text`` its JSON text, ``packed`` its MessagePack bytes (``None`` unless asked
  with ``fmt``), ``head`` = ``[type, seq, t, hand]`` (``None`` but the type for a gesture event), what
  the web process needs without decoding it;
* ``["rep", sid, n, errors]``: source message ``n`` handled; ``errors`` lists the error replies the
  source gets, ``[code, detail]`` as the in-process service gives them (``api.replies``), or
  ``[code, detail, samples]`` for the samples of a ``chk``'s batch it refused; after a ``chk`` a
  fifth item says whether the message was accepted (not refused whole);
* ``["reps", sid, first, last]``: the ``rep`` of each of the session's ``chk`` messages ``first`` to
  ``last``, each accepted and without error replies (``[]``, ``True``), in one message: a run of them
  with no output, reply or other message of the session between them in this process's output (what the
  session's messages cause keeps its order: outputs before their reply, a reply with errors a ``rep`` of
  its own); the web process answers the run in one step (about 1 us per reply passed on one by one, 0.4 us
  in runs of four: runs are long when a worker reads many messages at once, e.g. once it is behind);
* ``["cfgrep", sid, n, result, error]``: the applied configuration (or the enrolment's result), or the
  reason it was refused;
* ``["lost", sid, errors]``: what a session's new owner could not rebuild of its state (a stored
  hello or calibration it refuses, e.g. of another version), as error replies ``[code, detail]`` for
  the source, before any reply to the session's messages (logged here too; the frames' ``seq`` goes
  on and a refused hello still sets the hand; a configuration it refuses is logged, its defaults apply);
* ``["ready", pid]`` once, when the default estimator is loaded and messages are read;
* ``["alive"]`` every ``ALIVE_S`` while it is in a long operation it knows of (loading an estimator's
  kernels), so that the web process does not take it for stuck.

The process ends when the web process closes its end of the socket (or dies). Given the web process's
pid (``PARENT``), on Linux it is also killed when the web process ends (``PR_SET_PDEATHSIG``): a worker
stuck in a loop, stopped, or busy loading kernels never reads the end of its input, and outlived a
killed web process before. It ignores SIGINT and
SIGTERM: a terminal's Ctrl-C and a service manager's SIGTERM reach the whole process group, and they are
for the web process, which then closes its workers in order; a worker ending first printed a
``KeyboardInterrupt`` traceback and was taken for a crashed one (its sessions moved for nothing).
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Iterator

import msgpack

from ...pipeline.gc_policy import serving_gc
from ...protocol import PROTOCOL_VERSION, ProtocolError, parse_input, parse_message
from ...protocol.fast import read as read_fast
from ...protocol.messages import SamplesRefused, dump_message
from ...pipeline.frame_text import FrameOutput
from ...pipeline.hand import NOTHING_DROPPED
from ...protocol.wire import encode
from ...estimators.warm import (Compile, cached_not_warm, is_warm, needs_compiling, sharing_the_interpreter, warm,
                                warm_ahead)
from ..config import ServiceSettings
from ..metrics import Metrics
from ..outgoing import Outgoing
from ..replies import drop_replies, failure_reply
from ..sessions import LiveSession
from ..stacks import stacks_on_signal
from .owner import OutputSink, resume_reference

log = logging.getLogger("fingertrack")
HEADER = struct.Struct(">I")
READ_SIZE = 1 << 20
"""the most one read of the web process's socket takes, bytes"""
FLUSH_S = 0.002
"""outputs go back at least this often while a batch is being handled, s"""
HOLD_S = FLUSH_S
"""the longest the replies of reads that made no other output wait for the next write (``Worker.holds``), s"""
AT_ONCE_BATCH = 4
"""in a batch of at most this many messages every frame goes back as soon as it is made (``handle_batch``):
one hand at 1 kHz sends a worker 1-3 at a time, a pose first in 2 of 3 of them when the machine is busy"""
GROUP_SESSIONS = 4
"""a worker with at least this many active sessions (``ActiveSessions``) sends its outputs once per batch (or
every ``FLUSH_S`` of a long one), none as soon as it is made (``handle_batch``); the web process writes to it at
most every ``GROUP_S`` then (``hands.pool``)"""
ACTIVE_S = 1.0
"""a session counts as active for ``GROUP_SESSIONS`` until this long after its last source message, s (at most
half as long again: ``ActiveSessions``)"""
WARM_POLL_S = 0.05
"""how often a worker compiling kernels in a separate process looks whether it has finished, s"""
ALIVE_S = 0.2
"""how often a worker in a long operation it knows of says it is alive, s"""
OPEN_POLL_S = 0.005
"""how often a worker whose thread builds a session's hand looks whether it has finished, s"""


hand_over = getattr(os, "sched_yield", lambda: None)
"""called after a frame is written while its message has ticks left (``Worker.emitter``): the web process,
woken by that write, is often put on this worker's core (the kernel takes a writer to a socket for one about
to sleep, which this worker is not: it goes on with the ticks) and waited there until the worker's time slice
ran out (0.5-0.6 ms at 1 kHz, in 700-800 of 900 frames); yielding lets it pass the frame on first. Where no
other process waits for this core it returns at once. Not when the next frame's tick is covered by a pose already
(``next_frame_covered``: at 1 kHz one frame in nine, made by the IMU message right after the pose): that frame
waits for this message's ticks, and a yield put the web process's and the subscriber's turns before them too
(0.2-0.8 ms)."""


YIELD_TICKS = 4
"""``hand_over`` only while at least this many ticks are ready behind the frame just written: their time is what the
web process would wait for on this core (at 1 kHz a pose releases about eleven, the first making the frame). With
fewer (at 200 Hz a pose releases two or three, and no frame has four behind it) that wait is shorter than the
switches a yield costs the worker (its caches among them): at 25 hands, where the last message of each batch sends
its frame at once, a worker had about 850 involuntary context switches a second with the yields and 700 without."""


def _plain(value):
    """A numpy scalar or array as the Python number or list MessagePack can carry."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot send a {type(value).__name__}")


_PACKERS = threading.local()
"""Each thread's ``msgpack.Packer`` for ``frame`` (``msgpack.packb`` makes a new one, with its buffer, per call: about
1.3 us of a frame's 2.4; one packer is not to be shared by threads, whose ``default`` calls may interleave)."""


def frame(messages: list) -> bytes:
    try:
        pack = _PACKERS.pack
    except AttributeError:
        pack = _PACKERS.pack = msgpack.Packer(default=_plain).pack
    data = pack(messages)                   # (the same bytes as ``packb``; its buffer emptied even when it raises)
    return HEADER.pack(len(data)) + data


def whole_batches(buf: bytearray) -> Iterator[list]:
    """Each whole batch (``frame``'s) at the start of ``buf``, unpacked from the received bytes as they are,
    and taken off ``buf`` before it is yielded; a partial one stays for the next read."""
    while len(buf) >= HEADER.size:
        end = HEADER.size + HEADER.unpack_from(buf)[0]
        if len(buf) < end:
            return
        with memoryview(buf) as view, view[HEADER.size:end] as data:
            batch = msgpack.unpackb(data)
        del buf[:end]
        yield batch


class OwnedHand:
    """One session this worker owns: its ``LiveSession`` (no subscribers: the frames go back to the web
    process) and what a restarted worker needs to continue it (``hands.owner``)."""

    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics, state: dict | None):
        self.live = LiveSession(name, settings, metrics)
        self.sink = OutputSink(settings.output_rate_hz, packed=False)
        self.resume_angles: dict | None = None
        self.binary = False
        """a subscriber of the session reads MessagePack: its frames are encoded as that too"""
        self.drops = (0, 0)
        """the session's frames dropped for slow subscribers and source messages refused as overload, as
        the web process last said (each frame's ``status.dropped``)"""
        self.not_restored: list[list[str]] = []
        """what this worker could not rebuild of the session's state, as error replies for its source
        (``["lost", ...]``)"""
        if state:
            for kind in ("hello", "calibration"):
                if (raw := state.get(kind)) is None:
                    continue
                errors = self.handle(raw)
                if errors and kind == "hello" and raw.get("hand") in ("left", "right"):
                    # the hand at least: its calibration and angles are of that hand, and so must its frames be
                    self.handle({"type": "hello", "protocol": PROTOCOL_VERSION, "hand": raw["hand"]})
                for code, detail, *_ in errors:
                    self.lost(code, f"its {kind}: {detail}; send the {kind} again")
            self.sink.pending.clear()
            config = {k: v for k, v in (state.get("config") or {}).items() if k != "record"}
            try:
                self.live.update_config(config)
            except ValueError as err:               # e.g. an estimator unknown here: its defaults (a REST
                log.warning("session %r: its new hand worker could not restore its configuration %s: %s; the "
                            "defaults apply", name, config, err)               # setting: logged, as on the bus
            if state.get("seq"):
                self.sink.resume_after = (int(state["seq"]), float(state["t"]))
            self.resume_angles = state.get("angles") or None

    def lost(self, code: str, what: str) -> None:
        detail = f"the session's new hand worker (after a move or a restart) could not restore {what}"
        log.warning("%s (session %r)", detail, self.live.name)
        self.not_restored.append([code, detail])

    def encoded(self, sid: int, n: int) -> list[list]:
        """The outputs in ``sink.pending`` (then emptied) as ``out`` messages for the web process, each
        encoded here once: JSON text always, MessagePack too while a subscriber reads it."""
        if not self.sink.pending:                   # (most source messages: no output)
            return []
        outs = []
        for message in self.sink.pending:
            if type(message) is FrameOutput:        # (a frame of the hand: its text written from its arrays)
                message.set_drops(*self.drops)
                outs.append(["out", sid, n, ["frame", message.seq, message.t, message.hand], message.text(),
                             encode(message.message(), binary=True) if self.binary else None])
                continue
            if message["type"] == "frame":
                message["status"]["dropped"]["subscriber_frames"], message["status"]["dropped"]["overloaded"] = self.drops
                head = ["frame", message["seq"], message["t"], message["hand"]]
            else:
                head = [message["type"], None, None, None]
            out = Outgoing(message)
            outs.append(["out", sid, n, head, out.text(), out.packed() if self.binary else None])
        self.sink.pending.clear()
        return outs

    def check(self, data: str | bytes, binary: bool, emit=None) -> tuple[list[list], bool]:
        """A source message as it arrived (the web process only looked at its type): validated here as
        the web process validates the others (``protocol.parse_input``), then through the hand. Returns
        its error replies (``[code, detail]``, or ``[code, detail, samples]`` for an ``imu_batch``'s
        refused samples, whose valid samples go on) and whether it was accepted (not refused whole).
        ``emit``: as in ``handle_valid``."""
        if not binary and self.resume_angles is None and (msg := read_fast(data)) is not None:
            return self.handle_valid(None, msg, emit), True     # (``parse_input``'s first step, without its call)
        try:                                        # the decoded value only for a session taken over (``handle_valid``)
            raw, msg = parse_input(data, binary, value=self.resume_angles is not None)
        except SamplesRefused as err:
            refused = [err.code, err.detail, err.refused]
            return [refused, *self.handle_valid(dump_message(err.kept), err.kept, emit)], True
        except ProtocolError as err:
            return [[err.code, err.detail]], False
        return self.handle_valid(raw, msg, emit), True

    def handle(self, raw: dict, emit=None) -> list[list[str]]:
        """One source message through the hand; its outputs are in ``sink.pending``. Returns the error
        replies the source gets, ``[code, detail]`` (the same as the in-process service's). ``emit``: as
        in ``handle_valid``."""
        try:
            msg = parse_message(raw)
        except ProtocolError as err:                # validated by the web process: only a version skew
            return [[err.code, err.detail]]
        return self.handle_valid(raw, msg, emit)

    def handle_valid(self, raw: dict, msg, emit=None) -> list[list[str]]:
        """A validated source message through the hand (``handle``). ``emit``: called after each frame
        (with its gesture events) is in ``sink.pending`` when the message has later ticks to process (a
        pose at 1 kHz releases about eleven ticks, the first of which makes the frame); a frame of its last
        tick stays in ``sink.pending``, to go back with the message's reply (``Worker.dispatch``)."""
        if self.resume_angles is not None and (ref := resume_reference(self.resume_angles, raw)) is not None:
            self.resume_angles = None
            try:
                self.live.hand.accept(parse_message(ref))
            except (ProtocolError, ValueError):
                pass                                # angles the protocol refuses: start as a new session
        hand = self.live.hand
        try:
            dropped = hand.accept(msg)
            sink = self.sink
            for frame, events in hand.frame_outputs():
                frame.seq = sink.frame_seq(frame.seq, frame.t)
                sink.pending.append(frame)          # (its text and message made in ``encoded``)
                for event in events:
                    sink.put(Outgoing(event), 0.0)
                if emit is not None and hand.tick_ready():
                    emit()
        except Exception as err:                    # bad input, or a defect (logged in one line)
            return [list(failure_reply(self.live.name, msg, err))]
        if dropped is NOTHING_DROPPED:              # (almost every message)
            return []
        return [list(reply) for reply in drop_replies(msg, dropped)]


class ActiveSessions:
    """The sessions of one worker that sent a source message within about ``ACTIVE_S``, for ``GROUP_SESSIONS``
    (both ends of a worker link keep one): sessions that are open but silent (a subscriber's, or one kept after
    its glove left) make no worker group its messages, so one hand at 1 kHz beside three idle sessions keeps its
    at-once path. A session counts from its first message at once; the silent ones are let go at most every
    ``ACTIVE_S / 2`` (a sweep instead of a look at every session per message), so one counts until 1-1.5
    ``ACTIVE_S`` after its last message."""

    __slots__ = ("seen", "swept")

    def __init__(self):
        self.seen: dict[int, float] = {}
        """sid -> the time of its last source message (a monotonic clock, s)"""
        self.swept = float("-inf")

    def note(self, sid: int, now: float) -> None:
        self.seen[sid] = now

    def many(self, now: float) -> bool:
        """Whether at least ``GROUP_SESSIONS`` sessions are active at ``now`` (the same clock as ``note``)."""
        if now - self.swept >= ACTIVE_S / 2:
            self.swept = now
            since = now - ACTIVE_S
            self.seen = {sid: t for sid, t in self.seen.items() if t >= since}
        return len(self.seen) >= GROUP_SESSIONS


class Worker:
    def __init__(self, sock: socket.socket, settings: ServiceSettings):
        self.sock = sock
        self.settings = settings
        self.metrics = Metrics()
        self.hands: dict[int, OwnedHand] = {}
        self.active = ActiveSessions()
        """the sessions that sent source messages lately (``handle_batch``'s grouping)"""
        self.out: list = []
        self.warming: dict[str, Compile | threading.Thread] = {}
        """estimator name -> its compiling process, then the thread that loads its kernels here"""
        self.waiting: list[list] = []                         # cfg/enrol messages in order, until warm
        self.opening: dict[int, tuple[threading.Thread, list, list]] = {}
        """sid -> the thread building its hand, the hand once built (or the error), the session's messages
        that came meanwhile (in order)"""
        self.send_lock = threading.Lock()
        self.runs: dict[int, list] = {}
        """sid -> its ``reps`` message in ``out`` that its next accepted, error-free ``chk`` reply extends
        (``replied``), while nothing else of the session follows it there"""
        self.held_since: float | None = None
        """when the replies in ``out`` began to wait for the next write (``holds``); ``None`` while nothing waits"""

    def send(self) -> None:
        self.held_since = None
        if self.out:
            data, self.out = frame(self.out), []
            self.runs.clear()
            with self.send_lock:
                self.sock.sendall(data)

    @contextlib.contextmanager
    def alive(self):
        """``["alive"]`` every ``ALIVE_S`` from a thread while the block runs (a long operation)."""
        done = threading.Event()

        def beat() -> None:
            while not done.wait(ALIVE_S):
                try:
                    with self.send_lock:
                        self.sock.sendall(frame([["alive"]]))
                except OSError:
                    return                          # the web process is gone: the main thread finds out
        thread = threading.Thread(target=beat, daemon=True)
        thread.start()
        try:
            yield
        finally:
            done.set()
            thread.join()

    def run(self) -> None:
        """Read, handle and answer batches until the web process closes its end (replies alone held a little
        for the next write, ``holds``). Each read goes into one
        buffer kept for the worker's life (``READ_SIZE``), and each batch is unpacked from the received bytes
        in place (no copy of it): a ``recv`` of that size allocates a new object of it at every read, which
        the C library maps afresh from the system (``mmap``, ``munmap``, a page fault per page received) while
        its mapping threshold is below the size, 7 times the CPU of the read itself for a 20 kB message on this
        machine (not seen in the workers of ``bench load``, whose threshold had risen)."""
        buf = bytearray()
        chunk = memoryview(bytearray(READ_SIZE))
        sock = self.sock
        while True:
            timeout = OPEN_POLL_S if self.opening else WARM_POLL_S if self.warming else None
            if self.held_since is not None:
                left = self.held_since + HOLD_S - time.perf_counter()
                timeout = left if timeout is None else min(timeout, left)
            if timeout is None:                     # (a blocking read: no select before it)
                readable = True
            else:
                readable = timeout > 0 and bool(select.select([sock], [], [], timeout)[0])
            if readable:
                got = sock.recv_into(chunk)
                if not got:
                    return                          # the web process is gone
                buf += chunk[:got]
                for batch in whole_batches(buf):
                    self.handle_batch(batch)
            self.poll_opening()
            self.poll_warming()
            if self.out and not self.holds():
                self.send()

    def holds(self) -> bool:
        """Whether the outputs not sent yet are only replies (of reads that made no frame or event) and have
        waited less than ``HOLD_S``: they then go with the next write, a frame's (at 25 hands one comes about
        every millisecond), or when that time is up, instead of in a write of their own. Each write wakes the
        web process, which then often takes this worker's core (and the worker's caches) from it: at 25 hands
        the writes of replies alone were more than half of a worker's writes. Anything else (a frame, an event,
        a configuration's answer) goes at once, with the replies before it."""
        out = self.out
        if not out or any(message[0] != "rep" and message[0] != "reps" for message in out):
            return False                            # (nothing held: ``send`` ends a hold)
        now = time.perf_counter()
        if self.held_since is None:
            self.held_since = now
        return now - self.held_since < HOLD_S

    def handle_batch(self, batch: list) -> None:
        """The messages of a batch in order. In a batch of at most ``AT_ONCE_BATCH`` messages, and for
        the last message of any batch, each frame goes back as soon as it is made (``emit``): the ticks a
        message completes after its frame, and the messages after it in its batch, would otherwise hold
        it back; the frames of a larger batch's other messages go with the next send (a busy worker
        with many sessions: fewer writes, each a turn of the web process's loop). A worker with
        ``GROUP_SESSIONS`` sessions or more sends none at once: its batch's outputs go in one write at its
        end (or every ``FLUSH_S``): each write wakes the web process, which then often takes this worker's
        core, and at 25 hands a worker wrote about twice for each batch it read. Only active sessions count
        (``ActiveSessions``: a source message within about ``ACTIVE_S``)."""
        flushed = time.perf_counter()
        last = len(batch) - 1
        note = self.active.note
        for message in batch:
            if message[0] == "chk" or message[0] == "src":
                note(message[1], flushed)
        few = not self.active.many(flushed)
        small = few and len(batch) <= AT_ONCE_BATCH
        for i, message in enumerate(batch):
            self.dispatch(message, at_once=small or (few and i == last))
            if time.perf_counter() - flushed > FLUSH_S and not self.holds():
                self.send()
                flushed = time.perf_counter()

    def dispatch(self, message: list, at_once: bool = False) -> None:
        """One message from the web process; ``at_once``: a source message's frames are sent as soon as
        each is made (``handle_batch``)."""
        kind, sid = message[0], message[1]
        if sid in self.opening:                     # its hand is being built: after it, in order
            self.opening[sid][2].append(message)
            return
        if kind == "chk":                           # (most messages: a sample or a pose)
            owned = self.hands.get(sid)
            if owned is None:
                return
            n = message[2]
            errors, accepted = owned.check(message[3], message[4], self.emitter(owned, sid, n) if at_once else None)
            self.replied(owned, sid, n, None if accepted and not errors else ["rep", sid, n, errors, accepted], at_once)
        elif kind == "src":
            owned = self.hands.get(sid)
            if owned is None:
                return
            n, raw = message[2], message[3]
            errors = owned.handle(msgpack.unpackb(raw) if isinstance(raw, bytes) else raw,
                                  self.emitter(owned, sid, n) if at_once else None)
            self.replied(owned, sid, n, ["rep", sid, n, errors], at_once)
        elif kind == "fmt":
            if (owned := self.hands.get(sid)) is not None:
                owned.binary = bool(message[2])
        elif kind == "drops":
            if (owned := self.hands.get(sid)) is not None:
                owned.drops = (int(message[2]), int(message[3]))
        elif kind == "open":
            self.runs.pop(sid, None)
            box: list = []
            self.opening[sid] = (self.build(message[2], message[3], box), box, [])
        elif kind == "close":
            self.runs.pop(sid, None)
            owned = self.hands.pop(sid, None)
            if owned is not None:
                owned.live.close()
        elif kind in ("cfg", "enrol"):
            name = self.estimator_of(message)
            if name is not None and not is_warm(name) and name not in self.warming:
                self.warming[name] = Compile(name) if needs_compiling(name) else self.load(name)
            self.waiting.append(message)
            self.apply_waiting()

    def replied(self, owned: OwnedHand, sid: int, n: int, reply: list | None, at_once: bool) -> None:
        """Source message ``n``'s outputs not sent yet, then its ``reply`` (``None``: a ``chk`` accepted without
        error replies, in the session's ``reps`` run: extended while nothing else of the session follows it in
        ``out``, else begun); with ``at_once``, sent now if it has outputs (the frame of its last tick: one write with its
        reply, ``OwnedHand.handle_valid``)."""
        outs = owned.encoded(sid, n) if owned.sink.pending else None    # (most messages: no output)
        out, runs = self.out, self.runs
        if outs:
            out.extend(outs)
            runs.pop(sid, None)                     # (a run after them is another)
            run = None
        else:
            run = runs.get(sid)
        if reply is not None:
            out.append(reply)
            if run is not None:
                del runs[sid]
        elif run is not None and run[3] == n - 1:
            run[3] = n
        else:
            runs[sid] = run = ["reps", sid, n, n]
            out.append(run)
        if at_once and outs:
            with contextlib.suppress(OSError):      # the web process is gone: the run loop finds it out
                self.send()

    def emitter(self, owned: OwnedHand, sid: int, n: int):
        """What sends source message ``n``'s outputs made so far, with everything queued before them (for a
        message whose frames go back at once, ``dispatch``)."""
        def emit() -> None:
            self.out.extend(owned.encoded(sid, n))
            self.runs.pop(sid, None)                # (a run after them is another)
            with contextlib.suppress(OSError):      # the web process is gone: the reply's send finds it out,
                self.send()                         # outside the hand (not as a failure of this message)
            hand = owned.live.hand
            if hand.ticks_ready(YIELD_TICKS) and not hand.next_frame_covered():
                hand_over()                         # (else the next frame waits for this message's ticks alone)
        return emit

    def build(self, name: str, state: dict | None, box: list) -> threading.Thread:
        """A thread that builds a session's hand into ``box`` (its state's estimator may have to be loaded
        or compiled first) with the interpreter's lock handed over often, while the main thread serves the
        other sessions; ``poll_opening`` takes it from there."""
        def run() -> None:
            try:
                with self.alive(), sharing_the_interpreter():
                    built = OwnedHand(name, self.settings, self.metrics, state)
            except BaseException as err:            # raised on the main thread, as before the thread
                built = err
            box.append(built)
        thread = threading.Thread(target=run, name=f"open {name}", daemon=True)
        thread.start()
        return thread

    def poll_opening(self) -> None:
        """Sessions whose hand is built: theirs from now on, and the messages that waited for it handled."""
        for sid, (thread, box, held) in list(self.opening.items()):
            if not box:
                continue
            thread.join()
            del self.opening[sid]
            if isinstance(box[0], BaseException):
                raise box[0]
            self.hands[sid] = box[0]
            if box[0].not_restored:                 # said to the source before any reply of the new owner
                self.out.append(["lost", sid, box[0].not_restored])
                self.runs.pop(sid, None)
            self.handle_batch(held)

    @staticmethod
    def estimator_of(message: list) -> str | None:
        body = message[3]
        return body.get("estimator") if message[0] == "cfg" and isinstance(body, dict) else None

    @staticmethod
    def load(*names: str) -> threading.Thread:
        """A thread that loads the kernels of ``names``, one after another, into this process from the
        cache (compiles them if the cache failed) while the main thread goes on serving
        (``warm.sharing_the_interpreter``): on the main thread, loading ``inertial`` stopped this worker's
        other sessions for 130 ms."""
        def run() -> None:
            for name in names:
                with contextlib.suppress(ValueError):
                    warm(name)
        thread = threading.Thread(target=run, name=f"load {' '.join(names)}", daemon=True)
        thread.start()
        return thread

    def preload(self) -> None:
        """Once ready (``ServiceSettings.preload_kernels``): the kernels of every estimator in the disk cache
        and not loaded here (``warm.cached_not_warm``) loaded by one thread in the background, as a
        switched-to estimator's are (a change to one of them meanwhile waits for it, ``warming``), so that a
        later switch does not wait for them (a switch to ``inertial`` in the spare: 0.5-0.6 s -> 0.06 s)."""
        names = [name for name in cached_not_warm() if name not in self.warming]
        if names:
            thread = self.load(*names)
            self.warming.update(dict.fromkeys(names, thread))

    def poll_warming(self) -> None:
        """A compiling process that ended: a thread loads its kernels here; once they are loaded the
        changes that waited for them are applied."""
        loaded = []
        for name, job in list(self.warming.items()):
            if isinstance(job, threading.Thread):
                if not job.is_alive() or is_warm(name):     # (a thread loading several: each once it is loaded)
                    loaded.append(name)
                    del self.warming[name]
            elif job.poll() is not None:
                self.warming[name] = self.load(name)
        if loaded:
            self.apply_waiting()

    def apply_waiting(self) -> None:
        """Apply the waiting changes in order, per session, up to the first whose estimator is not warm."""
        blocked, still = set(), []
        for message in self.waiting:
            name = self.estimator_of(message)
            if message[1] in blocked or (name is not None and not is_warm(name) and name in self.warming):
                blocked.add(message[1])
                still.append(message)
            else:
                self.configure(message)
        self.waiting = still

    def configure(self, message: list) -> None:
        kind, sid, n, body = message
        self.runs.pop(sid, None)                    # (its answer after the replies before it)
        owned = self.hands.get(sid)
        if owned is None:
            self.out.append(["cfgrep", sid, n, None, "the session is gone"])
            return
        try:
            with self.alive():                      # loads the estimator here if it is not yet loaded
                result = owned.live.update_config(body) if kind == "cfg" else owned.live.enrol(body)
        except ValueError as err:
            self.out.append(["cfgrep", sid, n, None, str(err)])
            return
        self.out.append(["cfgrep", sid, n, result, None])


PR_SET_PDEATHSIG = 1
"""``prctl`` option: the signal this process gets when its parent ends (Linux, ``<linux/prctl.h>``)"""


def die_with_parent(parent: int) -> bool:
    """Have the kernel SIGKILL this process when ``parent`` (the process that started it) ends; if it
    has already ended, end now. ``False`` where ``prctl`` is not available (not Linux): the worker then
    ends at the end of its input only."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            return False
    except (OSError, AttributeError):
        return False
    # the signal comes when the thread that started this process ends: the web process's event loop
    # thread, which closes its workers first anyway
    if os.getppid() != parent:                      # it ended before the request: no signal will come
        os._exit(0)
    return True


def main(argv: list[str]) -> int:
    if len(argv) > 2:
        die_with_parent(int(argv[2]))
    for sig in (signal.SIGINT, signal.SIGTERM):     # for the web process, which closes this one (module docstring)
        signal.signal(sig, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s hand worker %(process)d: %(message)s")
    stacks_on_signal()                              # kill -USR1: its threads' stacks into the service log
    fd, given = int(argv[0]), json.loads(argv[1])
    sock = socket.socket(fileno=fd)
    sock.setblocking(True)
    settings = ServiceSettings(**given, record_all=False, record_dir=None)
    warm_ahead(settings.estimator)                  # the pipeline's and the default estimator's kernels first
    if len(argv) > 2 and settings.hand_worker_nice:
        # below its web process once its kernels are loaded (start-up as fast as before): on a machine short
        # of cores the web process, whose work is small and on every frame's path (and every health check's),
        # gets a core first when it has something to do (CFS weight 1024 against 335 at 5)
        try:
            os.nice(settings.hand_worker_nice)
        except OSError:
            pass
    worker = Worker(sock, settings)
    worker.out.append(["ready", os.getpid()])
    try:
        worker.send()
        if settings.preload_kernels:
            worker.preload()
        with serving_gc():                          # the loaded kernels and modules never scanned again
            worker.run()
    except (BrokenPipeError, ConnectionResetError):
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
