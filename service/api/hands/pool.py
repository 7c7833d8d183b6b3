"""The web process's side of the hand workers: ``HandPool`` starts ``settings.hand_workers`` worker
processes (``hands.worker``) and gives each new session to the one with the fewest sessions;
``ProcessSession`` looks like a ``LiveSession`` to the API (subscribers' bounded queues, recording,
sync barriers) while its hand runs in that worker.

The web process only moves messages: a validated source message goes to the worker at once
(pipelined: ``ingest`` does not wait for the hand; at most ``WINDOW`` messages of a session are
unanswered, beyond that the source waits); the worker's replies become the source's error replies,
and its frames and gesture events go to the subscribers as the bytes the worker encoded them to (this
process decodes a frame only to answer a summary or to move its session). What is sent to a worker
within one turn of the event loop goes in one write (a batch). A worker with at least ``GROUP_SESSIONS``
active sessions (a source message within about ``hands.worker.ACTIVE_S``: open but silent ones do not count)
is written at most every ``GROUP_S``: a message queued sooner after the last write waits for the
end of that time, with everything else queued meanwhile (one write and one wake of the worker for what
would have been several); one queued later goes at the end of its turn, as with fewer sessions (a single
hand, e.g. at 1 kHz, waits for nothing; a message waits at most ``GROUP_S`` more). Such a worker sends its
outputs once per batch it reads, not each frame as soon as it is made (``hands.worker``). At 25 hands (12-13
sessions per worker) this halved the workers' writes and involuntary context switches and cut the web
process's wakes by a third; the CPU it saved was within the machine's noise (a few %). The worker answers a
run of a session's accepted data messages without error replies or outputs between them in one ``reps``
message (``hands.worker``).

A worker that dies (a crash, a kill) is replaced by a new process in its slot, and its sessions move
at once to the live worker with the fewest sessions (with no other worker ready, they wait for the new
process): each is opened again from its compact state (``hands.owner``: hello, calibration,
configuration, the last frame's ``seq``, time and joint angles, applied as a reference pose) and every
source message the dead worker had not answered is sent again, in order, so no source message is lost.
A worker that answers nothing while it owes answers is killed and handled the same way: after
``hand_worker_stall_s`` (stuck in a loop, or in one message that long), or already after
``hand_worker_lag_s`` when it did not work meanwhile either (its main thread neither runnable nor using
CPU: a stopped process, or one blocked on something that does not come) while the other workers
answered at least ``LAG_EVIDENCE`` source messages (so the machine as a whole is not stalled, and the
others can take the sessions). A busy worker (one long message, or starved of a core on an overloaded
machine) is not killed for its silence before ``hand_worker_stall_s``: killing it would lose its
sessions' learned state and put its load on the other workers. A worker in a long operation it knows of (loading an
estimator's kernels) says it is alive meanwhile; silence is counted only while the worker owes answers
(from the later of its last byte and the moment it began to owe one: an idle worker is not silent) and
only while this process waits for the worker's bytes (not while it is busy passing on that worker's outputs, nor while bytes the worker
sent wait unread: an overloaded web process is not a stuck worker). What is lost: the hand's filter state beyond the joint angles (covariances, learned sensor offsets),
the optical track and the gesture recogniser's state (an active gesture starts again), and the time
the move takes (its sessions' frames come late then; other workers' sessions go on). Counted per
session as ``worker.restarts`` and ``worker.resent_after_restart`` (``GET /v1/sessions``) and in
``fingertrack_hand_worker_restarts_total``.

A worker runs ``hand_worker_nice`` nicer than the web process once it has loaded its kernels (``hands.worker``):
on a machine short of cores, the process that moves every message (and answers the health checks) gets a
core first when it has work.

A session switched to an estimator that runs per finger and sample through Python (every one but the
compiled ``chain``, ``FingerEstimator.whole_hand_compiled``: 8-140 % of a core per hand, against a few %)
runs in a worker process of its own (``hand_worker_isolate``; at most ``hand_worker_isolated_max`` at once,
past it the session stays on its shared worker, logged): it takes the spare worker (``hand_worker_spare``:
one such process started ahead, once the shared workers are ready, with the default estimator loaded,
``hand_worker_isolated_nice`` nicer than this process from its start, and replaced once the session that
took it runs its new estimator there and has caught up, so that the new one's start does not compete with
that session's worker while it catches up; a move given up while the spare starts leaves it the spare), moves
there at once with its state and every unanswered source message, as after a crash (``reopen``), and the
change applies there (its worker loads the estimator's kernels first, if it has any, while the session
goes on with its old estimator there). Without a spare (none allowed, or not started yet) one is started
for it with that estimator loaded, as nice, while the session goes on with its old estimator on its
shared worker; then it moves there, the new configuration in its state (a start took 9-40 s on a busy
machine). The spare counts in ``hand_worker_isolated_max`` (a process like theirs). On a machine short of cores it then cannot starve the shared
workers' sessions, but it may fall behind its own source, which it says: ``behind_s`` in ``GET
/v1/sessions``, the gauge ``fingertrack_session_behind_seconds``, a log line past ``BEHIND_WARN_S``.
Switched back to the compiled chain, the change applies in its own worker; once the session has caught
up (``CAUGHT_UP``, or after ``CATCH_UP_WAIT_S``) it moves to the shared worker with the fewest sessions,
and its own worker ends (as when the session closes). Only a switch moves a session: a new one starts on
a shared worker whatever the service's default estimator. A move loses what a restart loses (below; the
estimator switch itself restarts the filter anyway) and counts as ``worker.moves``; a worker builds a
moved-in (or new) session's hand in a thread (``hands.worker``), so its other sessions go on meanwhile.
"""
from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import fcntl
import itertools
import json
import logging
import os
import re
import socket
import struct
import sys
import termios
import threading
import time
from pathlib import Path

import msgpack
import orjson

from ..config import ServiceSettings
from ...estimators.registry import EstimatorSpec, estimator_class
from ..metrics import Metrics
from gestures.recognizer import GestureSettings

from ...protocol import ProtocolError, parse_input
from ...protocol.wire import fast_fields_only
from ..buffers import read_buffer
from ..outgoing import Outgoing
from ..sessions import LiveSession, SessionConfig, SessionConfigChange
from .worker import GROUP_SESSIONS, HEADER, ActiveSessions, frame

log = logging.getLogger("fingertrack")
WINDOW = 512
"""source messages of one session on their way to its worker at once (more: the source waits)"""
RESTART_BACKOFF_S = 1.0
"""pause before restarting a worker that died before it was ready, s"""
LAG_EVIDENCE = 20
"""source messages the other workers answer while one worker owing answers is silent, before that one
counts as stuck after ``hand_worker_lag_s`` (not ``hand_worker_stall_s``)"""
PACKED_WRITE_BYTES = 1 << 18
"""what is written to a worker at once of the batches packed while its transport's buffer was full
(``WorkerLink._write_packed``): about what its socket takes at once"""
OUTS_PER_TURN = 16
"""frames and events of a worker passed on to the subscribers' queues before the loop lets their senders
run (a turn of the loop per frame, and a wake of every subscriber's sender per frame, cost the web process
more than moving the frame); at most half a subscriber queue (``subscriber_queue_frames``), so that no
frame is dropped for it"""
GROUP_S = 0.002
"""the least time between two writes to a worker with ``GROUP_SESSIONS`` active sessions or more, s"""
CONFIG_WAIT_S = 300.0
"""longest wait for a worker to apply a configuration change (it may compile an estimator first), s"""
CAUGHT_UP = 16
"""a session leaves its own worker for a shared one once it has at most this many source messages unanswered
(the shared worker handles them again: a few ms)"""
CATCH_UP_WAIT_S = 30.0
"""longest wait for a session to catch up before it leaves its own worker anyway, s"""
BEHIND_WARN_S = 1.0
"""a session whose frames come this much later behind its source than they did at best is logged once (until it
has caught up to a tenth of it), s"""


def _own_group(loop) -> dict:
    """How a hand worker is started in a process group of its own, in the web process's session: a terminal's
    Ctrl-C to the service's group does not reach it while it imports (it ignores SIGINT only from ``main()``; the
    web process closes it). ``process_group=0`` on Python's loop; uvloop's subprocesses do not take that argument,
    so there the child calls ``setpgid(0, 0)`` (``os.setpgrp``, one system call) between fork and exec. Not a
    session of its own (``start_new_session``): on Linux with ``sched_autogroup`` a new session is a scheduling
    group of its own, whose ``hand_worker_nice`` no longer yields to the web process (measured: ``/health`` p99 at
    50 hands about 10 -> 20-35 ms, at 25 hands 6 -> 15 ms)."""
    if isinstance(loop, asyncio.BaseEventLoop):
        return {"process_group": 0}
    return {"preexec_fn": os.setpgrp}


class WorkerLink:
    """One worker slot: its process (replaced when it dies), the socket to it and its sessions."""

    def __init__(self, pool: "HandPool", slot: int, estimator: str | None = None, preload: bool = False):
        self.pool = pool
        self.slot = slot
        self.isolated = estimator is not None
        """the worker of one session on a costly estimator (``estimator``, the one it loads before it is
        ready), ``hand_worker_isolated_nice`` nicer than this process from its start (module docstring)"""
        self.given = {**pool.worker_settings, "preload_kernels": preload and pool.settings.preload_kernels,
                      **({} if estimator is None else {"estimator": estimator, "hand_worker_nice": 0})}
        """its settings; ``preload``: it loads the cached estimators' kernels once ready (``ServiceSettings.
        preload_kernels``): the spare, which the next session switched to one of them takes, and, only when
        such a session stays on its shared worker (``hand_worker_isolate`` off), the shared workers"""
        self.proc: asyncio.subprocess.Process | None = None
        self.pid: int | None = None
        self.ready = asyncio.Event()
        self.sessions: dict[int, ProcessSession] = {}
        self.owed = 0
        """source messages of its sessions it has not answered yet (the sum of their ``_pending``, kept
        as a count so that a source message costs no walk over the worker's sessions)"""
        self.restarts = 0
        self._writer: asyncio.Transport | None = None
        self._sock: socket.socket | None = None
        self._reader: _LinkReader | None = None
        self._out: list = []
        self._packed: collections.deque[bytes] = collections.deque()
        """batches packed while the transport's buffer is over its high-water mark (``_full``), and those after
        them, written in order in writes of about ``PACKED_WRITE_BYTES`` once it has drained: appending each to a
        buffer of megabytes (a worker seconds behind) moved the whole buffer in memory time and again, a tenth of
        this process's time at 50 hands"""
        self._full = False
        self._held: list = []                       # while restarting: messages other than source messages
        self._restarting = False
        self._flush_scheduled = False
        self.active = ActiveSessions()
        """its sessions that sent source messages lately (``GROUP_SESSIONS`` counts these)"""
        self._flush_timer: asyncio.TimerHandle | None = None
        """the delayed write of a grouping worker (``GROUP_S``), while one is due"""
        self._flushed = float("-inf")
        """when the last write to it was made (``time.monotonic``)"""
        self._tasks: list[asyncio.Task] = []
        self.starting: asyncio.Task | None = None
        """a spare's start (``HandPool._start_spare``), which a move taking it waits for"""
        self.heard = time.monotonic()
        """when the worker last sent anything, or began to owe answers (monotonic s)"""
        self._owing_from_flush = False
        """the next write to the worker carries the first answer it owes: its silence counts from then"""
        self.worked = time.monotonic()
        """when the watchdog last saw the worker's main thread runnable or its CPU time grown (monotonic s)"""
        self._cpu_ns: int | None = None
        self.answered_elsewhere_at_heard = 0
        """the pool's count of answered source messages when this worker last sent anything"""

    async def start(self) -> None:
        parent, child = socket.socketpair()
        self.ready.clear()
        try:
            self.proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "service.api.hands.worker", str(child.fileno()), json.dumps(self.given),
                str(os.getpid()), pass_fds=(child.fileno(),), **_own_group(asyncio.get_running_loop()))
        finally:
            child.close()
        self.pid = self.proc.pid
        if self.isolated:                           # from its start: its start-up yields to the serving processes too
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, self.pid,
                               min(19, os.getpriority(os.PRIO_PROCESS, 0) + self.pool.settings.hand_worker_isolated_nice))
        self._cpu_ns, self.worked = None, time.monotonic()
        self._packed, self._full = collections.deque(), False
        self._writer, self._reader = await asyncio.get_running_loop().create_unix_connection(
            lambda: _LinkReader(self), sock=parent)
        self._sock = parent
        self._tasks = [asyncio.create_task(self._watch(self.proc))]
        self._flush()

    def send(self, message: list) -> None:
        """Queue a message for the worker; what is queued within one turn of the loop goes in one write, and
        with ``GROUP_SESSIONS`` active sessions or more, what is queued within ``GROUP_S`` of its last write (module
        docstring). While the worker restarts, only ``close`` is held here: each session's ``reopen`` sends the
        rest (its state, its unanswered source messages and configuration changes)."""
        if self._restarting:
            if message[0] == "close":
                self._held.append(message)
            return
        self._out.append(message)
        if not self._flush_scheduled:
            self._flush_scheduled = True
            loop = self.pool.loop or asyncio.get_running_loop()
            now = time.monotonic()
            wait = self._flushed + GROUP_S - now if self.active.many(now) else 0.0
            if wait > 0.0:
                self._flush_timer = loop.call_later(wait, self._flush)
            else:
                loop.call_soon(self._flush)

    def _flush(self) -> None:
        self._flush_scheduled = False
        if self._flush_timer is not None:           # (a write before it was due: a stop)
            self._flush_timer.cancel()
            self._flush_timer = None
        if self._out and self._writer is not None and not self._writer.is_closing():
            data, self._out = frame(self._out), []
            self._flushed = time.monotonic()
            if self._full or self._packed:          # after those packed before it, once the buffer has drained
                self._packed.append(data)
                self._write_packed()
            else:
                self._write(data)

    def _write(self, data: bytes) -> None:
        self._writer.write(data)
        if self._owing_from_flush:                  # it has what it owes an answer to from now on
            self._owing_from_flush = False
            self._hear()

    def writable(self, yes: bool) -> None:
        """The transport's buffer went over its high-water mark (``False``) or drained below its low-water mark
        (``True``: what was packed meanwhile written, in order)."""
        self._full = not yes
        self._write_packed()

    def _write_packed(self) -> None:
        """The packed batches, in order, in writes of about ``PACKED_WRITE_BYTES``, until the transport's buffer
        is over its high-water mark again (``pause_writing`` calls ``writable`` within a write) or none is left."""
        packed = self._packed
        while packed and not self._full and self._writer is not None and not self._writer.is_closing():
            chunk, size = [], 0
            while packed and size < PACKED_WRITE_BYTES:
                chunk.append(packed.popleft())
                size += len(chunk[-1])
            self._write(b"".join(chunk))

    def _unread(self) -> bool:
        """Bytes from the worker that this process has not read yet (in the socket or the reader's buffer)."""
        if self._reader is not None and self._reader.unread():
            return True
        try:
            return self._sock is not None and struct.unpack("i", fcntl.ioctl(self._sock.fileno(), termios.FIONREAD,
                                                                             b"\0\0\0\0"))[0] > 0
        except OSError:
            return False

    def _hear(self) -> None:
        self.heard = time.monotonic()
        self.answered_elsewhere_at_heard = self.pool.answered

    def owe(self, besides: "ProcessSession | None" = None) -> None:
        """Before a source message goes to this worker: if it owed no answer until now (its sessions,
        ``besides`` one moving to it, have nothing unanswered), its silence counts from now. A worker
        has nothing to say while it owes nothing: silence since its last byte would count the idle
        time (before the first stream, a 30 s pause) and kill it at the first message it is sent."""
        others = self.owed - (len(besides._pending) if besides is not None and besides.link is self else 0)
        if not others:
            self._hear()
            self._owing_from_flush = True

    def _dispatch(self, message: list) -> None:
        kind = message[0]
        if kind == "ready":
            self.ready.set()
            return
        if kind == "alive":
            return
        live = self.sessions.get(message[1])
        if live is None:
            return
        if kind == "out":
            live.on_output(message[2], message[3], message[4], message[5])
        elif kind == "reps":
            self.pool.answered += message[3] - message[2] + 1
            live.on_replies(message[2], message[3])
        elif kind == "rep":
            self.pool.answered += 1
            live.on_reply(message[2], message[3], message[4] if len(message) > 4 else None)
        elif kind == "cfgrep":
            live.on_config_reply(message[2], message[3], message[4])
        elif kind == "lost":                        # said with the next reply (to the source then connected)
            live.lost.extend(message[2])

    async def _watch(self, proc: asyncio.subprocess.Process) -> None:
        """When the process ends (unless the service is closing): its sessions move to the live worker
        with the fewest sessions (or, with none ready, stay for the new process), and the slot gets a
        new process."""
        code = await proc.wait()
        if self.pool.closing:
            return
        was_ready = self.ready.is_set()
        self.ready.clear()
        self._restarting = True
        self.restarts += 1
        self.pool.metrics.worker_restarts.inc()
        if self._reader is not None:                # what it sent before it died comes first
            await asyncio.shield(self._reader.finished)
        if self._writer is not None:
            self._writer.close()
        self._writer, self._out, self._held = None, [], [m for m in self._out if m[0] == "close"]
        self._packed.clear()                        # (as lost as what its transport still held)
        # a session of its own worker waits for its new process (the shared workers are not for it)
        others = [] if self.isolated else [x for x in self.pool.links
                                           if x is not self and x.ready.is_set() and not x._restarting]
        log.warning("hand worker %d (pid %d) ended with %s; %d session(s) continue %s", self.slot, proc.pid, code,
                    len(self.sessions), "on the other workers" if others else "when it has restarted")
        if others:
            for live in list(self.sessions.values()):
                min(others, key=lambda x: len(x.sessions)).take(live)
        if not was_ready:
            await asyncio.sleep(RESTART_BACKOFF_S)  # it died starting: do not restart in a tight loop
        await self.start()
        self._restarting = False
        for live in list(self.sessions.values()):
            live.reopen()
        held, self._held = self._held, []
        for message in held:
            self.send(message)

    def take(self, live: "ProcessSession", config: dict | None = None, restart: bool = True) -> None:
        """``live``, a session of another worker, on this one from its state (``ProcessSession.reopen``)."""
        old = live.link
        if old.sessions.pop(live.sid, None) is not None:
            old.owed -= len(live._pending)
        live.link = self
        self.sessions[live.sid] = live
        self.owed += len(live._pending)
        # a close of it held here while this worker restarted (it left before) would follow the reopen
        self._held = [m for m in self._held if not (m[0] == "close" and m[1] == live.sid)]
        live.reopen(config, restart)

    def stalled(self, now: float, lag_s: float, limit_s: float) -> bool:
        """A ready worker that owes source messages an answer and has sent nothing for ``limit_s``, or
        for ``lag_s`` while the other workers answered ``LAG_EVIDENCE`` source messages and it did not
        work either (neither runnable nor using CPU: stopped, or blocked; module docstring)."""
        if not (self.ready.is_set() and not self._restarting and self.proc is not None and self.proc.returncode is None
                and self.owed):
            return False
        if self._unread():                          # it did send: this process is behind, not the worker
            self._hear()
            return False
        silent = now - self.heard
        if silent > limit_s:
            return True
        if self._working():                         # busy or waiting for a core: not stuck (module docstring)
            self.worked = now
        idle = now - max(self.heard, self.worked)
        return idle > lag_s and self.pool.answered - self.answered_elsewhere_at_heard >= LAG_EVIDENCE

    def _working(self) -> bool:
        """The worker's main thread is runnable now (running or waiting for a core) or has run since the
        last look (Linux ``/proc``; elsewhere ``False``: silence alone counts). A stopped process, or one
        blocked waiting for something that does not come, is neither."""
        try:
            state = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            cpu_ns = int(Path(f"/proc/{self.pid}/schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return False
        ran, self._cpu_ns = self._cpu_ns is not None and cpu_ns != self._cpu_ns, cpu_ns
        return state == "R" or ran

    async def stop(self, kill: bool = False) -> None:
        """The process ends at the end of its input (``kill``: at once; it has nothing left to do)."""
        for task in self._tasks:
            if task is not asyncio.current_task():
                task.cancel()
        if self._writer is not None:
            self._flush()                           # what waits for its turn or its group's time, first
            if self._packed and not self._writer.is_closing():
                self._writer.write(b"".join(self._packed))     # (a close writes what it holds first)
                self._packed.clear()
            self._writer.close()                    # the worker ends at the end of its input
        if kill and self.proc is not None and self.proc.returncode is None:
            self.proc.kill()
        if self.proc is not None and self.proc.returncode is None:
            try:
                await asyncio.wait_for(self.proc.wait(), 5.0)
            except asyncio.TimeoutError:
                self.proc.kill()
                await self.proc.wait()


class _LinkReader(asyncio.BufferedProtocol):
    """The web process's end of a worker's socket: the worker's batches (``hands.worker``) dispatched as
    their bytes arrive, in the callback that received them (no reading task and no turn of the loop per
    batch). Every arrival counts as a sign of life; after every ``outs_per_turn`` frames and events the
    rest waits for the next turn of the loop, so that the subscribers' senders go out before more frames
    come (their queues are bounded). What arrives meanwhile waits here; reading pauses only once
    ``READ_AHEAD`` bytes wait (pausing and resuming the socket at every batch with a frame cost this
    process two system calls and a selector change each time). Its reads go into the thread's ``read_buffer``
    (a ``BufferedProtocol``), not a new bytes object of 256 KiB each."""

    READ_AHEAD = 1 << 20
    """bytes from the worker received and not yet passed on beyond which reading its socket pauses (the
    worker then blocks in its writes: backpressure)"""

    def __init__(self, link: WorkerLink):
        self.link = link
        self._buf = bytearray()
        self._batch: list = []                      # the messages of the batch being dispatched
        self._next = 0                              # the next of them to dispatch
        self._transport: asyncio.Transport | None = None
        self._read_into: memoryview | None = None
        self._continuing = False
        self._paused = False
        self._lost = False
        self._loop = asyncio.get_running_loop()
        self.finished = self._loop.create_future()
        """done once the connection has ended and everything the worker sent before was dispatched"""

    def connection_made(self, transport) -> None:
        self._transport = transport

    def pause_writing(self) -> None:
        self.link.writable(False)

    def resume_writing(self) -> None:
        self.link.writable(True)

    def get_buffer(self, sizehint: int) -> memoryview:
        self._read_into = view = read_buffer()
        return view

    def buffer_updated(self, nbytes: int) -> None:
        self.data_received(self._read_into[:nbytes])

    def data_received(self, data: bytes | memoryview) -> None:
        self._buf += data
        self.link._hear()                           # a worker whose bytes still arrive is not silent
        if not self._continuing:
            self._run()
        elif not self._paused and len(self._buf) > self.READ_AHEAD:
            self._paused = True
            self._transport.pause_reading()

    def unread(self) -> bool:
        """Bytes or messages from the worker not dispatched yet."""
        return bool(self._buf) or self._next < len(self._batch)

    def _dispatch(self) -> None:
        link, per_turn, outs = self.link, self.link.pool.outs_per_turn, 0
        while True:
            batch = self._batch
            while self._next < len(batch):
                message = batch[self._next]
                self._next += 1
                link._dispatch(message)
                if message[0] == "out":
                    outs += 1
                    if outs == per_turn and self._next < len(batch):     # the rest after the senders' turn
                        self._pause()
                        return
            buf = self._buf
            if len(buf) < HEADER.size or len(buf) < HEADER.size + HEADER.unpack_from(buf)[0]:
                break
            size, = HEADER.unpack_from(buf)
            self._batch, self._next = msgpack.unpackb(buf[HEADER.size:HEADER.size + size]), 0
            del buf[:HEADER.size + size]
            if outs:                                # a batch after frames: after the senders' turn too
                self._pause()
                return
        if self._lost:
            self._finish()

    def _pause(self) -> None:
        self._continuing = True
        self._loop.call_soon(self._continue)

    def _continue(self) -> None:
        self._continuing = False
        self.link._hear()                           # this process was busy with its outputs, not waiting for it
        if self._paused:
            self._paused = False
            if not self._lost:
                self._transport.resume_reading()
        self._run()

    def _run(self) -> None:
        """``_dispatch`` until it has passed on everything or paused for the senders' turn. A message whose
        passing on raised (a defect) is logged and skipped, the rest still passed on, and the connection
        closed: the worker ends at the end of its input and its sessions move, as after a crash."""
        while True:
            try:
                self._dispatch()
                return
            except Exception:
                log.exception("hand worker %d: passing on its messages failed; it is ended", self.link.slot)
                if not self._lost:
                    self._transport.close()

    def connection_lost(self, exc) -> None:
        self._lost = True                           # the process ended: _watch restarts it
        if not self._continuing:                    # (else ``_continue`` goes on, then finishes)
            self._run()

    def eof_received(self) -> bool:
        return False                                # the end of its output: close our end too

    def _finish(self) -> None:
        if not self.finished.done():
            self.finished.set_result(None)


class HandPool:
    """The embedded service's hand worker processes (module docstring)."""

    def __init__(self, settings: ServiceSettings, metrics: Metrics):
        self.settings = settings
        self.metrics = metrics
        self.worker_settings = {"estimator": settings.estimator, "output_rate_hz": settings.output_rate_hz,
                                "hand_worker_nice": settings.hand_worker_nice}
        self.links = [WorkerLink(self, i, preload=not settings.hand_worker_isolate) for i in range(settings.hand_workers)]
        """the shared workers"""
        self.isolated: list[WorkerLink] = []
        """the workers of one session each, and the spare (module docstring)"""
        self.spare: WorkerLink | None = None
        """the worker started ahead for the next session switched to a costly estimator (module docstring)"""
        self._ready_once = False
        """the shared workers have all been ready once (the service has started)"""
        self._replacing: set[asyncio.Task] = set()
        """the waits to start a new spare after one was taken (``_replace_when_settled``)"""
        self._isolated_slots = itertools.count(settings.hand_workers)
        self.outs_per_turn = max(1, min(OUTS_PER_TURN, settings.subscriber_queue_frames // 2))
        self.loop: asyncio.AbstractEventLoop | None = None
        self.closing = False
        self._sids = itertools.count(1)
        self.answered = 0
        """source messages the workers answered (a count for the stall watchdog)"""
        self._watchdog: asyncio.Task | None = None

    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        await asyncio.gather(*(link.start() for link in self.links))
        self._watchdog = asyncio.create_task(self._watch_stalls())
        self._replace_spare()

    def _replace_spare(self) -> None:
        """Start a spare worker (module docstring) unless there is one, none is wanted, or
        ``hand_worker_isolated_max`` workers of their own run already."""
        wanted = self.settings.hand_worker_isolate and self.settings.hand_worker_spare and not self.closing
        if not wanted or self.spare is not None or len(self.isolated) >= self.settings.hand_worker_isolated_max:
            return
        link = self.spare = WorkerLink(self, next(self._isolated_slots), estimator=self.settings.estimator, preload=True)
        self.isolated.append(link)
        link.starting = asyncio.get_running_loop().create_task(self._start_spare(link))

    async def _start_spare(self, link: WorkerLink) -> None:
        """The spare's process, once the shared workers have been ready (it never slows the service's
        start; later, a shared worker's restart does not hold it back: a switch may be waiting for it)."""
        if not self._ready_once:
            await self.wait_ready()
            self._ready_once = True
        try:
            await link.start()
        except OSError as err:
            log.warning("the spare hand worker did not start (%s); a session switched to a costly estimator "
                        "waits for a worker of its own to start", err)
            if self.spare is link:
                self.spare = None
            await self.retire(link, replace=False)

    async def _take_spare(self) -> WorkerLink | None:
        """The spare worker, started, for a session to move to (its replacement starts later:
        ``_replace_when_settled``); ``None`` without one. A move given up while the spare starts (``call``'s
        timeout) leaves it the spare (or ends it, if another has taken its place meanwhile): no process
        holds a slot for no session."""
        link = self.spare
        starting = None if link is None else link.starting
        if link is None or starting is None:
            return None
        self.spare = None
        try:
            with contextlib.suppress(Exception):    # (shielded: a cancelled move must not cancel a process's start)
                await asyncio.shield(starting)
        except asyncio.CancelledError:
            if not self.closing and link in self.isolated:    # (closing: ``close`` ends it)
                if self.spare is None:
                    self.spare = link
                else:
                    self.loop.create_task(self.retire(link, replace=False))
            raise
        if link not in self.isolated or link.proc is None:
            return None                             # it did not start
        return link

    async def _replace_when_settled(self, live: "ProcessSession", link: WorkerLink, estimator: str) -> None:
        """A new spare (``_replace_spare``) once the session that took the spare ``link`` runs there on
        ``estimator`` (the change applied) and has caught up (``CAUGHT_UP``), once it has left that worker,
        or after ``CATCH_UP_WAIT_S`` at the latest: the new spare's start (seconds of CPU) does not compete
        with that session's worker while it catches up."""
        deadline = time.monotonic() + CATCH_UP_WAIT_S
        while time.monotonic() < deadline and not self.settled_in(live, link, estimator):
            await asyncio.sleep(0.05)
        self._replace_spare()

    @staticmethod
    def settled_in(live: "ProcessSession", link: WorkerLink, estimator: str) -> bool:
        """Whether ``live``, moved to the spare ``link`` for ``estimator``, runs it there and has caught up
        (at most ``CAUGHT_UP`` source messages unanswered), or has left that worker (or closed)."""
        if live.link is not link or live.sid not in link.sessions:
            return True
        return live.config.estimator == estimator and len(live._pending) <= CAUGHT_UP

    async def _watch_stalls(self) -> None:
        """A stuck worker (an endless loop, a stopped process; module docstring) is killed: its sessions
        move to the other workers as after a crash."""
        limit, lag = self.settings.hand_worker_stall_s, min(self.settings.hand_worker_lag_s, self.settings.hand_worker_stall_s)
        while True:
            await asyncio.sleep(min(1.0, lag / 4))
            now = time.monotonic()
            for link in [*self.links, *self.isolated]:
                if link.stalled(now, lag, limit):
                    log.warning("hand worker %d (pid %d) answered nothing for %.1f s while it owed answers; "
                                "killing it, its sessions move", link.slot, link.pid, now - link.heard)
                    link.proc.kill()

    async def wait_ready(self) -> None:
        """Until every worker has loaded the default estimator and reads messages."""
        await asyncio.gather(*(link.ready.wait() for link in self.links))

    async def close(self) -> None:
        self.closing = True
        if self._watchdog is not None:
            self._watchdog.cancel()
        for task in self._replacing:
            task.cancel()
        starts = [link.starting for link in self.isolated if link.starting is not None]
        for task in starts:
            task.cancel()
        await asyncio.gather(*starts, return_exceptions=True)
        # the spare has nothing to finish (and may be starting still, not reading its input yet)
        await asyncio.gather(*(link.stop(kill=link is self.spare) for link in [*self.links, *self.isolated]))

    def isolates(self, spec: EstimatorSpec) -> bool:
        """Whether a session on ``spec`` runs in a worker of its own (module docstring)."""
        return self.settings.hand_worker_isolate and not estimator_class(spec.name).whole_hand_compiled(spec.settings)

    def call(self, coroutine, timeout_s: float):
        """Run ``coroutine`` on the event loop and wait for its result (from a thread of the API)."""
        future = asyncio.run_coroutine_threadsafe(coroutine, self.loop)
        try:
            return future.result(timeout_s)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise ValueError(f"moving the session between hand workers took longer than {timeout_s:g} s") from None

    async def move(self, live: "ProcessSession", isolated: bool, config: dict | None = None) -> bool:
        """``live`` with its state (and ``config`` in place of its configuration) to a new worker of its own
        (``isolated``), once that has started, or to the shared worker with the fewest sessions once it has
        caught up (its own worker's backlog would otherwise be handled again there, beside other sessions);
        its former worker forgets it, and a worker of its own ends. False: not moved, ``hand_worker_isolated_max``
        workers of their own run already (or the session closed meanwhile)."""
        if isolated:
            wanted = (config or {}).get("estimator", live.config.estimator)
            target = await self._take_spare()
            spare = target is not None
            if spare:
                config = None                       # it goes on with its estimator there until the change applies
            elif len(self.isolated) >= self.settings.hand_worker_isolated_max:
                log.warning("session %s stays on its shared hand worker: %d hand workers of their own run "
                            "(hand_worker_isolated_max, a spare being taken counted)", live.name, len(self.isolated))
                return False
            else:
                target = WorkerLink(self, next(self._isolated_slots),
                                    estimator=(config or {}).get("estimator", live.config.estimator))
                self.isolated.append(target)
            try:
                if target.proc is None:
                    await target.start()
                await asyncio.wait_for(target.ready.wait(), CONFIG_WAIT_S)
            except (OSError, asyncio.TimeoutError) as err:
                await self.retire(target)
                why = str(err) if isinstance(err, OSError) else f"not ready within {CONFIG_WAIT_S:g} s"
                raise ValueError(f"the session's own hand worker did not start ({why}); the session stays as it "
                                 f"was") from None
            except BaseException:                   # cancelled (the service closing, the wait given up)
                await self.retire(target)
                raise
        else:
            deadline = time.monotonic() + CATCH_UP_WAIT_S
            while len(live._pending) > CAUGHT_UP and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            ready = [x for x in self.links if x.ready.is_set() and not x._restarting]
            target = min(ready or self.links, key=lambda x: len(x.sessions))
        old = live.link                             # (a restart may have moved it meanwhile)
        if live.sid not in old.sessions or self.closing:     # closed meanwhile
            if target.isolated:
                await self.retire(target)
            return False
        target.take(live, config, restart=False)
        if isolated and spare:
            replacing = asyncio.get_running_loop().create_task(self._replace_when_settled(live, target, wanted))
            self._replacing.add(replacing)
            replacing.add_done_callback(self._replacing.discard)
        old.send(["close", live.sid])
        if old.isolated:
            await self.retire(old)
        return True

    async def retire(self, link: WorkerLink, replace: bool = True) -> None:
        """A worker of one session that has left it (or never came) ends; a spare is started in its place
        if there is none (``replace``)."""
        if link in self.isolated:
            self.isolated.remove(link)
            await link.stop(kill=True)
        if replace:
            self._replace_spare()

    def session(self, name: str, settings: ServiceSettings, metrics: Metrics) -> "ProcessSession":
        """A new session on the worker with the fewest sessions (from the loop or a thread of the API)."""
        link = min(self.links, key=lambda x: len(x.sessions))
        return ProcessSession(name, settings, metrics, link, next(self._sids))


_exhaust = collections.deque(maxlen=0).extend
"""runs an iterator to its end in C, keeping nothing"""

_DATA_HEAD = re.compile(r'\{\s*"type"\s*:\s*"(imu_batch|imu|pose)"\s*,')
_COMPACT_HEADS = tuple((f'{{"type":"{kind}",', kind) for kind in ("imu_batch", "imu", "pose"))
"""the heads ``_DATA_HEAD`` matches as compact JSON writes them (a glove's), each with its type"""


def data_type(text: str) -> str | None:
    """The type of a JSON data message (``imu``, ``imu_batch``, ``pose``) read from its head, without
    decoding it: the text opens with its ``"type"`` key, has no other ``"type"`` (a repeated key's last
    value would count) and no backslash (an escaped key spells ``"type"`` differently). ``None``: not
    known this way (then it is decoded). What the text holds beyond its type is checked by the worker,
    with the same error replies as here (an invalid text keeps its ``invalid_json`` reply)."""
    for head, kind in _COMPACT_HEADS:            # (as compact JSON writes it: no pattern to match)
        if text.startswith(head):
            end = len(head)
            break
    else:
        match = _DATA_HEAD.match(text)
        if match is None:
            return None
        kind, end = match.group(1), match.end()
    if "\\" in text or _has_type_key(text, end):
        return None
    return kind


def _has_type_key(text: str, start: int) -> bool:
    """``'"type"' in text[start:]``, found by its ``p``: a letter few data messages hold (an ``imu_batch`` in
    ``"samples"``, a ``pose`` in ``"position"``), each found with the C library's one-byte search, where the
    search for the whole word went through a JSON text's many quotes and digits (about 1 us for a 1.5 KB batch,
    a tenth of the message's way through this process). A text with many ``p`` is searched the whole-word way."""
    i = text.find("p", start + 3)
    for _ in range(8):
        if i < 0:
            return False
        if text.startswith('"ty', i - 3) and text.startswith('e"', i + 1):
            return True
        i = text.find("p", i + 1)
    return text.find('"type"', i - 3) >= 0


class Unchecked:
    """A received data message passed to the worker as it arrived, validated there
    (``ProcessSession.parse_input``): its ``type``, its bytes and their encoding."""

    __slots__ = ("type", "data", "binary")

    def __init__(self, kind: str, data: str | bytes, binary: bool):
        self.type, self.data, self.binary = kind, data, binary


class ProcessSession(LiveSession):
    """A session whose hand runs in a worker process (module docstring)."""

    def __init__(self, name: str, settings: ServiceSettings, metrics: Metrics, link: WorkerLink, sid: int):
        super().__init__(name, settings, metrics)
        self.link, self.sid = link, sid
        self.hand_name: str | None = None
        self.hello: dict | None = None
        self.calibration: dict | None = None
        self._last: tuple[int, Outgoing] | None = None         # the last frame passed on: its seq, itself
        self._told: tuple | None = None             # (MessagePack wanted, drops, overloaded) as the worker last heard
        self.restarts = 0
        self.resent = 0
        self.moves = 0
        """times it moved to a worker of its own or back (module docstring)"""
        self._configuring = threading.Lock()        # one change at a time: a move must not cross another
        self._best_lag: float | None = None         # the least (arrival - source time) of its frames so far, s
        self._last_t: float | None = None
        self.behind_s = 0.0
        """how much later its last frame came behind its source's real time than its frames did at best, s"""
        self._behind_told = False
        metrics.behind.labels(name)                 # (its series shown from the start; set at each scrape: ``_pace``)
        self._n = 0
        self._pending: dict[int, tuple] = {}        # n -> (type, its message to the worker, t_ingest, calibration or None)
        self._replied = asyncio.Event()
        self._errors: collections.deque = collections.deque()
        """the source's error replies (``[code, detail, *samples]``) and answers (``answer_in_order``) to send, in order"""
        self._answers: collections.deque = collections.deque()
        """``(n, answer)``: an answer due once source messages up to number ``n`` are answered (``answer_in_order``)"""
        self._error_task: asyncio.Task | None = None
        self._source_error = None
        self._greeted = False
        """the current source connection's hello was accepted (before it, a message that is not a hello
        gets ``expected_hello``, or its decoding error: every message is decoded here)"""
        self._config_n = itertools.count(1)
        self.lost: list[list] = []
        """what the session's new worker could not restore of its state (``["lost", ...]``), for its source
        with the next reply"""
        self._config_waits: dict[int, tuple[threading.Event, list, list]] = {}   # n -> (answered, result, request)
        link.sessions[sid] = self
        self._to_worker(["open", sid, name, None])

    def _make_hand(self):
        return None                                 # it runs in the worker

    @property
    def last_frame(self) -> dict | None:
        """The last frame passed on (decoded from its bytes only when asked: a state, a summary)."""
        return None if self._last is None else self._last[1].message

    @property
    def last_status(self) -> dict:
        """The last frame's, as the worker wrote it."""
        frame_ = self.last_frame
        return {} if frame_ is None else frame_["status"]

    def _tell_worker(self) -> None:
        """The worker writes MessagePack too while a subscriber reads it, and the session's drop counts
        into its frames' status: tell it when they change."""
        binary = False
        for sub in self.subscribers:                # (asked at every source message and output: no generator)
            if sub.binary:
                binary = True
                break
        was = self._told
        if was is None or was[0] is not binary or was[1] != self.dropped_frames or was[2] != self.overloaded:
            if was is None or was[0] is not binary:
                self.link.send(["fmt", self.sid, binary])
            if was is None or was[1] != self.dropped_frames or was[2] != self.overloaded:
                self.link.send(["drops", self.sid, self.dropped_frames, self.overloaded])
            self._told = (binary, self.dropped_frames, self.overloaded)

    def _to_worker(self, message: list) -> None:
        """Send from the event loop or from a thread of the API (in order either way)."""
        loop = self.link.pool.loop
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            self.link.send(message)
        else:
            loop.call_soon_threadsafe(lambda: self.link.send(message))   # its link then (it may move)

    def state(self) -> dict:
        """The compact session state a restarted worker continues from (``hands.owner``)."""
        frame_ = self.last_frame or {}
        angles = {f: {j: v for j, v in a.items() if j != "mode"} for f, a in frame_.get("fingers", {}).items()}
        config = self.config.model_dump(exclude={"record"})
        return {"session": self.name, "worker": self.link.pid, "seq": frame_.get("seq", 0), "t": frame_.get("t"),
                "angles": angles or None, "hello": self.hello, "calibration": self.calibration, "config": config}

    def reopen(self, config: dict | None = None, restart: bool = True) -> None:
        """After its worker died (``restart``), or moving to another worker: on its new worker, the session
        from its state (with ``config`` in place of its configuration), then every unanswered message and
        configuration change."""
        if restart:
            self.restarts += 1
        else:
            self.moves += 1
        self.link.owe(besides=self)
        state = self.state()
        if config is not None:
            state["config"] = config
        self.link.send(["open", self.sid, self.name, state])
        self._told = None
        self._tell_worker()
        for n in sorted(self._pending):
            self.resent += restart
            body = self._pending[n][1]
            self.link.send([body[0], self.sid, n, *body[1:]])
        for n in sorted(self._config_waits):        # changes the dead worker had not answered
            self.link.send(self._config_waits[n][2])

    # -- source messages ---------------------------------------------------------------------------
    def attach_source(self, send_error) -> None:
        self._source_error = send_error
        self._greeted = False
        self._best_lag = None                       # a new source: its clock is another                       # a new connection: until its hello, every message decoded here

    def parse_input(self, data: str | bytes, binary: bool):
        """``(decoded value, message)`` of a received message: a data message (``imu``, ``imu_batch``,
        ``pose`` with only their fields) as ``Unchecked``, validated by the worker (the same checks and
        error replies, off this process's event loop); any other, or any while the session records, as
        ``LiveSession.parse_input`` gives it. Once the source has said hello, a JSON data message is
        known by its head alone (``data_type``) and not decoded here at all: decoding an ``imu_batch``
        took a quarter of this process's time per message."""
        if self.recorder is None:
            if not binary and self._greeted and (kind := data_type(data)) is not None:
                return None, Unchecked(kind, data, binary)
            try:
                raw = msgpack.unpackb(data, max_bin_len=0, max_ext_len=0) if binary else orjson.loads(data)
            except Exception:                       # the standard path names the problem
                raw = None
            if type(raw) is dict and fast_fields_only(raw):
                return raw, Unchecked(raw["type"], data, binary)
        return super().parse_input(data, binary)

    def forwardable(self, data: dict) -> "Unchecked | None":
        """A JSON data message known by its head (``parse_input``'s rule, the source greeted), while the
        session does not record and its worker has room (``WINDOW``: ``ingest`` does not wait then); the
        route's reader then hands it to ``ingest`` itself and wakes no processor for it."""
        text = data.get("text")
        return None if text is None else self.forwardable_text(text)

    def forwardable_text(self, text: str) -> "Unchecked | None":
        """``forwardable`` of a received text message."""
        if self.recorder is not None or not self._greeted or len(self._pending) >= WINDOW:
            return None
        kind = data_type(text)
        return None if kind is None else Unchecked(kind, text, False)

    def forward(self, parsed: "Unchecked") -> None:
        """A data message to the worker, which validates it (``ingest``, or the route at once for one
        ``forwardable`` gave, and only such: its ``WINDOW`` check is the bound on what waits for the worker
        then; ``forward`` does not wait)."""
        self._send_source(parsed.type, ["chk", parsed.data, parsed.binary], None)
        if self.recorder is not None:               # recording began since it was received: as validated
            self._record_unchecked(parsed)

    async def ingest(self, raw: dict, parsed) -> None:
        while len(self._pending) >= WINDOW:         # backpressure: the source waits for the worker
            self._replied.clear()
            await self._replied.wait()
        if isinstance(parsed, Unchecked):
            self.forward(parsed)
            return None
        self.metrics.of_session(self.name).received()
        if self.recorder is not None:
            from ...protocol.messages import dump_message
            self.recorder.write(dump_message(parsed))
        try:
            packed = msgpack.packb(raw)             # once: kept as it is for a restarted worker
        except (OverflowError, TypeError, ValueError):   # e.g. a 30-digit integer in an unknown field
            from ...protocol.messages import dump_message
            raw = dump_message(parsed)
            packed = msgpack.packb(raw)
        if parsed.type == "hello":
            self.hello = raw
            self._greeted = True
            self._best_lag = None
            self.hand_name = raw.get("hand", self.hand_name)
        kept = raw if parsed.type == "calibration" else None     # the session's state, once it is accepted
        self._send_source(parsed.type, ["src", packed], kept)
        return None

    def _send_source(self, kind: str, body: list, kept: dict | None) -> None:
        """Source message number ``n`` (the next) to the worker: ``body`` is its message without the
        session and the number (kept as it is for a restarted worker)."""
        link = self.link
        n = self._n = self._n + 1
        if not link.owed:                           # (``owe``'s case: it owed nothing until now)
            link.owe()
        self._pending[n] = (kind, body, time.perf_counter(), kept)
        link.active.note(self.sid, time.monotonic())
        link.owed += 1
        self._tell_worker()
        link.send([body[0], self.sid, n, *body[1:]])

    def _record_unchecked(self, parsed: "Unchecked") -> None:
        from ...protocol.messages import SamplesRefused, dump_message
        try:
            self.recorder.write(dump_message(parse_input(parsed.data, parsed.binary)[1]))
        except SamplesRefused as err:
            self.recorder.write(dump_message(err.kept))
        except ProtocolError:
            pass                                    # refused by the worker too, with the reason

    def on_output(self, n: int, head: list, text: str, packed: bytes | None) -> None:
        """An output of source message ``n`` as the worker encoded it, passed on as those bytes."""
        pending = self._pending.get(n)
        kind, seq, _, hand = head
        out = Outgoing.encoded(kind, text, packed)
        if kind == "frame":
            if self._last is not None and seq <= self._last[0]:
                return                              # already passed on (cannot happen without a restart)
            self._last = (seq, out)
            self.hand_name = hand or self.hand_name
            self._pace(head[2])
        self._deliver(out, pending[2] if pending else time.perf_counter())
        self._tell_worker()

    def _pace(self, t: float) -> None:
        """``behind_s`` after a frame of source time ``t``: its arrival here minus ``t`` beyond the least of
        that so far (a step back of the source's clock starts the count again); logged when it passes
        ``BEHIND_WARN_S`` (a session on a costly estimator in a worker of its own on a busy machine)."""
        lag = time.perf_counter() - t
        if self._best_lag is None or lag < self._best_lag or t < self._last_t:
            self._best_lag = lag
        self._last_t = t
        self.behind_s = lag - self._best_lag
        self.metrics.of_session(self.name).behind = self.behind_s     # (the gauge set at the next scrape)
        if self.behind_s > BEHIND_WARN_S and not self._behind_told:
            self._behind_told = True
            log.warning("session %s: its frames come %.1f s behind its source (estimator %s; its hand worker does "
                        "not keep pace)", self.name, self.behind_s, self.config.estimator)
        elif self._behind_told and self.behind_s < BEHIND_WARN_S / 10:
            self._behind_told = False
            log.warning("session %s: its frames keep pace with its source again", self.name)

    def on_reply(self, n: int, errors: list, accepted: bool | None = None) -> None:
        """Source message ``n`` handled: its error replies go to the source. ``accepted``: a message the
        worker validated (``chk``) was not refused whole (it counts as received, as a message validated
        here does)."""
        entry = self._pending.pop(n, None)
        if accepted:
            self.metrics.of_session(self.name).received()
        if entry is not None:
            self.link.owed -= 1
        if entry is not None and entry[0] == "calibration" and not errors:
            self.calibration = entry[3]
        self._answered(errors)

    def on_replies(self, first: int, last: int) -> None:
        """Source messages ``first`` to ``last``, each validated by the worker (``chk``), accepted and without
        error replies: ``on_reply(n, [], True)`` of each, in one go."""
        pending = self._pending
        before = len(pending)
        if last == first:
            pending.pop(first, None)
        else:                                       # (each popped in C)
            _exhaust(map(pending.pop, range(first, last + 1), itertools.repeat(None, last - first + 1)))
        self.link.owed -= before - len(pending)
        self.metrics.of_session(self.name).received(last - first + 1)
        self._answered(())

    def _answered(self, errors) -> None:
        """After replies: their error ``errors`` to the source, after what a new worker could not restore
        (``lost``, as on the bus); the answers and waits that were waiting for them released."""
        if self.lost:
            errors, self.lost = self.lost + list(errors), []
        if errors and self._source_error is not None:
            self._errors.extend(errors)
            self._send_errors_soon()
        if self._answers:
            self._release_answers()
        self._replied.set()

    def answer_in_order(self, answer) -> bool:
        """``answer()`` once every source message sent to the worker so far is answered, after their error
        replies and before those of the later ones, which go on to the worker meanwhile (a ``sync`` used to
        hold the source's later messages here until the worker had answered everything before it: at 1 kHz
        every 64th message, and the frames of the messages held back came milliseconds late). ``False`` once
        ``ingest_backlog_messages`` answers and replies wait already (for the worker, or to be sent to a
        source that does not read them): the caller then waits for ``settled`` as before, so
        the source's later messages wait in its backlog, whose bounds refuse a flood (syncs queued here
        unbounded would have grown the web process's memory without limit while the worker is behind)."""
        if len(self._answers) + len(self._errors) >= self.settings.ingest_backlog_messages:
            return False                            # (``_errors``: replies released and not yet sent, a source
                                                    # that reads nothing blocks their sending)
        self._answers.append((self._n, answer))
        self._release_answers()
        return True

    def _release_answers(self) -> None:
        """The answers whose messages are all answered, into the source's queue of replies (``_pending`` is in
        the order of its numbers)."""
        answers, released = self._answers, False
        while answers and (not self._pending or next(iter(self._pending)) > answers[0][0]):
            self._errors.append(answers.popleft()[1])
            released = True
        if released:
            self._send_errors_soon()

    def _send_errors_soon(self) -> None:
        if self._error_task is None or self._error_task.done():
            errors = self._errors                   # answers first in line written at once where they can be
            while errors and self._answered_now(errors[0]):   # (``routes.ingest.SyncAnswer.now``): no task
                errors.popleft()
            if not errors:
                self._replied.set()                 # (as ``_send_errors`` at its end)
                return
            self._error_task = asyncio.get_running_loop().create_task(self._send_errors())

    @staticmethod
    def _answered_now(item) -> bool:
        now = getattr(item, "now", None) if callable(item) else None
        if now is None:
            return False
        try:
            return now()
        except Exception:                           # a defect: answered the awaited way (which says why)
            return False

    async def _send_errors(self) -> None:
        while self._errors:
            item = self._errors.popleft()
            if callable(item):                      # an answer (``answer_in_order``)
                try:
                    await item()
                    continue
                except Exception as err:            # a defect (a closed connection is the answer's own affair):
                    # answered as a defect in a message's processing is (``replies.failure_reply``: logged in
                    # one line, ``internal_error`` in its place), and the later replies go on
                    log.warning("session %s: %s while answering its source: %s", self.name, type(err).__name__,
                                str(err)[:200])
                    item = ["internal_error", f"{type(err).__name__} while answering the source; answer dropped"]
            code, detail, *samples = item
            try:
                await self._source_error(code, detail, *samples)
            except Exception:                       # the source went away: its error replies with it
                self._errors = collections.deque(x for x in self._errors if callable(x))
        self._replied.set()

    async def settled(self) -> None:
        """Every message ingested so far was answered and its error reply sent: what a ``sync`` waits for
        when its answer cannot wait in its place (``answer_in_order``), and a ``hello``."""
        while self._pending or self._errors or (self._error_task is not None and not self._error_task.done()):
            self._replied.clear()
            await self._replied.wait()

    # -- configuration (from a thread of the API) -------------------------------------------------
    def _request(self, kind: str, body) -> dict:
        n, done, box = next(self._config_n), threading.Event(), []
        request = [kind, self.sid, n, body]
        self._config_waits[n] = (done, box, request)
        self._to_worker(request)
        if not done.wait(CONFIG_WAIT_S):
            self._config_waits.pop(n, None)
            raise ValueError(f"the hand worker did not answer within {CONFIG_WAIT_S:g} s; the change may apply later")
        result, error = box
        if error is not None:
            raise ValueError(error)
        return result

    def on_config_reply(self, n: int, result, error) -> None:
        waiting = self._config_waits.pop(n, None)
        if waiting is not None:
            waiting[1].extend((result, error))
            waiting[0].set()

    def update_config(self, change) -> dict:
        """Validated here (a bad change changes nothing), applied by the worker (which may compile the
        estimator's kernels first, in a separate process, while every session goes on), then kept here.
        A change to a costly estimator moves the session with it to a worker of its own first; once it is
        on the compiled chain again, it goes back to a shared worker (module docstring)."""
        pool = self.link.pool
        with self._configuring:                     # validated against the configuration it changes
            spec, params, gestures, record = self.checked_config(change)
            remote = SessionConfigChange.model_validate(change).model_dump(exclude_none=True, exclude={"record"})
            if remote:
                try:
                    if pool.isolates(spec) and not self.link.isolated:   # (past the limit it stays: logged)
                        moved = {"estimator": spec.name, "estimator_params": params, "gestures": gestures.model_dump()}
                        pool.call(pool.move(self, isolated=True, config=moved), 2 * CONFIG_WAIT_S)
                    applied = self._request("cfg", remote)
                    self.config = SessionConfig.model_validate({**applied, "record": record})
                finally:
                    now = EstimatorSpec.of(self.config.estimator, self.config.estimator_params)
                    if self.link.isolated and not pool.isolates(now):
                        pool.call(pool.move(self, isolated=False), CONFIG_WAIT_S + CATCH_UP_WAIT_S)
            else:
                self.config = self.config.model_copy(update={"record": record})
            self._apply_recording()
            return self.config.model_dump()

    def enrol(self, segments: list) -> dict:
        """Fitted by the worker, which holds the recent frames (``LiveSession.enrol``)."""
        with self._configuring:
            result = self._request("enrol", segments)
            self.config = self.config.model_copy(update={"gestures": GestureSettings.model_validate(result["gestures"])})
        return result

    def summary(self) -> dict:
        out = super().summary()
        out["hand"] = self.hand_name or "right"
        out["worker"] = {"slot": self.link.slot, "pid": self.link.pid, "own": self.link.isolated,
                         "restarts": self.restarts, "resent_after_restart": self.resent, "moves": self.moves}
        oldest = min((entry[2] for entry in self._pending.values()), default=None)   # a worker that answers nothing
        out["behind_s"] = max(self.behind_s, 0.0 if oldest is None else time.perf_counter() - oldest)
        return out

    def close(self) -> None:
        super().close()
        if self.link.sessions.pop(self.sid, None) is not None:
            self.link.owed -= len(self._pending)
        if not self.link.pool.closing:
            self._to_worker(["close", self.sid])
            if self.link.isolated:                  # its own worker has nothing left to do
                link, pool = self.link, self.link.pool
                pool.loop.call_soon_threadsafe(lambda: pool.loop.create_task(pool.retire(link)))
