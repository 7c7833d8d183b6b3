"""The load generator's WebSocket clients (``bench load``): lean, so that the generator is not the
bottleneck, and still able to see what the service gets wrong.

Both run websockets' sans-I/O protocol (its handshake, framing, ping/pong and closing handshake) in
the transport's own callbacks, with no task, queue or future per message:

* ``LeanSubscription`` reads ``/v1/stream/<session>`` and decodes each message only for the fields
  the load test checks (``type``, ``seq``, ``hand``, ``t``; the rest skipped but still parsed,
  ``msgspec``), as it arrives, in place: the transport reads into the connection's own buffer
  (``asyncio.BufferedProtocol``), where whole server messages are cut without websockets' parser
  (every other frame, and the handshake, still go to the protocol); a message that does not decode, or a frame without those fields, is counted
  (``malformed_count``), not dropped silently. A session's subscribers may share a ``SessionDecodes``:
  they get the same bytes, and one compares its whole message with one the other decoded before taking
  its fields. It reconnects with back-off, as ``clients.client.Subscription`` does, counting ``reconnects``.
  While the gloves stream, a ``TickReads`` may read it instead, at the gloves' timer's wakes, each
  frame's arrival then the kernel's receive time of its bytes (the process wakes for the gloves' due
  times, not again for each frame).
* ``LeanGlove`` streams a simulated glove's messages, each framed (masked) before the clock starts
  (``ws_frames``) and written as it is, with ``clients.client.Publisher``'s flow control (a ``sync``
  every 64 messages, at most 256 unconfirmed) and its reconnect (hello and calibration sent again);
  ``stream_gloves`` sends every glove of a process from one timer (a ``timerfd``: at the due time to
  the kernel timer's precision, where asyncio's timers come up to 1 ms late): at each wake, every
  message due, on one timeline of every glove's due times made before the clock starts
  (``GloveSchedule``), each message's send time kept.
"""
from __future__ import annotations

import asyncio
import ctypes
import os
import select
import socket
import struct
import sys
import time
from typing import Callable

import msgspec
from websockets.client import ClientProtocol
from websockets.protocol import State
from websockets.exceptions import InvalidStatus
from websockets.frames import Frame, Opcode
from websockets.http11 import Response
from websockets.uri import parse_uri

from clients.client import FATAL_CLOSE_CODES, Backoff, Refused, _path, _shown, _url
from service.protocol import decode, encode


class Received(msgspec.Struct, gc=False):
    """The fields of a service message the load test checks; every other field is skipped unread
    (a frame's fingers and joints), and a missing one is ``None`` (a malformed frame, counted)."""
    type: str
    seq: int | None = None
    hand: str | None = None
    t: float | None = None


_DECODERS = {False: msgspec.json.Decoder(Received), True: msgspec.msgpack.Decoder(Received)}


def decode_received(data: bytes | memoryview | str, binary: bool) -> Received:
    """``data`` (a whole WebSocket message) read for ``Received``'s fields; raises
    ``msgspec.DecodeError`` (a ``ValueError``) for what is not such a message."""
    return _DECODERS[binary].decode(data)


class SessionDecodes:
    """The messages one session's subscribers decoded and its other subscribers have not all read yet,
    kept as their bytes and ``Received``, so that the session's other subscribers, which get the same
    bytes (the service encodes a frame once for all of them), take a decode only after comparing their
    whole message with one already decoded: equal bytes decode to the same fields, and a message that
    differs in any byte is decoded on its own. Found by the message's length and first ``KEY`` bytes
    (a frame's type, time and seq); a kept message is let go once ``sharers - 1`` others took it, or
    when ``KEEP`` newer ones are kept (a subscriber that far behind the other decodes for itself).
    ``hits`` counts the messages taken so, ``decoded`` the ones decoded."""

    KEY, KEEP = 48, 256

    def __init__(self, binary: bool = False, sharers: int = 2):
        self.binary = binary
        self.sharers = sharers
        self.kept: dict[tuple[int, bytes], list] = {}       # (length, head) -> [bytes, Received, taken]
        self.hits = self.decoded = 0

    def decode(self, data: bytes | memoryview) -> Received:
        """``decode_received(data)``; raises as it does (nothing undecodable is kept)."""
        data = bytes(data)                          # (bytes with bytes: a memcmp; with a memoryview: per item)
        key = (len(data), data[:self.KEY])
        kept = self.kept.get(key)
        if kept is not None and kept[0] == data:
            self.hits += 1
            kept[2] += 1
            if kept[2] >= self.sharers - 1:
                del self.kept[key]
            return kept[1]
        msg = _DECODERS[self.binary].decode(data)
        self.decoded += 1
        if self.sharers > 1:
            self.kept[key] = [data, msg, 0]         # (a message with the same key as a kept one replaces it)
            if len(self.kept) > self.KEEP:
                del self.kept[next(iter(self.kept))]
        return msg


READ_SIZE = 65536
"""the least room a read is given in a connection's buffer"""


class _LeanConnection(asyncio.BufferedProtocol):
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
        self._framing = False                       # the handshake done: frames cut by ``_frames``
        self._head: bytes | None = b""              # the handshake's response so far (None: read)
        self._rbuf = bytearray(4 * READ_SIZE)       # read into (``get_buffer``); [_start, _end): not yet cut
        self._view = memoryview(self._rbuf)
        self._rstart = self._rend = 0
        self.failure: Exception | None = None
        """what refused it for good (``Refused``), or a defect on its message path"""
        self._closing = False
        self._task: asyncio.Task | None = None

    async def _connect(self) -> None:
        """Open the connection and complete the handshake; raises ``InvalidStatus`` (refused) or
        ``OSError``/``ConnectionError``."""
        loop = asyncio.get_running_loop()
        if self.transport is not None and not self.transport.is_closing():
            self.transport.abort()                  # the last connection ends first: its late close or EOF
        if self._lost is not None and not self._lost.done():   # would reach the new one (one protocol object)
            await self._lost
        self.proto = ClientProtocol(self.uri, max_size=None)
        self._opened, self._lost = loop.create_future(), loop.create_future()
        self._parts = []
        self._framing, self._head, self._rstart, self._rend = False, b"", 0, 0
        await loop.create_connection(lambda: self, self.uri.host, self.uri.port,
                                     ssl=True if self.uri.secure else None)
        self.proto.send_request(self.proto.connect())
        self._flush()
        await self._opened

    def connection_made(self, transport) -> None:
        self.transport = transport

    def _send(self, data: str | bytes) -> None:
        """One message through the protocol (text for ``str``, binary for ``bytes``)."""
        if isinstance(data, str):
            self.proto.send_text(data.encode())
        else:
            self.proto.send_binary(data)
        self._flush()

    def _flush(self) -> None:
        for data in self.proto.data_to_send():
            if data:
                self.transport.write(data)
            elif self.transport.can_write_eof():
                self.transport.write_eof()

    def get_buffer(self, sizehint: int) -> memoryview:
        """Where the transport reads to (``recv_into``): the free end of one buffer kept for the
        connection, at least ``READ_SIZE`` bytes (what is not yet read of a frame moved to its start,
        or a larger buffer). Reading into it spares a read its own ``bytes``: asyncio's ``recv`` asks
        for 256 KiB, which the allocator maps and unmaps at each read (about 11 us a read here)."""
        if len(self._rbuf) - self._rend < READ_SIZE:
            keep = self._rend - self._rstart
            if keep + READ_SIZE <= len(self._rbuf):
                self._view[:keep] = bytes(self._view[self._rstart:self._rend])
            else:
                grown = bytearray(2 * (keep + READ_SIZE))
                grown[:keep] = self._view[self._rstart:self._rend]
                self._rbuf, self._view = grown, memoryview(grown)
            self._rstart, self._rend = 0, keep
        return self._view[self._rend:]

    def buffer_updated(self, nbytes: int) -> None:
        try:
            self._received(nbytes)
        except Exception as err:                    # a defect on the message path: the run fails with it
            self.failure = err                      # (asyncio would close the connection and it reconnect)
            self._closing = True
            self.transport.abort()

    def _received(self, nbytes: int, arrival: float | None = None) -> None:
        """The frames of an open connection are cut in the buffer (``_frames``); the handshake's
        response goes to the protocol, exactly up to its end, so that its parser waits at a frame's
        start. ``arrival``: when the bytes came (None: now)."""
        if arrival is None:
            arrival = time.perf_counter()
        self._rend += nbytes
        if self._framing:
            self._frames(arrival)
            return
        data = bytes(self._view[self._rstart:self._rend])
        self._rstart = self._rend = 0
        if self._head is None:                      # the response is read: refused, the rest is its body
            self._to_proto(data, arrival)
            return
        self._head += data
        end = self._head.find(b"\r\n\r\n")
        if end < 0:
            self._to_proto(data, arrival)
            return
        cut = len(data) - (len(self._head) - end - 4)
        self._head = None
        self._to_proto(data[:cut], arrival)
        if self.proto.state is State.OPEN:
            self._framing = True
            rest = data[cut:]
            self._view[:len(rest)] = rest
            self._rend = len(rest)
            self._frames(arrival)
            self._opened_for_frames()
        elif cut < len(data):
            self._to_proto(data[cut:], arrival)

    def _frames(self, arrival: float) -> None:
        """Each whole frame in the buffer: an unfragmented text or binary message from the server (FIN
        set, no reserved bit, unmasked) goes to ``_message`` in place (a ``memoryview``); every other
        frame (ping, close, a fragment, anything the protocol must judge) to the protocol, whole, so
        that its parser always starts at a frame."""
        buf, view = self._rbuf, self._view
        pos, n = self._rstart, self._rend
        while n - pos >= 2:
            b0, b1 = buf[pos], buf[pos + 1]
            size, head = b1 & 0x7F, 2
            if size == 126:
                if n - pos < 4:
                    break
                size, head = int.from_bytes(buf[pos + 2:pos + 4], "big"), 4
            elif size == 127:
                if n - pos < 10:
                    break
                size, head = int.from_bytes(buf[pos + 2:pos + 10], "big"), 10
            if b1 & 0x80:
                head += 4                           # masked (a protocol error from a server: the protocol says so)
            end = pos + head + size
            if end > n:
                break
            if (b0 == 0x81 or b0 == 0x82) and b1 < 0x80 and not self._parts and self.proto.state is State.OPEN:
                self._message(view[pos + head:end], b0 == 0x82, arrival)
            else:
                self._to_proto(bytes(view[pos:end]), arrival)
            pos = end
        if pos == n:
            self._rstart = self._rend = 0
        else:
            self._rstart = pos

    def _to_proto(self, data: bytes, arrival: float) -> None:
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

    def _opened_for_frames(self) -> None:
        """The handshake is done and the connection's frames are cut from here on."""

    def eof_received(self):
        if self._rend > self._rstart:               # a frame cut short: the protocol sees it end
            self.proto.receive_data(bytes(self._view[self._rstart:self._rend]))
            self._rstart = self._rend = 0
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

    def _message(self, data: bytes | memoryview, binary: bool, arrival: float) -> None:
        """One whole data message: ``bytes``, or a ``memoryview`` of the buffer valid during the call."""
        raise NotImplementedError

    def _refusal(self, err: BaseException | None = None) -> Refused | None:
        """What refused this client for good (``clients.client``'s rule): an HTTP status other than 429
        and 5xx (``err``), or a closing code that means so; None where retrying may help."""
        if isinstance(err, InvalidStatus):
            status = err.response.status_code
            return None if status == 429 or status >= 500 else Refused(f"{_shown(self.url)}: HTTP {status}")
        code = self.proto.close_code if self.proto is not None else None
        if code in FATAL_CLOSE_CODES:
            return Refused(f"{_shown(self.url)}: closed by the service ({code}: {self.proto.close_reason})")
        return None

    async def _end(self) -> None:
        """Closed for good (no reconnect): the closing handshake, the background task stopped, and what
        refused this client for good raised, if anything did."""
        self._closing = True
        await self._close()
        if self._task is not None:
            died = self._task.done() and not self._task.cancelled() and self._task.exception()
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            if died:                                # e.g. a handshake that failed other than by a status
                raise died
        if self.failure is not None:
            raise self.failure

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


SO_TIMESTAMPNS = 35
"""``setsockopt`` option (Linux, ``<asm-generic/socket.h>``; Python does not name it): the kernel's receive
time of a read's data (``CLOCK_REALTIME``, a ``timespec``) comes with ``recvmsg`` as a control message of
this type (``SCM_TIMESTAMPNS``); for TCP, the time of the last segment the read took bytes from"""


class TickReads:
    """Subscribers read at the gloves' wakes (``stream_gloves`` calls ``read()`` at each), not each at
    its frames' own wakes: while the gloves stream, a subscriber's connection is taken from the event
    loop (its transport paused) and polled at every wake of the gloves' timer, at most one due time of
    the gloves' schedule apart (5 ms at 200 Hz), so that the process wakes for the gloves' timer and
    not again for each frame. What this changes for the time a frame is taken to arrive: it is not the
    moment this process read the bytes but the moment they reached the socket, the kernel's receive
    time (``SO_TIMESTAMPNS``) of the last TCP segment the read took bytes from (of a frame that ends
    before that segment, a bound after its own), on the kernel's wall clock (``CLOCK_REALTIME``),
    converted to ``time.perf_counter()``'s by their difference at the read and never after the read
    itself; a read without that time (none came) is taken at the read, counted in ``unstamped``.
    ``reads`` counts the reads so made. Linux only (``available``): elsewhere subscribers read as
    they would without it. ``start(subscribers)`` takes the subscribers' connections from the event
    loop, and each one that opens later while started; ``stop()`` gives them back (what is unread is
    then read by the loop at once)."""

    available = sys.platform.startswith("linux") and hasattr(select, "epoll")

    def __init__(self):
        self._poll = select.epoll() if self.available else None
        self._subs: dict[int, "LeanSubscription"] = {}
        self.active = False
        self.reads = self.unstamped = 0

    def start(self, subscribers) -> None:
        self.active = self._poll is not None
        for sub in subscribers:
            self.take(sub)

    def take(self, sub: "LeanSubscription") -> None:
        if not self.active or sub._raw is None or sub._polled or not sub._framing:
            return
        transport = sub.transport
        if transport is None or transport.is_closing() or not transport.is_reading():
            return
        transport.pause_reading()
        fd = sub._raw.fileno()
        self._poll.register(fd, select.EPOLLIN)
        self._subs[fd] = sub
        sub._polled = True

    def give_back(self, sub: "LeanSubscription", resume: bool = True) -> None:
        if not sub._polled:
            return
        sub._polled = False
        fd = sub._raw.fileno()
        self._subs.pop(fd, None)
        self._poll.unregister(fd)
        transport = sub.transport
        if resume and transport is not None and not transport.is_closing():
            transport.resume_reading()

    def read(self) -> None:
        """Read every subscriber whose connection has bytes (one ``epoll`` look, no wait)."""
        if not self._subs:
            return
        ready = self._poll.poll(0)
        if ready:
            offset_ns = time.time_ns() - time.perf_counter_ns()     # CLOCK_REALTIME minus perf_counter's clock
            subs = self._subs
            for fd, _ in ready:
                sub = subs.get(fd)
                if sub is not None:
                    sub._read_polled(offset_ns)

    def stop(self) -> None:
        self.active = False
        for sub in list(self._subs.values()):
            self.give_back(sub)

    def close(self) -> None:
        self.stop()
        if self._poll is not None:
            self._poll.close()
            self._poll = None


_ANCILLARY = socket.CMSG_SPACE(16) if hasattr(socket, "CMSG_SPACE") else 0
_TIMESPEC = struct.Struct("@qq")


class LeanSubscription(_LeanConnection):
    """A subscriber of ``session`` at the service ``url``: ``on_frame(frame, arrival)`` for each
    ``frame`` after the server's ``hello`` (a ``Received``; arrival: ``time.perf_counter()``);
    ``gestures`` and ``others`` count the other messages. ``malformed_count`` counts the messages that
    did not decode and the frames without their ``seq``, ``hand`` or ``t`` (``malformed`` keeps the
    first 10, as read); they are not passed on. ``start()`` connects in the background (reconnecting
    after a drop, with back-off, counted in ``reconnects``); ``close()`` ends it and raises what refused
    it for good, if anything did. ``shared``: the session's ``SessionDecodes``, which its other
    subscribers use too. ``reads``: a ``TickReads`` that reads it while the gloves stream (its frames'
    arrival then the kernel's receive time)."""

    def __init__(self, url: str, session: str, token: str, on_frame: Callable[[Received, float], None],
                 binary: bool = False, backoff: Backoff | None = None, shared: SessionDecodes | None = None,
                 reads: TickReads | None = None):
        super().__init__(_url(url, _path("stream", session), token, binary))
        self.reads = reads if reads is not None and reads.available else None
        self._raw: socket.socket | None = None      # the connection's socket (a duplicate), read by ``reads``
        self._polled = False
        self.binary = binary
        self._decode = (shared.decode if shared is not None and shared.binary == binary
                        else _DECODERS[binary].decode)
        self.on_frame = on_frame
        self.gestures = self.others = 0
        self.backoff = backoff or Backoff()
        self.server_hello: Received | None = None
        self.reconnects = 0
        self.malformed: list = []
        self.malformed_count = 0

    def start(self) -> None:
        self._task = asyncio.create_task(self._run())

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._drop_raw()
        if self.reads is None or transport.get_extra_info("sslcontext") is not None:
            return
        sock = transport.get_extra_info("socket")
        if sock is None:
            return
        try:
            raw = sock.dup()                        # (a socket.socket on the same connection)
            raw.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            raw.setblocking(False)
        except OSError:
            return
        self._raw = raw

    def _drop_raw(self) -> None:
        if self._raw is not None:
            if self._polled:
                self.reads.give_back(self, resume=False)
            self._raw.close()
            self._raw = None

    def _opened_for_frames(self) -> None:
        if self.reads is not None:
            self.reads.take(self)

    def connection_lost(self, exc) -> None:
        self._drop_raw()
        super().connection_lost(exc)

    def _read_polled(self, offset_ns: int) -> None:
        """One read of the connection's bytes for ``TickReads`` (``offset_ns``: ``CLOCK_REALTIME`` minus
        ``perf_counter``'s clock); its end (EOF) or an error goes back to the event loop, which reads it
        as it would have."""
        if self.transport is None or self.transport.is_closing():
            self.reads.give_back(self, resume=False)
            return
        try:
            nbytes, ancillary, _, _ = self._raw.recvmsg_into([self.get_buffer(-1)], _ANCILLARY)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.reads.give_back(self)
            return
        if not nbytes:
            self.reads.give_back(self)
            return
        now_ns = time.perf_counter_ns()
        arrival_ns = now_ns
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(data)
                arrival_ns = min(now_ns, sec * 1_000_000_000 + nsec - offset_ns)
                break
        else:
            self.reads.unstamped += 1
        self.reads.reads += 1
        try:
            self._received(nbytes, arrival_ns * 1e-9)
        except Exception as err:                    # a defect on the message path: the run fails with it
            self.failure = err
            self._closing = True
            self.transport.abort()

    async def _run(self) -> None:
        while not self._closing:
            err = None
            try:
                await self._connect()
                self.backoff.reset()
                await self._lost
            except (InvalidStatus, OSError) as failed:
                err = failed
            if self._closing:
                return
            self.failure = self._refusal(err)
            if self.failure is not None:
                return
            self.reconnects += 1
            await asyncio.sleep(self.backoff.next())

    def _message(self, data: bytes | memoryview, binary: bool, arrival: float) -> None:
        try:
            msg = self._decode(data) if binary == self.binary else decode_received(data, binary)
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
        await self._end()


def ws_frames(encoded: list[str | bytes]) -> list[bytes]:
    """Each message (text for ``str``, binary for ``bytes``) as the client's WebSocket frame on the
    wire: unfragmented, masked with its own random key (RFC 6455 5.3), ready to write as it is."""
    return [Frame(Opcode.TEXT, m.encode(), fin=True).serialize(mask=True) if isinstance(m, str)
            else Frame(Opcode.BINARY, m, fin=True).serialize(mask=True) for m in encoded]


class LeanGlove(_LeanConnection):
    """A glove's source connection (``/v1/ingest/<session>``): ``open(hello)`` connects and sends
    ``hello`` (``hello`` and the last calibration again after a reconnect); ``write(frame, message)``
    writes one message's ready frame (``ws_frames``) when ``ready()``, i.e. connected, the transport
    not paused, and fewer than ``max_unconfirmed`` messages (``max_unconfirmed_bytes`` bytes) not yet
    confirmed by an answered ``sync`` (one goes out every quarter of it, as ``Publisher`` does).
    ``on_ready()`` is called when it becomes ready again. ``errors`` keeps the service's error replies
    (``Received``-like dicts); ``close()`` waits for the service to have handled everything sent."""

    def __init__(self, url: str, session: str, token: str, binary: bool = False, max_unconfirmed: int = 256,
                 max_unconfirmed_bytes: int = 8 << 20, backoff: Backoff | None = None, max_errors: int = 1000):
        super().__init__(_url(url, _path("ingest", session), token, binary))
        self.binary = binary
        self.max_unconfirmed, self.max_unconfirmed_bytes = max_unconfirmed, max_unconfirmed_bytes
        self.backoff = backoff or Backoff()
        self.errors: list[dict] = []
        self.max_errors = max_errors
        self.reconnects = self.unconfirmed_at_drops = 0
        self.on_ready: Callable[[], None] = lambda: None
        self.hello: dict | None = None
        self.calibration: bytes | None = None
        self.connected = self._paused = False
        self._sent = self._sent_bytes = self._confirmed = self._confirmed_bytes = 0
        self._sync_id = 0
        self._marks: dict[int, tuple[int, int]] = {}
        self._waiters: dict[int, asyncio.Future] = {}
        self._server_hello: asyncio.Future | None = None

    async def open(self, hello: dict) -> None:
        """Connect and send ``hello``; raises what refused it (an ``error`` reply, an HTTP status)."""
        self.hello = hello
        loop = asyncio.get_running_loop()
        self._server_hello = loop.create_future()
        await self._connect()
        self._sent = self._sent_bytes = self._confirmed = self._confirmed_bytes = 0
        self._marks.clear()
        self._send(encode(hello, self.binary))
        reply = await self._server_hello
        if reply.get("type") == "error":
            raise Refused(f"{_shown(self.url)}: {reply.get('code')}: {reply.get('detail')}")
        if self.calibration is not None:
            self.transport.write(self.calibration)
        self.connected = True

    def ready(self) -> bool:
        if not self.connected or self._paused or self.proto.state is not State.OPEN:
            return False                            # (closing: the service's close frame came, the TCP close not yet)
        unconfirmed = self._sent - self._confirmed
        return unconfirmed < self.max_unconfirmed and (
            unconfirmed == 0 or self._sent_bytes - self._confirmed_bytes < self.max_unconfirmed_bytes)

    def write(self, frame: bytes, message: dict) -> None:
        """Write one message's ready frame (the caller checked ``ready()``)."""
        self.write_frame(frame, message.get("type") == "calibration")

    def write_frame(self, frame: bytes, calibration: bool = False) -> bool:
        """Write one ready frame (the caller checked ``ready()``; ``calibration``: the glove's calibration,
        sent again after a reconnect); a ``sync`` goes out every quarter of ``max_unconfirmed`` messages and
        when the glove is held; returns ``ready()`` after it."""
        if calibration:
            self.calibration = frame
        self.transport.write(frame)
        self._sent += 1
        self._sent_bytes += len(frame)
        ready = self.ready()
        if not ready or self._sent % max(1, self.max_unconfirmed // 4) == 0:
            self._send_sync()
        return ready

    def _send_sync(self, waiter: asyncio.Future | None = None) -> None:
        self._sync_id += 1
        self._marks[self._sync_id] = (self._sent, self._sent_bytes)
        if waiter is not None:
            self._waiters[self._sync_id] = waiter
        self._send(encode({"type": "sync", "id": self._sync_id}, self.binary))

    def _message(self, data: bytes | memoryview, binary: bool, arrival: float) -> None:
        data = bytes(data)
        try:
            msg = decode(data if binary else data.decode(), binary=binary)
        except ValueError as err:                   # kept as an error reply
            msg = {"type": "error", "code": "undecodable_reply", "detail": str(err)}
        kind = msg.get("type") if isinstance(msg, dict) else None
        if self._server_hello is not None and not self._server_hello.done():
            self._server_hello.set_result(msg if isinstance(msg, dict) else {"type": "error", "code": "bad_reply"})
        elif kind == "error":
            if len(self.errors) < self.max_errors:
                self.errors.append(msg)
        elif kind == "sync":
            mark = self._marks.pop(msg.get("id"), None)
            waiter = self._waiters.pop(msg.get("id"), None)
            if waiter is not None and not waiter.done():
                waiter.set_result(None)
            if mark is not None:
                was = self.ready()
                self._confirmed = max(self._confirmed, mark[0])
                self._confirmed_bytes = max(self._confirmed_bytes, mark[1])
                if not was and self.ready():
                    self.on_ready()

    def pause_writing(self) -> None:
        self._paused = True

    def resume_writing(self) -> None:
        self._paused = False
        if self.ready():
            self.on_ready()

    def connection_lost(self, exc) -> None:
        super().connection_lost(exc)
        for waiter in self._waiters.values():
            if not waiter.done():
                waiter.set_exception(ConnectionError("the connection closed before the service answered sync"))
        self._waiters.clear()
        if self._server_hello is not None and not self._server_hello.done():
            self._server_hello.set_exception(exc or ConnectionError("closed before the service's hello"))
        if self.connected and not self._closing:
            self.connected = False
            self.unconfirmed_at_drops += self._sent - self._confirmed
            self._task = asyncio.get_running_loop().create_task(self._reconnect())
        self.connected = False

    async def _reconnect(self) -> None:
        """After a drop: connect again with back-off (hello and calibration resent), then ``on_ready``;
        refused for good: ``failure``, and the glove stays closed."""
        err = None
        while not self._closing:
            self.failure = self._refusal(err)
            if self.failure is not None:
                self.on_ready()                     # the stream counts it as ended (it may wait for no other wake)
                return
            self.reconnects += 1
            await asyncio.sleep(self.backoff.next())
            try:
                await self.open(self.hello)
            except Refused as refused:
                self.failure = refused
                self.on_ready()
                return
            except (InvalidStatus, OSError) as failed:
                err = failed
                continue
            self.backoff.reset()
            self.on_ready()
            return

    async def close(self, sync_timeout_s: float = 30.0) -> None:
        """Once the service has answered a last ``sync`` (it has handled everything sent; at most
        ``sync_timeout_s``), the closing handshake; raises what refused it for good, if anything did."""
        if self.connected:
            waiter = asyncio.get_running_loop().create_future()
            self._send_sync(waiter)
            try:
                await asyncio.wait_for(waiter, sync_timeout_s)
            except (asyncio.TimeoutError, ConnectionError):
                pass
        await self._end()


PER_WAKE = 32
"""at most this many messages of one glove per wake of ``stream_gloves`` (a glove far behind catches up
over several turns of the loop, the subscribers read in between)"""


class _Ticker:
    """Calls ``callback`` at an absolute ``time.monotonic()`` time (``arm``; a later ``arm`` replaces
    it) with the kernel's timer precision: a ``timerfd`` (Linux) read by the event loop. asyncio's own
    timers wait in ``epoll``, whose timeout is whole milliseconds, rounded up: a glove's message due in
    3.4 ms went out at 4 ms, its frame then counted that much more behind schedule. Elsewhere (no
    ``timerfd``) ``loop.call_at``. ``close()`` stops it."""

    CLOCK_MONOTONIC, TFD_NONBLOCK, TFD_CLOEXEC, TFD_TIMER_ABSTIME = 1, 0o4000, 0o2000000, 1

    def __init__(self, loop: asyncio.AbstractEventLoop, callback: Callable[[], None]):
        self.loop, self.callback = loop, callback
        self._handle: asyncio.TimerHandle | None = None
        self._fd = -1
        timerfd = _timerfd()
        if timerfd is not None:
            create, self._settime, self._spec = timerfd
            fd = create(self.CLOCK_MONOTONIC, self.TFD_NONBLOCK | self.TFD_CLOEXEC)
            if fd >= 0:
                self._fd = fd
                loop.add_reader(fd, self._expired)

    @property
    def precise(self) -> bool:
        return self._fd >= 0

    def arm(self, when: float) -> None:
        if self._fd >= 0:
            sec = int(when)
            spec = self._spec(0, 0, sec, max(int((when - sec) * 1e9), 0 if sec else 1))     # (all zero: disarmed)
            if self._settime(self._fd, self.TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
                raise OSError(ctypes.get_errno(), "timerfd_settime failed")
            return
        if self._handle is not None:
            self._handle.cancel()
        self._handle = self.loop.call_at(self.loop.time() + (when - time.monotonic()), self._expired)

    def _expired(self) -> None:
        if self._fd >= 0:
            try:
                os.read(self._fd, 8)
            except BlockingIOError:                 # re-armed after it expired and before it was read
                return
        else:
            self._handle = None
        self.callback()

    def close(self) -> None:
        if self._fd >= 0:
            self.loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = -1
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None


_TIMERFD: list = []


def _timerfd():
    """libc's ``timerfd_create`` and ``timerfd_settime`` with the ``itimerspec`` structure they take,
    looked up once (Linux); None elsewhere."""
    if not _TIMERFD:
        found = None
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(None, use_errno=True)
                create, settime = libc.timerfd_create, libc.timerfd_settime
            except (OSError, AttributeError):
                pass
            else:
                create.argtypes, create.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int

                class ItimerSpec(ctypes.Structure):
                    _fields_ = [("interval_s", ctypes.c_long), ("interval_ns", ctypes.c_long),
                                ("value_s", ctypes.c_long), ("value_ns", ctypes.c_long)]
                settime.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(ItimerSpec), ctypes.c_void_p]
                settime.restype = ctypes.c_int
                found = (create, settime, ItimerSpec)
        _TIMERFD.append(found)
    return _TIMERFD[0]


class GloveSchedule:
    """The gloves' messages on one timeline, made before the clock starts: every distinct due time (s
    after the stream's start: a message's time minus its glove's first message's) with the gloves that
    have a message due then (a glove once per message due), each time's gloves in turn from a different
    one (a glove is not always the first or last to send); per glove its frames (None for a ``hello``,
    which ``LeanGlove.open`` sent) and which is its calibration."""

    def __init__(self, messages: list[list[tuple[float, dict]]], frames: list[list[bytes]]):
        count = len(messages)
        by_time: dict[float, list[int]] = {}
        for i, m in enumerate(messages):
            a0 = m[0][0] if m else 0.0
            for a, _ in m:
                by_time.setdefault(a - a0, []).append(i)
        self.offsets = sorted(by_time)
        self.gloves = [sorted(by_time[t], key=lambda i, k=k: (i - k) % count) for k, t in enumerate(self.offsets)]
        self.frames = [[None if x.get("type") == "hello" else f for (_, x), f in zip(m, fr)]
                       for m, fr in zip(messages, frames)]
        self.calibrations = [{j for j, (_, x) in enumerate(m) if x.get("type") == "calibration"} for m in messages]
        self.due = [[a - m[0][0] for a, _ in m] for m in messages]   # per glove, s after the start


async def stream_gloves(gloves: list[LeanGlove], messages: list[list[tuple[float, dict]]], frames: list[list[bytes]],
                        on_send: list[Callable[[float, dict], None]] | None, start: float, stop=None,
                        lags: list[float] | None = None, sent: list[list[float]] | None = None,
                        schedule: GloveSchedule | None = None, reads: TickReads | None = None) -> None:
    """Stream every glove in real time from one timer: glove i's message j is due ``messages[i][j][0] -
    messages[i][0][0]`` s after ``start`` (``time.perf_counter()``) and written as ``frames[i][j]``; at
    each wake every glove that is ``ready()`` writes what is due, the gloves taken in turn from a
    different one each due time (a glove not ready, e.g. held by flow control, waits without holding the
    others). A ``hello`` is not written (``LeanGlove.open`` sent it). The wakes come at the due times to
    the kernel timer's precision (``_Ticker``), never before. Each message's send time
    (``time.perf_counter()`` once written; a ``hello``'s once reached) is appended to ``sent[i]`` and
    passed to ``on_send[i](time, message)`` (either may be None). ``stop``: a ``threading.Event`` that ends
    the stream early once set. ``lags``: each message's send time minus its due time is appended there
    (s), glove after glove, at the end. ``schedule``: ``GloveSchedule(messages, frames)``, made before the
    clock starts (else here). ``reads``: subscribers read at each wake once the gloves have written
    (``TickReads``: started by the caller), given back to the event loop once the last message is due (no
    wake of the gloves' timer comes after it) and when the stream ends."""
    loop = asyncio.get_running_loop()
    plan = schedule or GloveSchedule(messages, frames)
    count = len(gloves)
    perf_counter, monotonic = time.perf_counter, time.monotonic
    t0 = monotonic() + (start - perf_counter())     # ``start`` on the monotonic clock (the timer's)
    due = [t0 + x for x in plan.offsets]
    who, plan_frames, calibrations = plan.gloves, plan.frames, plan.calibrations
    sent = sent if sent is not None else [[] for _ in gloves]
    sent_appends = [s.append for s in sent]
    ends = [len(f) for f in plan_frames]
    upto = [0] * count                              # glove i's messages due so far
    pos = [0] * count                               # and sent so far
    pending: dict[int, None] = {}                   # gloves with a message due and not sent (held, or > PER_WAKE)
    ended = [0]                                     # gloves through their messages or refused for good
    gone = [False] * count
    step = [0]                                      # the next due time's index
    done = loop.create_future()
    soon: list = [None]                             # a wake asked for at once (call_soon), not yet run
    ticker = _Ticker(loop, lambda: fire())

    def wake(when: float | None = None) -> None:
        if when is not None:
            ticker.arm(when)
        elif soon[0] is None:
            soon[0] = loop.call_soon(fire_soon)

    def fire_soon() -> None:
        soon[0] = None
        fire()

    def end(i: int) -> None:
        if not gone[i]:
            gone[i] = True
            ended[0] += 1
        pending.pop(i, None)

    def fire() -> None:
        if done.done():
            return
        now = monotonic()
        if stop is not None and stop.is_set():
            done.set_result(None)
            return
        k = step[0]
        visit: list[int] = list(pending) if pending else []
        while k < len(due) and due[k] <= now:
            for i in who[k]:
                upto[i] += 1
            visit += who[k]
            k += 1
        if k - step[0] > 1 or (pending and k > step[0]):
            visit = list(dict.fromkeys(visit))      # (a glove once per wake)
        step[0] = k
        again = False
        for i in visit:
            j, u = pos[i], upto[i]
            if j >= u or gone[i]:
                continue
            glove = gloves[i]
            if glove.failure is not None:
                end(i)
                continue
            if not glove.ready():
                pending[i] = None
                continue
            last = u if u - j <= PER_WAKE else j + PER_WAKE
            fr, append, calib = plan_frames[i], sent_appends[i], calibrations[i]
            while True:
                frame = fr[j]
                ready = glove.write_frame(frame, j in calib) if frame is not None else glove.ready()
                t = perf_counter()
                append(t)
                if on_send is not None and on_send[i] is not None:
                    on_send[i](t, messages[i][j][1])
                j += 1
                if j >= last or not ready:
                    break
            pos[i] = j
            if j >= ends[i]:
                end(i)
            elif j < u:
                pending[i] = None
                again = again or ready
            else:
                pending.pop(i, None)
        if reads is not None and reads.active:      # after the sends: they go first, the reads' times are the kernel's
            reads.read()
            if k >= len(due):
                reads.stop()
        if ended[0] >= count:
            done.set_result(None)
        elif again:
            wake()
        elif k < len(due):
            wake(due[k])

    def on_ready_for(i: int) -> Callable[[], None]:
        def on_ready() -> None:                     # a glove held back may write again (or was refused)
            if not done.done():
                if gloves[i].failure is not None and not gone[i]:
                    end(i)
                    if ended[0] >= count:
                        done.set_result(None)
                        return
                wake()
        return on_ready

    for i, g in enumerate(gloves):
        g.on_ready = on_ready_for(i)
        if not ends[i]:
            end(i)
    try:
        wake()
        if stop is not None:
            async def watch():
                while not done.done():
                    await asyncio.sleep(0.05)
                    if stop.is_set() and not done.done():
                        wake()
            watcher = loop.create_task(watch())
            await done
            watcher.cancel()
        else:
            await done
    finally:
        ticker.close()
        if soon[0] is not None:
            soon[0].cancel()
        if reads is not None:
            reads.stop()
        if lags is not None:
            for i, times in enumerate(sent):
                lags.extend(t - (start + d) for t, d in zip(times, plan.due[i]))
