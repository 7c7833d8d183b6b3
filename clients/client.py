"""Python client of the fingertrack service (asyncio, with a thin synchronous wrapper).

* ``Publisher``: a glove or tracker source. Sends ``hello`` (and the last ``calibration``) on every
  (re)connection, so a reconnect restores the source's state; server ``error`` replies are kept in
  ``errors`` (bounded).
* ``Subscription``: an async iterator of ``frame``/``gesture`` messages. On a dropped connection it
  reconnects with exponential back-off and the same session, token and format: the subscription and
  its options survive a reconnect.

Messages are dicts in protocol v1; ``service.protocol`` has the typed models (``parse_message``).
"""
from __future__ import annotations

import asyncio
import json
import random
from collections import deque
from typing import Any, AsyncIterator, Iterable

from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from service.protocol import PROTOCOL_VERSION, decode, encode, parse_message, parse_output


class Backoff:
    """Exponential back-off with jitter: ``initial_s``, doubling up to ``max_s``."""

    def __init__(self, initial_s: float = 0.1, max_s: float = 5.0, seed: int | None = None):
        self.initial_s, self.max_s = initial_s, max_s
        self.delay = initial_s
        self._rng = random.Random(seed)

    def next(self) -> float:
        d = self.delay * (0.5 + self._rng.random() / 2)
        self.delay = min(self.max_s, self.delay * 2)
        return d

    def reset(self) -> None:
        self.delay = self.initial_s


def _url(base: str, path: str, token: str | None, binary: bool) -> str:
    base = base.rstrip("/").replace("http://", "ws://").replace("https://", "wss://")
    query = []
    if token:
        query.append(f"token={token}")
    if binary:
        query.append("format=msgpack")
    return f"{base}{path}" + ("?" + "&".join(query) if query else "")


def _decode(data: str | bytes) -> dict:
    """A server message: MessagePack frames are binary, JSON ones text (``service.protocol.wire``)."""
    return decode(data, binary=isinstance(data, bytes))  # type: ignore[return-value]


class Publisher:
    def __init__(self, url: str, session: str, token: str, hand: str = "right", source: str = "python-client",
                 binary: bool = False, backoff: Backoff | None = None, max_errors: int = 1000):
        self.url = _url(url, f"/v1/ingest/{session}", token, binary)
        self.binary = binary
        self.hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "hand": hand, "source": source}
        self.calibration: dict | None = None
        self.backoff = backoff or Backoff()
        self.errors: deque = deque(maxlen=max_errors)
        self.server_hello: dict | None = None
        self._ws = None
        self._reader: asyncio.Task | None = None
        self.reconnects = 0
        self._sync_id = 0
        self._synced: dict[int, asyncio.Future] = {}

    async def connect(self) -> None:
        self._ws = await connect(self.url, max_size=None)
        await self._ws.send(encode(self.hello, self.binary))
        reply = _decode(await self._ws.recv())
        if reply.get("type") == "error":
            raise ConnectionRefusedError(f"{reply['code']}: {reply['detail']}")
        self.server_hello = reply
        if self.calibration is not None:
            await self._ws.send(encode(self.calibration, self.binary))
        self._reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        try:
            async for data in self._ws:
                msg = _decode(data)
                if msg.get("type") == "error":
                    self.errors.append(msg)
                elif msg.get("type") == "sync":
                    waiter = self._synced.pop(msg.get("id"), None)
                    if waiter is not None and not waiter.done():
                        waiter.set_result(None)
        except ConnectionClosed:
            pass
        finally:
            for waiter in self._synced.values():
                if not waiter.done():
                    waiter.set_exception(ConnectionError("the connection closed before the service answered sync"))
            self._synced.clear()

    async def send(self, message) -> None:
        """Send one source message (a dict or a ``service.protocol`` model), reconnecting (with
        back-off) if the connection dropped."""
        if hasattr(message, "model_dump"):
            message = message.model_dump(exclude_none=True)
        if message.get("type") == "calibration":
            self.calibration = message
        if message.get("type") == "hello":
            self.hello = message
            return
        while True:
            try:
                if self._ws is None:
                    await self.connect()
                    self.backoff.reset()
                    if message is self.calibration:
                        return                      # connect() has just sent it
                await self._ws.send(encode(message, self.binary))
                return
            except (ConnectionClosed, OSError):
                self._ws = None
                self.reconnects += 1
                await asyncio.sleep(self.backoff.next())

    async def send_reference_pose(self, t0: float, t1: float, pose: str | dict = "flat") -> None:
        """Tell the service that the hand held a known configuration from ``t0`` to ``t1`` (source
        clock, s): ``"flat"`` or joint angles in radians per finger (protocol ``reference_pose``).
        Send it when the hold is over; raises ``ProtocolError`` for a malformed pose."""
        message = {"type": "reference_pose", "t0": float(t0), "t1": float(t1), "pose": pose}
        parse_message(message)
        await self.send(message)

    async def sync(self, timeout_s: float = 120.0) -> None:
        """Return once the service has handled every message sent so far (protocol ``sync``), so its
        frames and error replies for them exist. Raises ``ConnectionError`` if the connection closes
        first and ``TimeoutError`` after ``timeout_s``."""
        if self._ws is None:
            return
        self._sync_id += 1
        waiter = asyncio.get_running_loop().create_future()
        self._synced[self._sync_id] = waiter
        await self._ws.send(encode({"type": "sync", "id": self._sync_id}, self.binary))
        await asyncio.wait_for(waiter, timeout_s)

    async def close(self, sync_timeout_s: float = 120.0) -> None:
        """Close after the service has handled everything sent (``sync``; skipped if the connection is
        already gone), so that its replies to the last messages are in ``errors``."""
        if self._ws is not None:
            try:
                await self.sync(sync_timeout_s)
            except (ConnectionClosed, ConnectionError, asyncio.TimeoutError):
                pass
            await self._ws.close()
        if self._reader is not None:
            await asyncio.gather(self._reader, return_exceptions=True)


class Subscription:
    def __init__(self, url: str, session: str, token: str, binary: bool = False, backoff: Backoff | None = None,
                 reconnect: bool = True, typed: bool = False):
        """``typed``: yield ``service.protocol`` models (``Frame``, ``Gesture``) instead of dicts."""
        self.url = _url(url, f"/v1/stream/{session}", token, binary)
        self.typed = typed
        self.backoff = backoff or Backoff()
        self.reconnect = reconnect
        self.reconnects = 0
        self.server_hello: dict | None = None
        self._ws = None
        self._closed = False

    async def __aiter__(self) -> AsyncIterator[dict]:
        while not self._closed:
            try:
                async with connect(self.url, max_size=None) as ws:
                    self._ws = ws
                    self.backoff.reset()
                    async for data in ws:
                        msg = _decode(data)
                        if msg.get("type") == "hello":
                            self.server_hello = msg
                            continue
                        yield parse_output(msg) if self.typed else msg
                    if ws.close_code in (1008, 1003):     # refused: token, role or protocol
                        raise PermissionError(f"stream closed by the server: {ws.close_code} {ws.close_reason}")
            except (ConnectionClosed, OSError) as err:
                if isinstance(err, InvalidStatus) or not self.reconnect or self._closed:
                    raise
            if not self.reconnect or self._closed:
                return
            self.reconnects += 1
            await asyncio.sleep(self.backoff.next())

    async def close(self) -> None:
        self._closed = True
        if self._ws is not None:
            await self._ws.close()


# -- thin synchronous wrapper ---------------------------------------------------------------------

def publish(url: str, session: str, token: str, messages: Iterable[dict], hand: str = "right") -> list[dict]:
    """Send messages as fast as the connection takes them; returns the server's error replies."""
    async def run():
        pub = Publisher(url, session, token, hand=hand)
        for m in messages:
            await pub.send(m)
        await asyncio.sleep(0.2)
        await pub.close()
        return list(pub.errors)
    return asyncio.run(run())


def collect(url: str, session: str, token: str, count: int, timeout_s: float = 10.0) -> list[dict]:
    """Receive ``count`` messages (or as many as arrive within ``timeout_s``)."""
    async def run():
        out: list[dict] = []
        sub = Subscription(url, session, token)

        async def take():
            async for m in sub:
                out.append(m)
                if len(out) >= count:
                    return
        try:
            await asyncio.wait_for(take(), timeout_s)
        except asyncio.TimeoutError:
            pass
        await sub.close()
        return out
    return asyncio.run(run())


def rest(url: str, method: str, path: str, token: str | None = None, body: Any = None,
         timeout_s: float = 10.0) -> tuple[int, Any]:
    """A REST call with the standard library: ``(status, decoded JSON or text)``."""
    import urllib.error
    import urllib.request
    req = urllib.request.Request(url.rstrip("/") + path, method=method,
                                 data=None if body is None else json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json",
                                          **({"Authorization": f"Bearer {token}"} if token else {})})
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:
            text = resp.read().decode()
            status = resp.status
    except urllib.error.HTTPError as err:
        text, status = err.read().decode(), err.code
    try:
        return status, json.loads(text)
    except ValueError:
        return status, text


def wait_healthy(url: str, timeout_s: float = 15.0, alive=lambda: True) -> None:
    """Poll ``GET /health`` until the service answers 200; ``alive()`` false (e.g. its process
    exited) or the timeout raises ``RuntimeError``."""
    import time
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if rest(url, "GET", "/health")[0] == 200:
                return
        except OSError:
            pass
        if time.monotonic() > deadline or not alive():
            raise RuntimeError(f"the service at {url} did not become healthy")
        time.sleep(0.1)
