"""Running the app with uvicorn: ``fingertrack serve`` and an in-process server for tests and the demo."""
from __future__ import annotations

import asyncio
import errno
import logging
import socket
import threading
import time

import uvicorn
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.protocol import State

try:
    from websockets.speedups import apply_mask
except ImportError:                                 # (websockets without its C extension)
    from websockets.utils import apply_mask

from .app import create_app
from .buffers import read_buffer
from .config import ServiceSettings, event_loop_name
from .outgoing import WIRE_EXTENSION
from ..pipeline.gc_policy import serving_gc  # noqa: F401  (re-exported: the CLI and the tests take it from here)

log = logging.getLogger(__name__)
_OPEN = State.OPEN
_ENDING = (State.CLOSING, State.CLOSED)

class DrainingWebSocket(WebSocketsSansIOProtocol, asyncio.BufferedProtocol):
    """uvicorn's WebSocket protocol, except that it pauses reading only once ``QUEUE_HIGH`` messages wait
    for the app, that it takes ready-made data frames to write as they are (``write_frames``, offered in
    the scope's extensions as ``WIRE_EXTENSION``), and where it fails a connection for a frame it cannot take (larger
    than ``ws_max_size``: close 1009; malformed: 1002; not UTF-8: 1007). uvicorn sends its close frame
    and closes the socket at once, while the rest of the peer's frame is still arriving: the kernel
    answers that data with a reset, and a peer still sending gets the reset instead of the close frame
    and its reason ("no close frame received"; 5 connections of the 100,000-message fuzz). Here what the
    peer still sends is read and dropped until it closes its side (or ``DRAIN_S`` pass), then the socket
    closes. Its reads go into the thread's ``read_buffer`` (a ``BufferedProtocol``), not a new bytes object each.

    Once the handshake is in, the received bytes are cut into whole frames here (``_frames_in``): a complete,
    unfragmented, masked text frame of an open connection is unmasked and handed to the app here, without the
    protocol library's parser (a generator per frame part) and uvicorn's event dispatch (together about a
    fifth of this process's CPU per glove message); every other frame goes to the library whole, so that its
    parser always starts at a frame's first byte, and anything the library would refuse (unmasked, reserved
    bits, an unknown opcode, a frame over ``ws_max_size``, an invalid control frame) goes to it with
    everything after it, so that it is refused there as before. Nothing is cut so while an extension is
    negotiated, nor ever again on that connection after the library was handed a frame's rest."""

    DRAIN_S = 5.0
    QUEUE_HIGH = 16
    """received messages the app has not taken yet before reading from the connection pauses (uvicorn pauses
    after every message and resumes once the app has taken it: two changes of the loop's selector per
    message, with routes that read all the time anyway; ``api.backlog`` bounds what waits beyond). While a
    route does not read (the ingest route only while it closes an overloaded connection), up to this many
    messages of up to ``ws_max_size`` each (4 x ``max_message_bytes``), plus one read, wait here: 16 times
    what uvicorn's own rule let wait."""
    _draining = False
    _framing: bool | None = None
    """``True``: received bytes are cut into frames here (``_frames_in``); ``None``: not yet (the handshake);
    ``False``: never on this connection (the library's parser may be inside a frame)"""
    _partial: bytearray | None = None
    """the start of a frame not yet received whole (at most ``ws_max_size`` and its head)"""
    _fragmented = False
    """a fragmented message's first frame was received and not yet its last (from the frames' heads)"""
    intake = None
    """``intake(text) -> bool``, set by the app's route (``routes.ingest``): a received text message offered to
    the app at once, in this callback, while nothing waits in the queue for the app before it; ``True``: taken
    (no queue, no wake of the app's task, no ASGI ``receive`` for it), ``False``: queued as usual."""

    _read_into: memoryview | None = None

    def get_buffer(self, sizehint: int) -> memoryview:
        self._read_into = view = read_buffer()
        return view

    def buffer_updated(self, nbytes: int) -> None:
        if self._framing and not self._draining:    # cut from the buffer itself (``_frames_in`` copies what it keeps)
            self._frames_in(self._read_into[:nbytes])
        else:
            self.data_received(bytes(self._read_into[:nbytes]))

    def send_receive_event_to_app(self) -> None:
        if self.intake is not None and self.curr_msg_data_type == "text" and len(self.frames) == 1 \
                and not self.close_sent and self._offer(self.frames[0]):
            self.frames = []
            return
        self._to_app()

    def _offer(self, payload: bytes) -> bool:
        """A received text message's payload to ``intake`` while nothing waits in the queue for the app before it;
        ``True``: taken. ``False`` for a payload that is not UTF-8 (refused by the app's way, as uvicorn does: 1007)."""
        if self.queue.qsize():
            return False
        try:
            text = payload.decode()
        except UnicodeDecodeError:
            return False
        try:
            return bool(self.intake(text))
        except Exception:                                     # a defect: the message and the connection's later
            log.exception("the ingest route's intake failed; this connection's messages go "   # ones are queued
                          "through the app's receive from now on")
            self.intake = None
            return False

    def _to_app(self) -> None:
        """The received message in ``frames`` queued for the app (uvicorn's way), reading paused once ``QUEUE_HIGH``
        messages wait."""
        paused, self.read_paused = self.read_paused, True     # (so that uvicorn does not pause here)
        try:
            super().send_receive_event_to_app()
        finally:
            self.read_paused = paused
        if not paused and self.queue.qsize() >= self.QUEUE_HIGH:
            self.read_paused = True
            self.transport.pause_reading()

    def handle_connect(self, event) -> None:
        super().handle_connect(event)
        if self.handshake_initiated and not self.close_sent:     # the app's task starts on the loop's next turn
            self.scope["extensions"][WIRE_EXTENSION] = self

    def write_frames(self, data: bytes) -> bool:
        """Write ``data``, whole WebSocket data frames as a server sends them (unmasked, not fragmented,
        uncompressed: ``api.outgoing.ws_frame``), as they are: one write for any number of frames, built once
        for every subscriber, instead of the ASGI ``websocket.send`` path per message (the app's, the
        server's and the protocol library's layers took more of this process's time than the frames' data).
        ``False``, nothing written: the connection cannot take them so (closing or closed, or an extension
        such as per-message deflate negotiated); the caller sends through ASGI then, which says why. The
        caller waits for ``writable`` first, as the ASGI send does."""
        if (self.disconnected or self.close_sent or not self.handshake_complete or self.initial_response is not None
                or self._draining or self.conn.state is not State.OPEN or self.conn.extensions
                or self.conn.expect_continuation_frame or self.transport.is_closing()):
            return False
        self.transport.write(data)
        return True

    def handle_parser_exception(self) -> None:
        assert self.conn.close_sent is not None
        close = self.conn.close_sent
        self.queue.put_nowait({"type": "websocket.disconnect", "code": close.code, "reason": close.reason})
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = True
        self._draining = True
        # uvicorn's timer of a close in progress: the app's end does not close the socket before it
        self.close_timer = self.loop.call_later(self.DRAIN_S, self.transport.close)

    def data_received(self, data: bytes) -> None:
        if self._draining:
            return                                # the rest of a frame already refused, dropped; the peer's end of
        if self._framing:                         # input closes the socket
            self._frames_in(data)
            return
        super().data_received(data)
        if self._framing is None and self.handshake_initiated:
            # the request was parsed whole (uvicorn hands it over in one piece): the parser waits for a frame's
            # first byte, unless frames came with the request
            self._framing = not self.close_sent and self.conn.parser_exc is None and not self.conn.reader.buffer

    def _frames_in(self, data: bytes | memoryview) -> None:
        """The received bytes, cut into whole frames (class docstring); ``data`` may be a view of the read buffer,
        which the next read overwrites: what is kept, or handed to the library, is copied."""
        partial = self._partial
        if partial:
            partial += data
            buf = partial
        else:
            buf = data
        conn, size, pos, limit = self.conn, len(buf), 0, self.config.ws_max_size
        while size - pos >= 2:
            head1, head2 = buf[pos], buf[pos + 1]
            length, start = head2 & 0x7F, pos + 2
            if length == 126:
                if size - pos < 4:
                    break
                length, start = buf[start] << 8 | buf[start + 1], start + 2
            elif length == 127:
                if size - pos < 10:
                    break
                length, start = int.from_bytes(buf[start:start + 8], "big"), start + 8
            opcode = head1 & 0x0F
            if not head2 & 0x80 or head1 & 0x70 or conn.extensions or length > limit \
                    or (opcode > 2 and (opcode < 8 or opcode > 10 or length > 125 or not head1 & 0x80)):
                self._give_up(buf[pos:])          # refused there as before (or an extension's: decoded there)
                return
            end = start + 4 + length
            if end > size:
                break
            if head1 == 0x81 and not self._fragmented and not self.close_sent and conn.state is _OPEN:
                payload = apply_mask(buf[start + 4:end], buf[start:start + 4])
                if self.intake is None or not self._offer(payload):
                    self.curr_msg_data_type = "text"
                    self.frames = [payload]
                    self._to_app()
            else:                                 # (the parser is at the next frame's start after it)
                if opcode < 3:                    # a message's first or next fragment, or its last
                    self._fragmented = not head1 & 0x80
                super().data_received(bytes(buf[pos:end]))
            pos = end
            if self._draining:
                return
            if conn.parser_exc is not None or conn.state in _ENDING:
                self._give_up(buf[pos:])
                return
        if pos == size:
            self._partial = None
        elif buf is partial:
            del partial[:pos]
        else:
            self._partial = bytearray(buf[pos:])

    def _give_up(self, rest) -> None:
        """No more frames cut here on this connection: ``rest`` (from a frame's first byte) and everything after it
        go to the library's parser."""
        self._framing, self._partial = False, None
        if rest:
            super().data_received(bytes(rest))


try:
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:                                 # httptools not installed: uvicorn's pure-Python parser (h11)
    HttpToolsProtocol = None

HTTPTOOLS_HOOKS = ("on_message_begin", "on_headers_complete", "on_body", "on_message_complete",
                   "data_received", "send_400_response")
"""uvicorn's httptools protocol's methods ``BoundedHttpTools`` overrides or calls (uvicorn internals, the same in
0.53-0.55); a uvicorn without one of them, or whose protocol takes its reads otherwise than through
``data_received`` (a ``BufferedProtocol``), would leave the head unbounded: then h11 serves HTTP, which bounds it
(logged once)."""
if HttpToolsProtocol is not None and (issubclass(HttpToolsProtocol, asyncio.BufferedProtocol) or not all(
        callable(getattr(HttpToolsProtocol, name, None)) for name in HTTPTOOLS_HOOKS)):
    log.warning("uvicorn's httptools protocol lacks a method the service's head bound needs (one of %s); HTTP is "
                "served with h11", ", ".join(HTTPTOOLS_HOOKS))
    HttpToolsProtocol = None


if HttpToolsProtocol is not None:
    class BoundedHttpTools(HttpToolsProtocol):
        """uvicorn's HTTP protocol on the C parser (httptools), with the request head bounded as the pure-Python
        parser bounds it: a request line and headers still incomplete after ``HEAD_LIMIT`` bytes get the same
        400 reply and the connection closes (uvicorn's httptools protocol keeps taking them: a client sending an
        endless header or URL grew this process by what it sent, 25 MB for 25 MB). A chunked body's trailers (the
        lines after its last chunk, kept like a head's) are counted the same way, from the last chunk's header on.
        Parsing a request costs a small part of the pure-Python parser's time (which was most of a ``GET /health``'s
        CPU here)."""

        HEAD_LIMIT = 16 * 1024
        """bytes of a request's head (request line and headers) taken while it is incomplete, after the read in
        which it began: h11's default (``h11_max_incomplete_event_size``), the limit before this parser. The read
        in which a head begins is not counted (the parser does not say where in it the head began, and a read
        of pipelined requests may end in the next one's head): a head is refused past at most one read (256 KiB,
        asyncio's) and this limit, never for the requests before it in the same read."""
        _in_head = True
        _head = 0
        _began = False

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._in_head, self._head, self._began = True, 0, True

        def on_headers_complete(self) -> None:
            self._in_head = False
            super().on_headers_complete()

        def on_chunk_header(self) -> None:       # a chunk's data or, after the last chunk, the trailers
            self._in_head, self._head, self._began = True, 0, True

        def on_body(self, body: bytes) -> None:
            self._in_head = False
            super().on_body(body)

        def on_message_complete(self) -> None:
            self._in_head = False
            super().on_message_complete()

        def data_received(self, data: bytes) -> None:
            self._began = False
            super().data_received(data)
            if self._in_head and not self._began and self.transport is not None and not self.transport.is_closing():
                self._head += len(data)
                if self._head > self.HEAD_LIMIT:
                    msg = "Invalid HTTP request received."
                    self.logger.warning("%s (its head is longer than %d bytes)", msg, self.HEAD_LIMIT)
                    self.send_400_response(msg)
else:
    BoundedHttpTools = None


def uvicorn_config(settings: ServiceSettings, app=None) -> uvicorn.Config:
    """uvicorn's configuration of the service: its HTTP and WebSocket protocols (above) on the event loop
    ``settings.event_loop`` names (``config.event_loop_name``)."""
    # messages above max_message_bytes get an error reply and the connection stays; only frames four
    # times larger are cut off at the WebSocket layer (close 1009)
    return uvicorn.Config(app or create_app(settings), host=settings.host, port=settings.port, log_level="warning",
                          loop=event_loop_name(settings),
                          http=BoundedHttpTools or "h11", ws=DrainingWebSocket,
                          ws_max_size=4 * settings.max_message_bytes, ws_ping_interval=settings.ping_interval_s,
                          ws_ping_timeout=settings.ping_timeout_s, ws_per_message_deflate=settings.websocket_compression,
                          timeout_graceful_shutdown=2, lifespan="on")


class FingertrackServer(uvicorn.Server):
    """uvicorn's server with the app's graceful drain run before connections are cut (uvicorn would
    otherwise close WebSockets with 1012 before the app's shutdown hook runs)."""

    async def shutdown(self, sockets=None) -> None:
        drain = getattr(getattr(self.config.app, "state", None), "drain", None)
        if drain is not None:
            await drain()
        await super().shutdown(sockets)


def listen_socket(host: str, port: int) -> socket.socket:
    """The bound listening socket of ``host:port``; ``OSError`` with one clear line when the port is
    taken or the address is not local (checked before the service prints or starts anything)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # the protocol named: asyncio turns Nagle's algorithm off (TCP_NODELAY) only on sockets that say
    # they are TCP, and accepted sockets inherit it; without it a frame written while the previous one
    # waits for its acknowledgement waited for the peer's delayed acknowledgement (about 40 ms)
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        what = "is already in use" if err.errno == errno.EADDRINUSE else f"cannot be used ({err.strerror})"
        raise OSError(f"port {port} on {host} {what}; stop the other service or choose another --port") from None
    sock.set_inheritable(True)
    return sock


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerThread:
    """A real uvicorn server on a localhost port, in a background thread (tests, demo).

    ``send_buffer_bytes`` fixes the kernel send buffer of every connection (set on the listening
    socket, which accepted sockets inherit), e.g. to make a stalled client's backpressure reach the
    service within seconds instead of after megabytes of autotuned buffer."""

    def __init__(self, settings: ServiceSettings, send_buffer_bytes: int | None = None):
        if settings.port == 0:
            settings = settings.model_copy(update={"port": free_port()})
        self.app = create_app(settings)
        self.settings = self.app.state.settings
        self.server = FingertrackServer(uvicorn_config(self.settings, self.app))
        sockets = None
        if send_buffer_bytes is not None:
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer_bytes)
            sock.bind((self.settings.host, self.settings.port))
            sockets = [sock]
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": sockets}, daemon=True)

    @property
    def url(self) -> str:
        return f"http://{self.settings.host}:{self.settings.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.settings.host}:{self.settings.port}"

    def __enter__(self) -> "ServerThread":
        self.thread.start()
        # bounds a failure only: a start may compile kernels first (a cold cache on a busy machine)
        deadline = time.monotonic() + 300
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("the server did not start")
            time.sleep(0.01)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)
