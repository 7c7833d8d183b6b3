"""The scripted load test (``fingertrack bench load``): a real service process, real gloves and
subscribers at a light load; its accounting and integrity checks."""
import pytest

from service.bench.load import _integrity, run_level
from service.cli import main
from service.pipeline.hand import PipelineSettings


def test_two_hands_at_once_every_frame_is_delivered_or_counted_and_stays_in_its_session():
    lv = run_level(hands=2, subscribers=2, seconds=3.0)
    assert lv["sessions_seen"] == 2
    # 3 s of a hand is a few hundred frames; each one reaches both subscribers of its session, or the
    # service counted it as dropped for a subscriber that fell behind (its queue holds 64 frames: on a
    # busy machine a subscriber may fall that far behind; dropping is then the promised behaviour)
    assert lv["frames_produced"] > 2 * 3.0 * 50
    assert lv["frames_delivered"] == lv["frames_expected"] - lv["frames_dropped"]
    assert lv["frames_dropped"] < lv["frames_expected"] / 2
    assert lv["integrity_violations"] == 0 and lv["source_errors"] == 0
    # how far behind schedule the frames arrive is a speed figure: `fingertrack bench load` reports it
    assert lv["schedule_delay_ms"] is not None and lv["schedule_delay_ms"]["p50"] > 0.0
    assert lv["service_cpu_share"] is None or 0.0 < lv["service_cpu_share"] < 2.0


def test_the_load_spread_over_two_generator_processes_is_accounted_for_as_from_one():
    """Two hands, one per load-generator process: every frame is delivered or counted as dropped, in
    order and in its own session, and each frame's wait is split into the pipeline's alignment wait
    (at least the reorder window: the tick's data must be that much older than the newest sample) and
    the delay beyond it."""
    lv = run_level(hands=2, subscribers=2, seconds=3.0, generators=2)
    assert lv["generator_processes"] == 2 and lv["sessions_seen"] == 2
    assert lv["frames_produced"] > 2 * 3.0 * 50
    assert lv["frames_unaccounted"] == 0
    assert lv["frames_delivered"] == lv["frames_expected"] - lv["frames_dropped"]
    assert lv["integrity_violations"] == 0 and lv["source_errors"] == 0
    assert lv["alignment_wait_ms"]["p50"] >= PipelineSettings().reorder_window_s * 1e3 - 1e-6
    assert lv["behind_schedule_beyond_alignment_ms"] is not None
    # the same without each session's first second: a subset of those frames (3 s of data: most of them)
    later = lv["behind_schedule_beyond_alignment_after_first_s_ms"]
    assert later is not None and later["max"] <= lv["behind_schedule_beyond_alignment_ms"]["max"]
    assert 0.0 < lv["generator_cpu_share_max"] and lv["generator_cpu_share"] >= lv["generator_cpu_share_max"]
    assert 0.0 <= lv["generator_system_cpu_s_per_hand_s"] <= lv["generator_cpu_s_per_hand_s"] and lv["generator_cpu_s_per_hand_s"] > 0.0
    # no glove sent before its message was due; every message a subscriber read was decoded or compared
    assert lv["glove_send_lag_ms"]["p50"] >= 0.0 and lv["glove_send_lag_ms"]["max"] >= lv["glove_send_lag_ms"]["p99"]
    assert lv["subscriber_messages_decoded"] + lv["subscriber_messages_compared"] >= lv["frames_delivered"]


def test_the_integrity_check_sees_reordering_and_cross_talk():
    ok = [(0.0, 0.001, 1, "right", 0.0), (0.0, 0.001, 2, "right", 0.01)]
    assert _integrity({("a", 0): ok}, {"a": "right"}) == 0
    swapped = [ok[1], ok[0]]                                        # seq goes backwards
    foreign = ok + [(0.0, 0.001, 3, "left", 0.02)]                  # a frame of the other hand's session
    assert _integrity({("a", 0): swapped, ("a", 1): foreign}, {"a": "right"}) == 2


def test_bad_load_arguments_are_refused(tmp_path):
    with pytest.raises(SystemExit):
        main(["bench", "load", "--hands", "1,x", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        main(["bench", "load", "--hands", "0", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        main(["bench", "load", "--subscribers", "0", "--out", str(tmp_path)])


def _frame(seq, hand, t):
    """A frame as the service sends it, down to its nested fingers and joints (skipped unread)."""
    return {"type": "frame", "t": t, "seq": seq, "hand": hand,
            "fingers": {"index": {"mcp": 0.1, "pip": 0.2, "dip": 0.2, "mode": "optical"}},
            "joints": {"palm": {"position": [0.0, 1.0, 0.0], "orientation": [0.0, 0.0, 0.0, 1.0]}},
            "status": {"imu": {"index.1": "ok"}, "latency_ms": 1.0}}


def test_the_load_subscriber_passes_every_frame_on_and_counts_what_does_not_decode():
    """A real WebSocket server sends a load-generator subscriber a repeated seq, a frame of the other
    hand, a frame without its seq, a frame in two fragments, a MessagePack frame, a ping, text that is
    not JSON and a gesture: every whole frame is passed on with its fields, the integrity check finds
    the repeated seq and the foreign hand, and the two undecodable messages are counted, not lost."""
    import asyncio
    import json

    import msgspec
    from websockets.asyncio.server import serve

    from service.bench.loadclients import LeanSubscription

    async def handler(ws):
        await ws.send(json.dumps({"type": "hello", "protocol": 1}))
        for seq, hand in [(1, "right"), (2, "right"), (2, "right"), (3, "left")]:
            await ws.send(json.dumps(_frame(seq, hand, seq / 90)))
        await ws.send(json.dumps({k: v for k, v in _frame(4, "right", 0.0).items() if k != "seq"}))
        text = json.dumps(_frame(5, "right", 5 / 90))
        await ws.send([text[:40], text[40:]])                          # two fragments
        await ws.send(msgspec.msgpack.encode(_frame(6, "right", 6 / 90)))
        await ws.ping()
        await ws.send("{not json")
        await ws.send(json.dumps({"type": "gesture", "t": 0.1, "gesture": "point", "event": "start"}))
        await ws.wait_closed()

    async def main():
        async with serve(handler, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            rows = []
            sub = LeanSubscription(f"http://127.0.0.1:{port}", "a", "token",
                                   lambda m, arrival: rows.append((arrival, 0.0, m.seq, m.hand, m.t)))
            sub.start()
            while sub.gestures < 1 and sub.reconnects == 0:            # the gesture comes last
                await asyncio.sleep(0.01)
            await sub.close()
            return rows, sub

    rows, sub = asyncio.run(asyncio.wait_for(main(), 60))
    assert [r[2] for r in rows] == [1, 2, 2, 3, 5, 6]
    assert [r[3] for r in rows] == ["right", "right", "right", "left", "right", "right"]
    assert rows[-1][4] == 6 / 90 and sub.server_hello is not None and sub.reconnects == 0
    assert _integrity({("a", 0): rows}, {"a": "right"}) == 2         # the repeated seq, the left hand's frame
    assert sub.malformed_count == 2 and sub.others == 0


def test_a_load_subscriber_refused_by_the_service_says_so_when_closed():
    import asyncio

    from websockets.asyncio.server import serve

    from clients.client import Refused
    from service.bench.loadclients import LeanSubscription

    async def main():
        async with serve(lambda ws: ws.wait_closed(), "127.0.0.1", 0,
                         process_request=lambda conn, request: conn.respond(403, "bad token\n")) as server:
            port = server.sockets[0].getsockname()[1]
            sub = LeanSubscription(f"http://127.0.0.1:{port}", "a", "token", lambda m, arrival: None)
            sub.start()
            while sub.failure is None:
                await asyncio.sleep(0.01)
            with pytest.raises(Refused, match="HTTP 403"):
                await sub.close()

    asyncio.run(asyncio.wait_for(main(), 60))


def test_the_load_gloves_send_every_message_from_one_timer_and_one_held_glove_holds_no_other():
    """Two gloves streamed by ``stream_gloves`` to a real WebSocket server that answers glove a's
    ``sync`` only once glove b has sent everything: a stops at its flow-control limit (16 unconfirmed
    messages) while b streams on to its end; then a finishes. Each glove's server gets exactly the
    texts given, in order, and hello once."""
    import asyncio
    import json
    import time

    from websockets.asyncio.server import serve

    from service.bench.loadclients import LeanGlove, stream_gloves, ws_frames

    got = {"a": [], "b": []}
    b_done = answer_a = None

    def messages(name):
        out = [(0.0, {"type": "hello", "protocol": 1, "hand": "right", "source": name})]
        out.append((0.0, {"type": "calibration"}))
        out += [(0.001 * k, {"type": "imu", "t": 0.001 * k, "id": "index.1", "gyr": [0, 0, k], "acc": [0, 9.81, 0]})
                for k in range(100)]
        return out

    async def main():
        nonlocal b_done, answer_a
        b_done, answer_a = asyncio.Event(), asyncio.Event()
        msgs = {n: messages(n) for n in got}

        async def handler(ws):
            name = ws.request.path.split("?")[0].rsplit("/", 1)[-1]
            held_syncs = []

            async def answer_later():                     # a's syncs, once b is through
                await answer_a.wait()
                for i in held_syncs:
                    await ws.send(json.dumps({"type": "sync", "id": i}))
                held_syncs.clear()
            later = asyncio.create_task(answer_later())
            async for data in ws:
                m = json.loads(data)
                if m["type"] == "sync":
                    if name == "a" and not later.done():
                        held_syncs.append(m["id"])
                    else:
                        await ws.send(json.dumps({"type": "sync", "id": m["id"]}))
                    continue
                got[name].append(data)
                if m["type"] == "hello":
                    await ws.send(json.dumps({"type": "hello", "protocol": 1}))
                if name == "b" and len(got["b"]) == len(msgs["b"]):
                    b_done.set()

        async with serve(handler, "127.0.0.1", 0) as server:
            url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
            gloves = [LeanGlove(url, n, "token", max_unconfirmed=16) for n in got]
            await asyncio.gather(*(g.open(msgs[n][0][1]) for g, n in zip(gloves, got)))
            texts = {n: [json.dumps(m) for _, m in msgs[n]] for n in got}
            sent = {n: [] for n in got}
            stream = asyncio.create_task(stream_gloves(
                gloves, [msgs[n] for n in got], [ws_frames(texts[n]) for n in got],
                [lambda w, m, n=n: sent[n].append(m) for n in got], start=time.perf_counter()))
            await b_done.wait()
            held = len(got["a"])
            answer_a.set()
            await stream
            for g in gloves:
                await g.close()
            return texts, held, sent

    texts, held, sent = asyncio.run(asyncio.wait_for(main(), 60))
    assert held == 1 + 16                                    # hello, then the 16 messages flow control allows
    for n in ("a", "b"):                                    # hello as the glove encodes it, the rest as given
        assert json.loads(got[n][0]) == json.loads(texts[n][0]) and got[n][1:] == texts[n][1:]
        assert len(sent[n]) == len(texts[n])


def test_a_load_glove_whose_connection_drops_reconnects_and_streams_on():
    """The server closes a glove's first connection (1011) after 10 data messages: the glove connects
    again, sends hello and its calibration again, and streams on from where it was, in order, to its
    last message; the messages lost with the connection are counted (``unconfirmed_at_drops``)."""
    import asyncio
    import contextlib
    import json
    import time

    from websockets.asyncio.server import serve
    from websockets.exceptions import ConnectionClosed

    from service.bench.loadclients import LeanGlove, stream_gloves, ws_frames

    msgs = [(0.0, {"type": "hello", "protocol": 1, "hand": "left", "source": "g"}), (0.0, {"type": "calibration"})]
    msgs += [(0.001 * k, {"type": "imu", "t": 0.001 * k, "id": "index.1", "gyr": [0, 0, k], "acc": [0, 9.81, 0]})
             for k in range(100)]
    texts = [json.dumps(m) for _, m in msgs]
    connections = []

    async def handler(ws):
        got = []
        connections.append(got)
        with contextlib.suppress(ConnectionClosed):
            async for data in ws:
                m = json.loads(data)
                if m["type"] == "sync":
                    await ws.send(json.dumps({"type": "sync", "id": m["id"]}))
                    continue
                got.append(data)
                if m["type"] == "hello":
                    await ws.send(json.dumps({"type": "hello", "protocol": 1}))
                if len(connections) == 1 and len(got) == 12:         # hello, calibration, 10 samples
                    await ws.close(1011, "going away")

    async def main():
        async with serve(handler, "127.0.0.1", 0) as server:
            glove = LeanGlove(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "g", "token")
            await glove.open(msgs[0][1])
            await stream_gloves([glove], [msgs], [ws_frames(texts)], [lambda w, m: None], start=time.perf_counter())
            await glove.close()
            return glove

    glove = asyncio.run(asyncio.wait_for(main(), 60))
    assert glove.reconnects == 1 and len(connections) == 2
    first, second = connections                 # (the server may read a few more before its close is through)
    assert len(first) >= 12 and first[1:] == texts[1:len(first)]
    assert json.loads(second[0])["type"] == "hello" and second[1] == texts[1]      # calibration sent again
    resumed = texts.index(second[2])
    assert len(first) <= resumed and second[2:] == texts[resumed:]                   # in order, to the end
    assert glove.unconfirmed_at_drops >= resumed - len(first)


@pytest.mark.parametrize("clients", ["lean", "product"])
def test_the_generator_alone_streams_every_glove_and_reads_a_frame_per_pose(clients, capsys):
    """``python -m service.bench.generator_alone``: the sink sends each of a session's two subscribers a
    frame per pose its glove sent, and every one of them is read, with either kind of client."""
    import json

    from clients.glove import source_messages
    from service.bench.generator_alone import main as alone
    from service.sim.session import SimConfig

    assert alone(["--hands", "1", "--seconds", "1", "--clients", clients]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    config = SimConfig(motion="random", t_m_s=1.0, noise="both", hand_motion="slow-rotation", seed=0, hand="right")
    poses = sum(1 for _, m in source_messages(config) if m["type"] == "pose")
    assert out["clients"] == clients and out["frames_received"] == out["frames_sent"] == 2 * poses
    assert out["cpu_ms_per_hand_s"] > 0.0


def _imu_messages(n: int) -> list:
    out = [(0.0, {"type": "hello", "protocol": 1, "hand": "right", "source": "g"})]
    return out + [(0.001 * k, {"type": "imu", "t": 0.001 * k, "id": "index.1", "gyr": [0, 0, k], "acc": [0, 9.81, 0]})
                  for k in range(n)]


def test_a_load_glove_refused_for_good_while_flow_control_holds_it_ends_the_stream_with_the_refusal():
    """The service answers no ``sync`` (the glove is held at its 16 unconfirmed messages), then closes it
    with 1008 (refused for good): ``stream_gloves`` ends (it waited for a wake that never came) and the
    glove's close raises the refusal."""
    import asyncio
    import json
    import time

    from websockets.asyncio.server import serve

    from clients.client import Refused
    from service.bench.loadclients import LeanGlove, stream_gloves, ws_frames

    msgs = _imu_messages(500)

    async def handler(ws):
        count = 0
        async for data in ws:
            m = json.loads(data)
            if m["type"] == "hello":
                await ws.send(json.dumps({"type": "hello", "protocol": 1}))
            elif m["type"] != "sync":               # syncs never answered
                count += 1
                if count == 16:
                    await asyncio.sleep(0.2)        # the glove is held by then
                    await ws.close(1008, "refused for the test")
                    return

    async def main():
        async with serve(handler, "127.0.0.1", 0) as server:
            glove = LeanGlove(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "g", "token", max_unconfirmed=16)
            await glove.open(msgs[0][1])
            frames = ws_frames([json.dumps(m) for _, m in msgs])
            await stream_gloves([glove], [msgs], [frames], [lambda w, m: None], time.perf_counter())
            with pytest.raises(Refused, match="1008"):
                await glove.close(sync_timeout_s=1.0)

    asyncio.run(asyncio.wait_for(main(), 60))


def test_a_load_glove_whose_service_sent_its_close_frame_holds_no_other_glove_back():
    """The service sends glove a a close frame (1013) and closes TCP only later (a busy server): glove a
    writes nothing meanwhile (its connection is closing) and glove b, in the same process and timer, sends
    every message without waiting for a's TCP close; a reconnects and both end."""
    import asyncio
    import json
    import time

    from websockets.frames import Close, Frame, Opcode
    from websockets.http11 import Request
    from websockets.server import ServerProtocol

    from service.bench.loadclients import LeanGlove, stream_gloves, ws_frames

    tcp_close_after_s = 5.0
    closes: list = []
    tcp_closed: list = []

    class Service(asyncio.Protocol):
        def connection_made(self, transport):
            self.transport, self.proto, self.count, self.closing = transport, ServerProtocol(), 0, False
            self.path = ""

        def data_received(self, data):
            if self.closing:
                return                              # reads and drops, as a draining server may
            self.proto.receive_data(data)
            for event in self.proto.events_received():
                if isinstance(event, Request):
                    self.path = event.path.split("?")[0]
                    self.proto.send_response(self.proto.accept(event))
                elif event.opcode is Opcode.TEXT:
                    m = json.loads(event.data)
                    if m["type"] in ("hello", "sync"):
                        reply = {"type": "hello", "protocol": 1} if m["type"] == "hello" else m
                        self.proto.send_text(json.dumps(reply).encode())
                    elif self.path.endswith("/a") and not closes:
                        self.count += 1
                        if self.count == 30:
                            self.transport.write(Frame(Opcode.CLOSE, Close(1013, "busy").serialize()).serialize(mask=False))
                            self.closing = True
                            closes.append(True)

                            def close_tcp(transport=self.transport):
                                tcp_closed.append(True)
                                transport.close()
                            asyncio.get_running_loop().call_later(tcp_close_after_s, close_tcp)
                            return
            for chunk in self.proto.data_to_send():
                if chunk:
                    self.transport.write(chunk)

    async def main():
        loop = asyncio.get_running_loop()
        errors: list = []
        loop.set_exception_handler(lambda _, context: errors.append(context.get("exception")))
        server = await loop.create_server(Service, "127.0.0.1", 0)
        url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
        gloves = [LeanGlove(url, n, "token") for n in "ab"]
        msgs = [_imu_messages(400), _imu_messages(400)]
        for glove, m in zip(gloves, msgs):
            await glove.open(m[0][1])
        sent_b: list = []
        await stream_gloves(gloves, msgs, [ws_frames([json.dumps(x) for _, x in m]) for m in msgs],
                            [lambda w, m: None, lambda w, m: sent_b.append(bool(tcp_closed))], time.perf_counter())
        for glove in gloves:
            await glove.close(sync_timeout_s=1.0)
        server.close()
        return errors, sent_b, gloves[0].reconnects

    errors, sent_b, reconnects = asyncio.run(asyncio.wait_for(main(), 60))
    assert not errors and len(sent_b) == 401 and reconnects >= 1
    assert closes and not sent_b[-1]                        # b sent everything before a's TCP close came


def _raw_server_port(handle):
    """A raw TCP server (``asyncio.start_server``) of ``handle(reader, writer)``: the WebSocket handshake and
    frames written by hand, so that a test can answer as no WebSocket library would."""
    import asyncio
    return asyncio.start_server(handle, "127.0.0.1", 0)


def _accept(request: str) -> bytes:
    import base64
    import hashlib

    key = next(line.split(":", 1)[1].strip() for line in request.split("\r\n")
               if line.lower().startswith("sec-websocket-key"))
    accept = base64.b64encode(hashlib.sha1((key + "258EAFA5-E914-47DA-95CA-C5AB0DC85B11").encode()).digest()).decode()
    return (f"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Accept: {accept}\r\n\r\n").encode()


def _text(obj) -> bytes:
    import json
    payload = json.dumps(obj).encode()
    return b"\x81" + bytes([len(payload)]) + payload


def test_a_load_subscriber_fails_with_what_ended_it_a_bad_handshake_or_a_defect_on_its_message_path():
    """A handshake answered 101 without ``Upgrade`` (no HTTP status to retry on) and an exception in the
    frame callback each end the subscriber, and its close raises it (before, the first was swallowed and
    the second became silent reconnects)."""
    import asyncio

    from websockets.exceptions import InvalidUpgrade

    from service.bench.loadclients import LeanSubscription

    async def no_upgrade(reader, writer):
        await reader.readuntil(b"\r\n\r\n")
        writer.write(b"HTTP/1.1 101 Switching Protocols\r\nContent-Length: 0\r\n\r\n")
        await writer.drain()
        writer.close()

    async def one_frame(reader, writer):
        writer.write(_accept((await reader.readuntil(b"\r\n\r\n")).decode()))
        writer.write(_text({"type": "hello", "protocol": 1}) + _text({"type": "frame", "seq": 1, "hand": "right", "t": 0.0}))
        await writer.drain()
        await asyncio.sleep(30)

    def broken(frame, arrival):
        raise KeyError("a defect in the frame callback")

    async def run(handle, on_frame):
        server = await _raw_server_port(handle)
        try:
            sub = LeanSubscription(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "a", "t", on_frame)
            sub.start()
            while not sub._task.done() and sub.failure is None:
                await asyncio.sleep(0.01)
            try:
                await sub.close()
            except Exception as err:
                return err, sub.reconnects
            return None, sub.reconnects
        finally:
            server.close()

    err, _ = asyncio.run(asyncio.wait_for(run(no_upgrade, lambda f, a: None), 60))
    assert isinstance(err, InvalidUpgrade)
    err, reconnects = asyncio.run(asyncio.wait_for(run(one_frame, broken), 60))
    assert isinstance(err, KeyError) and reconnects == 0


def test_a_load_subscriber_s_refused_connection_closed_late_does_not_end_the_next_one():
    """The first handshake gets a 503 whose TCP close comes 1 s later, after the subscriber connected again:
    the late close of the old connection does not end the new one, whose frames all arrive."""
    import asyncio

    from clients.client import Backoff
    from service.bench.loadclients import LeanSubscription

    connections = []

    async def handle(reader, writer):
        first = not connections
        connections.append(writer)
        request = (await reader.readuntil(b"\r\n\r\n")).decode()
        if first:
            writer.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n\r\n")
            await writer.drain()
            await asyncio.sleep(1.0)
            writer.close()
            return
        writer.write(_accept(request) + _text({"type": "hello", "protocol": 1}))
        for i in range(20):
            writer.write(_text({"type": "frame", "seq": i, "hand": "right", "t": i / 90}))
            await writer.drain()
            await asyncio.sleep(0.1)
        await asyncio.sleep(30)

    async def main():
        server = await _raw_server_port(handle)
        seqs: list = []
        sub = LeanSubscription(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "a", "t",
                               lambda frame, arrival: seqs.append(frame.seq), backoff=Backoff(0.1, seed=1))
        sub.start()
        while len(seqs) < 20 and len(connections) < 3:
            await asyncio.sleep(0.01)
        reconnects = sub.reconnects
        for writer in connections:
            writer.transport.abort()
        await sub.close()
        server.close()
        return seqs, reconnects, len(connections)

    seqs, reconnects, connections_seen = asyncio.run(asyncio.wait_for(main(), 60))
    assert seqs == list(range(20)) and reconnects == 1 and connections_seen == 2


def test_a_load_subscriber_cuts_the_same_frames_from_the_bytes_however_they_are_read():
    """A raw server answers the handshake and sends messages of each length encoding (7-bit, 16-bit,
    64-bit), a ping, a message in two fragments, a MessagePack frame and a frame that is not JSON:
    once in one write with the handshake's response, and once cut into pieces of 1 to 7 bytes written
    apart. The subscriber cuts the frames itself from what it reads (the protocol gets the handshake,
    the ping and the fragments whole): both times every frame comes out whole and in order, the ping is
    answered with a pong carrying its payload, and the bad frame is counted."""
    import asyncio
    import json

    import msgspec
    from websockets.frames import Frame, Opcode

    from service.bench.loadclients import LeanSubscription

    def frame(seq, pad=0):
        return {"type": "frame", "t": seq / 90, "seq": seq, "hand": "right", "joints": {"pad": "x" * pad}}

    text = json.dumps(frame(5)).encode()
    messages = [Frame(Opcode.TEXT, json.dumps({"type": "hello", "protocol": 1}).encode()),
                Frame(Opcode.TEXT, json.dumps(frame(1)).encode()),
                Frame(Opcode.TEXT, json.dumps(frame(2, pad=7000)).encode()),      # 16-bit length
                Frame(Opcode.PING, b"are you there"),
                Frame(Opcode.TEXT, json.dumps(frame(3, pad=70000)).encode()),     # 64-bit length
                Frame(Opcode.BINARY, msgspec.msgpack.encode(frame(4))),
                Frame(Opcode.TEXT, text[:30], fin=False), Frame(Opcode.CONT, text[30:]),
                Frame(Opcode.TEXT, b"{not json"),
                Frame(Opcode.TEXT, json.dumps({"type": "gesture", "t": 0.1}).encode())]
    wire = b"".join(m.serialize(mask=False) for m in messages)
    pongs: list = []

    async def run(pieces: bool):
        async def handle(reader, writer):
            data = _accept((await reader.readuntil(b"\r\n\r\n")).decode()) + wire
            if not pieces:
                writer.write(data)
            else:
                i, k = 0, 0
                while i < len(data):
                    step = 1 + k % 7 if i < 600 or len(data) - i < 600 else 4096
                    writer.write(data[i:i + step])
                    await writer.drain()
                    await asyncio.sleep(0.001 if step < 10 else 0)
                    i, k = i + step, k + 1
            await writer.drain()
            got = await reader.readexactly(2 + 4 + len(b"are you there"))     # the pong, masked
            mask = got[2:6]
            pongs.append((got[0], bytes(b ^ mask[j % 4] for j, b in enumerate(got[6:]))))
            await asyncio.sleep(30)

        server = await _raw_server_port(handle)
        rows: list = []
        sub = LeanSubscription(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "a", "t",
                               lambda m, arrival: rows.append((m.seq, m.hand, m.t)))
        sub.start()
        while sub.gestures < 1 and sub._task is not None and not sub._task.done():
            await asyncio.sleep(0.01)
        while len(pongs) < (2 if pieces else 1):
            await asyncio.sleep(0.01)
        malformed, others, reconnects, failure = sub.malformed_count, sub.others, sub.reconnects, sub.failure
        sub._closing = True
        sub.transport.abort()
        await asyncio.gather(sub._task, return_exceptions=True)
        server.close()
        return rows, malformed, others, reconnects, failure

    for pieces in (False, True):
        rows, malformed, others, reconnects, failure = asyncio.run(asyncio.wait_for(run(pieces), 60))
        assert rows == [(s, "right", s / 90) for s in (1, 2, 3, 4, 5)], pieces
        assert (malformed, others, reconnects, failure) == (1, 0, 0, None)
    assert pongs == [(0x8A, b"are you there")] * 2


class _FakeTransport:
    """What a lean client writes (the handshake, pongs, closes), kept; aborts and EOF noted."""

    def __init__(self):
        self.out, self.aborted = bytearray(), False

    def write(self, data):
        self.out += data

    def abort(self):
        self.aborted = True

    def can_write_eof(self):
        return True

    def write_eof(self):
        self.out += b"<EOF>"

    def is_closing(self):
        return self.aborted


def _ws_frame(b0: int, payload: bytes, mask: bool = False, length_bits: int | None = None) -> bytes:
    """A WebSocket frame as a server would write it (``mask``: as no server may), its length in 7, 16 or
    64 bits (the least that fits unless ``length_bits``)."""
    n, m = len(payload), 0x80 if mask else 0
    if length_bits == 16 or (length_bits is None and 126 <= n < 65536):
        head = bytes([b0, 126 | m]) + n.to_bytes(2, "big")
    elif length_bits == 64 or (length_bits is None and n >= 65536):
        head = bytes([b0, 127 | m]) + n.to_bytes(8, "big")
    else:
        head = bytes([b0, n | m])
    if not mask:
        return head + payload
    key = b"\x01\x02\x03\x04"
    return head + key + bytes(c ^ key[i % 4] for i, c in enumerate(payload))


def _frame_text(seq: int, size: int = 0) -> bytes:
    import json

    base = {"type": "frame", "t": seq / 90, "seq": seq, "hand": "right", "joints": {"pad": ""}}
    base["joints"]["pad"] = "x" * max(0, size - len(json.dumps(base)))
    return json.dumps(base).encode()


def _handshake_response(request) -> bytes:
    """A server's valid answer to a client's handshake ``request``."""
    import base64
    import hashlib

    accept = base64.b64encode(hashlib.sha1((request.headers["Sec-WebSocket-Key"] +
                                            "258EAFA5-E914-47DA-95CA-C5AB0DC85B11").encode()).digest()).decode()
    return (f"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Accept: {accept}\r\n\r\n").encode()


def _outcome_of_library(wire: bytes, eof: bool) -> dict:
    """What websockets' own client protocol alone makes of the server's bytes after a valid handshake
    response: the data messages (checked as the load subscriber checks them), its state, its close code
    and what it wrote back."""
    import msgspec
    from websockets.client import ClientProtocol
    from websockets.frames import Opcode
    from websockets.http11 import Response
    from websockets.uri import parse_uri

    from service.bench.loadclients import decode_received

    proto = ClientProtocol(parse_uri("ws://127.0.0.1:9/v1/stream/a?token=t"), max_size=None)
    request = proto.connect()
    proto.send_request(request)
    out = bytearray(b"".join(proto.data_to_send()))
    head = _handshake_response(request)
    proto.receive_data(head + wire)
    if eof:
        proto.receive_eof()
    got = {"rows": [], "malformed": 0}
    parts, binary = [], False
    for event in proto.events_received():
        if isinstance(event, Response) or event.opcode not in (Opcode.TEXT, Opcode.BINARY, Opcode.CONT):
            continue
        if event.opcode is not Opcode.CONT:
            binary = event.opcode is Opcode.BINARY
        parts.append(event.data)
        if event.fin:
            try:
                m = decode_received(b"".join(parts), binary)
                if m.type == "frame":
                    got["rows"].append((m.seq, m.hand, m.t))
            except (msgspec.DecodeError, UnicodeDecodeError):
                got["malformed"] += 1
            parts = []
    for data in proto.data_to_send():
        out += data if data else b"<EOF>"
    got.update(state=proto.state.name, close=proto.close_sent.code if proto.close_sent else None,
               written=_frames_written(out))
    return got, head


def _frames_written(out: bytearray) -> list:
    """The (masked) frames a client wrote after its handshake request, as (opcode, payload)."""
    from websockets.frames import Frame
    from websockets.streams import StreamReader

    out = bytes(out).replace(b"<EOF>", b"")
    reader = StreamReader()
    reader.feed_data(out[out.find(b"\r\n\r\n") + 4:])
    reader.feed_eof()
    frames = []
    while True:
        parser = Frame.parse(reader.read_exact, mask=True)
        try:
            next(parser)
        except StopIteration as done:
            frames.append((done.value.opcode.name, bytes(done.value.data)))
            continue
        except EOFError:
            pass
        return frames


def _outcome_of_lean(wire: bytes, cuts, eof: bool) -> dict:
    """What ``LeanSubscription`` makes of the same bytes read in pieces ending at ``cuts`` (through its
    own buffer, as the transport reads into it), and whether it cut frames itself."""
    import asyncio

    from websockets.client import ClientProtocol

    from service.bench.loadclients import LeanSubscription

    loop = asyncio.new_event_loop()
    try:
        got = {"rows": [], "malformed": 0}
        sub = LeanSubscription("http://127.0.0.1:9", "a", "t", lambda m, a: got["rows"].append((m.seq, m.hand, m.t)))
        sub.proto = ClientProtocol(sub.uri, max_size=None)
        sub._opened, sub._lost = loop.create_future(), loop.create_future()
        sub.transport = _FakeTransport()
        request = sub.proto.connect()
        sub.proto.send_request(request)
        sub._flush()
        data, start = _handshake_response(request) + wire, 0     # (the same length as the library's)
        for cut in [c for c in cuts if 0 < c < len(data)] + [len(data)]:
            chunk, start = data[start:cut], cut
            while chunk:
                room = sub.get_buffer(-1)
                k = min(len(room), len(chunk))
                assert k, "the subscriber gave no room to read into"
                room[:k], chunk = chunk[:k], chunk[k:]
                sub.buffer_updated(k)
        if eof:
            sub.eof_received()
        assert sub.failure is None, sub.failure
        got["malformed"] = sub.malformed_count
        got.update(state=sub.proto.state.name, close=sub.proto.close_sent.code if sub.proto.close_sent else None,
                   written=_frames_written(sub.transport.out))
        return got, sub._framing
    finally:
        loop.close()


def test_a_load_subscriber_makes_of_any_bytes_what_the_websocket_library_makes_of_them():
    """The load subscriber's own cutting of whole data frames accepts exactly what websockets' client
    protocol accepts and leaves the rest to it: for each case (length encodings, a ping between fragments,
    a masked frame from the server, RSV bits, an unknown opcode, a text frame inside a fragmented message,
    data after a close, text that is not UTF-8, a frame cut short by EOF, frames larger than its buffer),
    read whole, in seeded random pieces and (the small ones) byte by byte, the frames delivered, the
    malformed count, the protocol's state and close code and what the client wrote back are the library's;
    and it did cut frames itself where the connection stayed open."""
    import random

    hello = _ws_frame(0x81, b'{"type":"hello","protocol":1}')

    def f(seq, size=0, **kw):
        return _ws_frame(0x81, _frame_text(seq, size), **kw)

    import msgspec
    cases = {
        "lengths": hello + b"".join(f(i, n) for i, n in enumerate([0, 125, 126, 127, 65535, 65536, 70000], 1))
        + _ws_frame(0x81, _frame_text(20), length_bits=16) + _ws_frame(0x81, _frame_text(21), length_bits=64)
        + _ws_frame(0x82, msgspec.msgpack.encode({"type": "frame", "t": 1.0, "seq": 22, "hand": "left"}))
        + _ws_frame(0x81, b"") + _ws_frame(0x81, b'{"type":"gesture","t":0.1}'),
        "ping and pong between fragments": hello + _ws_frame(0x01, _frame_text(1)[:20]) + _ws_frame(0x89, b"hi")
        + _ws_frame(0x8A, b"x") + _ws_frame(0x00, _frame_text(1)[20:40]) + _ws_frame(0x80, _frame_text(1)[40:]) + f(2),
        "masked by the server": hello + f(1) + f(2, mask=True) + f(3),
        "masked and long": hello + f(1) + f(2, 70000, mask=True) + f(3),
        "rsv1": hello + f(1) + _ws_frame(0xC1, _frame_text(2)) + f(3),
        "unknown opcode": hello + f(1) + _ws_frame(0x83, _frame_text(2)) + f(3),
        "text inside fragments": hello + _ws_frame(0x01, _frame_text(1)[:20]) + f(2) + _ws_frame(0x80, _frame_text(1)[20:]) + f(3),
        "data after a close": hello + f(1) + _ws_frame(0x88, (1000).to_bytes(2, "big") + b"bye") + f(2),
        "not utf-8": hello + _ws_frame(0x81, b'{"type":"fr\xffame","seq":1}') + f(2),
        "cut short by eof": hello + f(1) + f(2)[:-3],
        "larger than the buffer": hello + f(1) + f(2, 300_000) + f(3, 10) + f(4, 1_200_000) + _ws_frame(0x89, b"x")
        + f(5, 200_000) + f(6),
    }
    rng = random.Random(5)
    for name, wire in cases.items():
        eof = name == "cut short by eof"
        want, head = _outcome_of_library(wire, eof)
        total = len(head) + len(wire)
        chunkings = [[]] + [sorted(rng.sample(range(1, total), min(total - 1, k))) for k in (1, 1, 2, 5, 40) for _ in range(3)]
        if total < 3000:
            chunkings.append(range(1, total))
        for cuts in chunkings:
            got, cut_itself = _outcome_of_lean(wire, cuts, eof)
            assert got == want, (name, list(cuts)[:8])
            if want["state"] == "OPEN":
                assert cut_itself, name
    assert len(_outcome_of_library(cases["lengths"], False)[0]["rows"]) == 10     # (the cases mean something)


def test_a_session_s_subscribers_take_a_message_decoded_for_another_only_when_its_bytes_are_the_same():
    """``SessionDecodes``: a message whose bytes equal one already decoded for the session is taken as it
    is (counted in ``hits``) and let go once every other subscriber took it; one of the same length and
    the same first bytes that differs further on (another seq) is decoded on its own, and one that does
    not decode raises though a message of its length and head was kept."""
    import json

    import msgspec

    from service.bench.loadclients import SessionDecodes

    def text(seq):                                   # the seq past the head the messages are found by
        return json.dumps({"type": "frame", "pad": "x" * SessionDecodes.KEY, **_frame(seq, "right", 0.1)}).encode()

    shared = SessionDecodes(sharers=2)
    first = text(12)
    a = shared.decode(memoryview(bytearray(first)))
    b = shared.decode(memoryview(bytearray(first)))                 # the other subscriber, the same bytes
    assert (a.seq, a.hand, a.t) == (b.seq, b.hand, b.t) == (12, "right", 0.1)
    assert (shared.decoded, shared.hits, len(shared.kept)) == (1, 1, 0)   # both took it: let go
    assert shared.decode(first).seq == 12 and (shared.decoded, shared.hits) == (2, 1)
    other = text(21)
    assert len(other) == len(first) and other[:SessionDecodes.KEY + 8] == first[:SessionDecodes.KEY + 8]
    assert shared.decode(memoryview(bytearray(other))).seq == 21 and (shared.decoded, shared.hits) == (3, 1)
    assert shared.decode(first).seq == 12 and (shared.decoded, shared.hits) == (4, 1)     # not taken for the other
    broken = first[:-1] + b"x"                                      # same length and head, not JSON
    with pytest.raises(msgspec.DecodeError):
        shared.decode(broken)
    assert shared.decode(first).seq == 12 and (shared.decoded, shared.hits) == (4, 2)


def test_two_subscribers_sharing_their_session_s_decodes_still_see_their_own_order_and_hands():
    """Two subscribers of one session with one ``SessionDecodes``, from a real WebSocket server: the first
    gets frames 1, 2, 3, the second the same frames as 1, 3, 2 and then a frame of the other hand with
    the seq of one it had: the rows are each subscriber's own, and the integrity check finds the second
    subscriber's reordering and the foreign hand."""
    import asyncio
    import json

    from websockets.asyncio.server import serve

    from service.bench.loadclients import LeanSubscription, SessionDecodes

    order = {"0": [(1, "right"), (2, "right"), (3, "right")], "1": [(1, "right"), (3, "right"), (2, "right"), (4, "left")]}

    async def handler(ws):
        which = ws.request.path.split("?")[0].rsplit("/", 1)[-1][-1]
        await ws.send(json.dumps({"type": "hello", "protocol": 1}))
        for seq, hand in order[which]:
            await ws.send(json.dumps(_frame(seq, hand, seq / 90)))
        await ws.wait_closed()

    async def main():
        async with serve(handler, "127.0.0.1", 0) as server:
            url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
            shared = SessionDecodes()
            rows = {"0": [], "1": []}
            subs = [LeanSubscription(url, f"s{k}", "t", lambda m, arrival, k=k: rows[k].append((arrival, 0.0, m.seq, m.hand, m.t)),
                                     shared=shared) for k in "01"]
            for s in subs:
                s.start()
            while len(rows["0"]) < 3 or len(rows["1"]) < 4:
                await asyncio.sleep(0.01)
            for s in subs:
                await s.close()
            return rows, shared

    rows, shared = asyncio.run(asyncio.wait_for(main(), 60))
    assert [(r[2], r[3]) for r in rows["0"]] == order["0"] and [(r[2], r[3]) for r in rows["1"]] == order["1"]
    assert shared.decoded + shared.hits == 2 + 7 and shared.hits >= 1      # the hellos too; one taken at least
    assert _integrity({("a", 0): rows["0"]}, {"a": "right"}) == 0
    assert _integrity({("a", 1): rows["1"]}, {"a": "right"}) == 2


def test_the_gloves_timer_wakes_once_per_arm_at_the_latest_time_armed_and_never_before_it():
    """``_Ticker`` (a ``timerfd`` on Linux): armed twice, it calls back once, not before the later time;
    armed in the past it calls back at once; closed, it calls back no more. ``stream_gloves`` sends no
    message before its due time (each lag >= 0, one per message)."""
    import asyncio
    import json
    import sys
    import time

    from service.bench.loadclients import _Ticker

    async def ticks():
        loop = asyncio.get_running_loop()
        calls: list = []
        ticker = _Ticker(loop, lambda: calls.append(time.monotonic()))
        assert ticker.precise or not sys.platform.startswith("linux")
        first = time.monotonic() + 0.002
        ticker.arm(first)
        later = time.monotonic() + 0.0055
        ticker.arm(later)                                   # replaces the first
        while not calls:
            await asyncio.sleep(0.001)
        await asyncio.sleep(0.02)
        assert len(calls) == 1 and calls[0] >= later
        ticker.arm(time.monotonic() - 1.0)                  # past: at once
        while len(calls) < 2:
            await asyncio.sleep(0.001)
        ticker.arm(time.monotonic() + 0.003)
        ticker.close()
        await asyncio.sleep(0.02)
        assert len(calls) == 2

    asyncio.run(asyncio.wait_for(ticks(), 60))

    from websockets.asyncio.server import serve

    from service.bench.loadclients import LeanGlove, stream_gloves, ws_frames

    msgs = _imu_messages(60)

    async def handler(ws):
        async for data in ws:
            m = json.loads(data)
            if m["type"] in ("hello", "sync"):
                await ws.send(json.dumps({"type": "hello", "protocol": 1} if m["type"] == "hello" else m))

    async def stream():
        async with serve(handler, "127.0.0.1", 0) as server:
            glove = LeanGlove(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "g", "t")
            await glove.open(msgs[0][1])
            lags: list = []
            await stream_gloves([glove], [msgs], [ws_frames([json.dumps(m) for _, m in msgs])], [lambda w, m: None],
                                time.perf_counter(), lags=lags)
            await glove.close()
            return lags

    lags = asyncio.run(asyncio.wait_for(stream(), 60))
    assert len(lags) == len(msgs) and min(lags) >= 0.0


def test_a_subscriber_read_at_the_gloves_wakes_takes_a_frame_s_arrival_as_the_moment_its_bytes_reached_the_socket():
    """``TickReads``: a subscriber taken from the event loop is read only at ``read()``; a frame written
    by the server, then left unread 30 ms, arrives (the kernel's receive time) between the server's
    write's start and end, not at the read; ``stop()`` gives the connection back to the loop, which reads
    the next frame by itself."""
    import asyncio
    import time

    from websockets.frames import Frame, Opcode

    from service.bench.loadclients import LeanSubscription, TickReads

    if not TickReads.available:
        pytest.skip("TickReads needs Linux (epoll, SO_TIMESTAMPNS)")

    def wire(obj) -> bytes:
        import json
        return Frame(Opcode.TEXT, json.dumps(obj).encode()).serialize(mask=False)

    async def main():
        conn = {}

        async def handle(reader, writer):
            writer.write(_accept((await reader.readuntil(b"\r\n\r\n")).decode()) + wire({"type": "hello", "protocol": 1}))
            conn["writer"] = writer
            await reader.read()

        server = await _raw_server_port(handle)
        port = server.sockets[0].getsockname()[1]
        reads, rows = TickReads(), []
        sub = LeanSubscription(f"http://127.0.0.1:{port}", "a", "t", lambda m, arrival: rows.append((arrival, m.seq)),
                               reads=reads)
        sub.start()
        while sub.server_hello is None:
            await asyncio.sleep(0.01)
        reads.start([sub])
        writer = conn["writer"]
        # frames until one came with the kernel's time (the kernel turns its receive times on shortly after
        # the first socket asks)
        seq = 0
        while reads.reads == reads.unstamped and seq < 200:
            seq += 1
            writer.write(wire(_frame(seq, "right", seq / 90)))
            time.sleep(0.005)
            reads.read()
        assert reads.reads > reads.unstamped and [s for _, s in rows] == list(range(1, seq + 1))
        moments = []
        for k in range(3):
            seq += 1
            before = time.perf_counter()
            writer.write(wire(_frame(seq, "right", seq / 90)))          # sent at once (nothing queued)
            after = time.perf_counter()
            time.sleep(0.03)                        # the loop does not run: only read() reads the subscriber
            assert len(rows) == seq - 1
            reads.read()
            moments.append((before, after, time.perf_counter()))
        assert len(rows) == seq
        for (arrival, _), (before, after, read_at) in zip(rows[-3:], moments):
            assert before - 1e-3 <= arrival <= after + 1e-3 and arrival < read_at - 0.02
        reads.stop()                                # back to the loop: the next frame read without read()
        writer.write(wire(_frame(seq + 1, "right", (seq + 1) / 90)))
        while len(rows) < seq + 1:
            await asyncio.sleep(0.01)
        await sub.close()
        server.close()
        return rows, sub

    rows, sub = asyncio.run(asyncio.wait_for(main(), 60))
    assert [s for _, s in rows] == list(range(1, len(rows) + 1)) and sub.reconnects == 0 and not sub._polled


def test_a_subscriber_read_at_the_gloves_wakes_whose_connection_ends_reconnects_and_is_read_so_again():
    """The server ends a polled subscriber's first connection (a close frame, then TCP) after two frames:
    ``read()`` gives the end to the event loop, the subscriber reconnects, is taken again once open, and
    reads the second connection's frames at ``read()`` too; every frame comes once, in order."""
    import asyncio
    import json

    from websockets.frames import Close, Frame, Opcode

    from service.bench.loadclients import LeanSubscription, TickReads

    if not TickReads.available:
        pytest.skip("TickReads needs Linux (epoll, SO_TIMESTAMPNS)")

    def wire(obj) -> bytes:
        return Frame(Opcode.TEXT, json.dumps(obj).encode()).serialize(mask=False)

    connections = []

    async def handle(reader, writer):
        connections.append(writer)
        n = len(connections)
        writer.write(_accept((await reader.readuntil(b"\r\n\r\n")).decode()) + wire({"type": "hello", "protocol": 1}))
        for seq in ((1, 2) if n == 1 else (3, 4, 5)):
            writer.write(wire(_frame(seq, "right", seq / 90)))
            await asyncio.sleep(0.01)
        if n == 1:
            writer.write(Frame(Opcode.CLOSE, Close(1011, "restarting").serialize()).serialize(mask=False))
            await asyncio.sleep(0.05)
            writer.close()
            return
        await reader.read()

    async def main():
        server = await _raw_server_port(handle)
        reads, rows = TickReads(), []
        sub = LeanSubscription(f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}", "a", "t",
                               lambda m, arrival: rows.append(m.seq), reads=reads)
        reads.start([])                             # taken as soon as it is open
        sub.start()
        while len(rows) < 5:
            reads.read()
            await asyncio.sleep(0.002)
        polled_then = sub._polled
        await sub.close()
        server.close()
        return rows, sub, reads, polled_then

    rows, sub, reads, polled_then = asyncio.run(asyncio.wait_for(main(), 60))
    assert rows == [1, 2, 3, 4, 5] and sub.reconnects == 1 and len(connections) == 2
    assert polled_then and reads.reads >= 2 and not sub._polled


def test_the_gloves_schedule_puts_every_message_on_one_timeline_and_starts_each_time_with_another_glove():
    from service.bench.loadclients import GloveSchedule

    def msgs(t0):
        return [(t0, {"type": "hello"}), (t0, {"type": "calibration"}), (t0 + 0.25, {"type": "imu_batch"}),
                (t0 + 0.5, {"type": "imu_batch"})]
    messages = [msgs(0.0), msgs(2.0), msgs(0.5)[:3]]
    frames = [[b"h", b"c", b"1", b"2"], [b"H", b"C", b"3", b"4"], [b"x", b"y", b"5"]]
    plan = GloveSchedule(messages, frames)
    assert plan.offsets == [0.0, 0.25, 0.5]                       # each glove's times from its first message
    assert plan.gloves == [[0, 0, 1, 1, 2, 2], [1, 2, 0], [0, 1]]     # hello and calibration at 0: twice each
    assert plan.frames[0] == [None, b"c", b"1", b"2"] and plan.calibrations == [{1}, {1}, {1}]
    assert plan.due[2] == [0.0, 0.0, 0.25]


def test_a_frame_s_latency_counts_from_its_glove_s_latest_send_before_it_arrived():
    import numpy as np

    from service.bench.load import _rows
    from service.bench.loadclients import Received

    got = [(0.5, Received("frame", 1, "right", 0.0)), (1.25, Received("frame", 2, "right", 0.01)),
           (2.0, Received("frame", 3, "right", 0.02))]
    rows = _rows(got, [1.0, 1.2, 1.3, 2.0])       # a frame read after sends made after it arrived
    assert np.isnan(rows[0][1]) and rows[1][1] == pytest.approx(0.05) and rows[2][1] == 0.0
    assert [r[2:] for r in rows] == [(1, "right", 0.0), (2, "right", 0.01), (3, "right", 0.02)]
    assert _rows([], [1.0]) == [] and np.isnan(_rows(got[:1], [])[0][1])
