"""Each output message is serialised once for all its subscribers (per wire format), and is built in
the shape its protocol model declares."""
import asyncio
import json
from typing import Union, get_args, get_origin, get_type_hints

import msgpack
import pytest
from typing_extensions import is_typeddict

from clients.glove import source_messages
from service.api import outgoing
from service.api.config import ServiceSettings
from service.api.metrics import Metrics
from service.api.routes.socket import server_hello
from service.api.sessions import LiveSession, Subscriber
from service.pipeline.tracked import replay
from service.protocol import encode, parse_message
from service.protocol.outgoing import WIRE_SHAPES, FrameDict, GestureDict, ServerHelloDict
from service.sim.session import SimConfig


def test_one_encoding_per_message_and_format_for_many_subscribers(monkeypatch):
    calls = {"json": 0, "msgpack": 0}
    real_encode, real_dumps = outgoing.encode, json.dumps

    def counting_encode(message, binary):
        calls["msgpack" if binary else "json"] += 1
        return real_encode(message, binary)

    monkeypatch.setattr(outgoing, "encode", counting_encode)

    async def run():
        live = LiveSession("enc", ServiceSettings.load(port=0), Metrics())
        subs = [Subscriber(10_000, 10_000, binary=b) for b in (False, False, False, True, True)]
        live.subscribers.update(subs)
        for _, m in source_messages(SimConfig(motion="point", duration_s=0.4, noise="none", seed=1)):
            await live.ingest(m, parse_message(m))
        return live, subs

    live, subs = asyncio.run(run())
    assert live.frames_out > 10
    queues = [[item for _, item, _ in s.queue] for s in subs]
    assert all(len(q) == len(queues[0]) for q in queues)
    for items in zip(*queues):                    # every subscriber holds the very same message object
        assert all(item is items[0] for item in items)
    for s in subs:                                # what the stream handler sends, per subscriber
        for _, item, _ in s.queue:
            data = item.packed() if s.binary else item.text()
            decoded = msgpack.unpackb(data) if s.binary else json.loads(data)
            assert decoded == json.loads(real_dumps(item.message))
    n = len(queues[0])
    assert calls == {"json": n, "msgpack": n}     # not n x subscribers


def test_each_wire_shape_spells_its_models_fields_in_order():
    """One definition per message: the TypedDict the service builds is its published model's twin."""
    assert {m.__name__ for m in WIRE_SHAPES} >= {"ServerHello", "SyncReply", "Frame", "Gesture", "ErrorMessage"}
    for model, shape in WIRE_SHAPES.items():
        assert list(shape.__annotations__) == list(model.model_fields), model.__name__
        required = {name for name, f in model.model_fields.items() if f.is_required()}
        assert required <= shape.__required_keys__, model.__name__


def _shape_problems(value, tp, path="message") -> list[str]:
    """Where ``value`` differs from the TypedDict ``tp``: keys it does not declare, required keys
    missing, keys out of the declared order; nested TypedDicts, dicts of them and optionals followed."""
    if is_typeddict(tp):
        hints = get_type_hints(tp)
        found = [f"{path}: {k!r} not declared" for k in value if k not in hints]
        found += [f"{path}: {k!r} missing" for k in tp.__required_keys__ if k not in value]
        if [k for k in value if k in hints] != [k for k in hints if k in value]:
            found.append(f"{path}: keys {list(value)} not in the order {list(hints)}")
        for k in value:
            if k in hints:
                found += _shape_problems(value[k], hints[k], f"{path}.{k}")
        return found
    if get_origin(tp) is dict:
        return [p for k, v in value.items() for p in _shape_problems(v, get_args(tp)[1], f"{path}.{k}")]
    if get_origin(tp) is Union and value is not None:
        return _shape_problems(value, next(a for a in get_args(tp) if a is not type(None)), path)
    return []


def test_the_pipeline_and_the_recogniser_build_the_declared_shapes():
    sim = [parse_message(m) for _, m in source_messages(SimConfig(motion="point", duration_s=2.0, noise="none", seed=3))]
    out = list(replay(sim))
    frames = [m for m in out if m["type"] == "frame"]
    events = [m for m in out if m["type"] == "gesture"]
    assert len(frames) > 100 and ("point", "start") in [(e["gesture"], e["event"]) for e in events]
    assert any("ray" in f["gesture"] for f in frames)          # the pointing ray is followed too
    for m in out:
        shape = FrameDict if m["type"] == "frame" else GestureDict
        assert _shape_problems(m, shape) == []
    assert _shape_problems({"type": "frame", "t": 0.0}, FrameDict) != []       # the check can fail


def test_the_service_replies_are_built_in_their_declared_order():
    assert list(server_hello("s", waiting=True)) == list(ServerHelloDict.__annotations__)
    assert list(server_hello("s")) == [k for k in ServerHelloDict.__annotations__ if k != "waiting"]
    assert _shape_problems(server_hello("s"), ServerHelloDict) == []


def test_a_session_s_cached_series_count_as_labels_does_and_start_again_after_the_session_is_forgotten():
    """``Metrics.of_session``: the per-message series looked up once count into the same series as
    ``labels``; a frame series appears only once used; after ``forget_session`` (a removed session) the
    name's next session counts from zero."""
    from service.api.metrics import Metrics

    metrics = Metrics()
    metrics.of_session("a").messages_in.inc()
    metrics.of_session("a").messages_in.inc()
    text = metrics.render().decode()
    assert 'fingertrack_messages_in_total{session="a"} 2.0' in text and 'messages_out_total{session="a"}' not in text
    metrics.of_session("a").messages_out.inc()
    metrics.of_session("a").latency.observe(0.001)
    metrics.forget_session("a")
    assert 'session="a"' not in metrics.render().decode()
    metrics.of_session("a").messages_in.inc()
    text = metrics.render().decode()
    assert 'fingertrack_messages_in_total{session="a"} 1.0' in text and 'messages_out_total{session="a"}' not in text


def test_a_session_s_messages_counted_locally_show_at_the_next_scrape_as_counted_one_by_one():
    """``SessionSeries.sent``, ``sent_one``, ``received``, ``behind``: messages written to subscribers and received are counted
    in plain numbers and published into ``messages_out``, the latency histogram, ``messages_in`` and the
    ``behind`` gauge at the next scrape (``render``), with the counts, buckets (a latency on a bound counts in
    that bound's bucket, one past the last finite bound in +Inf), sum and value that ``inc``/``observe``/``set``
    per message give; a forgotten session's unpublished counts go with it."""
    from service.api.metrics import Metrics

    def text(metrics: Metrics, admin: bool = True) -> list[str]:        # (the series' creation times differ)
        return [line for line in metrics.render(admin).decode().splitlines() if "_created" not in line]

    latencies = [0.0, 0.0005, 0.00050048828125, 0.001, 0.25, 0.5, 0.75, 3.0, 0.0029296875, 0.5, 2.0 ** -12]
    one_by_one, local = Metrics(), Metrics()
    for name in ("a", "b"):
        for i, x in enumerate(latencies):
            series = one_by_one.of_session(name)
            series.messages_out.inc()
            series.latency.observe(x)
        local.of_session(name).sent([-x for x in latencies[:4]], 0.0)   # now - t0 = x exactly (binary fractions)
        local.of_session(name).sent([-x for x in latencies[4:8]], 0.0)
        for x in latencies[8:]:
            local.of_session(name).sent_one(x)              # (one message's)
    assert text(local) == text(one_by_one)            # published by the scrape itself
    assert text(local) == text(one_by_one)            # ... once
    local.of_session("a").sent([-0.002], 0.0)
    one_by_one.of_session("a").messages_out.inc()
    one_by_one.of_session("a").latency.observe(0.002)
    for k in (1, 3):
        local.of_session("a").received(k)
        one_by_one.of_session("a").messages_in.inc(k)
    local.of_session("b").behind = 0.5
    local.of_session("b").behind = 0.25                       # the last one counts
    one_by_one.behind.labels("b").set(0.25)
    assert text(local, admin=False) == text(one_by_one, admin=False)     # (no session series shown)
    assert text(local) == text(one_by_one)
    local.of_session("b").sent([-0.001], 0.0)
    local.forget_session("b")
    one_by_one.forget_session("b")
    assert text(local) == text(one_by_one)
    assert not any('session="b"' in line for line in text(local))
    assert 'fingertrack_messages_out_total{session="a"} 12.0' in text(local)
    assert 'fingertrack_messages_in_total{session="a"} 4.0' in text(local)
    local.of_session("a").behind = 0.125
    assert 'fingertrack_session_behind_seconds{session="a"} 0.125' in text(local)


def test_the_metrics_text_is_the_client_library_s_byte_for_byte_as_series_come_and_go():
    """``Metrics.render``: its own writer (each series' line heads formatted once) gives what
    ``prometheus_client.generate_latest`` gives, for admins and others, with every kind of series, label
    values to escape, special values, and series removed and made again; a registry it does not know
    (a gauge set to a function) is left to the library."""
    import random

    from prometheus_client import generate_latest

    from service.api.metrics import Metrics, _WithoutSessions

    metrics, rng = Metrics(), random.Random(7)

    def same() -> None:
        for admin in (True, False):
            expected = generate_latest(metrics.registry if admin else _WithoutSessions(metrics.registry))
            assert metrics._exposition.render(admin) == expected
            assert metrics.render(admin) == expected

    same()
    for i in range(12):
        series = metrics.of_session(f"hand-{i}")
        series.messages_in.inc(rng.random() * 1e7)
        for _ in range(rng.randrange(4)):
            series.latency.observe(rng.random() * 0.03)
        if i % 3:
            series.messages_out.inc()
        metrics.behind.labels(f"hand-{i}").set(float("nan") if i == 5 else rng.random() * 1e8)
        same()
    metrics.of_session("hand-0").latency._buckets[0].inc(2e6)   # a count written in Go's exponent form
    same()
    metrics.errors.labels('odd "code" \\ with\na line').inc()
    metrics.disconnects.labels("x").inc(1e300)
    metrics.connection_gc.observe(0.25)
    metrics.worker_restarts.inc()
    metrics.sessions.set(-3)
    metrics.subscribers.set(float("inf"))
    same()
    metrics.forget_session("hand-4")
    same()
    metrics.of_session("hand-4").latency.observe(0.001)      # the same name, a new series
    same()
    metrics.forget_session("hand-7")                         # ... made again with no render between
    metrics.of_session("hand-7").messages_in.inc(2)
    same()
    kept = len(metrics._exposition._heads)
    metrics.render(False)                                    # a render without the session series keeps theirs
    assert len(metrics._exposition._heads) == kept
    metrics.forget_session("hand-8")
    same()
    assert len(metrics._exposition._heads) < kept            # a removed session's are dropped
    metrics.sessions.set_function(lambda: 42)
    assert metrics._exposition.render(True) is None
    assert b"fingertrack_sessions 42.0" in metrics.render()


def test_the_metrics_text_comes_from_the_client_library_once_the_service_s_writer_fails(monkeypatch, caplog):
    """A prometheus_client whose internals the writer does not know (its attributes renamed): one warning,
    then ``generate_latest``'s text at every scrape; /metrics never fails."""
    from prometheus_client import generate_latest

    from service.api import metrics as metrics_module

    metrics = metrics_module.Metrics()
    metrics.of_session("a").messages_in.inc()
    import types
    monkeypatch.setattr(metrics_module, "_om", types.SimpleNamespace())  # its internals renamed (as 0.20-0.22's are)
    with caplog.at_level("WARNING", logger="service.api.metrics"):
        assert metrics.render() == generate_latest(metrics.registry)
        assert metrics.render() == generate_latest(metrics.registry)
    assert metrics._exposition is None
    assert sum("exposition writer failed" in r.message for r in caplog.records) == 1


def test_a_messages_websocket_frame_is_built_once_as_the_protocol_library_builds_it():
    """``Outgoing.wire``: the frame a server writes for ``send_text``/``send_binary`` (no extension), for
    every length encoding (7, 7+16 and 7+64 bits), built once per format."""
    from websockets.frames import Frame, Opcode

    for n in (0, 1, 125, 126, 127, 65535, 65536, 70000):
        packed = bytes(range(256)) * (n // 256) + bytes(range(n % 256))
        text = "x" * n
        out = outgoing.Outgoing.encoded("frame", text, packed)
        assert out.wire(False) == Frame(Opcode.TEXT, text.encode()).serialize(mask=False, extensions=[]), n
        assert out.wire(True) == Frame(Opcode.BINARY, packed).serialize(mask=False, extensions=[]), n
        assert out.wire(False) is out.wire(False) and out.wire(True) is out.wire(True)
    # a non-ASCII text: its length in UTF-8 bytes
    out = outgoing.Outgoing.encoded("gesture", '{"a":"é"}')
    assert out.wire(False) == Frame(Opcode.TEXT, '{"a":"é"}'.encode()).serialize(mask=False, extensions=[])


def test_ready_made_frames_are_written_only_to_an_open_connection_without_extensions():
    """``DrainingWebSocket.write_frames`` writes only what the protocol library would write as it is: to an
    open connection with no extension negotiated (per-message deflate compresses each copy), nothing
    fragmented in between, not closing; otherwise it refuses and the caller sends through ASGI."""
    from websockets.extensions.permessage_deflate import PerMessageDeflate
    from websockets.protocol import State
    from websockets.server import ServerProtocol

    from service.api.server import DrainingWebSocket

    class Transport:
        closing = False
        written: list = []

        def is_closing(self):
            return self.closing

        def write(self, data):
            self.written.append(data)

    def protocol(**changes):
        p = DrainingWebSocket.__new__(DrainingWebSocket)
        p.disconnected = p.close_sent = False
        p.handshake_complete, p.initial_response = True, None
        p.conn, p.transport = ServerProtocol(state=State.OPEN), Transport()
        p.transport.written = []
        for name, value in changes.items():
            target = p.conn if name in ("state", "extensions", "expect_continuation_frame") else p
            setattr(target, name, value)
        return p

    frame = outgoing.ws_frame(b'{"type":"sync","id":1}', False)     # (recorded as sent: a service message)
    ok = protocol()
    assert ok.write_frames(frame) and ok.transport.written == [frame]
    refused = [protocol(disconnected=True), protocol(close_sent=True), protocol(handshake_complete=False),
               protocol(initial_response=(403, [], b"")), protocol(_draining=True), protocol(state=State.CLOSING),
               protocol(extensions=[PerMessageDeflate(False, False, 12, 12)]), protocol(expect_continuation_frame=True)]
    closing = protocol()
    closing.transport.closing = True
    for p in [*refused, closing]:
        assert not p.write_frames(frame) and not p.transport.written


def test_ready_made_frames_wait_for_room_and_go_only_to_a_connected_socket():
    """``send_outputs`` waits while the connection's buffers are full (``writable`` clear) before it writes,
    as the ASGI send does, and is watched meanwhile (``sending``, which ``drop_stuck`` reads); a socket no
    longer connected gets its outputs through ASGI's send (which raises as it would), never as a write."""
    from types import SimpleNamespace

    from starlette.websockets import WebSocketState

    from service.api.routes import socket

    class Wire:
        def __init__(self):
            self.writable, self.written = asyncio.Event(), []

        def write_frames(self, data):
            self.written.append(data)
            return True

    class Connection:                        # hashable, as a WebSocket is (``sending``'s key)
        def __init__(self, state):
            self.state, self.application_state = SimpleNamespace(wire=Wire(), binary=False), state
            self.app = SimpleNamespace(state=SimpleNamespace(sessions=SimpleNamespace(sending={})))

    def connection(state=WebSocketState.CONNECTED):
        return Connection(state)

    messages = [outgoing.Outgoing({"type": "gesture", "t": float(k), "gesture": "point"}) for k in range(3)]

    async def full_then_drained():
        ws = connection()
        task = asyncio.create_task(socket.send_outputs(ws, messages))
        for _ in range(20):                  # turns of the loop: the task runs until it waits
            await asyncio.sleep(0)
        waited = (not task.done(), ws.state.wire.written[:], ws in ws.app.state.sessions.sending)
        ws.state.wire.writable.set()
        await task
        return waited, ws.state.wire.written, ws.app.state.sessions.sending

    (pending, written_while_full, watched), written, sending = asyncio.run(full_then_drained())
    assert pending and written_while_full == [] and watched
    assert written == [b"".join(m.wire(False) for m in messages)] and sending == {}

    sent = []

    async def asgi_send(ws, message):
        sent.append(message)

    async def gone():
        ws = connection(WebSocketState.DISCONNECTED)
        ws.state.wire.writable.set()
        original = socket.send
        socket.send = asgi_send
        try:
            await socket.send_outputs(ws, messages)
        finally:
            socket.send = original
        return ws.state.wire.written

    assert asyncio.run(gone()) == [] and sent == messages


async def _turns_until(condition, what: str, turns: int = 10_000) -> None:
    """Turns of the loop until ``condition()``; a failure after ``turns`` of them (no clock: a count)."""
    for _ in range(turns):
        if condition():
            return
        await asyncio.sleep(0)
    raise AssertionError(f"not after {turns} turns of the loop: {what}")


def test_a_waiting_sender_s_queued_outputs_are_written_at_once_in_one_write_per_turn_else_it_wakes():
    """``routes.stream``: while a subscriber's sender waits with nothing queued, what is queued within a turn
    of the loop goes out in one write of its ready-made frames at the end of that turn, without waking the
    sender, and is counted (``messages_out``); while the connection's buffers are full, or it does not take
    ready-made frames, the sender is woken and sends them in order as before (waiting for room, or
    through ASGI)."""
    from types import SimpleNamespace

    from starlette.websockets import WebSocketState

    from service.api.metrics import Metrics
    from service.api.routes import stream
    from service.api.sessions import Subscriber

    class Wire:
        def __init__(self):
            self.writable, self.written, self.takes = asyncio.Event(), [], True
            self.writable.set()

        def write_frames(self, data):
            if self.takes:
                self.written.append(data)
            return self.takes

    class Connection:
        def __init__(self):
            self.state, self.application_state = SimpleNamespace(wire=Wire(), binary=False), WebSocketState.CONNECTED
            self.app = SimpleNamespace(state=SimpleNamespace(sessions=SimpleNamespace(sending={})))
            self.texts = []

        async def send_text(self, text):
            self.texts.append(text)

    class Wake(asyncio.Event):
        woken = 0

        async def wait(self):
            await super().wait()
            self.woken += 1

    frames = [outgoing.Outgoing({"type": "frame", "t": float(k), "seq": k}) for k in range(9)]

    async def run():
        ws, sub, metrics = Connection(), Subscriber(100, 100, wake=Wake()), Metrics()
        sessions = SimpleNamespace(closing=False)
        closer = asyncio.get_running_loop().create_future()
        sender = asyncio.create_task(stream._send_all(ws, "s", False, sub, closer, sessions, metrics))
        await _turns_until(lambda: sub.writer is not None, "the sender waiting")
        hello = ws.state.wire.written[:]             # the server's hello: a ready-made frame too
        ws.state.wire.written.clear()
        for f in frames[:3]:                         # one turn: one write, the sender not woken
            sub.put(f, 0.0)
        await asyncio.sleep(0)
        at_once = (ws.state.wire.written[:], sub.wake.woken, sub.writer is not None)
        ws.state.wire.writable.clear()               # full: the sender wakes and waits for room
        for f in frames[3:5]:
            sub.put(f, 0.0)
        for _ in range(10):
            await asyncio.sleep(0)
        while_full = (len(ws.state.wire.written), sub.writer is None)
        ws.state.wire.writable.set()
        await _turns_until(lambda: sub.writer is not None and not sub.queue, "the sender to send and wait again")
        ws.state.wire.takes = False                  # no ready-made frames: through ASGI, by the sender
        for f in frames[5:]:
            sub.put(f, 0.0)
        await _turns_until(lambda: len(ws.texts) >= 4, "the sender's ASGI sends")
        closer.set_result(None)
        sub.wake.set()
        await sender
        out = metrics.render().decode()
        return hello, at_once, while_full, ws.state.wire.written, ws.texts, out

    hello, at_once, while_full, written, texts, out = asyncio.run(run())
    assert hello == [outgoing.ws_frame(encode(server_hello("s", waiting=False), False).encode(), False)]
    assert at_once == ([b"".join(f.wire(False) for f in frames[:3])], 0, True)
    assert while_full == (1, True)
    assert written == [at_once[0][0], b"".join(f.wire(False) for f in frames[3:5])]
    assert texts == [f.text() for f in frames[5:]]
    assert 'fingertrack_messages_out_total{session="s"} 9.0' in out


@pytest.mark.parametrize("why", ["server closing", "subscriber closed", "peer gone", "connection disconnected"])
def test_the_end_of_turn_writer_writes_nothing_once_the_subscriber_s_stream_is_ending_and_wakes_the_sender(why):
    """``routes.stream``'s end-of-turn writer leaves what was queued to the sender (woken, nothing written
    at the end of the turn) when the server is shutting down, the subscriber was closed as too slow, its
    peer left, or its connection is no longer open: the sender then closes with the reason or ends."""
    from types import SimpleNamespace

    from starlette.websockets import WebSocketState

    from service.api.metrics import Metrics
    from service.api.routes import stream

    class Wire:
        def __init__(self):
            self.writable, self.written = asyncio.Event(), []
            self.writable.set()

        def write_frames(self, data):
            self.written.append(data)
            return True

    class Connection:
        def __init__(self):
            self.state, self.application_state = SimpleNamespace(wire=Wire(), binary=False), WebSocketState.CONNECTED
            self.app = SimpleNamespace(state=SimpleNamespace(sessions=SimpleNamespace(sending={})))
            self.texts, self.closed = [], None

        async def send_text(self, text):
            self.texts.append(text)

        async def close(self, code, reason):
            self.closed = code

    async def run():
        ws, sub = Connection(), Subscriber(100, 100)
        sessions = SimpleNamespace(closing=False)
        closer = asyncio.get_running_loop().create_future()
        sender = asyncio.create_task(stream._send_all(ws, "s", False, sub, closer, sessions, Metrics()))
        await _turns_until(lambda: sub.writer is not None, "the sender waiting")
        ws.state.wire.written.clear()               # the server's hello (a ready-made frame)
        sub.put(outgoing.Outgoing({"type": "frame", "t": 0.0, "seq": 1}), 0.0)
        await asyncio.sleep(0)
        before = (len(ws.state.wire.written), sub.wake.is_set())     # the writer takes it: the control
        await _turns_until(lambda: sub.writer is not None and not sub.wake.is_set(), "the sender waiting again")
        if why == "server closing":
            sessions.closing = True
        elif why == "subscriber closed":
            sub.closed = True
        elif why == "peer gone":
            closer.set_result(None)
        else:
            ws.application_state = WebSocketState.DISCONNECTED
        sub.put(outgoing.Outgoing({"type": "frame", "t": 0.1, "seq": 2}), 0.0)
        await asyncio.sleep(0)                      # the end of this turn: the writer's
        after = (len(ws.state.wire.written), sub.wake.is_set())
        if not closer.done():
            closer.set_result(None)
        sub.wake.set()
        await asyncio.wait_for(sender, 60)          # (bounds a failure)
        return before, after

    before, after = asyncio.run(run())
    assert before == (1, False)
    assert after == (1, True)


def test_a_subscriber_s_end_of_turn_writer_that_fails_is_logged_once_and_left_to_the_sender(caplog):
    """``Subscriber._write_soon``: a writer that raises (a defect) is logged, dropped for good
    (``writer_failed``: the sender does not set it again) and the sender woken to send what is queued."""
    import asyncio

    from service.api.outgoing import Outgoing
    from service.api.sessions import Subscriber

    async def run():
        sub, calls = Subscriber(10, 10), []

        def broken():
            calls.append(1)
            raise RuntimeError("a defect in the writer")
        sub.writer = broken
        sub.put(Outgoing({"type": "gesture", "gesture": "point", "event": "start"}), 0.0)
        assert not sub.wake.is_set()                # the write is due at the end of the turn
        await asyncio.sleep(0)
        return sub, calls

    with caplog.at_level("ERROR", logger="service.api.sessions"):
        sub, calls = asyncio.run(run())
    assert calls == [1] and sub.writer is None and sub.writer_failed and sub.wake.is_set() and len(sub.queue) == 1
    assert sum("end of the turn failed" in r.getMessage() for r in caplog.records) == 1
