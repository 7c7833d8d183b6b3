"""The embedded service's hand worker processes (``service.api.hands``), against a real server
(uvicorn on a free localhost port) with real WebSocket clients: a killed worker is restarted and its
session goes on while the other worker's session never notices; a session switched to an estimator
whose kernels this worker has not loaded does not stall another session of the same worker. Waits are
for events and counts; timeouts only bound a failure."""
import asyncio
import os
import signal
import time

import pytest

from clients.client import Publisher, Subscription, rest
from clients.glove import source_messages
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.session import SimConfig

SOURCE, VIEWER, ADMIN = "src-token-w", "view-token-w", "admin-token-w"
RATE_HZ = 90.0


def _settings(workers: int, **extra) -> ServiceSettings:
    return ServiceSettings.load(port=0, admin_token=ADMIN, tokens={SOURCE: "source", VIEWER: "viewer"},
                                hand_workers=workers, subscriber_queue_frames=10_000, output_rate_hz=RATE_HZ, **extra)


def _sessions(server) -> dict:
    return {s["session"]: s for s in rest(server.url, "GET", "/v1/sessions", ADMIN)[1]}


async def _until(condition, what: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        await asyncio.sleep(0.02)


async def _collect(sub: Subscription, frames: list) -> None:
    async for m in sub:
        if m["type"] == "frame":
            frames.append(m)


def _messages(hand: str, seconds: float, seed: int) -> list[tuple[float, dict]]:
    return source_messages(SimConfig(motion="sequence", hand=hand, noise="white", seed=seed, duration_s=seconds))


async def _stream(url: str, session: str, hand: str, msgs, paced: bool, sync_every: int = 50,
                  stop: asyncio.Event | None = None) -> None:
    """One glove: every message in order (in real time when ``paced``), a sync every ``sync_every``."""
    pub = Publisher(url, session, SOURCE, hand=hand, source="worker-test")
    t0_wall, t0 = time.perf_counter(), msgs[0][0]
    for k, (arrival, m) in enumerate(msgs):
        if stop is not None and stop.is_set():
            break
        if paced:
            await asyncio.sleep(max(0.0, t0_wall + (arrival - t0) - time.perf_counter()))
        await pub.send(m)
        if k % sync_every == sync_every - 1:
            await pub.sync()
    await pub.close()                               # syncs: every message is handled when it returns


async def _finish(server, streams, frames: dict, subs: dict, tasks) -> dict:
    """The streams to their end, every frame the service sent received; the sessions' summaries."""
    await asyncio.gather(*streams)
    summary = await asyncio.to_thread(_sessions, server)
    await _until(lambda: all(len(frames[n]) >= summary[n]["frames_out"] for n in frames), "every frame the service sent")
    for sub in subs.values():
        await sub.close()
    for task in tasks:
        task.cancel()
    return summary


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "stopped"])
def test_a_dead_or_stuck_hand_worker_s_session_moves_on_while_the_other_worker_s_does_not_notice(how):
    """SIGKILL: the worker is gone; SIGSTOP: it is stuck, owes answers and is killed after
    ``hand_worker_stall_s``. Either way its session continues on the other worker."""
    msgs = {"right": _messages("right", 6.0, 1), "left": _messages("left", 6.0, 2)}
    with ServerThread(_settings(2, hand_worker_stall_s=5.0)) as server:
        async def run():
            frames = {"a": [], "b": []}
            subs = {name: Subscription(server.ws_url, name, VIEWER) for name in frames}
            tasks = [asyncio.create_task(_collect(subs[n], frames[n])) for n in frames]
            await _until(lambda: all(s.server_hello is not None for s in subs.values()), "the subscriptions")
            streams = [asyncio.create_task(_stream(server.url, "a", "right", msgs["right"], paced=False)),
                       asyncio.create_task(_stream(server.url, "b", "left", msgs["left"], paced=False))]
            await _until(lambda: len(frames["a"]) >= 100, "100 frames of session a")
            workers = {n: s["worker"] for n, s in (await asyncio.to_thread(_sessions, server)).items()}
            assert workers["a"]["pid"] != workers["b"]["pid"]        # one session per worker
            killed_at = len(frames["a"])
            os.kill(workers["a"]["pid"], how)
            summary = await _finish(server, streams, frames, subs, tasks)
            return frames, killed_at, workers, summary
        frames, killed_at, workers, summary = asyncio.run(run())
    a, b = frames["a"], frames["b"]
    # session a: continued by a new process of its worker slot, from the last estimate, in order
    assert summary["a"]["worker"]["restarts"] == 1 and summary["a"]["worker"]["pid"] != workers["a"]["pid"]
    assert len(a) > killed_at + 100, "session a's frames did not go on after its worker was killed"
    assert all(x["seq"] < y["seq"] and x["t"] < y["t"] for x, y in zip(a, a[1:]))
    assert {f["hand"] for f in a} == {"right"}
    assert a[-1]["t"] > msgs["right"][-1][0] - 0.2            # to the end of its source's data
    # session b, on the other worker: every frame, in order, no gap, none of a's
    assert summary["b"]["worker"]["restarts"] == 0
    assert [f["seq"] for f in b] == list(range(1, len(b) + 1)) and len(b) == summary["b"]["frames_out"]
    assert {f["hand"] for f in b} == {"left"}


def test_a_stopped_worker_s_sessions_move_long_before_the_stall_limit_while_another_worker_streams_on():
    """Sessions a and c on one worker, b on the other, all in real time. The first worker is stopped
    (SIGSTOP) with the stall limit at its default (10 s): since the other worker goes on answering, the
    stopped one counts as stuck after ``hand_worker_lag_s`` (1 s), so a and c continue on the other
    worker before b has had 5 s of frames (at the stall limit it would be 10 s: 900 frames)."""
    msgs = {"a": _messages("right", 14.0, 1), "b": _messages("left", 14.0, 2), "c": _messages("right", 14.0, 3)}
    hands = {"a": "right", "b": "left", "c": "right"}
    with ServerThread(_settings(2)) as server:
        async def run():
            frames = {n: [] for n in msgs}
            subs = {n: Subscription(server.ws_url, n, VIEWER) for n in frames}
            tasks = [asyncio.create_task(_collect(subs[n], frames[n])) for n in frames]
            await _until(lambda: all(s.server_hello is not None for s in subs.values()), "the subscriptions")
            streams = []
            for n in ("a", "b", "c"):                    # opened in this order: a and c share a worker
                streams.append(asyncio.create_task(_stream(server.url, n, hands[n], msgs[n], paced=True)))
                await _until(lambda: len(frames[n]) >= 1, f"session {n}'s first frame")
            await _until(lambda: all(len(f) >= 45 for f in frames.values()), "45 frames of each session")
            workers = {n: s["worker"] for n, s in (await asyncio.to_thread(_sessions, server)).items()}
            assert workers["a"]["pid"] == workers["c"]["pid"] != workers["b"]["pid"]
            os.kill(workers["a"]["pid"], signal.SIGSTOP)
            b_at_stop = len(frames["b"])
            applied = {n: frames[n][-1]["status"]["reference_poses"]["applied"] for n in ("a", "c")}

            def resumed(n):                              # a frame of the new worker: the resume's reference pose
                return any(f["status"]["reference_poses"]["applied"] > applied[n] for f in frames[n][-50:])
            await _until(lambda: resumed("a") and resumed("c"), "sessions a and c on the other worker")
            b_meanwhile = len(frames["b"]) - b_at_stop
            summary = await _finish(server, streams, frames, subs, tasks)
            return frames, b_meanwhile, summary
        frames, b_meanwhile, summary = asyncio.run(run())
    assert b_meanwhile < 5 * RATE_HZ, f"session b got {b_meanwhile} frames before a and c went on"
    for n in ("a", "c"):
        assert summary[n]["worker"]["restarts"] == 1
        assert all(x["seq"] < y["seq"] for x, y in zip(frames[n], frames[n][1:]))
    for n, f in frames.items():
        assert {x["hand"] for x in f} == {hands[n]}
    b = frames["b"]                                      # the other worker's session: every frame, in order
    assert summary["b"]["worker"]["restarts"] == 0
    assert [f["seq"] for f in b] == list(range(1, len(b) + 1)) and len(b) == summary["b"]["frames_out"]


def test_switching_a_session_to_an_estimator_not_loaded_in_its_worker_does_not_stall_another_session():
    """Both sessions on one worker. While session b's switch to ``inertial`` is pending (its kernels are
    compiled by a separate process first, or loaded by a thread of the worker when they are cached) and
    just after it, session a, streaming in real time, gets every frame of whole 100 ms windows of its
    stream time. (A cached load takes a fraction of a second: the windows counted run until 0.5 s of
    a's stream time after the reply, so that a short switch is judged too.) Without a worker of its own for
    the switched session (``hand_worker_isolate``; ``tests/test_hand_pool.py`` has that case): the
    switch happens in the worker that serves a."""
    # (without the kernels loaded ahead, which would leave no load to the switch)
    with ServerThread(_settings(1, hand_worker_isolate=False, preload_kernels=False)) as server:
        async def run():
            frames: list = []
            sub = Subscription(server.ws_url, "a", VIEWER)
            collector = asyncio.create_task(_collect(sub, frames))
            await _until(lambda: sub.server_hello is not None, "the subscription")
            stop = asyncio.Event()
            a = asyncio.create_task(_stream(server.url, "a", "right", _messages("right", 20.0, 3), paced=True,
                                            sync_every=1_000_000, stop=stop))
            await _stream(server.url, "b", "left", _messages("left", 1.0, 4), paced=False)
            await _until(lambda: len(frames) >= 20, "session a's first frames")
            before = len(frames)
            status, body = await asyncio.to_thread(rest, server.url, "PUT", "/v1/sessions/b/config", ADMIN,
                                                   {"estimator": "inertial"}, timeout_s=300.0)
            replied_t = frames[-1]["t"]
            await _until(lambda: frames[-1]["t"] >= replied_t + 0.5, "session a's frames after the switch")
            during = frames[before:]
            stop.set()
            await a
            await sub.close()
            collector.cancel()
            return status, body, during, await asyncio.to_thread(_sessions, server)
        status, body, during, summary = asyncio.run(run())
    assert status == 200 and body["estimator"] == "inertial", body
    assert summary["b"]["config"]["estimator"] == "inertial"
    windows: dict[int, int] = {}
    for f in during:
        windows[int(f["t"] // 0.1)] = windows.get(int(f["t"] // 0.1), 0) + 1
    full = [w for w, count in windows.items() if count >= int(0.1 * RATE_HZ)]
    assert len(full) >= 3, f"session a's frames while b switched, per 100 ms window: {sorted(windows.items())}"
    assert summary["a"]["worker"]["pid"] == summary["b"]["worker"]["pid"]


def _serve_as_from_a_terminal(port: int, **kwargs):
    """``fingertrack serve`` in a process group of its own, started as a terminal's shell starts it: with
    SIGINT at its default. A process that inherits SIGINT ignored keeps ignoring a Ctrl-C (uvicorn
    shuts down on it and exits 0), and this process may have it ignored: a shell without job control
    starts background commands so, and pytest-xdist's workers inherit that. A handler set here is
    reset to the default in the child when it executes the service."""
    import subprocess
    import sys

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)],
                                start_new_session=True, **kwargs)
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("spare", [False, True])
def test_ctrl_c_on_serve_ends_it_and_its_workers_in_order_without_a_traceback(spare):
    """A terminal's Ctrl-C reaches the service's process group: the web process closes its hand workers
    in order, so neither a worker's KeyboardInterrupt traceback nor a 'hand worker ... ended' warning (a
    crash taken for real) appears, and no worker is left behind. With the spare worker on (the
    default), Ctrl-C comes as soon as the spare exists, while it is still importing (before its
    ``main`` ignores SIGINT): each worker runs in a process group of its own, so the Ctrl-C does not
    reach it (it reached the spare and killed it with a traceback before)."""
    import subprocess
    import sys

    from clients.client import wait_healthy
    from service.api.server import free_port

    port = free_port()
    env = {**os.environ, "FINGERTRACK_HAND_WORKER_SPARE": "true" if spare else "false"}
    proc = _serve_as_from_a_terminal(port, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        wait_healthy(f"http://127.0.0.1:{port}", 300.0, alive=lambda: proc.poll() is None)

        def workers_now() -> list[str]:
            return subprocess.run(["pgrep", "-P", str(proc.pid), "-f", "service.api.hands.worker"],
                                  capture_output=True, text=True).stdout.split()

        workers = workers_now()
        give_up = time.monotonic() + 120.0                              # a failure bound only
        while spare and len(workers) < 3 and proc.poll() is None and time.monotonic() < give_up:
            time.sleep(0.01)
            workers = workers_now()
        assert len(workers) == (3 if spare else 2), workers
        os.killpg(proc.pid, signal.SIGINT)
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, output            # the CLI's exit status after Ctrl-C (128 + SIGINT)
    assert "Traceback" not in output and "KeyboardInterrupt" not in output, output
    assert "ended with" not in output, output
    for pid in workers:
        with pytest.raises(ProcessLookupError):
            os.kill(int(pid), 0)


def test_json_and_messagepack_subscribers_of_a_worker_session_get_the_same_frames_also_when_one_joins_mid_stream():
    """The worker encodes a session's frames once for every subscriber (JSON always, MessagePack once a
    subscriber reads it) and the web process passes those bytes on: a JSON and a MessagePack subscriber
    from the start, and a MessagePack subscriber joining mid-stream (whose first frames the worker
    wrote as JSON only), receive the same frames, value for value; the session's summary shows the last
    frame's status."""
    msgs = _messages("left", 2.0, 11)

    async def run(server):
        frames = {"json": [], "packed": [], "late": []}
        subs = {"json": Subscription(server.url, "fmt", VIEWER), "packed": Subscription(server.url, "fmt", VIEWER, binary=True)}
        tasks = [asyncio.create_task(_collect(subs[k], frames[k])) for k in subs]
        await _until(lambda: all(s.server_hello is not None for s in subs.values()), "the subscriptions' hellos")
        stream = asyncio.create_task(_stream(server.url, "fmt", "left", msgs, paced=True))
        await _until(lambda: len(frames["json"]) >= 20, "the first frames")
        subs["late"] = Subscription(server.url, "fmt", VIEWER, binary=True)
        tasks.append(asyncio.create_task(_collect(subs["late"], frames["late"])))
        summary = await _finish(server, [stream], {"fmt": frames["json"]}, subs, [])
        await _until(lambda: len(frames["packed"]) >= summary["fmt"]["frames_out"], "every frame in MessagePack")
        for task in tasks:
            task.cancel()
        return frames, summary["fmt"]

    with ServerThread(_settings(1)) as server:
        frames, summary = asyncio.run(run(server))
    by_seq = {f["seq"]: f for f in frames["json"]}
    assert len(frames["json"]) == summary["frames_out"] > 90
    assert frames["packed"] == frames["json"]
    assert frames["late"] and frames["late"] == [by_seq[f["seq"]] for f in frames["late"]]
    assert summary["status"] == frames["json"][-1]["status"]
    assert {f["hand"] for f in frames["json"]} == {"left"}


def _gone(pid: int) -> bool:
    """The process has ended (no longer there, or a zombie waiting for its new parent to reap it)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (FileNotFoundError, ProcessLookupError):
        return True


@pytest.mark.skipif(not os.path.isdir("/proc") or not hasattr(os, "killpg"), reason="Linux process table")
def test_hand_workers_end_when_the_web_process_is_killed_also_a_stopped_one():
    """SIGKILL to ``serve`` (no chance to close its workers): the running worker ends at the end of its
    input, and the stopped one, which never reads it, is killed by the kernel with its parent
    (``PR_SET_PDEATHSIG``); before, a stopped or stuck worker stayed for good."""
    import subprocess
    import sys

    from clients.client import wait_healthy
    from service.api.server import free_port

    port = free_port()
    proc = _serve_as_from_a_terminal(port, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        wait_healthy(f"http://127.0.0.1:{port}", 300.0, alive=lambda: proc.poll() is None)
        workers = [int(p) for p in subprocess.run(["pgrep", "-P", str(proc.pid), "-f", "service.api.hands.worker"],
                                                  capture_output=True, text=True).stdout.split()]
        assert len(workers) == 2, workers
        os.kill(workers[0], signal.SIGSTOP)
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 60.0          # bounds a failure only
        while not all(_gone(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        left = [pid for pid in workers if not _gone(pid)]
        assert not left, f"hand workers left after their web process was killed: {left}"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        for pid in workers:
            if not _gone(pid):
                os.kill(pid, signal.SIGKILL)


def _answers(reply: list, n: int) -> bool:
    """Whether a worker's message is the reply to message ``n`` (a ``rep``, or a ``reps`` run covering it)."""
    return (reply[0] == "rep" and reply[2] == n) or (reply[0] == "reps" and reply[2] <= n <= reply[3])


class _Peer:
    """A ``hands.worker.Worker`` run by a thread of this process, and the web process's end of its socket."""

    def __init__(self, preload: bool = False):
        import socket
        import threading

        from service.api.hands import worker as hands_worker

        self.mod = hands_worker
        self.ours, theirs = socket.socketpair()
        self.worker = hands_worker.Worker(theirs, _settings(1))
        if preload:                                 # as the process's main does once it has said it is ready
            self.worker.preload()
        self.thread = threading.Thread(target=self.worker.run, daemon=True)
        self.thread.start()
        self.received: list = []
        self.writes: list[list] = []
        """the worker's messages as its writes grouped them"""
        self._buffer = bytearray()

    def send(self, messages: list) -> None:
        """Write ``messages`` as one frame, reading the worker's outputs meanwhile, as the web process does: the
        worker writes them with a blocking send, so a peer that only wrote while those outputs filled the socket
        would wait for the worker while the worker waited for it."""
        import select

        data = memoryview(self.mod.frame(messages))
        while data:
            readable, writable, _ = select.select([self.ours], [self.ours], [], 120.0)     # a bound for a failure only
            assert readable or writable, "the worker neither read nor wrote for 120 s"
            if readable:
                self._read("the end of a send")
            if writable:
                data = data[self.ours.send(data):]

    def until(self, condition, what: str) -> None:
        while not condition():
            self._read(what)

    def _read(self, what: str) -> None:
        """One read of the worker's outputs (waiting for them up to 120 s), its whole messages taken."""
        import msgpack

        self.ours.settimeout(120.0)                 # a bound for a failure only
        try:
            chunk = self.ours.recv(1 << 20)
        except TimeoutError:
            raise AssertionError(f"nothing from the worker for 120 s waiting for {what}") from None
        assert chunk, f"the worker ended before {what}"
        self._buffer.extend(chunk)
        while len(self._buffer) >= 4 and len(self._buffer) >= 4 + (size := self.mod.HEADER.unpack_from(self._buffer)[0]):
            self.writes.append(msgpack.unpackb(bytes(self._buffer[4:4 + size])))
            self.received.extend(self.writes[-1])
            del self._buffer[:4 + size]

    def replies(self, sid: int) -> list:
        """The session's replies in order, a ``reps`` run as the ``rep`` of each of its messages."""
        out = []
        for m in self.received:
            if m[0] == "rep" and m[1] == sid:
                out.append(m)
            elif m[0] == "reps" and m[1] == sid:
                out.extend(["rep", sid, n, [], True] for n in range(m[2], m[3] + 1))
        return out

    def close(self) -> None:
        self.ours.close()
        self.thread.join(60.0)


def test_a_worker_serves_its_other_sessions_while_a_thread_loads_an_estimator_s_kernels(monkeypatch):
    """The worker loads a switched-to estimator's kernels in a thread (on its main thread, loading
    ``inertial`` from the cache stopped its other sessions for 130 ms): while the loading is held,
    another session's source messages are answered, frames included; the change applies once it is
    loaded, and not before."""
    import threading

    from service.api import sessions
    from service.api.hands import worker as hands_worker

    entered, release, loaded = threading.Event(), threading.Event(), set()

    def held_warm(name, params=None):
        entered.set()
        assert release.wait(120.0), "the test never released the loading"
        loaded.add(name)
    monkeypatch.setattr(hands_worker, "warm", held_warm)
    monkeypatch.setattr(hands_worker, "is_warm", lambda name: name != "vector" or name in loaded)
    monkeypatch.setattr(hands_worker, "needs_compiling", lambda name: False)    # in the cache: no process
    monkeypatch.setattr(sessions, "warm_ahead", lambda name, params=None: None)
    peer = _Peer()
    try:
        msgs = [m for _, m in _messages("right", 1.0, 5)]
        peer.send([["open", 1, "a", None], ["open", 2, "b", None], ["cfg", 2, 1, {"estimator": "vector"}]])
        assert entered.wait(120.0), "the kernels' loading never began"
        peer.send([["src", 1, n, m] for n, m in enumerate(msgs, 1)])
        peer.until(lambda: len(peer.replies(1)) == len(msgs), "session a's replies")
        assert any(m[0] == "out" and m[1] == 1 and m[3][0] == "frame" for m in peer.received)
        assert not any(m[0] == "cfgrep" for m in peer.received)      # b's change waits for its kernels
        release.set()
        peer.until(lambda: any(m[0] == "cfgrep" for m in peer.received), "b's change")
        reply, = [m for m in peer.received if m[0] == "cfgrep"]
        assert reply[1:3] == [2, 1] and reply[3]["estimator"] == "vector" and reply[4] is None, reply
    finally:
        release.set()
        peer.close()


def test_a_worker_loads_the_cached_estimators_kernels_before_any_switch_and_a_switch_meanwhile_waits_for_them(monkeypatch):
    """``preload_kernels``: once ready, a worker loads the kernels of the estimators found in the disk cache
    in a thread, one after another, before any session asks for them, while it serves its sessions; a
    change to one of them that comes meanwhile waits for that load (it starts no second one) and applies
    once that one is loaded, while the next still loads."""
    import threading

    from service.api import sessions
    from service.api.hands import worker as hands_worker

    entered = {"vector": threading.Event(), "ekf": threading.Event()}
    release = {"vector": threading.Event(), "ekf": threading.Event()}
    loads, loaded = [], set()

    def held_warm(name, params=None):
        loads.append(name)
        entered[name].set()
        assert release[name].wait(600.0), "the test never released the loading"   # (past the 120 s a wait for the worker takes)
        loaded.add(name)
    monkeypatch.setattr(hands_worker, "cached_not_warm", lambda: ["vector", "ekf"])
    monkeypatch.setattr(hands_worker, "warm", held_warm)
    monkeypatch.setattr(hands_worker, "is_warm", lambda name: name not in entered or name in loaded)
    monkeypatch.setattr(hands_worker, "needs_compiling", lambda name: False)
    monkeypatch.setattr(sessions, "warm_ahead", lambda name, params=None: None)
    peer = _Peer(preload=True)
    try:
        assert entered["vector"].wait(120.0), "the cached kernels' loading never began"   # no session, no change yet
        msgs = [m for _, m in _messages("right", 1.0, 5)]
        peer.send([["open", 1, "a", None], ["open", 2, "b", None], ["cfg", 2, 1, {"estimator": "vector"}]])
        peer.send([["src", 1, n, m] for n, m in enumerate(msgs, 1)])
        peer.until(lambda: len(peer.replies(1)) == len(msgs), "session a's replies")
        assert any(m[0] == "out" and m[1] == 1 and m[3][0] == "frame" for m in peer.received)
        assert not any(m[0] == "cfgrep" for m in peer.received)      # b's change waits for the load under way
        release["vector"].set()
        peer.until(lambda: any(m[0] == "cfgrep" for m in peer.received), "b's change")
        reply, = [m for m in peer.received if m[0] == "cfgrep"]
        assert reply[1:3] == [2, 1] and reply[3]["estimator"] == "vector" and reply[4] is None, reply
        assert not release["ekf"].is_set()          # applied while the next one still loads
        assert entered["ekf"].wait(120.0) and loads == ["vector", "ekf"]   # each loaded once, ahead of the change
    finally:
        for event in release.values():
            event.set()
        peer.close()


def test_a_worker_serves_its_other_sessions_while_a_thread_builds_a_moved_in_session_s_hand(monkeypatch):
    """A session opened on a worker (new, moved in from another worker, or after a restart) has its hand
    built by a thread (10-20 ms of the interpreter on the main thread would stop the worker's other
    sessions): while b's build is held, a's source messages are answered; b's messages, sent meanwhile,
    are answered after it, in order, with b's frames continuing from its state's ``seq``."""
    import threading

    from service.api.hands import worker as hands_worker

    entered, release = threading.Event(), threading.Event()

    class HeldHand(hands_worker.OwnedHand):
        def __init__(self, name, settings, metrics, state):
            if name == "b":
                entered.set()
                assert release.wait(120.0), "the test never released the build"
            super().__init__(name, settings, metrics, state)
    monkeypatch.setattr(hands_worker, "OwnedHand", HeldHand)
    peer = _Peer()
    try:
        msgs = [m for _, m in _messages("right", 1.0, 6)]
        hello = {"type": "hello", "protocol": 1, "hand": "right", "source": "worker-test"}
        state = {"session": "b", "seq": 500, "t": -1.0, "angles": None, "hello": hello,
                 "calibration": None, "config": {"estimator": "chain", "estimator_params": {}}}
        peer.send([["open", 1, "a", None], ["src", 1, 1, hello]])
        peer.until(lambda: len(peer.replies(1)) == 1, "a's hello answered")
        peer.send([["open", 2, "b", state]])
        assert entered.wait(120.0), "b's build never began"
        peer.send([["src", 2, n, m] for n, m in enumerate(msgs, 1)])
        peer.send([["src", 1, n, m] for n, m in enumerate(msgs, 2)])
        peer.until(lambda: len(peer.replies(1)) == len(msgs) + 1, "a's replies")
        assert peer.replies(2) == []                # b's wait for its hand
        release.set()
        peer.until(lambda: len(peer.replies(2)) == len(msgs), "b's replies")
        assert [m[2] for m in peer.replies(2)] == list(range(1, len(msgs) + 1))             # in order
        seqs = [m[3][1] for m in peer.received if m[0] == "out" and m[1] == 2 and m[3][0] == "frame"]
        assert seqs and seqs[0] > 500 and all(x < y for x, y in zip(seqs, seqs[1:])), seqs[:5]
    finally:
        release.set()
        peer.close()


def _note_answers(monkeypatch, events: list, name: str, yes: str, no: str) -> None:
    """``TrackedHand``'s method ``name`` noted in ``events`` at each call: ``yes`` or ``no`` by its answer."""
    from service.pipeline.tracked import TrackedHand

    method = getattr(TrackedHand, name)

    def noted(self, *args):
        answer = method(self, *args)
        events.append(yes if answer else no)
        return answer
    monkeypatch.setattr(TrackedHand, name, noted)


def test_a_worker_sends_each_frame_as_soon_as_it_is_made_not_with_the_rest_of_its_message(monkeypatch):
    """At 1 kHz a pose completes about eleven ticks, the first of which makes the frame: the worker
    sends that frame before it processes the others (their time was in every frame's latency). A
    message alone in its batch, or in a small batch (two here): each frame goes in a write before the
    next tick is processed, in a write of its own while its message has ticks left, else (the frame of
    its message's last tick) in the write of its message's reply, before the reply (one write, not two).
    A frame written while its message has ticks left is followed by a yield of the core (``hand_over``: the
    web process, woken by the write, passes it on before those ticks) when at least ``YIELD_TICKS`` of them are
    ready (``ticks_ready``; with fewer the web process's wait is short) and the next frame's tick does not wait
    only for the reorder window (``next_frame_covered``: then the next frame waits for those ticks alone), and
    no other write is. Many messages
    in one batch: the earlier ones' outputs go in one write with their replies (fewer writes for a busy
    worker), each output before its reply."""
    from service.api.hands import worker as worker_module
    from service.pipeline.hand import HandSession

    events: list[str] = []                          # "tick", "frame" (a tick that made one), "send" (a write)
    emit_frames = HandSession._emit_frames

    def noted(self, t):
        frames = emit_frames(self, t)
        events.append("frame" if frames else "tick")
        return frames

    monkeypatch.setattr(HandSession, "_emit_frames", noted)
    monkeypatch.setattr(worker_module, "hand_over", lambda: events.append("yield"))
    _note_answers(monkeypatch, events, "next_frame_covered", "covered", "open")
    _note_answers(monkeypatch, events, "ticks_ready", "many", "few")
    peer = _Peer()
    send = peer.worker.send

    def noted_send():
        if peer.worker.out:
            events.append("send")
        send()

    peer.worker.send = noted_send
    try:
        config = SimConfig(motion="sequence", hand="right", noise="white", seed=7, duration_s=0.6, rate_hz=1000.0)
        msgs = list(enumerate((m for _, m in source_messages(config)), 2))
        hello = {"type": "hello", "protocol": 1, "hand": "right", "source": "worker-test"}
        peer.send([["open", 1, "a", None], ["src", 1, 1, hello]])
        peer.until(lambda: len(peer.replies(1)) == 1, "the hello answered")
        third = len(msgs) // 3
        for size, part in ((1, msgs[:third]), (2, msgs[third:2 * third])):
            start, first_event = len(peer.writes), len(events)
            for k in range(0, len(part), size):
                batch = part[k:k + size]
                peer.send([["src", 1, n, m] for n, m in batch])
                peer.until(lambda: len(peer.replies(1)) == batch[-1][0], f"message {batch[-1][0]} answered")
            writes = peer.writes[start:]
            assert sum(x[0] == "out" and x[3][0] == "frame" for w in writes for x in w) >= 10, size
            alone = with_reply = 0
            for w in writes:                        # a frame (with its events) per write, before its reply
                assert sum(x[0] == "out" and x[3][0] == "frame" for x in w) <= 1, (size, w)
                for i, x in enumerate(w):
                    if x[0] == "out" and x[3][0] == "frame":
                        replied = any(y[0] == "rep" and y[2] == x[2] for y in w)
                        assert not any(y[0] == "rep" and y[2] == x[2] for y in w[:i]), (size, w)
                        alone += not replied
                        with_reply += replied
            assert alone >= 5 and with_reply >= 1, (size, alone, with_reply)
            # every frame is written before the next tick is processed; the core is yielded after each frame
            # written alone (its message has ticks left) whose next frame is not covered yet, after no other write
            seen = events[first_event:]
            made = [i for i, e in enumerate(seen) if e == "frame"]
            assert len(made) >= 10
            for i in made:
                assert seen[i + 1:i + 2] == ["send"], (size, seen[i:i + 4])
            # (asked first whether YIELD_TICKS ticks are ready behind the frame: with fewer there is no yield)
            counted = [i for i, e in enumerate(seen) if e in ("many", "few")]
            assert len(counted) == alone, (size, len(counted), alone)
            for i in counted:                       # (at 1 kHz a pose's frame has about ten ticks behind it)
                assert seen[i - 2:i + 1] == ["frame", "send", "many"], (size, seen[i - 2:i + 2])
            asked = [i for i, e in enumerate(seen) if e in ("covered", "open")]
            assert len(asked) == sum(seen[i] == "many" for i in counted), size
            assert 0 < sum(seen[i] == "covered" for i in asked) < len(asked), (size, [seen[i] for i in asked])
            for i in asked:
                assert seen[i - 1] == "many", (size, seen[i - 3:i + 2])
                assert (seen[i + 1:i + 2] == ["yield"]) == (seen[i] == "open"), (size, seen[i - 3:i + 3])
            assert seen.count("yield") == sum(seen[i] == "open" for i in asked), size
        # the rest in one batch: outputs and replies together, each output before its reply
        start, yielded = len(peer.writes), events.count("yield")
        peer.send([["src", 1, n, m] for n, m in msgs[2 * third:]])
        peer.until(lambda: len(peer.replies(1)) == len(msgs) + 1, "the batch answered")
        late = [x for w in peer.writes[start:] for x in w]
        assert sum(x[0] == "out" and x[3][0] == "frame" for x in late) >= 10
        # (only the batch's last message sends its frames at once: at most its one frame mid-message)
        assert events.count("yield") - yielded <= 1, "a yield after a frame of a large batch's earlier message"
        assert any(x[0] == "rep" for w in peer.writes[start:] for x in w if any(y[0] == "out" for y in w))
        replied = set()
        for x in late:
            if x[0] == "rep":
                replied.add(x[2])
            elif x[0] == "out":
                assert x[2] not in replied, "an output came after its message's reply"
    finally:
        peer.close()


def test_a_worker_does_not_yield_after_a_frame_with_few_ticks_behind_it(monkeypatch):
    """At 200 Hz (the load bench's gloves, ``bench cpu``'s recording) a pose releases two or three ticks, and the
    tick after its frame's is held back for the next frame's run (``HandSession._defer``): nothing is left to
    process behind the frame (``tick_ready``), so it goes in the write of its message's reply, one write (it went
    alone before, the reply in another write, in about half of the frames), and no yield follows it (nor is
    ``ticks_ready`` or ``next_frame_covered`` asked)."""
    from service.api.hands import worker as worker_module

    events: list[str] = []
    monkeypatch.setattr(worker_module, "hand_over", lambda: events.append("yield"))
    _note_answers(monkeypatch, events, "ticks_ready", "many", "few")
    _note_answers(monkeypatch, events, "next_frame_covered", "asked", "asked")
    from service.bench.cpu import recording_lines, worker_messages

    peer = _Peer()
    try:
        msgs = worker_messages(recording_lines(2.0, seed=3, batched=True))     # (as the web process sends them)
        peer.send([["open", 1, "a", None], msgs[0]])
        peer.until(lambda: len(peer.replies(1)) == 1, "the first reply")   # (the hand built: not all in one batch)
        for k, m in enumerate(msgs[1:], 2):         # one message a batch, as a hand alone in its worker
            peer.send([m])
            peer.until(lambda: len(peer.replies(1)) == k, f"reply {k}")
        assert not events, events[:10]
        frames = 0
        for w in peer.writes:                       # each frame with its message's reply, after the frame
            assert sum(x[0] == "out" and x[3][0] == "frame" for x in w) <= 1, w
            for i, x in enumerate(w):
                if x[0] == "out" and x[3][0] == "frame":
                    frames += 1
                    assert any(_answers(y, x[2]) for y in w[i + 1:]), w
        assert frames >= 100
    finally:
        peer.close()


def test_a_worker_holds_replies_alone_for_its_next_write_and_sends_them_when_nothing_else_comes(monkeypatch):
    """The replies of reads that made no frame wait for the worker's next write (``Worker.holds``): held
    without end (``HOLD_S`` of a minute), no write carries replies alone, every reply comes, in order, and
    each before any later message's output; a configuration's answer is not held. With the default hold,
    a reply with nothing after it comes without more input, also after a batch with no output at all."""
    from service.api.hands import worker as hands_worker

    idle = hands_worker.Worker(None, _settings(1))
    assert not idle.holds() and idle.held_since is None     # nothing to hold: no hold begins (none would end)
    idle.out.append(["rep", 1, 1, []])
    assert idle.holds() and idle.held_since is not None
    msgs = [m for _, m in _messages("right", 0.4, 3)]
    monkeypatch.setattr(hands_worker, "HOLD_S", 60.0)
    peer = _Peer()
    try:
        peer.send([["open", 1, "a", None]])
        for n, m in enumerate(msgs, 1):             # one batch each: most make no frame
            peer.send([["src", 1, n, m]])
        peer.send([["cfg", 1, len(msgs) + 1, {}]])  # answered at once, with the replies held before it
        peer.until(lambda: any(m[0] == "cfgrep" for m in peer.received), "the configuration's answer")
        assert [m[2] for m in peer.replies(1)] == list(range(1, len(msgs) + 1))
        assert all(any(m[0] != "rep" for m in w) for w in peer.writes), [[m[0] for m in w] for w in peer.writes]
        assert sum(m[0] == "out" for m in peer.received) >= 5 and len(peer.writes) >= 5
        replied = set()
        for m in peer.received:                     # a reply before the outputs of later messages
            if m[0] == "rep":
                replied.add(m[2])
            elif m[0] == "out":
                assert set(range(1, m[2])) <= replied, m[2]
    finally:
        peer.close()
    monkeypatch.setattr(hands_worker, "HOLD_S", hands_worker.FLUSH_S)
    monkeypatch.setattr(hands_worker, "FLUSH_S", 0.0)  # (a batch's flush check after each message, also one with no output)
    peer = _Peer()
    try:
        peer.send([["open", 1, "a", None]])
        peer.send([["src", 1, 1, msgs[0]]])
        peer.until(lambda: len(peer.replies(1)) == 1, "the reply of a message with nothing after it")
        assert [[m[0] for m in w] for w in peer.writes] == [["rep"]]
    finally:
        peer.close()


def test_what_a_session_s_new_worker_cannot_restore_is_told_to_its_source_before_any_reply():
    """A session opened from a state whose stored hello and calibration (each with a field of the wrong
    type, as a state of another version could be) the worker refuses: one ``lost`` message names both, before the replies to the session's messages;
    the refused hello still sets the hand (the frames are the left hand's) and ``seq`` goes on."""
    peer = _Peer()
    try:
        hello = {"type": "hello", "protocol": 1, "hand": "left", "source": 5}
        calibration = {"type": "calibration", "fingers": "not an object"}
        state = {"session": "b", "seq": 40, "t": -1.0, "angles": None, "hello": hello, "calibration": calibration,
                 "config": {"estimator": "chain", "estimator_params": {}}}
        msgs = [m for _, m in _messages("left", 0.4, 9) if m["type"] != "hello"]
        peer.send([["open", 2, "b", state], *[["src", 2, n, m] for n, m in enumerate(msgs, 1)]])
        peer.until(lambda: len(peer.replies(2)) == len(msgs), "b's replies")
        kinds = [m[0] for m in peer.received if m[0] in ("lost", "rep", "out")]
        assert kinds[0] == "lost" and kinds.count("lost") == 1, kinds[:5]
        lost, = [m for m in peer.received if m[0] == "lost"]
        details = " | ".join(detail for _, detail in lost[2])
        assert lost[1] == 2 and "its hello" in details and "its calibration" in details, lost
        heads = [m[3] for m in peer.received if m[0] == "out" and m[3][0] == "frame"]
        assert heads and {h[3] for h in heads} == {"left"} and heads[0][1] > 40, heads[:3]
    finally:
        peer.close()


def _worker_replies(read_size: int, monkeypatch, batches: list) -> tuple[list, int]:
    """A worker reading its socket ``read_size`` bytes at a time, sent ``batches`` for one session: its
    replies (message number, errors) and how many outputs it wrote."""
    from service.api.hands import worker as hands_worker

    monkeypatch.setattr(hands_worker, "READ_SIZE", read_size)     # (read when the worker's loop starts)
    peer = _Peer()
    try:
        peer.send([["open", 1, "a", None]])
        for batch in batches:
            peer.send(batch)
        total = sum(m[0] == "src" for batch in batches for m in batch)
        peer.until(lambda: len(peer.replies(1)) == total, f"{total} replies")
        return [(m[2], m[3]) for m in peer.replies(1)], sum(m[0] == "out" for m in peer.received)
    finally:
        peer.close()


@pytest.mark.parametrize("read_size", [1, 3, 7, 4096])
def test_a_worker_reading_a_few_bytes_at_a_time_answers_as_with_whole_batches(read_size, monkeypatch):
    """The worker's read loop keeps a batch that arrives over several reads (reads of 1 to 4096 bytes)
    until it is whole: the same replies, in order, and the same outputs as with reads of a whole batch."""
    msgs = [m for _, m in _messages("right", 0.3, 5)]
    batches = [[["src", 1, n, m]] for n, m in enumerate(msgs[:10], 1)] + \
        [[["src", 1, n, m] for n, m in enumerate(msgs[10:], 11)]]
    got = _worker_replies(read_size, monkeypatch, batches)
    want = _worker_replies(1 << 20, monkeypatch, batches)
    assert got == want and [n for n, _ in got[0]] == list(range(1, len(msgs) + 1)) and got[1] > 0


def test_a_batch_larger_than_a_read_is_answered_whole():
    """A batch of more than ``READ_SIZE`` bytes (the worker's buffer grows for it) is answered in full."""
    from service.api.hands import worker as hands_worker

    msgs = [m for _, m in _messages("right", 0.2, 5)]
    big = [["fmt", 1, 0]] * 400_000 + [["src", 1, n, m] for n, m in enumerate(msgs, 1)]
    assert len(hands_worker.frame(big)) > hands_worker.READ_SIZE
    peer = _Peer()
    try:
        peer.send([["open", 1, "a", None]])
        peer.send(big)
        peer.until(lambda: len(peer.replies(1)) == len(msgs), "the big batch's replies")
        assert [m[2] for m in peer.replies(1)] == list(range(1, len(msgs) + 1))
    finally:
        peer.close()


def test_the_web_process_gone_in_the_middle_of_a_batch_ends_the_worker():
    from service.api.hands import worker as hands_worker

    peer = _Peer()
    peer.ours.sendall(hands_worker.frame([["open", 1, "a", None]])[:-2])
    peer.ours.close()
    peer.thread.join(60.0)                          # (bounds a failure)
    assert not peer.thread.is_alive()


def _answered_in_order(items: list, first: int) -> int:
    """A session's outputs and replies (``out``, ``rep``, ``reps``) as the worker sent them: each reply answers
    the next message(s) in order, and each output comes after every earlier message's reply and before its own
    message's; the last message answered."""
    answered = first - 1
    for m in items:
        if m[0] == "out":
            assert m[2] == answered + 1, (m[:3], answered)
        elif m[0] == "rep":
            assert m[2] == answered + 1, (m[:3], answered)
            answered = m[2]
        else:
            assert m[2] == answered + 1 and m[3] >= m[2], (m, answered)
            answered = m[3]
    return answered


def test_a_worker_answers_a_run_of_accepted_messages_in_one_reply_in_order_with_their_outputs_and_errors(monkeypatch):
    """Two sessions' data messages (``chk``) interleaved in large batches (a worker with many sessions): the
    accepted ones without error replies are answered by ``reps`` runs, far fewer replies than messages; every
    message is answered once, in order, after its outputs and before the next message's; a message refused
    (invalid JSON) gets a ``rep`` of its own with its error, in its place."""
    import json

    from service.api.hands import worker as hands_worker

    monkeypatch.setattr(hands_worker, "FLUSH_S", 3600.0)   # a batch's replies in one write however slow the machine
    msgs = {sid: [m for _, m in _messages(hand, 0.5, sid) if m["type"] in ("imu", "imu_batch", "pose")]
            for sid, hand in ((1, "right"), (2, "left"))}
    count = len(msgs[1])
    bad = count // 2 + 2                            # session 1's message number ``bad``: not JSON
    peer = _Peer()
    try:
        peer.send([["open", sid, f"s{sid}", None] for sid in msgs] +
                  [["src", sid, 1, {"type": "hello", "protocol": 1, "hand": hand, "source": "worker-test"}]
                   for sid, hand in ((1, "right"), (2, "left"))])
        checks = [["chk", sid, n, "{not json" if (sid, n) == (1, bad) else json.dumps(m), False]
                  for n in range(2, count + 2) for sid in msgs if n - 2 < len(msgs[sid]) for m in [msgs[sid][n - 2]]]
        for i in range(0, len(checks), 16):
            peer.send(checks[i:i + 16])

        peer.until(lambda: all(len(peer.replies(sid)) == len(msgs[sid]) + 1 for sid in msgs), "every message's reply")
        for sid in msgs:
            items = [m for m in peer.received if m[1:2] == [sid] and m[0] in ("out", "rep", "reps")]
            assert _answered_in_order(items, 1) == len(msgs[sid]) + 1
            assert sum(m[0] == "out" for m in items) >= 5
        refused = [m for m in peer.received if m[0] == "rep" and m[1] == 1 and m[2] == bad]
        assert len(refused) == 1 and refused[0][3][0][0] == "invalid_json" and refused[0][4] is False
        replies = sum(m[0] in ("rep", "reps") for m in peer.received)
        assert replies < len(checks) / 2, (replies, len(checks))
    finally:
        peer.close()


@pytest.mark.parametrize("idle_others", [False, True])
def test_a_worker_with_many_sessions_sends_a_batch_s_outputs_in_one_write_at_its_end(monkeypatch, idle_others):
    """With ``GROUP_SESSIONS`` sessions a worker sends no frame as soon as it is made (a pose at 1 kHz makes one
    while it has ticks left, which a worker with few sessions writes alone: the test above): each batch's outputs
    go in one write with its replies, and each output before its reply."""
    from service.api.hands import worker as hands_worker

    # the other sessions' hellos keep them active, or (idle_others) only the batch's own sessions count: then
    # the worker has one active session and sends a frame made while ticks are left at once, alone
    monkeypatch.setattr(hands_worker, "ACTIVE_S", 0.0 if idle_others else 3600.0)
    config = SimConfig(motion="sequence", hand="right", noise="white", seed=7, duration_s=0.3, rate_hz=1000.0)
    msgs = list(enumerate((m for _, m in source_messages(config)), 2))
    hello = {"type": "hello", "protocol": 1, "hand": "right", "source": "worker-test"}
    sessions = range(1, hands_worker.GROUP_SESSIONS + 1)
    peer = _Peer()
    try:
        peer.send([x for sid in sessions for x in (["open", sid, f"s{sid}", None], ["src", sid, 1, hello])])
        peer.until(lambda: all(len(peer.replies(sid)) == 1 for sid in sessions), "the hellos answered")
        start = len(peer.writes)
        for n, m in msgs:
            peer.send([["src", 1, n, m]])
            peer.until(lambda: len(peer.replies(1)) == n, f"message {n} answered")
        writes = peer.writes[start:]
        assert sum(x[0] == "out" and x[3][0] == "frame" for w in writes for x in w) >= 10
        alone = sum(x[0] == "out" and not any(_answers(y, x[2]) for y in w[i + 1:])
                    for w in writes for i, x in enumerate(w))
        if idle_others:
            assert alone > 0
        else:
            assert alone == 0, [[y[:3] for y in w] for w in writes]
    finally:
        peer.close()


def test_a_configuration_change_ends_a_session_s_reps_run(monkeypatch):
    """A configuration change between a session's data messages (numbered apart from them) ends the session's
    ``reps`` run: the data message after it is answered after the configuration's answer, those before it
    before it, as they came (the batch in one write: no flush in between ends the run)."""
    import json

    from service.api.hands import worker as hands_worker

    monkeypatch.setattr(hands_worker, "FLUSH_S", 3600.0)

    data = [m for _, m in _messages("right", 0.2, 5) if m["type"] in ("imu", "imu_batch", "pose")][:3]
    hello = {"type": "hello", "protocol": 1, "hand": "right", "source": "worker-test"}
    peer = _Peer()
    try:
        peer.send([["open", 1, "a", None], ["src", 1, 1, hello]])
        peer.until(lambda: len(peer.replies(1)) == 1, "the hello answered")
        peer.send([["chk", 1, 2, json.dumps(data[0]), False], ["chk", 1, 3, json.dumps(data[1]), False],
                   ["cfg", 1, 1, {}], ["chk", 1, 4, json.dumps(data[2]), False]])
        peer.until(lambda: len(peer.replies(1)) == 4 and any(m[0] == "cfgrep" for m in peer.received),
                   "every answer")
        order = [m for m in peer.received if m[0] in ("rep", "reps", "cfgrep")]
        at = next(i for i, m in enumerate(order) if m[0] == "cfgrep")
        assert all(any(_answers(m, n) for m in order[:at]) for n in (2, 3)), order
        assert any(_answers(m, 4) for m in order[at + 1:]) and not any(_answers(m, 4) for m in order[:at]), order
    finally:
        peer.close()
