"""The Python client library's edges (``clients/client.py``): the service URL it is given, session
names and tokens in its URLs, and a ``close`` that ends even when the service never answers."""
import asyncio
import json

import pytest
from websockets.asyncio.server import serve

from clients.client import Publisher, Refused, Subscription, service_url
from service.api.config import ServiceSettings
from service.api.server import ServerThread

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE, ADMIN = "src-token-1", "admin-token-1"


@pytest.mark.parametrize("url, named", [
    ("127.0.0.1:8765", "must start with http://"),          # no scheme (it ended in a traceback showing the token)
    ("localhost:8765", "must start with http://"),
    ("ftp://host", "must start with http://"),
    ("http://", "must start with http://"),
    ("http://host:99999", "Port out of range"),
    ("http://host:abc", "Port could not be cast"),
    ("http://host:0", "port 0"),
    ("http://ho st:8765", "no valid host"),
    ("http://[::1", "Invalid IPv6 URL"),
    ("http://host:8765/?token=secret-in-query", "no query or fragment"),
    ("http://user:pass-word@host:8765#frag", "no query or fragment"),
])
def test_a_bad_service_url_is_refused_naming_what_is_wrong(url, named):
    with pytest.raises(ValueError) as err:
        service_url(url)
    text = str(err.value)
    assert named in text
    assert "secret-in-query" not in text and "pass-word" not in text      # secrets are never shown
    for make in (lambda: Publisher(url, "s", "tok-not-shown"), lambda: Subscription(url, "s", "tok-not-shown")):
        with pytest.raises(ValueError) as err:
            make()
        assert named in str(err.value) and "tok-not-shown" not in str(err.value)


@pytest.mark.parametrize("url", ["http://127.0.0.1:8765", "https://h.example/prefix/", "ws://[::1]:80", "wss://h"])
def test_a_service_url_with_scheme_and_host_is_taken(url):
    assert service_url(url) == url


def test_the_session_name_and_token_are_percent_encoded():
    pub = Publisher("https://h.example/prefix/", "a b/c", "t&k=1", binary=True)
    assert pub.url == "wss://h.example/prefix/v1/ingest/a%20b%2Fc?token=t%26k%3D1&format=msgpack"
    assert Subscription("http://h:1", "s", "tok").url == "ws://h:1/v1/stream/s?token=tok"


def test_a_bad_session_name_is_refused_with_the_services_reason():
    """The name goes to the service encoded, so the service refuses it with its reason (it was an
    HTTP 400 traceback when a space broke the request line)."""
    settings = ServiceSettings.load(port=0, admin_token=ADMIN, tokens={SOURCE: "source"})
    with ServerThread(settings) as srv:
        async def run():
            pub = Publisher(srv.url, "bad name!", SOURCE)
            with pytest.raises(Refused) as err:
                await pub.send({"type": "pose", "t": 0.0, "valid": False})
            return str(err.value)
        text = asyncio.run(run())
    assert "1008" in text and "session name must be" in text and SOURCE not in text


def test_close_ends_when_the_service_never_answers_sync():
    """A peer that takes the hello and then reads without answering (a service wedged or far behind):
    ``close`` waits ``sync_timeout_s``, says so through ``on_event`` and closes the connection."""
    received, closed = [], asyncio.Event()

    async def wedged(ws):
        await ws.send(json.dumps({"type": "hello", "protocol": 1, "server": "fingertrack", "session": "s"}))
        async for data in ws:                         # reads everything, answers nothing
            received.append(json.loads(data))
        closed.set()

    async def run():
        lines = []
        async with serve(wedged, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            pub = Publisher(f"http://127.0.0.1:{port}", "s", SOURCE, on_event=lines.append)
            await pub.send({"type": "pose", "t": 0.0, "valid": False})
            await asyncio.wait_for(pub.close(sync_timeout_s=0.2), 60)   # the outer bound only guards the test
            await asyncio.wait_for(closed.wait(), 60)
        return lines
    lines = asyncio.run(run())
    assert [m["type"] for m in received] == ["hello", "pose", "sync"]
    assert len(lines) == 1 and "did not answer sync within 0.2 s" in lines[0] and SOURCE not in lines[0]


def test_a_glove_stream_sends_its_messages_encoded_before_it_starts():
    """``stream_glove`` sends each message as encoded before its clock started (``encoded``, or its
    own encoding of them then): the ``Publisher`` encodes no sample or pose while it streams, the
    service gets exactly those texts, in order, with the syncs of its flow control between them."""
    import clients.client as client_module
    from clients.glove import encoded_messages, source_messages, stream_glove
    from service.sim.session import SimConfig

    config = SimConfig(motion="random", duration_s=0.4, noise="both", seed=1)
    messages = source_messages(config)
    marked = encoded_messages(messages)
    marked[-1] = marked[-1][:-1] + ',"mark":1}'            # the text given is what goes out, as it is
    encoded_while_streaming = []
    encode = client_module.encode

    def counting_encode(message, binary):
        encoded_while_streaming.append(message["type"])
        return encode(message, binary)

    async def run(given):
        received = []

        async def service(ws):
            await ws.send(json.dumps({"type": "hello", "protocol": 1, "server": "fingertrack", "session": "s"}))
            async for data in ws:
                if json.loads(data)["type"] == "sync":
                    await ws.send(data)
                else:
                    received.append(data)

        async with serve(service, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            pub = await stream_glove(f"http://127.0.0.1:{port}", "s", SOURCE, config, speed=20.0, messages=messages,
                                     encoded=given)
            await asyncio.wait_for(pub.close(), 60)
        return received

    client_module.encode = counting_encode
    try:
        for given in (marked, None):
            encoded_while_streaming.clear()
            received = asyncio.run(run(given))
            sent = encoded_messages(messages)          # the hello first, as the Publisher sends it on connecting
            expected = sent[:-1] + [marked[-1]] if given is not None else sent
            assert received == expected and len(received) > 100
            # the Publisher encodes only what it sends on connecting (hello, calibration) and its syncs
            assert set(encoded_while_streaming) <= {"hello", "calibration", "sync"}
    finally:
        client_module.encode = encode
    with pytest.raises(ValueError, match="encoded messages for"):
        asyncio.run(stream_glove("http://127.0.0.1:1", "s", SOURCE, config, messages=messages, encoded=marked[1:]))
