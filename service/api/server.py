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

from .app import create_app
from .config import ServiceSettings
from .outgoing import WIRE_EXTENSION
from ..pipeline.gc_policy import serving_gc  # noqa: F401  (re-exported: the CLI and the tests take it from here)

log = logging.getLogger(__name__)


class DrainingWebSocket(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol, except that it pauses reading only once ``QUEUE_HIGH`` messages wait
    for the app, that it takes ready-made data frames to write as they are (``write_frames``, offered in
    the scope's extensions as ``WIRE_EXTENSION``), and where it fails a connection for a frame it cannot take (larger
    than ``ws_max_size``: close 1009; malformed: 1002; not UTF-8: 1007). uvicorn sends its close frame
    and closes the socket at once, while the rest of the peer's frame is still arriving: the kernel
    answers that data with a reset, and a peer still sending gets the reset instead of the close frame
    and its reason ("no close frame received"; 5 connections of the 100,000-message fuzz). Here what the
    peer still sends is read and dropped until it closes its side (or ``DRAIN_S`` pass), then the socket
    closes."""

    DRAIN_S = 5.0
    QUEUE_HIGH = 16
    """received messages the app has not taken yet before reading from the connection pauses (uvicorn pauses
    after every message and resumes once the app has taken it: two changes of the loop's selector per
    message, with routes that read all the time anyway; ``api.backlog`` bounds what waits beyond). While a
    route does not read (the ingest route only while it closes an overloaded connection), up to this many
    messages of up to ``ws_max_size`` each (4 x ``max_message_bytes``), plus one read, wait here: 16 times
    what uvicorn's own rule let wait."""
    _draining = False
    intake = None
    """``intake(text) -> bool``, set by the app's route (``routes.ingest``): a received text message offered to
    the app at once, in this callback, while nothing waits in the queue for the app before it; ``True``: taken
    (no queue, no wake of the app's task, no ASGI ``receive`` for it), ``False``: queued as usual."""

    def send_receive_event_to_app(self) -> None:
        intake = self.intake
        if intake is not None and self.curr_msg_data_type == "text" and len(self.frames) == 1 \
                and not self.close_sent and self.queue.empty():
            try:
                text = self.frames[0].decode()
            except UnicodeDecodeError:
                pass                                          # refused below, as uvicorn does (1007)
            else:
                try:
                    taken = intake(text)
                except Exception:                             # a defect: the message and the connection's
                    log.exception("the ingest route's intake failed; this connection's messages go "   # later ones
                                  "through the app's receive from now on")                             # are queued
                    self.intake = taken = None
                if taken:
                    self.frames = []
                    return
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
        if not self._draining:
            super().data_received(data)
        # else: the rest of a frame already refused, dropped; the peer's end of input closes the socket


try:
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:                                 # httptools not installed: uvicorn's pure-Python parser (h11)
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
    # messages above max_message_bytes get an error reply and the connection stays; only frames four
    # times larger are cut off at the WebSocket layer (close 1009)
    return uvicorn.Config(app or create_app(settings), host=settings.host, port=settings.port, log_level="warning",
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
