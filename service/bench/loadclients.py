"""The load generator's WebSocket clients (``bench load``): lean, so that the generator is not the
bottleneck, and still able to see what the service gets wrong.

Both run websockets' sans-I/O protocol (its handshake, framing, ping/pong and closing handshake) in
the transport's own callbacks, with no task, queue or future per message:

* ``LeanSubscription`` reads ``/v1/stream/<session>`` and decodes each message only for the fields
  the load test checks (``type``, ``seq``, ``hand``, ``t``; the rest skipped unread, ``msgspec``),
  as it arrives; a message that does not decode, or a frame without those fields, is counted
  (``malformed_count``), not dropped silently. It reconnects with back-off, as
  ``clients.client.Subscription`` does, counting ``reconnects``.
"""
from __future__ import annotations

import asyncio
import time
from typing import Callable

import msgspec
from websockets.client import ClientProtocol
from websockets.exceptions import InvalidStatus
from websockets.frames import Opcode
from websockets.http11 import Response
from websockets.uri import parse_uri

from clients.client import FATAL_CLOSE_CODES, Backoff, _path, _shown, _url


class Received(msgspec.Struct):
    """The fields of a service message the load test checks; every other field is skipped unread
    (a frame's fingers and joints), and a missing one is ``None`` (a malformed frame, counted)."""
    type: str
    seq: int | None = None
    hand: str | None = None
    t: float | None = None


_DECODERS = {False: msgspec.json.Decoder(Received), True: msgspec.msgpack.Decoder(Received)}


def decode_received(data: bytes | str, binary: bool) -> Received:
    """``data`` (a whole WebSocket message) read for ``Received``'s fields; raises
    ``msgspec.DecodeError`` (a ``ValueError``) for what is not such a message."""
    return _DECODERS[binary].decode(data)


class _LeanConnection(asyncio.Protocol):
    """One WebSocket client connection run in the transport's callbacks; ``_message(data, arrival)``
    gets each whole data message (``binary``: sent as a binary message, MessagePack; ``arrival``:
    ``time.perf_counter()`` when its bytes were read)."""

    def __init__(self, url: str):
        self.url = url
        self.uri = parse_uri(url)
        self.proto: ClientProtocol | None = None
        self.transport: asyncio.Transport | None = None
        self._opened: asyncio.Future | None = None
        self._lost: asyncio.Future | None = None
        self._parts: list[bytes] = []
        self._binary_message = False

    async def _connect(self) -> None:
        """Open the connection and complete the handshake; raises ``InvalidStatus`` (refused) or
        ``OSError``/``ConnectionError``."""
        loop = asyncio.get_running_loop()
        self.proto = ClientProtocol(self.uri, max_size=None)
        self._opened, self._lost = loop.create_future(), loop.create_future()
        self._parts = []
        await loop.create_connection(lambda: self, self.uri.host, self.uri.port,
                                     ssl=True if self.uri.secure else None)
        self.proto.send_request(self.proto.connect())
        self._flush()
        await self._opened

    def connection_made(self, transport) -> None:
        self.transport = transport

    def _flush(self) -> None:
        for data in self.proto.data_to_send():
            if data:
                self.transport.write(data)
            elif self.transport.can_write_eof():
                self.transport.write_eof()

    def data_received(self, data: bytes) -> None:
        arrival = time.perf_counter()
        self.proto.receive_data(data)
        for event in self.proto.events_received():
            if isinstance(event, Response):
                if not self._opened.done():
                    if self.proto.handshake_exc is None:
                        self._opened.set_result(None)
                    else:
                        self._opened.set_exception(self.proto.handshake_exc)
            elif event.opcode in (Opcode.TEXT, Opcode.BINARY, Opcode.CONT):
                if event.opcode is not Opcode.CONT:
                    self._binary_message = event.opcode is Opcode.BINARY
                self._parts.append(event.data)
                if event.fin:
                    whole = self._parts[0] if len(self._parts) == 1 else b"".join(self._parts)
                    self._parts = []
                    self._message(whole, self._binary_message, arrival)
        self._flush()

    def eof_received(self):
        self.proto.receive_eof()
        self._flush()
        return None

    def connection_lost(self, exc) -> None:
        for fut in (self._opened, self._lost):
            if fut is not None and not fut.done():
                if fut is self._opened:
                    fut.set_exception(exc or ConnectionError("closed during the handshake"))
                else:
                    fut.set_result(None)

    def _message(self, data: bytes, binary: bool, arrival: float) -> None:
        raise NotImplementedError

    async def _close(self, timeout_s: float = 10.0) -> None:
        """The closing handshake (code 1000), then the TCP connection closed (at the latest after
        ``timeout_s``)."""
        if self.transport is None or self._lost is None or self._lost.done():
            return
        if self.proto.state.name == "OPEN":
            self.proto.send_close(1000)
            self._flush()
        try:
            await asyncio.wait_for(asyncio.shield(self._lost), timeout_s)
        except asyncio.TimeoutError:
            self.transport.abort()


class LeanSubscription(_LeanConnection):
    """A subscriber of ``session`` at the service ``url``: ``on_frame(frame, arrival)`` for each
    ``frame`` after the server's ``hello`` (a ``Received``; arrival: ``time.perf_counter()``);
    ``gestures`` and ``others`` count the other messages. ``malformed_count`` counts the messages that
    did not decode and the frames without their ``seq``, ``hand`` or ``t`` (``malformed`` keeps the
    first 10, as read); they are not passed on. ``start()`` connects in the background (reconnecting
    after a drop, with back-off, counted in ``reconnects``); ``close()`` ends it and raises what refused
    it for good, if anything did."""

    def __init__(self, url: str, session: str, token: str, on_frame: Callable[[Received, float], None],
                 binary: bool = False, backoff: Backoff | None = None):
        super().__init__(_url(url, _path("stream", session), token, binary))
        self.binary = binary
        self.on_frame = on_frame
        self.gestures = self.others = 0
        self.backoff = backoff or Backoff()
        self.server_hello: Received | None = None
        self.reconnects = 0
        self.malformed: list = []
        self.malformed_count = 0
        self.failure: BaseException | None = None
        self._closing = False
        self._task: asyncio.Task | None = None

    def start(self) -> None:
        self._task = asyncio.create_task(self._run())

    async def _run(self) -> None:
        while not self._closing:
            try:
                await self._connect()
                self.backoff.reset()
                await self._lost
            except InvalidStatus as err:
                status = err.response.status_code
                if status != 429 and status < 500:
                    self.failure = ConnectionRefusedError(f"{_shown(self.url)}: HTTP {status}")
                    return
            except (OSError, ConnectionError):
                pass
            if self._closing:
                return
            code = self.proto.close_code if self.proto is not None else None
            if code in FATAL_CLOSE_CODES:
                self.failure = ConnectionRefusedError(f"{_shown(self.url)}: closed by the service ({code}: "
                                                      f"{self.proto.close_reason})")
                return
            self.reconnects += 1
            await asyncio.sleep(self.backoff.next())

    def _message(self, data: bytes, binary: bool, arrival: float) -> None:
        try:
            msg = decode_received(data, binary)
        except (msgspec.DecodeError, UnicodeDecodeError):
            self._malformed(bytes(data[:200]))
            return
        if msg.type == "frame":
            if msg.seq is None or msg.hand is None or msg.t is None:
                self._malformed(msg)
            else:
                self.on_frame(msg, arrival)
        elif msg.type == "gesture":
            self.gestures += 1
        elif msg.type == "hello":
            self.server_hello = msg
        else:
            self.others += 1

    def _malformed(self, what) -> None:
        self.malformed_count += 1
        if len(self.malformed) < 10:
            self.malformed.append(what)

    async def close(self) -> None:
        self._closing = True
        await self._close()
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        if self.failure is not None:
            raise self.failure
