"""A source connection's backlog: what the service has received from it and not yet processed, and the
rule when the service cannot keep up with the source.

The ingest route reads its WebSocket all the time into an ``IngestBacklog`` while a second task
processes the messages in order, so the connection's keepalive pings and pongs pass however far
processing lags; while the processor waits for work with nothing queued, the reader hands a JSON data
message of a connection whose hello was handed on, for a session whose hand runs in a worker, to the
session itself, as the processor would (``LiveSession.forwardable``: one task's wake less per message). (A route that stopped reading while it was busy left the source's pong behind
unread data: after ``ping_timeout_s`` the connection was closed with 1011 and everything the source
had sent and the service not yet read was lost without a word.)

The backlog holds at most ``ingest_backlog_messages`` messages and ``ingest_backlog_bytes`` bytes.
When it is full the service cannot keep up with the source: every data message (``pose``, ``imu``,
``imu_batch``) received from then on is refused with an ``overloaded`` error reply until the
backlog has drained to half its bound (counted: the session summary's ``overloaded``, the frame
status's ``dropped.overloaded`` and ``fingertrack_overloaded_messages_total``). Other messages
(``hello``, ``calibration``, ``reference_pose``, ``sync``, anything unparsable) are few and carry
state or a question: they are queued even then, up to twice the bound, so a ``sync`` is answered.
Nothing received is dropped without a reply: a message is processed, or refused with a reply.
Replies leave in the order of the messages they answer, refusals included: a message refused at the
door (``overloaded``, or its size, or the rate limit) is answered when the processor reaches its
place (``put_reply``: its reply, not the message, is queued, outside the bounds above). Such replies
waiting at a time are bounded too, to a quarter of ``ingest_backlog_bytes`` (64 KiB at least; each counted as its text
plus ``REPLY_OVERHEAD_BYTES``: 8 MiB, some 25,000 replies by default); a source that keeps sending
beyond that is closed with 1013 and the reason (what it sent before is still processed).

A source that must not lose data paces itself: the Python ``Publisher`` keeps at most
``max_unconfirmed`` messages beyond its last answered ``sync`` (flow control), well inside the
default bound, so a recording replayed at full speed is slowed down, not refused.
"""
from __future__ import annotations

import asyncio
from collections import deque

DATA_TYPES = ("pose", "imu", "imu_batch")
"""What an overloaded session refuses (the rest carries state and is always queued)."""
REPLY_OVERHEAD_BYTES = 200
"""What a queued reply takes beyond its detail's text (the tuples that hold it), counted generously."""


class IngestBacklog:
    """A bounded FIFO of received WebSocket messages (``put`` by the reader, ``get`` by the processor;
    ``None`` from ``get``: the connection ended and everything before it was taken)."""

    def __init__(self, max_messages: int, max_bytes: int):
        self.max_messages, self.max_bytes = max_messages, max_bytes
        self.max_reply_bytes = max(max_bytes // 4, 1 << 16)
        """Replies to refused messages that may wait for their place (``put_reply``), bytes."""
        self._items: deque = deque()
        self._bytes = 0
        self._messages = 0                   # received messages in _items (the rest: replies, the end)
        self._reply_bytes = 0
        self._ready = asyncio.Event()
        self._waiting = False                # the processor waits in ``get`` for the next item
        self.greeted = False
        """The processor has handed this connection's hello to its session (set by the route): from then on
        the reader may hand a data message on itself (``LiveSession.forwardable``), not before (after a
        takeover the session may be greeted by the older connection's hello)."""
        self.overloaded = False
        """True from the moment the backlog was full until it drained to half."""

    def __len__(self) -> int:
        """Received messages waiting (not the replies to refused ones)."""
        return self._messages

    def _fits(self, size: int, factor: int = 1) -> bool:
        if not self._messages:               # one message always fits (a single one larger than the byte bound)
            return True
        return self._messages < factor * self.max_messages and self._bytes + size <= factor * self.max_bytes

    def put(self, item, size: int, data_message) -> bool:
        """Queue a received message of ``size`` bytes; ``False`` if it is refused because the service
        cannot keep up. ``data_message()`` says whether it is a data message (asked only when it
        might be refused; other messages are queued up to twice the bound)."""
        if self.overloaded and self._messages <= self.max_messages // 2 and self._bytes <= self.max_bytes // 2:
            self.overloaded = False
        if self.overloaded or not self._fits(size):
            if data_message():
                self.overloaded = True
                return False
            if not self._fits(size, factor=2):
                return False
        self._items.append((item, size))
        self._bytes += size
        self._messages += 1
        self._ready.set()
        return True

    def put_reply(self, reply: tuple[str, str]) -> bool:
        """Queue the ``(code, detail)`` error reply of a message refused at the door, in the message's
        place (``get`` returns the tuple); ``False`` if ``max_reply_bytes`` of replies wait already."""
        size = len(reply[1]) + REPLY_OVERHEAD_BYTES
        if self._reply_bytes + size > self.max_reply_bytes:
            return False
        self._items.append((reply, -size))
        self._reply_bytes += size
        self._ready.set()
        return True

    def close(self) -> None:
        """The connection ended: ``get`` returns ``None`` after the messages already queued."""
        self._items.append((None, 0))
        self._ready.set()

    def idle(self) -> bool:
        """Nothing waits here and the processor waits for the next item: a message handled at once now
        keeps its place in the order."""
        return self._waiting and not self._items

    async def get(self):
        while not self._items:
            self._ready.clear()
            self._waiting = True
            try:
                await self._ready.wait()
            finally:
                self._waiting = False
        item, size = self._items.popleft()
        if size < 0:                         # a reply in a refused message's place
            self._reply_bytes += size
        elif item is not None:
            self._bytes -= size
            self._messages -= 1
        return item
