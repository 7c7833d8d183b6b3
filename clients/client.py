"""Python client of the fingertrack service (asyncio, with a thin synchronous wrapper).

* ``Publisher``: a glove or tracker source. Sends ``hello`` (and the last ``calibration``) on every
  (re)connection, so a reconnect restores the source's state; server ``error`` replies are kept in
  ``errors`` (bounded).
* ``Subscription``: an async iterator of ``frame``/``gesture`` messages. On a dropped connection it
  reconnects with exponential back-off and the same session, token and format: the subscription and
  its options survive a reconnect.

Both report every retry through ``on_event`` (a callable taking one line of text; by default the
``fingertrack.client`` logger), e.g. "no service at ws://host:8765/v1/ingest/s, retrying in 3.2 s"; the ``Publisher`` also reports each
reconnect, what it sent again and how many messages of the dropped connection were never confirmed
(``unconfirmed_at_drops``). A
refusal that retrying cannot fix (a bad token or role, a token not valid for the session, another
source on the session, an unsupported protocol) raises ``Refused`` with the service's reason. URLs
in these lines and errors never show the token.

Messages are dicts in protocol v1; ``service.protocol`` has the typed models (``parse_message``).
"""
from __future__ import annotations

import asyncio
import json
import logging
import random
from collections import deque
from typing import Any, AsyncIterator, Callable, Iterable
from urllib.parse import quote, urlsplit

from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from service.protocol import PROTOCOL_VERSION, decode, encode, parse_message, parse_output
from service.protocol.messages import dump_message


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


URL_SCHEMES = ("http", "https", "ws", "wss")


def service_url(url: str) -> str:
    """The service's address, checked: ``http``, ``https``, ``ws`` or ``wss``, a host, a port in
    1-65535 if one is given, an optional path prefix (a reverse proxy's), and no query or fragment
    (the clients add the paths and the token). Raises ``ValueError`` naming what is wrong; the
    address is shown without its user, password and query, which may hold secrets."""
    if not isinstance(url, str):
        raise ValueError(f"the service URL must be text such as http://127.0.0.1:8765, got {type(url).__name__}")
    try:
        parts = urlsplit(url.strip())
        port = parts.port
    except ValueError as err:                    # e.g. "Port out of range 0-65535", an unclosed [
        raise ValueError(f"service URL {_shown(url)!r}: {err}") from None
    shown = _shown(url)
    if parts.scheme not in URL_SCHEMES or not parts.netloc:
        raise ValueError(f"service URL {shown!r} must start with http://, https://, ws:// or wss:// and name a host, "
                         "e.g. http://127.0.0.1:8765")
    if not parts.hostname or any(c.isspace() for c in parts.netloc):
        raise ValueError(f"service URL {shown!r} names no valid host, e.g. http://127.0.0.1:8765")
    if port == 0:
        raise ValueError(f"service URL {shown!r}: port 0 is not a port a service listens on (1-65535)")
    if parts.query or parts.fragment:
        raise ValueError(f"service URL {shown!r} must have no query or fragment: the token is given on its own, "
                         "the client adds it")
    return url.strip()


def _url(base: str, path: str, token: str | None, binary: bool) -> str:
    """The WebSocket URL of ``path`` under the (checked) service URL ``base``, the token and the
    session name percent-encoded."""
    parts = urlsplit(service_url(base))
    scheme = {"http": "ws", "https": "wss"}.get(parts.scheme, parts.scheme)
    query = []
    if token:
        query.append(f"token={quote(token, safe='')}")
    if binary:
        query.append("format=msgpack")
    return f"{scheme}://{parts.netloc}{parts.path.rstrip('/')}{path}" + ("?" + "&".join(query) if query else "")


def _path(kind: str, session: str) -> str:
    return f"/v1/{kind}/{quote(session, safe='')}"


_log = logging.getLogger("fingertrack.client")
CLOSE_SYNC_TIMEOUT_S = 30.0
"""How long ``Publisher.close`` waits for the service to answer its last ``sync``, s."""
FATAL_CLOSE_CODES = (1003, 1008)
"""Close codes that mean refused for good (1013, "try again later", is retried)."""


class Refused(PermissionError):
    """The service refused this client for a reason retrying will not fix; ``str()`` is the reason."""


def _shown(url: str) -> str:
    """A URL fit to print: without its query (which holds the token) and its user and password."""
    url = str(url).split("?", 1)[0].split("#", 1)[0]
    scheme, sep, rest = url.partition("://")
    if sep and "@" in rest.split("/", 1)[0]:
        rest = rest.split("@", 1)[1]
    return f"{scheme}{sep}{rest}"


def _handshake_refusal(url: str, err: InvalidStatus) -> Refused | None:
    """``Refused`` with the service's detail for a handshake refused for good (not 429 or 5xx)."""
    status = err.response.status_code
    if status == 429 or status >= 500:
        return None
    try:
        detail = json.loads(err.response.body or b"{}").get("detail", "")
    except (ValueError, AttributeError):
        detail = ""
    return Refused(f"{_shown(url)}: HTTP {status}" + (f": {detail}" if detail else ""))


def _closed_for_good(url: str, ws) -> Refused | None:
    if ws is not None and ws.close_code in FATAL_CLOSE_CODES:
        return Refused(f"{_shown(url)}: closed by the service ({ws.close_code}: {ws.close_reason})")
    return None


def _retry_line(url: str, ws, err: BaseException | None, delay: float) -> str:
    if ws is None:
        why = f"no service at {_shown(url)}" + (f" ({type(err).__name__})" if err is not None else "")
    else:
        why = f"connection to {_shown(url)} closed ({ws.close_code}: {ws.close_reason or 'no reason'})"
    return f"{why}, retrying in {delay:.1f} s"


def _decode(data: str | bytes) -> dict:
    """A server message: MessagePack frames are binary, JSON ones text (``service.protocol.wire``)."""
    return decode(data, binary=isinstance(data, bytes))  # type: ignore[return-value]


class Publisher:
    def __init__(self, url: str, session: str, token: str, hand: str = "right", source: str = "python-client",
                 binary: bool = False, backoff: Backoff | None = None, max_errors: int = 1000,
                 on_event: Callable[[str], None] | None = None, max_unconfirmed: int | None = 256,
                 max_unconfirmed_bytes: int = 8 << 20):
        """``max_unconfirmed`` (``max_unconfirmed_bytes``): flow control, at most that many messages
        (bytes) sent and not yet confirmed handled by the service (a ``sync`` answered; one goes out
        by itself every quarter of it); ``send`` waits beyond it, so a source faster than the service
        is slowed down instead of refused ``overloaded`` (the service's backlog holds 1024 messages
        by default). ``None``: no flow control."""
        self.url = _url(url, _path("ingest", session), token, binary)
        self.max_unconfirmed, self.max_unconfirmed_bytes = max_unconfirmed, max_unconfirmed_bytes
        self.on_event = on_event or _log.warning
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
        self._sent = self._sent_bytes = 0            # on this connection
        self._confirmed = self._confirmed_bytes = 0  # of those, handled by the service
        self._marks: dict[int, tuple[int, int]] = {}  # sync id -> (messages, bytes) sent before it
        self._progress = asyncio.Event()              # a sync was answered, or the connection ended
        self.unconfirmed_at_drops = 0
        """Messages sent on connections that dropped before the service confirmed them (a ``sync``
        answered): they may be lost; each drop is reported through ``on_event``."""
        self._dropped: int | None = None              # unconfirmed messages of the last drop, until reconnected

    async def connect(self) -> None:
        try:
            self._ws = await connect(self.url, max_size=None)
        except InvalidStatus as err:
            refused = _handshake_refusal(self.url, err)
            if refused is not None:
                raise refused from None
            raise ConnectionRefusedError(f"HTTP {err.response.status_code}") from None
        await self._ws.send(encode(self.hello, self.binary))
        reply = _decode(await self._ws.recv())
        if reply.get("type") == "error":
            raise Refused(f"{_shown(self.url)}: {reply['code']}: {reply['detail']}")
        self.server_hello = reply
        if self._dropped is not None:
            resent = "hello and calibration" if self.calibration is not None else "hello"
            self.on_event(f"reconnected to {_shown(self.url)}; resent {resent}; "
                          f"{self._dropped} messages sent on the dropped connection were not confirmed and may be lost")
            self._dropped = None
        self._sent = self._sent_bytes = self._confirmed = self._confirmed_bytes = 0
        self._marks.clear()
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
                    mark = self._marks.pop(msg.get("id"), None)
                    if mark is not None:
                        self._confirmed = max(self._confirmed, mark[0])
                        self._confirmed_bytes = max(self._confirmed_bytes, mark[1])
                        self._progress.set()
                    waiter = self._synced.pop(msg.get("id"), None)
                    if waiter is not None and not waiter.done():
                        waiter.set_result(None)
        except ConnectionClosed:
            pass
        finally:
            self._progress.set()
            for waiter in self._synced.values():
                if not waiter.done():
                    waiter.set_exception(ConnectionError("the connection closed before the service answered sync"))
            self._synced.clear()

    async def send(self, message, encoded: str | bytes | None = None) -> None:
        """Send one source message (a dict or a ``service.protocol`` model), reconnecting (with
        back-off) if the connection dropped. ``encoded``: the message as ``encode(message,
        self.binary)`` wrote it beforehand (a real-time stream's messages, before its clock starts),
        sent as it is instead of encoding it again."""
        if hasattr(message, "model_dump"):
            message = message.model_dump(exclude_none=True)
        elif not isinstance(message, dict):         # a sample or pose as ``parse_line`` reads it (``protocol.fast``)
            message = {k: v for k, v in dump_message(message).items() if v is not None}
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
                data = encode(message, self.binary) if encoded is None else encoded
                await self._wait_for_room(len(data))
                await self._ws.send(data)
                self._sent += 1
                self._sent_bytes += len(data)
                if self.max_unconfirmed is not None and self._sent % max(1, self.max_unconfirmed // 4) == 0:
                    await self._send_sync()
                return
            except Refused:
                raise
            except (ConnectionClosed, OSError) as err:
                ws, self._ws = self._ws, None
                refused = _closed_for_good(self.url, ws if isinstance(err, ConnectionClosed) else None)
                if refused is None and isinstance(err, ConnectionClosed) and err.rcvd is not None \
                        and err.rcvd.code in FATAL_CLOSE_CODES:
                    refused = Refused(f"{_shown(self.url)}: closed by the service ({err.rcvd.code}: {err.rcvd.reason})")
                if refused is not None:
                    raise refused from None
                if ws is not None and self._dropped is None:       # a connection that was up dropped
                    self._dropped = self._sent - self._confirmed
                    self.unconfirmed_at_drops += self._dropped
                delay = self.backoff.next()
                self.reconnects += 1
                self.on_event(_retry_line(self.url, ws, err, delay))
                await asyncio.sleep(delay)

    def _over(self, size: int) -> bool:
        """Flow control: would a message of ``size`` bytes exceed what may be unconfirmed?"""
        unconfirmed = self._sent - self._confirmed
        return unconfirmed >= self.max_unconfirmed or \
            (unconfirmed > 0 and self._sent_bytes + size - self._confirmed_bytes > self.max_unconfirmed_bytes)

    async def _wait_for_room(self, size: int) -> None:
        """Flow control (``max_unconfirmed``): wait until the service has confirmed enough of what was
        sent; a wait of more than 10 s is reported through ``on_event`` (once per wait)."""
        if self.max_unconfirmed is None or not self._over(size):
            return
        if max((m[0] for m in self._marks.values()), default=-1) < self._sent:
            await self._send_sync()                   # a confirmation of everything sent so far
        waited = 0.0
        while self._reader is not None and not self._reader.done() and self._over(size):
            self._progress.clear()
            try:
                await asyncio.wait_for(self._progress.wait(), 10.0)
            except asyncio.TimeoutError:
                waited += 10.0
                if waited == 10.0:
                    self.on_event(f"{_shown(self.url)}: the service has not handled the last {self._sent - self._confirmed} "
                                  "messages for 10 s; waiting before sending more")

    async def _send_sync(self, waiter: asyncio.Future | None = None) -> int:
        """Send a ``sync``; its answer confirms what was sent before it (and completes ``waiter``)."""
        self._sync_id += 1
        key = self._sync_id
        self._marks[key] = (self._sent, self._sent_bytes)
        if waiter is not None:
            self._synced[key] = waiter
        await self._ws.send(encode({"type": "sync", "id": key}, self.binary))
        return key

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
        first and ``TimeoutError`` after ``timeout_s`` (sending the barrier included: a service that
        stopped reading blocks the send)."""
        if self._ws is None:
            return
        waiter = asyncio.get_running_loop().create_future()

        async def barrier():
            await self._send_sync(waiter)
            await waiter
        try:
            await asyncio.wait_for(barrier(), timeout_s)
        finally:
            for key in [k for k, w in self._synced.items() if w is waiter]:
                del self._synced[key]

    async def close(self, sync_timeout_s: float = CLOSE_SYNC_TIMEOUT_S) -> None:
        """Close after the service has handled everything sent (``sync``; skipped if the connection is
        already gone), so that its replies to the last messages are in ``errors``. Bounded: a ``sync``
        not answered within ``sync_timeout_s`` (a service far behind, or gone without closing) is
        reported through ``on_event`` and the connection is closed anyway (its closing handshake
        waits at most 10 s more); the replies to the last messages may then be missing."""
        if self._ws is not None:
            try:
                await self.sync(sync_timeout_s)
            except asyncio.TimeoutError:
                self.on_event(f"{_shown(self.url)}: the service did not answer sync within {sync_timeout_s:g} s; "
                              "closing without its replies to the last messages")
            except (ConnectionClosed, ConnectionError):
                pass
            await self._ws.close()
        if self._reader is not None:
            await asyncio.gather(self._reader, return_exceptions=True)


class Subscription:
    def __init__(self, url: str, session: str, token: str, binary: bool = False, backoff: Backoff | None = None,
                 reconnect: bool = True, typed: bool = False, on_event: Callable[[str], None] | None = None):
        """``typed``: yield ``service.protocol`` models (``Frame``, ``Gesture``) instead of dicts."""
        self.url = _url(url, _path("stream", session), token, binary)
        self.on_event = on_event or _log.warning
        self.typed = typed
        self.backoff = backoff or Backoff()
        self.reconnect = reconnect
        self.reconnects = 0
        self.server_hello: dict | None = None
        self._ws = None
        self._closed = False

    async def __aiter__(self) -> AsyncIterator[dict]:
        while not self._closed:
            ws, failure = None, None
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
            except InvalidStatus as err:
                refused = _handshake_refusal(self.url, err)
                if refused is not None:
                    raise refused from None
                failure = err
            except (ConnectionClosed, OSError) as err:
                failure = err
            if (refused := _closed_for_good(self.url, ws)) is not None:
                raise refused
            if not self.reconnect or self._closed:
                if failure is not None and not self._closed:
                    raise failure
                return
            delay = self.backoff.next()
            self.reconnects += 1
            self.on_event(_retry_line(self.url, ws, failure, delay))
            await asyncio.sleep(delay)

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
