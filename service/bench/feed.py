"""A real hand worker process fed over its socket (``python -m service.bench.feed HANDS SECONDS BATCH MODE``):
the hand worker's CPU per hand and second of data when its messages come in small batches with idle time
between, as at a moderate load, against the same messages queued up, as when it is behind.

``HANDS`` sessions of ``bench cpu``'s batched recording (``SECONDS`` long, seed 0) are opened on one
``python -m service.api.hands.worker`` process (``hands.worker``, the embedded service's worker, started
as the web process starts it, at nice 0), their messages interleaved hand after hand and written in
batches of ``BATCH`` messages (the web process's unit, ``WorkerLink``), either

* ``paced``: each batch only once the worker has answered every message of the one before (it waits on
  its socket between batches, as a worker that keeps up waits between the web process's writes), or
* ``queued``: every batch written at once (a thread reads the answers): the worker reads many batches at a
  time and never waits, as one that is behind;
* ``inprocess``: no process and no socket: the batches through ``Worker.handle_batch`` in this process, each
  write dropped (``bench cpu --worker``'s harness, many sessions), its CPU time (``time.process_time``).

Printed: the worker's CPU time (user + system, ``/proc``) from after the sessions' first messages to the
last answer, per hand and second of data. The worker's kernels are loaded by a session over the first
second before that (then closed). Linux only (``/proc``)."""
from __future__ import annotations

import json
import operator
import os
import socket
import subprocess
import sys
import threading
import time

from ..api.hands.worker import frame, whole_batches
from .cpu import recording_lines, worker_messages


class _Feed:
    def __init__(self):
        self.sock, theirs = socket.socketpair()
        settings = {"estimator": "chain", "output_rate_hz": 90.0, "hand_worker_nice": 0, "preload_kernels": False}
        self.proc = subprocess.Popen([sys.executable, "-m", "service.api.hands.worker", str(theirs.fileno()),
                                      json.dumps(settings)], pass_fds=[theirs.fileno()])
        theirs.close()
        self.replies = 0
        self.changed = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        buf = bytearray()
        while True:
            try:
                chunk = self.sock.recv(1 << 16)
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            answered = sum(1 if m[0] == "rep" else m[3] - m[2] + 1 if m[0] == "reps" else 0
                           for batch in whole_batches(buf) for m in batch)
            if answered:
                with self.changed:
                    self.replies += answered
                    self.changed.notify_all()

    def send(self, messages: list) -> None:
        self.sock.sendall(frame(messages))

    def until(self, replies: int) -> None:
        with self.changed:
            if not self.changed.wait_for(lambda: self.replies >= replies, timeout=120):
                raise RuntimeError(f"the worker answered {self.replies} of {replies} messages")

    def cpu_s(self) -> float:
        fields = open(f"/proc/{self.proc.pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()
        self.sock.close()


def _in_process(base: list, hands: int, batch: int) -> float:
    """``inprocess``: the sessions' batches through ``Worker.handle_batch`` here (``cpu._pass_worker``'s
    worker, many sessions), after one session through the whole recording that loads the kernels; CPU seconds."""
    from ..api.config import ServiceSettings
    from ..api.hands import worker as hands_worker
    from ..api.server import serving_gc
    from .cpu import _Discarded

    service = ServiceSettings(estimator="chain", record_all=False, record_dir=None)
    for sids, stream in (((0,), base), (range(1, hands + 1), base)):
        worker = hands_worker.Worker(_Discarded(), service)
        for sid in sids:
            worker.hands[sid] = hands_worker.OwnedHand(f"hand{sid}", service, worker.metrics, None)
        worker.handle_batch([[base[0][0], sid, *base[0][2:]] for sid in sids])
        messages = [[m[0], sid, *m[2:]] for m in stream[1:] for sid in sids]
        def handle_all() -> None:
            for i in range(0, len(messages), batch):
                worker.handle_batch(messages[i:i + batch])
                worker.send()
        with serving_gc():
            t0 = time.process_time()
            # the measured pass through ``operator.call``, for callgrind (README, "CPU per hand")
            if sids == (0,):
                handle_all()
            else:
                operator.call(handle_all)
            cpu = time.process_time() - t0
    return cpu


def run(hands: int, seconds: float, batch: int, mode: str) -> dict:
    if mode not in ("paced", "queued", "inprocess"):
        raise ValueError(f"mode must be paced, queued or inprocess, not {mode!r}")
    base = worker_messages(recording_lines(seconds, seed=0, batched=True))
    if mode == "inprocess":
        cpu = _in_process(base, hands, batch)
        return {"hands": hands, "seconds": seconds, "batch": batch, "mode": mode, "worker_cpu_s": cpu, "wall_s": cpu,
                "cpu_ms_per_hand_s": cpu / hands / seconds * 1e3}
    feed = _Feed()
    try:
        warm = [[m[0], 0, *m[2:]] for m in base[: max(1, int(len(base) / seconds))]]
        feed.send([["open", 0, "warm", None]])
        feed.send(warm)
        feed.until(len(warm))
        feed.send([["close", 0]])
        sids = range(1, hands + 1)
        for sid in sids:
            feed.send([["open", sid, f"hand{sid}", None]])
        done = len(warm)
        feed.send([[base[0][0], sid, *base[0][2:]] for sid in sids])    # each hand built and its hello handled
        done += hands
        feed.until(done)
        stream = [[m[0], sid, *m[2:]] for m in base[1:] for sid in sids]
        c0, t0 = feed.cpu_s(), time.perf_counter()
        for i in range(0, len(stream), batch):
            feed.send(stream[i:i + batch])
            if mode == "paced":
                feed.until(done + min(i + batch, len(stream)))
        feed.until(done + len(stream))
        time.sleep(0.05)                            # (the worker's last send counted)
        cpu, wall = feed.cpu_s() - c0, time.perf_counter() - t0
    finally:
        feed.close()
    return {"hands": hands, "seconds": seconds, "batch": batch, "mode": mode, "worker_cpu_s": cpu, "wall_s": wall,
            "cpu_ms_per_hand_s": cpu / hands / seconds * 1e3}


def main(argv: list[str]) -> int:
    if len(argv) != 4:
        print(__doc__.split("\n\n")[0], file=sys.stderr)
        return 2
    r = run(int(argv[0]), float(argv[1]), int(argv[2]), argv[3])
    print(f"{r['hands']} hands, batches of {r['batch']}, {r['mode']}: the worker's CPU {r['worker_cpu_s']:.2f} s over "
          f"{r['wall_s']:.2f} s, {r['cpu_ms_per_hand_s']:.1f} ms per hand and second of data")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
