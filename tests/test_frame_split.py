"""``server.DrainingWebSocket`` splits a connection's frames itself once its handshake came alone: what the
app receives and what the peer gets back (pongs, close frames and codes) are the same as when the protocol
library splits them (``SPLIT_FRAMES = False``), whatever the chunks the bytes arrive in, except that the
messages that came in the same read as a refused frame reach the app here (uvicorn drops them); a handshake
with frames right behind it in the same write keeps the library's path. Real uvicorn servers on free
ports, a raw socket client."""
import asyncio
import base64
import os
import random
import socket
import struct
import threading
import time

import uvicorn

from service.api.server import DrainingWebSocket, free_port

LIMIT = 1000


def _frame(opcode: int, payload: bytes, fin: bool = True, masked: bool = True, rsv: int = 0) -> bytes:
    head = bytes([(0x80 if fin else 0) | rsv | opcode])
    n = len(payload)
    length = bytes([n]) if n < 126 else bytes([126]) + struct.pack("!H", n) if n < 1 << 16 \
        else bytes([127]) + struct.pack("!Q", n)
    if not masked:
        return head + length + payload
    mask = os.urandom(4)
    return head + bytes([length[0] | 0x80]) + length[1:] + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


class _LibrarySplits(DrainingWebSocket):
    SPLIT_FRAMES = False


def _server(protocol=DrainingWebSocket):
    received: list = []

    async def app(scope, receive, send):
        if scope["type"] == "lifespan":
            while True:
                message = await receive()
                kind = message["type"].replace("lifespan.", "")
                await send({"type": f"lifespan.{kind}.complete"})
                if kind == "shutdown":
                    return
        assert (await receive())["type"] == "websocket.connect"
        await send({"type": "websocket.accept"})
        while True:
            message = await receive()
            received.append({k: v for k, v in message.items() if k != "reason"})
            if message["type"] == "websocket.disconnect":
                return

    config = uvicorn.Config(app, host="127.0.0.1", port=free_port(), ws=protocol, ws_max_size=LIMIT,
                            ws_ping_interval=None, log_level="critical", lifespan="on")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.01)
    return server, thread, received, config.port


def _exchange(port: int, frames: list[bytes], chunks, with_handshake: bool) -> bytes:
    """The handshake (alone, or with the frames right behind it), the frames in ``chunks(data)`` pieces;
    everything the server sent until it closed."""
    key = base64.b64encode(os.urandom(16)).decode()
    request = (f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode()
    data = b"".join(frames)
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        got = b""
        if with_handshake:
            sock.sendall(request + data)
        else:
            sock.sendall(request)
            while b"\r\n\r\n" not in got:
                got += sock.recv(65536)
            try:
                for piece in chunks(data):
                    sock.sendall(piece)
                    time.sleep(0.001)        # (separate arrivals, most of the time)
            except OSError:                  # the server closed after a close handshake: the rest goes nowhere
                pass
        try:
            sock.shutdown(socket.SHUT_WR)
            while chunk := sock.recv(65536):
                got += chunk
        except OSError:
            pass
    return got.split(b"\r\n\r\n", 1)[1]


def _replies(data: bytes) -> list[tuple[int, bytes]]:
    """The server's frames: (opcode, payload)."""
    out, at = [], 0
    while at + 2 <= len(data):
        opcode, n, at = data[at] & 0x0F, data[at + 1] & 0x7F, at + 2
        if n == 126:
            n, at = struct.unpack("!H", data[at:at + 2])[0], at + 2
        out.append((opcode, data[at:at + n]))
        at += n
    return out


def test_frames_split_here_reach_the_app_as_the_library_gives_them_in_any_chunks():
    streams = {
        "messages": [_frame(1, b"a"), _frame(1, "é€ 😀".encode() * 30), _frame(2, b"\x00\xff" * 70),
                     _frame(9, b"ping!"), _frame(1, b"first ", fin=False), _frame(10, b"unasked pong"),
                     _frame(0, b"second"), _frame(1, b"x" * LIMIT), _frame(1, b""),
                     _frame(8, struct.pack("!H", 1000) + b"bye")],
        "invalid utf-8": [_frame(1, b"ok"), _frame(1, b"\xff\xfe"), _frame(1, b"never")],
        "too large": [_frame(1, b"ok"), _frame(1, b"y" * (LIMIT + 1)), _frame(1, b"never")],
        "too large at its header": [_frame(1, b"ok"), _frame(1, b"z" * 70_000)[:200]],
        "unmasked": [_frame(1, b"ok"), _frame(1, b"plain", masked=False), _frame(1, b"never")],
        "reserved bit": [_frame(1, b"ok"), _frame(1, b"rsv", rsv=0x40), _frame(1, b"never")],
        "text inside a fragmented one": [_frame(1, b"a", fin=False), _frame(1, b"b"), _frame(1, b"never")],
        "ends mid-frame": [_frame(1, b"ok"), _frame(1, b"cut short")[:5]],
    }
    ways = {"whole": lambda d: [d], "bytes": lambda d: [d[i:i + 1] for i in range(len(d))],
            "random": lambda d: _random_chunks(d, random.Random(len(d)))}
    servers = [_server(_LibrarySplits), _server()]
    seen: dict = {}
    try:
        for name, frames in streams.items():
            for way, chunks in ways.items():
                results = []
                for server, thread, received, port in servers:
                    received.clear()
                    replies = _replies(_exchange(port, frames, chunks, with_handshake=False))
                    deadline = time.monotonic() + 30
                    while not received or received[-1]["type"] != "websocket.disconnect":
                        assert time.monotonic() < deadline, (name, way, received)
                        time.sleep(0.01)
                    results.append((list(received), replies))
                (mine, mine_replies), (library, library_replies) = results[1], results[0]
                assert mine_replies == library_replies and mine[-1] == library[-1], (name, way)
                # uvicorn drops the messages that came in the same read as a frame the library refuses; here
                # they reach the app: the library's messages are the first of these
                assert mine[:len(library) - 1] == library[:-1], (name, way)
                assert mine == seen.setdefault(name, mine), (name, way)       # the same in any chunks
                if name == "messages":
                    assert {"type": "websocket.receive", "text": "first second"} in results[1][0]
                    assert (10, b"ping!") in results[1][1]
        # frames right behind the handshake: the library's path, as before
        for server, thread, received, port in servers:
            received.clear()
            _exchange(port, streams["messages"], None, with_handshake=True)
            deadline = time.monotonic() + 30
            while not received or received[-1]["type"] != "websocket.disconnect":
                assert time.monotonic() < deadline, received
                time.sleep(0.01)
            results.append(list(received))
        assert results[-1] == results[-2]
    finally:
        for server, thread, _, _ in servers:
            server.should_exit = True
            thread.join(10)


def _random_chunks(data: bytes, rnd: random.Random) -> list[bytes]:
    out, at = [], 0
    while at < len(data):
        n = rnd.randrange(1, 40)
        out.append(data[at:at + n])
        at += n
    return out
