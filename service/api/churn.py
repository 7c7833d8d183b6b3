"""Memory of ended WebSocket connections given back soon after they end, not when the garbage
collector next happens to run.

A connection that ends leaves reference cycles (the server's protocol object, its transport, socket,
stream reader and permessage-deflate state refer to each other), so its memory is freed only by a
cycle collection. A serving process makes those rare (``server.serving_gc``: young collections
every 50,000 allocations, to keep their pauses out of the frame latency), and a connection is a few
hundred objects: a storm of 2,000 connects left every one of them waiting, about 30 KB each with
their zlib state (service RSS +31 %, measured with ``fingertrack bench robustness``). Freed memory
then stays in the C allocator's heap unless it is handed back to the system (glibc keeps it).

``ChurnCollector``: ``note()`` at the end of every WebSocket connection (``CollectAfterConnections``,
an ASGI middleware, does it for every route and every refused handshake); ``delay_s`` after the
first end not yet collected, one full collection runs on the event loop and, if it freed anything,
``malloc_trim`` gives the freed heap back (glibc only; elsewhere the collection alone); passes go on
every ``delay_s`` while connections end, and one more after the last pass that saw an end (it takes
the connections whose transport closed after the route ended: a closing handshake may outlast it).
So at most one collection per ``delay_s``, and only while connections end: a service that streams to
the same connections collects nothing extra. Each collection is timed (``collections``, ``seconds``,
the metric ``fingertrack_connection_gc_seconds``).
"""
from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import gc
import time


def _malloc_trim():
    """glibc's ``malloc_trim``, or ``None`` where the C library has none (musl, macOS, Windows)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        trim = libc.malloc_trim
    except (OSError, AttributeError, TypeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


class ChurnCollector:
    """One cycle collection (and heap trim) ``delay_s`` after connections ended; see the module."""

    def __init__(self, delay_s: float = 1.0, observe=None):
        self.delay_s = delay_s
        self.observe = observe
        """Called with each collection's duration, s (e.g. a metric's ``observe``)."""
        self.collections = 0
        self.seconds = 0.0
        """Time spent in the collections and trims, s (on the event loop)."""
        self._pending: asyncio.TimerHandle | None = None
        self._ended = 0                          # connections ended since the last pass began
        self._trim = _malloc_trim()

    def note(self) -> None:
        """A connection ended (call on the event loop)."""
        self._ended += 1
        if self._pending is None:
            self._pending = asyncio.get_running_loop().call_later(self.delay_s, self._run)

    def _run(self) -> None:
        ended, self._ended, self._pending = self._ended, 0, None
        self.collect()
        if ended:                                # one more pass: ends since, and transports that closed late
            self._pending = asyncio.get_running_loop().call_later(self.delay_s, self._run)

    def collect(self) -> int:
        """Collect now; returns the number of unreachable objects found."""
        t0 = time.perf_counter()
        found = gc.collect()
        if found and self._trim is not None:
            self._trim(0)
        took = time.perf_counter() - t0
        self.collections += 1
        self.seconds += took
        if self.observe is not None:
            self.observe(took)
        return found

    def cancel(self) -> None:
        if self._pending is not None:
            self._pending.cancel()
            self._pending = None


class CollectAfterConnections:
    """ASGI middleware: ``collector.note()`` when a WebSocket connection's handling ends (HTTP requests
    leave no connection state behind and are not counted)."""

    def __init__(self, app, collector: ChurnCollector):
        self.app, self.collector = app, collector

    async def __call__(self, scope, receive, send):
        if scope["type"] != "websocket":
            return await self.app(scope, receive, send)
        try:
            return await self.app(scope, receive, send)
        finally:
            self.collector.note()
