"""The WebSocket protocol's own cutting of received bytes into frames (``server.DrainingWebSocket._frames_in``):
whole unfragmented text frames are handed to the app without the protocol library's parser, every other frame
goes to the library whole, and what the library refuses is still refused as before. A real server, a raw socket
client that writes its frames in pieces of any size."""
from __future__ import annotations

import base64
import json
import os
import random
import socket
import struct

import pytest

from service.api.config import ServiceSettings
from service.api.server import ServerThread

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE = "src-token-framing"


@pytest.fixture(scope="module")
def server():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source"})
    with ServerThread(settings) as srv:
        yield srv


def _frame(opcode: int, payload: bytes, fin: bool = True, rsv: int = 0, masked: bool = True) -> bytes:
    head = bytes([(0x80 if fin else 0) | rsv | opcode])
    n = len(payload)
    size = bytes([n]) if n < 126 else bytes([126]) + struct.pack("!H", n) if n < 1 << 16 else \
        bytes([127]) + struct.pack("!Q", n)
    if not masked:
        return head + size + payload
    mask = bytes((n + k * 37) & 0xFF for k in range(4))     # (any mask; fixed, so that the test ids are too)
    return head + bytes([size[0] | 0x80]) + size[1:] + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def _text(obj) -> bytes:
    return _frame(1, json.dumps(obj).encode())


class _Client:
    """A raw WebSocket client of ``/v1/ingest/{session}``: the handshake, then bytes as given, and the server's
    frames read back (``frames``: ``(opcode, payload)``)."""

    def __init__(self, server, session: str):
        port = int(server.url.rsplit(":", 1)[1])
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=30)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /v1/ingest/{session}?token={SOURCE} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                           f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           f"Sec-WebSocket-Version: 13\r\n\r\n").encode())
        data = b""
        while b"\r\n\r\n" not in data:
            data += self.sock.recv(4096)
        assert b" 101 " in data.split(b"\r\n")[0], data[:200]
        self.buf = data.split(b"\r\n\r\n", 1)[1]

    def frame(self) -> tuple[int, bytes] | None:
        """The server's next frame; ``None`` once the connection has ended."""
        while True:
            if len(self.buf) >= 2:
                n, start = self.buf[1] & 0x7F, 2
                if n == 126 and len(self.buf) >= 4:
                    n, start = struct.unpack("!H", self.buf[2:4])[0], 4
                elif n == 127 and len(self.buf) >= 10:
                    n, start = struct.unpack("!Q", self.buf[2:10])[0], 10
                if n < 126 or start > 2:
                    if len(self.buf) >= start + n:
                        opcode, payload = self.buf[0] & 0x0F, self.buf[start:start + n]
                        self.buf = self.buf[start + n:]
                        return opcode, payload
            try:
                more = self.sock.recv(65536)
            except ConnectionResetError:
                more = b""
            if not more:
                return None
            self.buf += more

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def handed_to_library(monkeypatch):
    """Every piece of received bytes the protocol library's parser was given (on any connection)."""
    from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
    real, given = WebSocketsSansIOProtocol.data_received, []

    def counted(self, data):
        given.append(bytes(data))
        return real(self, data)
    monkeypatch.setattr(WebSocketsSansIOProtocol, "data_received", counted)
    return given


def test_frames_split_anywhere_are_answered_in_order_and_only_other_frames_reach_the_library(server, handed_to_library):
    """A hello, 60 syncs, a ping and a sync in two fragments, all written in pieces of 1-40 bytes (seeded): the
    hello and every sync answered in order, the ping with its pong; the library was given the handshake, the
    ping and the fragments, each whole, and none of the plain text frames (failing without the framing: every
    piece went to the library)."""
    rng = random.Random(16)
    client = _Client(server, "framing-split")
    fragment = json.dumps({"type": "sync", "id": 30}).encode()
    frames = [_text({"type": "hello", "protocol": 1, "hand": "right"})]
    frames += [_text({"type": "sync", "id": k}) for k in range(30)]
    frames += [_frame(9, b"ping!"), _frame(1, fragment[:7], fin=False), _frame(0, fragment[7:])]
    frames += [_text({"type": "sync", "id": k}) for k in range(31, 61)]
    data = b"".join(frames)
    pos = 0
    while pos < len(data):
        step = rng.randint(1, 40)
        client.sock.sendall(data[pos:pos + step])
        pos += step
    got, pongs = [], []
    while len(got) < 62:
        opcode, payload = client.frame()
        if opcode == 10:
            pongs.append(payload)
        else:
            assert opcode == 1, (opcode, payload)
            got.append(json.loads(payload))
    client.close()
    assert got[0]["type"] == "hello"
    assert [m.get("id") for m in got[1:]] == list(range(61)), got
    assert pongs == [b"ping!"]
    after_handshake = [d for d in handed_to_library if not d.startswith(b"GET ")]
    assert after_handshake == [frames[31], frames[32], frames[33]], after_handshake


@pytest.mark.parametrize("bad, code", [
    (_frame(1, b'{"type":"sync","id":1}', masked=False), 1002),     # unmasked
    (_frame(1, b'{"type":"sync","id":1}', rsv=0x40), 1002),          # a reserved bit, no extension
    (_frame(0, b'{"type":"sync","id":1}'), 1002),                    # a continuation with no message begun
    (_frame(3, b"x"), 1002),                                          # an unknown opcode
    (_frame(9, b"p" * 126), 1002),                                    # a control frame over 125 bytes
    (_frame(1, b'{"type":"sync","id":"\xff"}'), 1007),               # not UTF-8
], ids=["unmasked", "reserved-bit", "lone-continuation", "unknown-opcode", "long-control", "not-utf8"])
def test_a_frame_the_library_refuses_after_good_ones_is_refused_as_before(server, bad, code):
    """Good frames (answered), then a good one and one the protocol library refuses, in one write: the connection
    is closed with the library's code (1002 protocol error, 1007 not UTF-8), as before the framing."""
    client = _Client(server, f"framing-bad-{code}-{bad[0]:02x}-{len(bad)}-{bad[1]:02x}")
    client.sock.sendall(_text({"type": "hello", "protocol": 1, "hand": "right"})
                        + b"".join(_text({"type": "sync", "id": k}) for k in range(3)))
    got = [json.loads(client.frame()[1]) for _ in range(4)]
    assert [m.get("id") for m in got] == [None, 0, 1, 2], got
    client.sock.sendall(_text({"type": "sync", "id": 3}) + bad)
    close = None
    while (frame := client.frame()) is not None:
        opcode, payload = frame
        if opcode == 8:
            close = struct.unpack("!H", payload[:2])[0]
            break
        assert json.loads(payload) == {"type": "sync", "id": 3}
    client.close()
    assert close == code
