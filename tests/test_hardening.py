"""The reliability and security findings against the service, each reproduced against a real server
(``ServerThread``: uvicorn on a free localhost port, real WebSocket clients): hostile or absurd input,
diverging filters, NaN on the wire, recordings, tokens and settings, compiled kernels, and the command
line's errors."""
import asyncio
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import msgpack
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from clients.client import Publisher, Refused, Subscription, rest
from clients.glove import source_messages
from service import numba_cache_dir
from service.api.config import ServiceSettings, SettingsError
from service.api.server import ServerThread
from service.pipeline.hand import HandSession
from service.pipeline.tracked import TrackedHand
from service.protocol import ProtocolError, parse_line, parse_message
from service.protocol.messages import Imu, ImuBatch, ImuSample, Pose, SamplesRefused
from service.protocol.wire import encode
from service.sim.session import SimConfig

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE, SOURCE2, VIEWER, ADMIN = "src-token-1", "src-token-2", "view-token-1", "admin-token-1"
HELLO = {"type": "hello", "protocol": 1, "hand": "right"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    rec = tmp_path_factory.mktemp("recordings")
    settings = ServiceSettings.load(port=0, admin_token=ADMIN, record_dir=str(rec),
                                    tokens={SOURCE: "source", VIEWER: "viewer"})
    with ServerThread(settings) as srv:
        yield srv


def _messages(seed=1, motion="grasp"):
    return [m for _, m in source_messages(SimConfig(motion=motion, noise="white", seed=seed, t_m_s=1.0))]


async def _replies(ws, messages, sentinel=True):
    """Send each message, then a sentinel (an unknown type, always answered): the replies of each
    message are the ones before its sentinel's reply."""
    out = []
    for m in messages:
        await ws.send(m if isinstance(m, (str, bytes)) else json.dumps(m))
        await ws.send(json.dumps({"type": "__sentinel__"}))
        got = []
        while True:
            data = await ws.recv()
            reply = msgpack.unpackb(data) if isinstance(data, bytes) else json.loads(data)
            if reply.get("code") == "unknown_type" and "__sentinel__" in reply.get("detail", ""):
                break
            got.append(reply)
        out.append(got)
    return out


def _sessions(server, token=ADMIN):
    return {s["session"]: s for s in rest(server.url, "GET", "/v1/sessions", token)[1]}


async def _stream_watched(server, name, messages):
    """Stream ``messages`` (after a hello) into session ``name`` in lockstep (``_replies``) while a
    subscriber watches it; returns the replies and every frame up to the session's last."""
    frames = []
    sub = Subscription(server.ws_url, name, VIEWER)

    async def collect():
        async for m in sub:
            if m["type"] == "frame":
                frames.append(m)
    task = asyncio.create_task(collect())
    while sub.server_hello is None:
        await asyncio.sleep(0.02)
    async with connect(f"{server.ws_url}/v1/ingest/{name}?token={SOURCE}") as ws:
        # in lockstep: when a message's reply has come, the frames it made are in the subscriber's queue
        replies = await _replies(ws, [HELLO, *messages])
    produced = _sessions(server)[name]["frames_out"]
    deadline = time.monotonic() + 120                # bounds a failure
    while not frames or frames[-1]["seq"] < produced:  # the last frame (a slow subscriber loses the oldest)
        assert time.monotonic() < deadline, f"frame {produced} never arrived"
        await asyncio.sleep(0.02)
    await sub.close()
    task.cancel()
    return replies, frames


# -- F1, F2, F8: absurd but schema-valid numbers ---------------------------------------------------------

def test_huge_timestamps_are_refused_and_the_service_keeps_answering(server):
    t0 = 2.0 ** 47          # where t + 1/90 == t in float64: the frame schedule used to loop forever

    def batch(t):
        return {"type": "imu_batch", "samples": [{"t": t, "id": s, "gyr": [0, 0, 0], "acc": [0, 9.81, 0]}
                                                 for s in ("index.1", "index.2")]}

    async def go():
        async with connect(f"{server.ws_url}/v1/ingest/hang?token={SOURCE}") as ws:
            return await _replies(ws, [HELLO, {"type": "pose", "t": t0, "position": [0, 1, 0], "orientation": [0, 0, 0, 1]},
                                       batch(t0), {"type": "pose", "t": t0 + 0.0625, "position": [0, 1, 0],
                                                   "orientation": [0, 0, 0, 1]}, batch(t0 + 0.0625)])
    replies = asyncio.run(go())
    assert [r[0]["type"] for r in replies] == ["hello", "error", "error", "error", "error"]
    assert all(r[0]["code"] == "invalid_message" and "t: Input should be less than or equal to" in r[0]["detail"]
               for r in replies[1:])
    assert rest(server.url, "GET", "/health")[0] == 200


def test_the_frame_schedule_ends_where_float64_cannot_step(tmp_path):
    """Past the protocol's range check (messages built without validation), the pipeline itself must
    not loop: at 2**47 s one frame step does not change the time."""
    hand = HandSession()
    t0 = 2.0 ** 47
    done = threading.Event()

    def feed():
        for k in range(4):
            t = t0 + 0.0625 * k
            hand.handle(Pose.model_construct(type="pose", t=t, position=[0, 1, 0], orientation=[0, 0, 0, 1], valid=True))
            hand.handle(ImuBatch.model_construct(type="imu_batch", samples=[
                ImuSample.model_construct(t=t, id=s, gyr=[0, 0, 0], acc=[0, 9.81, 0]) for s in ("index.1", "index.2")]))
        done.set()
    worker = threading.Thread(target=feed, daemon=True)
    worker.start()
    assert done.wait(120), "the pipeline hangs on timestamps of 2**47 s"


@pytest.mark.parametrize("bad, field", [
    ({"type": "imu", "t": 0.0, "id": "index.1", "gyr": [1e300, 0, 0], "acc": [0, 9.81, 0]}, "gyr.0"),
    ({"type": "imu", "t": 0.0, "id": "index.1", "gyr": [0, 0, 0], "acc": [0, 9.81, 5e3]}, "acc.2"),
    ({"type": "pose", "t": 0.0, "position": [1e300, 0, 0], "orientation": [0, 0, 0, 1]}, "position.0"),
    ({"type": "calibration", "fingers": {"index": {"base": {"position": [1e300, 0, 0]}}}}, "fingers.index.base.position.0"),
    ({"type": "calibration", "fingers": {"index": {"lengths": [1e-300, 1e-300, 1e-300]}}}, "fingers.index.lengths.0"),
])
def test_physically_impossible_values_are_refused_naming_the_field(bad, field):
    with pytest.raises(Exception) as err:
        parse_message(bad)
    assert err.value.code == "invalid_message" and field in err.value.detail


def test_one_absurd_sample_does_not_poison_a_session(server):
    """A source sends one out-of-range gyro sample mid-stream: it gets an error naming the field, and
    the session keeps producing frames for the well-formed messages after it."""
    msgs = _messages(seed=2)
    half = len(msgs) // 2
    t_bad = next(m for m in msgs[half:] if m["type"] == "imu_batch")["samples"][0]["t"]
    bad = {"type": "imu", "t": t_bad + 1e-4, "id": "index.1", "gyr": [1e300, 0, 0], "acc": [0, 9.81, 0]}

    replies, frames = asyncio.run(_stream_watched(server, "poison", [*msgs[2:half], bad, *msgs[half:]]))
    bad_reply = replies[half - 1]
    assert bad_reply and bad_reply[0]["code"] == "invalid_message" and "gyr.0" in bad_reply[0]["detail"]
    assert not [r for r in replies[half:] for r in r]            # the well-formed rest: accepted in silence
    after = [f for f in frames if f["t"] > t_bad]
    assert len(after) > 20
    for f in after:
        assert all(math.isfinite(v) for fi in f["fingers"].values() for k, v in fi.items() if k != "mode")


def _batch_with(batch: dict, index: int, sample: dict) -> dict:
    return {**batch, "samples": [*batch["samples"][:index], sample, *batch["samples"][index:]]}


def test_an_invalid_sample_refuses_only_itself_and_the_batch_goes_on():
    """The imu_batch rule: samples with a problem of their own are refused one by one, named by index;
    a batch whose problem is not inside single samples, or with no valid sample, is refused whole."""
    batch = next(m for m in _messages(seed=4) if m["type"] == "imu_batch")
    bad = {"t": 0.0, "id": "index.1", "gyr": [1e300, 0, 0], "acc": [0, 9.81, 0]}
    odd = _batch_with(_batch_with(batch, 1, bad), 4, {"t": 0.0, "id": "index.1", "gyr": [0, 0, 0]})
    with pytest.raises(SamplesRefused) as err:
        parse_message(odd)
    assert err.value.code == "invalid_samples" and err.value.refused == [1, 4]
    assert f"2 of {len(odd['samples'])} samples refused (samples 1, 4)" in err.value.detail
    assert "samples.1.gyr.0" in err.value.detail and "samples.4.acc" in err.value.detail
    assert err.value.kept == parse_message(batch)                 # the others, in their order
    for whole in ({**batch, "samples": [bad, bad]},                   # no valid sample
                  {**batch, "samples": []},                           # none at all
                  {**batch, "samples": "none"},                       # a problem outside the samples
                  {**batch, "samples": batch["samples"] * 4096}):     # too many
        with pytest.raises(ProtocolError) as err:
            parse_message(whole)
        assert not isinstance(err.value, SamplesRefused) and err.value.code == "invalid_message"


def test_a_batch_with_one_bad_sample_streams_as_the_batch_without_it():
    """Live: one out-of-range sample inside a batch is answered ``invalid_samples`` naming it, and the
    session's frames equal those of the same stream without that sample (the batch's other samples
    were processed; refusing the whole batch would lose ten samples and change the angles)."""
    msgs = _messages(seed=5)[2:]
    k = next(i for i, m in enumerate(msgs) if m["type"] == "imu_batch" and i > len(msgs) // 3)
    bad = {"t": msgs[k]["samples"][0]["t"], "id": "index.2", "gyr": [0, 0, 0], "acc": [0, 9.81, 1e300]}
    attacked = [*msgs[:k], _batch_with(msgs[k], 3, bad), *msgs[k + 1:]]

    settings = ServiceSettings.load(port=0, admin_token=ADMIN, tokens={SOURCE: "source", VIEWER: "viewer"},
                                    subscriber_queue_frames=10_000)       # every frame kept for the comparison
    with ServerThread(settings) as srv:
        replies, frames = asyncio.run(_stream_watched(srv, "batch-bad", attacked))
        ref_replies, ref_frames = asyncio.run(_stream_watched(srv, "batch-ref", msgs))
    assert [r for r in ref_replies[1:] if r] == []
    errors = [(i, e) for i, r in enumerate(replies[1:]) for e in r]
    assert len(errors) == 1 and errors[0][0] == k
    reply = errors[0][1]
    assert reply["code"] == "invalid_samples" and reply["samples"] == [3] and "samples.3.acc.2" in reply["detail"]
    assert len(frames) > 20 and [f["seq"] for f in frames] == list(range(1, len(frames) + 1))
    assert [(f["t"], f["fingers"]) for f in frames] == [(f["t"], f["fingers"]) for f in ref_frames]


def test_a_diverged_filter_resets_and_the_frames_stay_finite():
    """Past the protocol's checks (a sample built without validation), a non-finite gyro makes the
    estimator diverge: the pipeline resets it, says so in the status, and every later frame is finite."""
    msgs = [parse_message(m) for m in _messages(seed=3)]
    hand = TrackedHand()
    out = []
    injected = False
    for m in msgs:
        out += hand.handle(m)
        if not injected and isinstance(m, ImuBatch) and len(out) > 20:
            t = m.samples[0].t + 1e-4
            out += hand.handle(Imu.model_construct(type="imu", t=t, id="index.1", gyr=[1e300, 0, 0], acc=[0, 9.81, 0]))
            injected = True
    frames = [m for m in out if m["type"] == "frame"]
    assert frames[-1]["status"]["filter_resets"] >= 1
    later = [f for f in frames if f["status"]["filter_resets"] >= 1]
    assert len(later) > 20
    for f in later:
        json.dumps(f, allow_nan=False)          # raises on NaN or infinity anywhere


def test_one_finger_diverging_does_not_take_the_hands_shared_acceleration_error_with_it():
    """The fingers advanced together share one estimate of the optics' acceleration error (``chain``).
    A finger whose filter diverges (its state made non-finite once, as a numerical failure would) may
    carry that into the shared error in its tick: the fingers updated after it in that tick are reset
    with it, and the shared error restarts. Kept non-finite, it reset every finger on every later tick
    (930 resets in 170 frames here)."""
    from service.pipeline.hand import PipelineSettings
    from service.sim.session import simulate

    msgs = list(simulate(SimConfig(motion="pinch", noise="both", seed=4, duration_s=3.0)).messages(include_truth=False))
    session = HandSession("right", PipelineSettings())
    frames, resets_then = [], None
    for m in msgs:
        frames += session.handle(parse_message(m)).frames
        if resets_then is None and len(frames) > 100 and session._fingers["index"].estimator._state is not None:
            session._fingers["index"].estimator._state["x"][0, 0] = math.nan
            resets_then = session.counters.filter_resets
    assert resets_then == 0 and len(frames) > 250
    assert 1 <= session.counters.filter_resets <= 5          # one tick's worth: index and the fingers after it
    assert all(math.isfinite(v) for v in session._together._dl.tolist() + session._together._pd.ravel().tolist())


def test_nothing_sent_contains_nan():
    message = {"type": "gesture", "t": 1.0, "ray": {"origin": [0.0, 1.0, 0.0], "direction": [math.nan, math.inf, 0.0]}}
    text = encode(message, binary=False)
    back = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} on the wire"))
    assert back["ray"]["direction"] == [None, None, 0.0]
    assert back["invalid"] == ["ray.direction[0]", "ray.direction[1]"]
    packed = msgpack.unpackb(encode(message, binary=True))
    assert packed["invalid"] == back["invalid"]


# -- F6, F7, F13: messages that used to drop the connection or differ on replay ------------------------------

def test_hostile_encodings_get_error_replies_and_the_connection_stays(server):
    async def go():
        async with connect(f"{server.ws_url}/v1/ingest/hostile?token={SOURCE}") as ws:
            replies = await _replies(ws, [
                HELLO,
                "[" * 970 + "]" * 970,                    # a depth bomb (it raised RecursionError and dropped the connection)
                "[" * 100_000 + "]" * 100_000,            # nested too deeply for the JSON parser whatever the stack
                msgpack.packb({"type": "imu", "t": 1.0, "id": "index.1", "gyr": [0, 0, 0], "acc": [0, 9.81, 0],
                               "blob": b"\x00\x01"}),                          # bin value in an unknown field
                msgpack.packb({"type": "imu", "t": 1.0, "id": "index.1", "gyr": [0, 0, 0], "acc": [0, 9.81, 0],
                               "x": msgpack.ExtType(5, b"zz")}),
                "\u00e9" * 1_000_100,                                          # 2,000,200 bytes, 1,000,100 characters
                _messages()[1],                                     # a calibration placing index.1 and index.2
                {"type": "imu", "t": 2.0, "id": "index.0", "gyr": [0, 0, 0], "acc": [0, 9.81, 0]},   # not placed
            ])
            await ws.send('{"type":"hello","protocol":' + "9" * 130 + ',"hand":"right"}')
            reply = json.loads(await ws.recv())
            try:
                await ws.recv()
            except Exception:
                pass
            return replies, reply, ws.close_code, ws.close_reason
    replies, reply, code, reason = asyncio.run(go())
    # 970 levels: parsed or not depending on the stack depth the parser starts at; refused either way
    assert [r["code"] for r in replies[1]] in (["invalid_json"], ["invalid_message"])
    assert [[r["code"] for r in rs] for rs in replies[2:]] == [["invalid_json"], ["invalid_msgpack"], ["invalid_msgpack"],
                                                               ["message_too_large"], [], ["unknown_sensor"]]
    assert "nested too deeply" in replies[2][0]["detail"]
    assert "2000200 bytes" in replies[5][0]["detail"]
    # a 130-digit protocol: refused with a reason that fits a close frame (it used to drop the connection)
    assert reply["code"] == "unsupported_protocol"
    assert code == 1008 and reason.startswith("unsupported protocol 999")


def test_a_defect_while_processing_is_answered_and_the_connection_stays(monkeypatch):
    """The defect is injected in this process: the session's hand runs on the event loop here
    (``hand_workers=0``); a hand worker process answers the same way (``hands.worker``)."""
    from service.api.sessions import LiveSession
    ingest = LiveSession.ingest

    async def faulty(self, raw, parsed):            # an injected defect in this session's processing
        if self.name == "defect" and parsed.type == "pose":
            raise TypeError("injected")
        return await ingest(self, raw, parsed)
    monkeypatch.setattr(LiveSession, "ingest", faulty)

    async def go(server):
        async with connect(f"{server.ws_url}/v1/ingest/defect?token={SOURCE}") as ws:
            return await _replies(ws, [HELLO, {"type": "pose", "t": 1.0, "valid": False}, _messages()[1]])
    settings = ServiceSettings.load(port=0, admin_token=ADMIN, tokens={SOURCE: "source"}, hand_workers=0)
    with ServerThread(settings) as server:
        replies = asyncio.run(go(server))
    assert [[r["code"] for r in rs] for rs in replies[1:]] == [["internal_error"], []]
    assert "TypeError while processing pose" in replies[1][0]["detail"] and "injected" not in replies[1][0]["detail"]


def test_a_recording_holds_what_was_processed_and_replays_without_skips(server, tmp_path):
    rest(server.url, "PUT", "/v1/sessions/rec7/config", ADMIN, {"record": True})
    msgs = _messages(seed=4)

    async def go():
        async with connect(f"{server.ws_url}/v1/ingest/rec7?token={SOURCE}") as ws:
            lines = [json.dumps(HELLO)] + [json.dumps(m) for m in msgs[2:]]
            # an unknown field with a literal that parses to infinity, and a MessagePack NaN in one
            lines[5] = lines[5][:-1] + ',"note":1e400}'
            replies = await _replies(ws, lines)
            mp = dict(msgs[-1], t=msgs[-1].get("t", 0), q=float("nan"))
            replies += await _replies(ws, [msgpack.packb(mp)])
            return replies
    asyncio.run(go())
    path = _sessions(server)["rec7"]["recording"]
    assert path
    rest(server.url, "PUT", "/v1/sessions/rec7/config", ADMIN, {"record": False})       # closes the file
    text = open(path, encoding="utf-8").read()
    assert "Infinity" not in text and "NaN" not in text and '"note"' not in text
    for line in text.splitlines():
        parse_line(line)                    # every recorded line replays


# -- F9, F10, F11: tokens and what each role sees ----------------------------------------------------------

def test_any_token_text_is_compared_safely(server):
    for token in ("tökén", "", " ", "a" * 5000):
        assert rest(server.url, "GET", "/v1/sessions", token)[0] == 401
    assert rest(server.url, "GET", "/v1/sessions?token=")[0] == 401

    async def handshake(token):
        try:
            async with connect(f"{server.ws_url}/v1/stream/x?token={token}"):
                return 101
        except InvalidStatus as err:
            return err.response.status_code
    assert asyncio.run(handshake("t%C3%B6k%C3%A9n")) in (401, 403)       # refused, not a server error


@pytest.mark.parametrize("values, setting", [
    ({"tokens": {"": "source"}}, "tokens"), ({"tokens": {"short": "viewer"}}, "tokens"),
    ({"admin_token": "a"}, "admin_token"), ({"tokens": {"has space 123": "source"}}, "tokens"),
    ({"tokens": {"valid-token-1": "root"}}, "tokens"), ({"estimator": "nosuch"}, "estimator"),
    ({"record_dir": "/proc/version"}, "record_dir"), ({"record_dir": "/proc/version/rec"}, "record_dir"),
])
def test_bad_settings_are_refused_at_start_naming_the_setting(values, setting):
    with pytest.raises(SettingsError) as err:
        ServiceSettings.load(**values)
    lines = str(err.value).splitlines()
    assert len(lines) == 1 and f"'{setting}" in lines[0]
    for token in values.get("tokens", {}):
        if token.strip():
            assert token not in str(err.value)


def test_a_bad_bus_url_is_named_without_its_password():
    with pytest.raises(SettingsError) as err:
        ServiceSettings.load(bus="http://user:pw-not-shown@bus.example:4222")
    assert "'bus'" in str(err.value) and "bus.example:4222" in str(err.value)
    assert "pw-not-shown" not in str(err.value)


def test_each_role_sees_only_what_it_needs(server):
    rest(server.url, "PUT", "/v1/sessions/seen/config", ADMIN, {"record": True})
    viewer = _sessions(server, VIEWER)["seen"]
    admin = _sessions(server, ADMIN)["seen"]
    assert viewer["recording"] is True and admin["recording"].endswith(".jsonl")
    for token in (SOURCE, VIEWER):
        status, text = rest(server.url, "GET", "/metrics", token)
        assert status == 200 and "fingertrack_sessions" in text and 'session="' not in text
    assert 'session="' in rest(server.url, "GET", "/metrics", ADMIN)[1]
    rest(server.url, "PUT", "/v1/sessions/seen/config", ADMIN, {"record": False})


def test_the_docs_page_loads_nothing_from_elsewhere(server):
    status, page = rest(server.url, "GET", "/docs")
    assert status == 200 and "swagger-ui-bundle.js" in page
    assert "http://" not in page.replace(server.url, "") and "https://" not in page
    script = page.split('src="')[1].split('"')[0]
    assert rest(server.url, "GET", script)[0] == 200


def test_a_full_session_table_is_not_ready():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    max_sessions=1)
    with ServerThread(settings) as srv:
        assert rest(srv.url, "GET", "/ready")[0] == 200
        assert rest(srv.url, "PUT", "/v1/sessions/only/config", ADMIN, {"record": False})[0] == 200
        status, body = rest(srv.url, "GET", "/ready")
        assert status == 503 and body["ready"] is False and "full" in body["reason"]


def test_a_viewer_creates_no_session_and_waits_for_its_source():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    max_sessions=2, idle_timeout_s=0.5)
    with ServerThread(settings) as srv:
        async def go():
            hellos = []
            for i in range(8):                       # typo names: no table entries
                async with connect(f"{srv.ws_url}/v1/stream/typo{i}?token={VIEWER}") as ws:
                    hellos.append(json.loads(await ws.recv()))
            assert _sessions(srv) == {}
            # a viewer waiting for "later" gets the session's frames from the first on once a source starts it
            frames = []
            sub = Subscription(srv.ws_url, "later", VIEWER)

            async def collect():
                async for m in sub:
                    frames.append(m)
                    return
            task = asyncio.create_task(collect())
            while sub.server_hello is None:
                await asyncio.sleep(0.02)
            pub = Publisher(srv.url, "later", SOURCE)
            for m in _messages(seed=5)[2:]:
                await pub.send(m)
                if task.done():
                    break
            await task
            await pub.close()
            await sub.close()
            return hellos, frames, sub.server_hello
        hellos, frames, hello = asyncio.run(go())
        assert all(h["waiting"] is True for h in hellos) and hello["waiting"] is True
        assert frames and frames[0]["type"] == "frame" and frames[0]["seq"] == 1
        # both clients gone: the session is removed after the idle timeout (bounded wait)
        deadline = time.monotonic() + 120
        while "later" in _sessions(srv):
            assert time.monotonic() < deadline, "an idle session was never removed"
            time.sleep(0.1)
        assert not srv.app.state.sessions.waiting
        assert rest(srv.url, "GET", "/ready")[0] == 200


def _gauge(server, name):
    text = rest(server.url, "GET", "/metrics", ADMIN)[1]
    return float(next(line.split()[1] for line in text.splitlines() if line.startswith(name + " ")))


def test_a_token_has_quotas_of_sessions_and_connections():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", SOURCE2: "source", VIEWER: "viewer"},
                                    admin_token=ADMIN, max_sessions=3, max_sessions_per_token=2,
                                    max_connections_per_token=3)
    with ServerThread(settings) as srv:
        async def go():
            async def close_of(ws):
                try:
                    await ws.recv()
                except Exception:
                    pass
                return ws.close_code, ws.close_reason
            a = await connect(f"{srv.ws_url}/v1/ingest/a?token={SOURCE}")
            b = await connect(f"{srv.ws_url}/v1/ingest/b?token={SOURCE}")
            for ws in (a, b):
                await ws.send(json.dumps(HELLO))
                await ws.recv()
            c = await connect(f"{srv.ws_url}/v1/ingest/c?token={SOURCE}")     # a third session for this token
            quota = await close_of(c)
            d = await connect(f"{srv.ws_url}/v1/ingest/d?token={SOURCE2}")     # another token still may
            await d.send(json.dumps(HELLO))
            other = json.loads(await d.recv())["type"]
            streams = [await connect(f"{srv.ws_url}/v1/stream/a?token={VIEWER}") for _ in range(3)]
            try:
                await connect(f"{srv.ws_url}/v1/stream/a?token={VIEWER}")
                fourth = None
            except InvalidStatus as err:
                fourth = err.response.status_code, json.loads(err.response.body)["detail"]
            await streams[0].close()
            while _gauge(srv, "fingertrack_subscribers") != 2:   # its handler has ended (and released it)
                await asyncio.sleep(0.05)
            async with connect(f"{srv.ws_url}/v1/stream/a?token={VIEWER}") as again:   # a closed one frees its place
                again_hello = json.loads(await again.recv())["type"]
            for ws in (a, b, d, *streams[1:]):
                await ws.close()
            return quota, other, fourth, again_hello
        quota, other, fourth, again_hello = asyncio.run(go())
        assert quota[0] == 1013 and "limit per token" in quota[1]
        assert other == "hello"
        assert fourth is not None and fourth[0] == 429 and "open connections" in fourth[1]
        assert again_hello == "hello"


def test_one_source_per_session_and_tokens_scoped_to_names():
    scoped = "booth-token-1"
    settings = ServiceSettings.load(port=0, admin_token=ADMIN, tokens={
        SOURCE: "source", SOURCE2: "source", VIEWER: "viewer", scoped: {"role": "source", "sessions": ["booth-*"]},
        "booth-viewer-1": {"role": "viewer", "sessions": ["booth-*"]}})
    with ServerThread(settings) as srv:
        async def go():
            first = await connect(f"{srv.ws_url}/v1/ingest/glove1?token={SOURCE}")
            await first.send(json.dumps(HELLO))
            await first.recv()
            other = await connect(f"{srv.ws_url}/v1/ingest/glove1?token={SOURCE2}")
            try:
                await other.recv()
            except Exception:
                pass
            refused = other.close_code, other.close_reason
            again = await connect(f"{srv.ws_url}/v1/ingest/glove1?token={SOURCE}")   # the same glove reconnecting
            await again.send(json.dumps(HELLO))
            await again.recv()
            try:
                await first.recv()
            except Exception:
                pass
            replaced = first.close_code, first.close_reason
            await again.close()
            names = []
            for name in ("booth-1", "lobby"):
                try:
                    async with connect(f"{srv.ws_url}/v1/ingest/{name}?token={scoped}") as ws:
                        await ws.send(json.dumps(HELLO))
                        names.append(json.loads(await ws.recv())["type"])
                except InvalidStatus as err:
                    names.append(err.response.status_code)
            return refused, replaced, names
        refused, replaced, names = asyncio.run(go())
        assert refused[0] == 1008 and "already has a source" in refused[1]
        assert replaced[0] == 1008 and "replaced" in replaced[1]
        assert names == ["hello", 403]
        assert set(_sessions(srv)) == {"glove1", "booth-1"}
        assert set(_sessions(srv, "booth-viewer-1")) == {"booth-1"}        # a scoped viewer lists its sessions only
        assert settings.masked()["tokens"] == {"source": 3, "viewer": 2}


def test_clients_stop_on_a_refusal_with_its_reason_and_report_retries():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", SOURCE2: "source", VIEWER: "viewer"},
                                    admin_token=ADMIN)
    with ServerThread(settings) as srv:
        out = asyncio.run(_refusals_and_retries(srv))
    assert "already has a source" in out["second"] and SOURCE2 not in out["second"]
    assert "HTTP 403" in out["token"] and "wrong-token" not in out["token"]
    assert all(line.startswith("no service at ws://127.0.0.1:") and "retrying in" in line and SOURCE not in line
               for line in out["retries"])


async def _refusals_and_retries(server):
    """Refusals raise ``Refused`` with the reason (no token in it); retries are reported."""
    holder = await connect(f"{server.ws_url}/v1/ingest/held?token={SOURCE}")
    await holder.send(json.dumps(HELLO))
    await holder.recv()
    out = {}
    try:                                          # another token on a session that has a source
        await Publisher(server.url, "held", SOURCE2).send(_messages()[1])
    except Refused as err:
        out["second"] = str(err)
    await holder.close()
    try:
        async for _ in Subscription(server.ws_url, "held", "wrong-token-1"):
            pass
    except Refused as err:
        out["token"] = str(err)
    lines = []
    with socket.socket() as probe:                # a port with no service
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    pub = Publisher(f"http://127.0.0.1:{port}", "none", SOURCE, on_event=lines.append)
    task = asyncio.create_task(pub.send(_messages()[1]))
    while len(lines) < 2:
        await asyncio.sleep(0.02)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    out["retries"] = lines
    return out


def test_the_publisher_reports_a_reconnect_what_it_resent_and_what_may_be_lost():
    """The service restarts on the same port between two messages: the Publisher reports the drop, the
    reconnect, that it sent hello and calibration again and how many messages were unconfirmed."""
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source"}, admin_token=ADMIN)
    msgs = _messages()
    calibration = next(i for i, m in enumerate(msgs) if m["type"] == "calibration")
    lines = []

    async def go(port):
        pub = Publisher(f"http://127.0.0.1:{port}", "again", SOURCE, on_event=lines.append)
        for m in msgs[calibration:calibration + 20]:
            await pub.send(m)
        await pub.sync()
        for m in msgs[calibration + 20:calibration + 25]:          # sent, not confirmed
            await pub.send(m)
        return pub

    async def rest_of(pub):
        for m in msgs[calibration + 25:calibration + 60]:
            await pub.send(m)
        await pub.close()
        return pub

    with ServerThread(settings) as first:
        port = first.settings.port
        loop = asyncio.new_event_loop()
        pub = loop.run_until_complete(go(port))
    with ServerThread(settings.model_copy(update={"port": port})) as second:
        pub = loop.run_until_complete(rest_of(pub))
        loop.close()
        assert _sessions(second)["again"]["sources"] == 0
    reconnected = [x for x in lines if x.startswith("reconnected to")]
    assert len(reconnected) == 1 and pub.reconnects >= 1 and SOURCE not in reconnected[0]
    assert "resent hello and calibration" in reconnected[0]
    assert f"{pub.unconfirmed_at_drops} messages sent on the dropped connection" in reconnected[0]
    # the five after the sync, and those sent before the client saw the connection gone
    assert 5 <= pub.unconfirmed_at_drops <= 40
    assert any("retrying in" in x for x in lines)


def test_a_subscriber_that_never_reads_is_disconnected_and_forgotten():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    subscriber_send_timeout_s=1.0)
    with ServerThread(settings, send_buffer_bytes=8192) as srv:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
        sock.connect(("127.0.0.1", srv.settings.port))
        sock.sendall((f"GET /v1/stream/stall?token={VIEWER} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
                      "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += sock.recv(1)
        assert b" 101 " in head

        async def stream_until_dropped():
            # frames until the service let the stalled subscriber go (its send blocked on the full
            # socket for subscriber_send_timeout_s), or to the end of the recording and then wait
            pub = Publisher(srv.url, "stall", SOURCE)
            for m in _messages(seed=6, motion="sequence")[2:]:
                await pub.send(m)
                await asyncio.sleep(0)
                sessions = await asyncio.to_thread(_sessions, srv)
                if sessions["stall"]["subscribers"] == 0 and sessions["stall"]["frames_out"] > 0:
                    break
            else:
                while (await asyncio.to_thread(_sessions, srv))["stall"]["subscribers"]:
                    await asyncio.sleep(0.1)
            await pub.close()
        asyncio.run(stream_until_dropped())
        assert _sessions(srv)["stall"]["subscribers"] == 0
        assert 'fingertrack_disconnects_total{reason="send_timeout"} 1.0' in rest(srv.url, "GET", "/metrics", ADMIN)[1]
        assert not srv.app.state.sessions.sending          # nothing of it is held
        sock.settimeout(30)
        try:
            while sock.recv(65536):              # what was buffered, then the end: the server let go
                pass
        except ConnectionResetError:
            pass
        sock.close()


# -- F5: a source the service cannot keep up with ---------------------------------------------------------------

def _metric(server, name: str, session: str) -> float:
    text = rest(server.url, "GET", "/metrics", ADMIN)[1]
    line = next((x for x in text.splitlines() if x.startswith(f'{name}{{session="{session}"}}')), None)
    return 0.0 if line is None else float(line.split()[-1])


def _flood(server, name: str, messages: list, max_unconfirmed):
    """Send ``messages`` through a ``Publisher`` as fast as it lets them go, then its closing sync."""
    async def go():
        pub = Publisher(server.url, name, SOURCE, max_unconfirmed=max_unconfirmed, max_errors=100_000)
        for m in messages:
            await pub.send(m)
        await pub.close(sync_timeout_s=600)          # bounds a failure only
        return list(pub.errors)
    return asyncio.run(go())


def test_a_source_faster_than_the_service_is_refused_overloaded_and_nothing_is_lost_silently():
    """Data messages beyond a full backlog are refused one by one with ``overloaded`` (counted in the
    session summary, the frame status and the metrics) while the connection keeps being read; every
    other message is processed, so processed + refused = sent. With the Publisher's flow control the
    same flood is slowed down instead: nothing refused, everything processed."""
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    ingest_backlog_messages=8)
    msgs = _messages(seed=7, motion="sequence")
    data = [m for m in msgs if m["type"] in ("pose", "imu", "imu_batch")]
    with ServerThread(settings) as srv:
        errors = _flood(srv, "flood", msgs, max_unconfirmed=None)
        summary = _sessions(srv)["flood"]
        refused = [e for e in errors if e["code"] == "overloaded"]
        # the refusals leave gaps in the data: one longer than the clock step starts a new clock, told as such
        assert refused and {e["code"] for e in errors} <= {"overloaded", "clock_step"}, [e["code"] for e in errors][:20]
        assert all("cannot keep up with this source" in e["detail"] for e in refused)
        assert summary["overloaded"] == len(refused) == _metric(srv, "fingertrack_overloaded_messages_total", "flood")
        assert 0 < summary["status"]["dropped"]["overloaded"] <= len(refused)
        processed = _metric(srv, "fingertrack_messages_in_total", "flood")      # msgs[0] is the hello
        assert processed == len(msgs) - len(refused) and len(refused) < len(data)

        paced = _flood(srv, "paced", msgs, max_unconfirmed=4)                  # flow control: slowed, not refused
        assert paced == [] and _sessions(srv)["paced"]["overloaded"] == 0
        assert _metric(srv, "fingertrack_messages_in_total", "paced") == len(msgs)


def _server_connections() -> int:
    """WebSocket server connection states in memory (live, or garbage not yet collected)."""
    import gc
    from websockets.server import ServerProtocol
    return sum(1 for o in gc.get_objects() if type(o) is ServerProtocol)


def _churn(srv, connects: int) -> None:
    async def go():
        for i in range(connects):
            async with connect(f"{srv.ws_url}/v1/stream/churn?token={VIEWER}") as ws:
                await ws.recv()                                  # the hello
            with pytest.raises(InvalidStatus):
                async with connect(f"{srv.ws_url}/v1/stream/churn?token=wrong-{i}"):
                    pass
    asyncio.run(go())


def test_connections_that_ended_leave_nothing_behind_once_their_cycles_are_collected():
    """Ended connections are reference cycles that wait for a collection, which a serving process makes
    rare (finding F14, the storm's RSS growth); the collection run after connections end frees them.
    Automatic collection is off here, so only that one can: with it put off, they stay in memory."""
    import gc
    settings = ServiceSettings.load(port=0, tokens={VIEWER: "viewer"}, admin_token=ADMIN)
    gc.collect()
    gc.disable()
    try:
        with ServerThread(settings.model_copy(update={"connection_gc_delay_s": 60.0})) as srv:
            before = _server_connections()
            _churn(srv, 10)
            assert srv.app.state.churn.collections == 0
            assert _server_connections() - before >= 10             # held until some collection
        gc.collect()
        with ServerThread(settings.model_copy(update={"connection_gc_delay_s": 0.2})) as srv:
            before = _server_connections()
            churn = srv.app.state.churn
            _churn(srv, 10)
            while churn._pending is not None or churn.collections < 2:   # passes until one saw no end
                time.sleep(0.05)
            assert _server_connections() <= before
            text = rest(srv.url, "GET", "/metrics", ADMIN)[1]
            assert f"fingertrack_connection_gc_seconds_count {float(churn.collections)}" in text
    finally:
        gc.enable()


def test_replies_leave_in_the_order_of_the_messages_overloaded_refusals_included():
    """Each message is followed by a sentinel of its own (an unknown type ``__sK__``, always answered or
    refused): with a backlog of 8 the service falls behind and refuses data messages ``overloaded``,
    and every reply still comes after the replies to all earlier messages: a reply naming message k
    (its ``t``) or sentinel k arrives after sentinel k-1's and before sentinel k's. A refused stretch
    can leave a gap longer than the clock step: the next processed message then gets its ``clock_step``
    notice, in its place too."""
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source"}, admin_token=ADMIN, ingest_backlog_messages=8)
    data = [m for m in _messages(seed=3, motion="sequence") if m["type"] in ("pose", "imu", "imu_batch")][:600]

    def t_of(m):
        return m["samples"][0]["t"] if m["type"] == "imu_batch" else m["t"]

    async def go(url):
        async with connect(f"{url}/v1/ingest/order?token={SOURCE}", max_size=None) as ws:
            await ws.send(json.dumps(HELLO))
            assert json.loads(await ws.recv())["type"] == "hello"
            for k, m in enumerate(data):
                await ws.send(json.dumps(m))
                await ws.send(json.dumps({"type": f"__s{k}__"}))
            replies = []
            while not replies or f"__s{len(data) - 1}__" not in replies[-1]["detail"]:
                replies.append(json.loads(await ws.recv()))
            return replies

    with ServerThread(settings) as srv:
        replies = asyncio.run(go(srv.ws_url))
    owner = {}                                   # the messages a data reply may name, by their time
    for k, m in enumerate(data):
        owner.setdefault(f"{m['type']} at t={t_of(m)}", set()).add(k)
    k, overloaded = 0, 0                         # k: the first message whose sentinel is not answered yet
    for r in replies:
        assert r["type"] == "error", r
        named = r["detail"].split(":")[0]
        if r["code"] == "unknown_type" or named.startswith("__s"):   # a sentinel: answered, or refused itself
            assert named == f"__s{k}__" or f"'__s{k}__'" in r["detail"], (k, r)
            k += 1
        elif r["code"] == "clock_step":         # a refused stretch left a gap that starts a new clock
            head = f"{data[k]['type']} at t={t_of(data[k])}"                # message k is processed
            assert r["detail"].startswith(head) and r["detail"][len(head)] in ".: ", (k, r)
        else:
            assert r["code"] == "overloaded" and k in owner.get(named, ()), (k, r)
            overloaded += 1
    assert k == len(data) and overloaded > 0


def test_replies_to_refused_messages_wait_in_their_place_within_a_bound():
    """A refused message's reply takes its place among the received messages, outside their bounds;
    the replies waiting at a time are bounded (the route closes a source beyond it)."""
    from service.api.backlog import REPLY_OVERHEAD_BYTES, IngestBacklog

    async def go():
        backlog = IngestBacklog(max_messages=2, max_bytes=1024)
        assert backlog.put({"n": 0}, 10, lambda: True) and backlog.put({"n": 1}, 10, lambda: True)
        assert not backlog.put({"n": 2}, 10, lambda: True)          # full: the data message is refused
        detail = "x" * 100
        fitted = 0
        while backlog.put_reply(("overloaded", detail)):
            fitted += 1
        assert fitted == backlog.max_reply_bytes // (len(detail) + REPLY_OVERHEAD_BYTES) and len(backlog) == 2
        assert backlog.put({"type": "sync"}, 10, lambda: False)     # state and questions still queued
        order = [await backlog.get() for _ in range(fitted + 3)]
        assert order[:2] == [{"n": 0}, {"n": 1}] and order[-1] == {"type": "sync"}
        assert order[2:-1] == [("overloaded", detail)] * fitted and len(backlog) == 0
        assert backlog.put_reply(("overloaded", detail))            # room again once they left
    asyncio.run(go())


# -- item 4: kernels and their cache -------------------------------------------------------------------------

def test_the_kernel_cache_is_a_writable_per_user_folder(tmp_path):
    assert numba_cache_dir({"NUMBA_CACHE_DIR": str(tmp_path / "operator")}) == str(tmp_path / "operator")
    assert numba_cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == str(tmp_path / "fingertrack" / "numba")
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    # an unwritable home cache (a read-only root file system): the temporary folder instead
    chosen = numba_cache_dir({"XDG_CACHE_HOME": str(blocked)})
    assert chosen is not None and chosen.startswith(__import__("tempfile").gettempdir())
    # an unwritable NUMBA_CACHE_DIR is passed over too (numba would cache beside the package's source)
    assert numba_cache_dir({"NUMBA_CACHE_DIR": str(blocked / "numba"), "XDG_CACHE_HOME": str(tmp_path)}) \
        == str(tmp_path / "fingertrack" / "numba")


def test_switching_to_a_compiled_estimator_warms_it_off_the_loop(server):
    """The PUT compiles the kernels in another process and a worker thread; meanwhile the event loop
    keeps answering (``/health`` answered while the PUT is pending)."""
    from service.estimators import warm
    warm._WARM.discard("inertial")          # as in a fresh service process
    result = {}

    def put():
        # answered once the kernels are compiled: tens of seconds on a busy machine with a cold cache
        result["put"] = rest(server.url, "PUT", "/v1/sessions/warm/config", ADMIN, {"estimator": "inertial"},
                             timeout_s=900)
    worker = threading.Thread(target=put)
    worker.start()
    answered = 0
    while worker.is_alive():
        answered += rest(server.url, "GET", "/health")[0] == 200
        worker.join(0.05)                   # asked again 20 times a second, not back to back (a core's worth of
                                            # requests for as long as the compile took)
    worker.join()
    assert result["put"][0] == 200 and result["put"][1]["estimator"] == "inertial"
    assert answered >= 1


def test_kernels_compile_in_a_process_at_a_lower_priority_and_load_with_the_interpreter_shared():
    """The separate process that compiles kernels beside a serving process runs at the idle scheduling
    priority (``--idle``, Linux's ``SCHED_IDLE``) or at niceness ``COMPILE_NICE`` (5); while
    kernels load in a thread of a serving process, the interpreter's lock changes hands every 0.5 ms
    (nested loads too), and the interval before is restored after the last."""
    from service.estimators import warm

    command = warm.compile_command("inertial", {"a": 1})
    assert command[1:5] == ["-m", "service.estimators.warm", "--background", "inertial"] and json.loads(command[5]) == {"a": 1}
    assert warm.compile_command("inertial", idle=True)[3:6] == ["--background", "--idle", "inertial"]
    show = "import os; from service.estimators.warm import main; code = main({}); print(code, os.nice(0), os.sched_getscheduler(0))"
    done = subprocess.run([sys.executable, "-c", show.format("['--background']")], capture_output=True, text=True, timeout=300)
    assert done.stdout.splitlines()[-1] == f"2 {warm.COMPILE_NICE} {os.SCHED_OTHER}", done
    done = subprocess.run([sys.executable, "-c", show.format("['--background', '--idle']")], capture_output=True, text=True,
                          timeout=300)
    assert done.stdout.splitlines()[-1].split()[::2] == ["2", str(os.SCHED_IDLE)], done
    before = sys.getswitchinterval()
    with warm.sharing_the_interpreter():
        with warm.sharing_the_interpreter():
            assert sys.getswitchinterval() == pytest.approx(warm.LOAD_SWITCH_INTERVAL_S)
        assert sys.getswitchinterval() == pytest.approx(warm.LOAD_SWITCH_INTERVAL_S)
    assert sys.getswitchinterval() == before


def test_a_compile_at_the_idle_priority_not_done_in_time_goes_on_at_a_nicer_one_and_one_done_in_time_does_not(monkeypatch):
    """``warm.Compile``: its process starts at the idle priority; one still running after ``COMPILE_IDLE_S``
    (here a process that would sleep a minute) is killed and the compile started again at niceness
    ``COMPILE_NICE``, whether the caller waits (``wait``) or looks now and then (``poll``); one that ends
    in time is the only one."""
    from service.estimators import warm
    started = []

    def command(name, params=None, idle=False):
        started.append((name, params, idle))
        return [sys.executable, "-c", "import time; time.sleep(60)" if idle else ""]
    monkeypatch.setattr(warm, "compile_command", command)
    monkeypatch.setattr(warm, "COMPILE_IDLE_S", 0.05)
    compiling = warm.Compile("inertial", {"a": 1})
    first = compiling.process
    assert compiling.wait() == 0
    assert first.returncode == -signal.SIGKILL and compiling.process is not first and not compiling.idle
    assert started == [("inertial", {"a": 1}, True), ("inertial", {"a": 1}, False)]
    started.clear()
    compiling = warm.Compile("inertial")
    first = compiling.process
    while (code := compiling.poll()) is None:
        time.sleep(0.01)
    assert code == 0 and first.returncode == -signal.SIGKILL
    assert started == [("inertial", None, True), ("inertial", None, False)]
    started.clear()
    monkeypatch.setattr(warm, "compile_command", lambda name, params=None, idle=False:
                        started.append(idle) or [sys.executable, "-c", ""])
    monkeypatch.setattr(warm, "COMPILE_IDLE_S", 300.0)
    assert warm.Compile("inertial").wait() == 0 and started == [True]


def test_without_a_kernel_cache_no_separate_process_compiles_what_this_one_compiles_again(monkeypatch):
    """A separate compile fills the on-disk cache; without a cache (``JIT_CACHE`` false: no writable
    folder) its work would be lost and the warming process compiles everything again (a read-only
    service's start took twice the CPU), so none is started. With a cache and the kernels not in it, it is."""
    import asyncio
    import service
    from service.estimators import warm
    started = []
    monkeypatch.setattr(warm, "compile_command", lambda name, params=None, idle=False:
                        started.append(name) or [sys.executable, "-c", ""])
    monkeypatch.setattr(warm, "warm", lambda name, params=None: None)     # this process's own part: not the subject
    monkeypatch.setattr(warm, "_on_disk", lambda kernels: False)          # nothing in the cache
    monkeypatch.setattr(warm, "_WARM", set())
    monkeypatch.setattr(service, "JIT_CACHE", False)
    assert not warm.needs_compiling("chain")
    warm.warm_ahead("chain")
    warm._WARM.clear()
    asyncio.run(warm.warm_off_loop("chain"))
    assert started == []
    monkeypatch.setattr(service, "JIT_CACHE", True)
    warm._WARM.clear()
    assert warm.needs_compiling("chain")
    warm.warm_ahead("chain")
    warm._WARM.clear()
    asyncio.run(warm.warm_off_loop("chain"))
    assert started == ["chain", "chain"]


# -- item 7: errors a person can act on ------------------------------------------------------------------------

def _cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=300,
                          env=env)


def test_serve_checks_the_port_first_and_prints_a_configured_admin_token_never(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = _cli("serve", "--port", str(port))
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [f"fingertrack serve: error: port {port} on 127.0.0.1 is already in use; "
                                                "stop the other service or choose another --port"]
    config = tmp_path / "cfg.json"
    config.write_text(json.dumps({"admin_token": "configured-admin-secret", "tokens": {SOURCE: "source"}}))
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", "0", "--config", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        while not lines or not lines[-1].startswith("listening on"):
            line = proc.stdout.readline()
            assert line, "".join(lines)
            lines.append(line)
    finally:
        proc.terminate()
        proc.wait(60)
    text = "".join(lines)
    assert "configured-admin-secret" not in text and SOURCE not in text and "src" not in text
    assert "admin token: the configured one" in text and "not shown" in text


def test_replay_of_a_file_that_is_not_a_recording_fails(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("\n".join(f"line {i}" for i in range(50)))
    done = _cli("replay", str(path))
    assert done.returncode == 2 and "is not a recording" in done.stderr
    assert len(done.stderr.splitlines()) <= 12 and "Traceback" not in done.stderr


# -- a service that stops answering can be looked into ---------------------------------------------------------

def _wait_for(predicate, what, alive, bound_s=120.0):
    deadline = time.monotonic() + bound_s                # bounds a failure only
    while not predicate():
        assert alive(), f"{what}: the process ended"
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def test_serve_and_its_hand_workers_write_their_stacks_on_sigusr1_and_go_on(tmp_path):
    import os
    import signal
    from service.bench.process import descendants, service_process
    log = tmp_path / "service.log"
    with service_process(log_path=log) as svc:
        workers = descendants(svc.pid)
        assert len(workers) == 1                         # one_hand_worker's one
        for pid, where in ((svc.pid, "service/cli.py"), (workers[0], "hands/worker.py")):
            before = log.read_text().count("most recent call first")
            os.kill(pid, signal.SIGUSR1)                 # without a handler: the default action ends the process
            alive = lambda: os.path.exists(f"/proc/{pid}") and svc.alive()   # noqa: E731
            _wait_for(lambda: log.read_text().count("most recent call first") > before, f"no stacks from {pid}", alive)
            _wait_for(lambda: where in log.read_text(), f"the stacks of {pid} do not show {where}", alive)
            assert svc.alive() and all(os.path.exists(f"/proc/{w}") for w in workers)
        assert rest(svc.url, "GET", "/health")[0] == 200
        assert rest(svc.url, "GET", "/v1/sessions", svc.admin)[0] == 200
    assert "Traceback (most recent call last)" not in log.read_text()


def test_a_frame_too_large_is_closed_with_its_reason_while_the_peer_still_sends(server):
    """uvicorn closed the socket right after its 1009 close frame: the rest of the frame, still arriving,
    was answered with a reset, and a peer still sending lost the close frame (5 connections of the fuzz)."""
    import base64
    import os
    import struct
    port = int(server.url.rsplit(":", 1)[1])
    for _ in range(3):
        with socket.create_connection(("127.0.0.1", port), timeout=60) as s:
            key = base64.b64encode(os.urandom(16)).decode()
            s.sendall((f"GET /v1/ingest/too-large?token={SOURCE} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
                       f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
            data = b""
            while b"\r\n\r\n" not in data:
                data += s.recv(4096)
            assert b" 101 " in data.split(b"\r\n")[0]
            data = data.split(b"\r\n\r\n", 1)[1]
            # a masked text frame that says it holds 64 MiB (the limit is 4 MiB), and its first 64 KiB
            s.sendall(bytes([0x81, 0x80 | 127]) + struct.pack(">Q", 64 << 20) + os.urandom(4) + b"x" * (64 << 10))
            while len(data) < 4 or len(data) < 2 + data[1]:   # the server's close frame (unmasked, short)
                more = s.recv(4096)
                assert more, "the connection ended without a close frame"
                data += more
            assert data[0] == 0x88 and struct.unpack(">H", data[2:4])[0] == 1009, data[:40]
            for _ in range(4):                          # the rest of the frame keeps coming
                s.sendall(b"y" * (64 << 10))
            s.shutdown(socket.SHUT_WR)
            while s.recv(65536):                        # then the service ends the connection, no reset
                pass
    assert rest(server.url, "GET", "/health")[0] == 200


def test_an_estimator_step_that_raises_on_its_first_sample_leaves_no_half_state():
    """Campaign F6(b): a step raising ``ValueError`` on an estimator's first sample used to leave its
    state set while its time was not, so the next sample raised ``TypeError`` (float - None) and
    dropped the connection. State and time now change together, after the step."""
    import numpy as np
    from service.estimators.base import samples_from_session
    from service.estimators.registry import REGISTRY
    from service.sim.session import simulate

    sess = simulate(SimConfig(motion="random", t_m_s=0.2, noise="both", hand_motion="random", seed=5))
    smp = samples_from_session(sess, "index")
    est = REGISTRY["integration"](sess.calibration.finger("index"))
    step, calls = est._step, []

    def failing_once(*args):
        calls.append(1)
        if len(calls) == 1:
            raise ValueError("injected")
        return step(*args)
    est._step = failing_once
    with pytest.raises(ValueError, match="injected"):
        est.update(*smp.sample(0))
    assert not est.started and est.state == {"t_last": None, "filter": None}
    out = est.update(*smp.sample(1))                # no TypeError: it starts afresh
    assert est.started and est.last_t == out.t and np.all(np.isfinite(out.phi))


def _raw_http(port: int, data: bytes, chunks: int = 0, until_closed: bool = False) -> bytes:
    """``data`` sent on a new connection (then ``chunks`` more of 64 KiB of ``a``, as long as the server reads),
    and everything the server answers until it closes the connection (or one reply when it keeps it, unless
    ``until_closed``: a reply before the server closes, e.g. a route answering before the body has come). A
    server that never answers fails the test after 10 s (``socket.timeout``), not after minutes."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(data)
        try:
            for _ in range(chunks):
                s.sendall(b"a" * (64 << 10))
        except OSError:                                 # refused and closed meanwhile
            pass
        out = b""
        try:
            while more := s.recv(65536):
                out += more
                if not until_closed and out.startswith(b"HTTP/1.1 200") and b"\r\n\r\n" in out:
                    break
        except ConnectionResetError:                    # (after its reply: the rest of what was sent came after it)
            pass
        return out


def test_the_http_parser_refuses_malformed_requests_with_400_and_no_traceback(server, caplog):
    """The C parser (httptools, a dependency; uvicorn's pure-Python one, h11, answered a malformed chunked body
    with 400 and an 'Exception in ASGI application' traceback, took HTTP/9.9 and an HTTP/2 preface as requests
    and let a request with both Content-Length and Transfer-Encoding through): each of these malformed requests
    gets 400 and the connection closes, nothing is logged with a traceback, and the service answers on."""
    from service.api.server import BoundedHttpTools
    assert BoundedHttpTools is not None and server.server.config.http is BoundedHttpTools, "httptools is not installed"
    port = int(server.url.rsplit(":", 1)[1])
    malformed = [b"\x16\x03\x01\x00\xa5\x01\x00\x00\xa1\x03\x03\r\n\r\n", b"GET\r\n\r\n",
                 b"GET /health HTTP/1.1\r\nHost 127.0.0.1\r\n\r\n", b"GET /health HTTP/1.1\r\nHo st: x\r\n\r\n",
                 b"GET /health HTTP/9.9\r\nHost: x\r\n\r\n", b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n",
                 b"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n",
                 b"POST /health HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n",
                 b"GET /hea\x00lth HTTP/1.1\r\nHost: x\r\n\r\n"]
    with caplog.at_level("WARNING"):
        for request in malformed:
            reply = _raw_http(port, request)
            assert reply.startswith(b"HTTP/1.1 400 ") and reply.endswith(b"Invalid HTTP request received."), (request, reply)
        assert _raw_http(port, b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n" * 3).count(b"HTTP/1.1 200 ") >= 1
    assert sum(r.getMessage() == "Invalid HTTP request received." for r in caplog.records) == len(malformed)
    assert not [r for r in caplog.records if r.exc_info], [r.getMessage() for r in caplog.records if r.exc_info]
    assert rest(server.url, "GET", "/health")[0] == 200


def test_the_head_bound_rests_on_uvicorn_methods_that_exist_and_refuses_an_endless_head_within_seconds():
    """``BoundedHttpTools`` overrides and calls uvicorn internals (``HTTPTOOLS_HOOKS``; the same in uvicorn
    0.53-0.55, which pyproject does not cap): each must exist on uvicorn's httptools protocol, which must take its
    reads through ``data_received``, and the bound must work on a real socket. A uvicorn that renamed one would
    leave heads unbounded without an error; the server test below would fail only on its socket timeout. Here
    a protocol served on an event loop of its own answers an endless header with 400 within 5 s (a hook
    renamed, or ``data_received`` bypassed: a timeout here, in seconds)."""
    import contextlib

    import uvicorn
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
    from uvicorn.server import ServerState

    from service.api.server import HTTPTOOLS_HOOKS, BoundedHttpTools
    assert BoundedHttpTools is not None, "httptools is not installed, or uvicorn's protocol lacks a hook (logged)"
    missing = [name for name in HTTPTOOLS_HOOKS if not callable(getattr(HttpToolsProtocol, name, None))]
    assert not missing and not issubclass(HttpToolsProtocol, asyncio.BufferedProtocol), missing

    async def app(scope, receive, send):
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"2")]})
        await send({"type": "http.response.body", "body": b"ok"})

    async def run():
        config = uvicorn.Config(app, http=BoundedHttpTools, lifespan="off", log_level="critical")
        config.load()
        state, loop = ServerState(), asyncio.get_running_loop()
        listener = await loop.create_server(lambda: BoundedHttpTools(config=config, server_state=state, app_state={}),
                                            "127.0.0.1", 0)
        port = listener.sockets[0].getsockname()[1]
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")          # a request within the bound: answered
            ok = await asyncio.wait_for(reader.readuntil(b"ok"), 5)
            writer.write(b"GET / HTTP/1.1\r\nHost: x\r\nX: ")

            async def endless():
                with contextlib.suppress(OSError):
                    for _ in range(256):                # 1 MiB at most
                        writer.write(b"a" * 4096)
                        await writer.drain()
            async def answer():
                out = b""
                with contextlib.suppress(ConnectionResetError):     # (a reset after the reply: more was sent)
                    while more := await reader.read(65536):
                        out += more
                return out
            feeding = asyncio.create_task(endless())
            reply = await asyncio.wait_for(answer(), 5)
            feeding.cancel()
            writer.close()
            return ok, reply
        finally:
            listener.close()
    ok, reply = asyncio.run(run())
    assert ok.startswith(b"HTTP/1.1 200 "), ok
    assert reply.startswith(b"HTTP/1.1 400 ") and reply.endswith(b"Invalid HTTP request received."), reply[:200]


@pytest.mark.parametrize("part", ["header", "url"])
def test_a_request_head_longer_than_the_limit_is_refused_while_it_arrives(server, part):
    """uvicorn's httptools protocol has no bound on a request's head: an endless header or URL was kept (25 MB
    sent, 25 MB more in this process, no reply ever). Now a head still incomplete past ``HEAD_LIMIT`` bytes
    (16 KiB, h11's bound before) gets 400 and the connection closes while the client still sends (1 MiB here);
    a head within the limit (a 10 kB cookie) is answered."""
    from service.api.server import BoundedHttpTools
    port = int(server.url.rsplit(":", 1)[1])
    start = b"GET /health HTTP/1.1\r\nHost: x\r\nX: " if part == "header" else b"GET /health?"
    reply = _raw_http(port, start, chunks=16)
    assert reply.startswith(b"HTTP/1.1 400 ") and reply.endswith(b"Invalid HTTP request received."), reply[:200]
    ok = _raw_http(port, b"GET /health HTTP/1.1\r\nHost: x\r\nCookie: " + b"c" * 10_000 + b"\r\n\r\n")
    assert ok.startswith(b"HTTP/1.1 200 "), ok[:200]
    assert BoundedHttpTools.HEAD_LIMIT == 16 * 1024


@pytest.mark.parametrize("method", ["POST /v1/sessions", "GET /health"])
def test_an_endless_trailer_after_a_chunked_body_is_refused_while_it_arrives(server, method):
    """The trailer section after a chunked body's last chunk is parsed like a head (a line kept until it ends):
    an endless trailer was kept (64 MB sent, 56 MB more in this process, no 400 ever; the pure-Python parser
    refused it). Now it counts against ``HEAD_LIMIT`` as a head does: the connection gets 400 and closes while
    the client still sends (1 MiB here), whether or not the route answered before reading the body; a short
    trailer is answered."""
    port = int(server.url.rsplit(":", 1)[1])
    start = method.encode() + b" HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n1\r\nz\r\n0\r\nT: "
    reply = _raw_http(port, start, chunks=16, until_closed=True)
    assert b"HTTP/1.1 400 " in reply and reply.endswith(b"Invalid HTTP request received."), reply[-300:]
    ok = _raw_http(port, b"GET /health HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n1\r\nz\r\n0\r\n"
                         b"T: " + b"t" * 2048 + b"\r\n\r\n")
    assert ok.startswith(b"HTTP/1.1 200 "), ok[:200]


def test_pipelined_requests_longer_than_the_head_limit_in_one_read_are_all_answered(server):
    """The head limit counts a head's bytes from the read after the one in which it began: a client writing
    1000 pipelined ``GET /health`` (36 kB) at once, the last one's head cut short and completed by a later
    write, gets 1001 answers, not a 400 for the last one (counting that read whole refused it)."""
    port = int(server.url.rsplit(":", 1)[1])
    one = b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=60) as s:
        s.sendall(one * 1000 + one[:20])
        out = b""
        for total in (1000, 1001):                      # answered one after the other, the last one when whole
            while out.count(b"HTTP/1.1 ") < total:
                more = s.recv(1 << 20)
                assert more, out[-300:]                 # closed (after a 400)
                out += more
            if total == 1000:
                assert b"HTTP/1.1 400" not in out, out[-300:]
                s.sendall(one[20:])
    assert out.count(b"HTTP/1.1 200 ") == 1001 and b"HTTP/1.1 400" not in out
