"""What a viewer token can do to the session table, tried against a real server (uvicorn on a free
localhost port, real WebSocket clients): it cannot create a session, fill the table, evict a session,
keep one alive nor close one. Subscribing to a name no source has created waits for it (the server's
hello says ``"waiting": true``) without a table entry; a session whose source left is removed after
``idle_timeout_s`` even while viewers watch it, and they go on waiting for its next source."""
import asyncio
import json
import time

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from clients.client import rest
from clients.glove import source_messages
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.session import SimConfig

SOURCE, SOURCE2, VIEWER, ADMIN = "src-token-1", "src-token-2", "view-token-1", "admin-token-1"
HELLO = {"type": "hello", "protocol": 1, "hand": "right"}
BOUND_S = 120
"""Bounds a failure only (an event that never comes); no test waits for it to pass."""


def _settings(hand_workers=0, **extra) -> ServiceSettings:
    return ServiceSettings.load(port=0, admin_token=ADMIN, hand_workers=hand_workers,
                                tokens={SOURCE: "source", SOURCE2: "source", VIEWER: "viewer"}, **extra)


def _table(srv) -> dict[str, dict]:
    status, body = rest(srv.url, "GET", "/v1/sessions", ADMIN)
    assert status == 200
    return {s["session"]: s for s in body}


def _messages(seed=3, t_m_s=1.0) -> list[str]:
    """A simulated glove's messages after its hello (calibration first)."""
    return [json.dumps(m) for _, m in source_messages(SimConfig(motion="grasp", noise="white", seed=seed, t_m_s=t_m_s))
            if m["type"] != "hello"]


async def _bounded(awaitable):
    """``awaitable``'s result; an error if it never comes (bounds a failure only)."""
    return await asyncio.wait_for(awaitable, BOUND_S)


async def _refused(url: str) -> int | None:
    """The HTTP status of a refused WebSocket handshake (``None``: accepted)."""
    try:
        ws = await connect(url)
    except InvalidStatus as err:
        return err.response.status_code
    await ws.close()
    return None


async def _source(srv, name: str, token: str = SOURCE):
    """A source connection that said hello and was answered (the session exists from then on)."""
    ws = await connect(f"{srv.ws_url}/v1/ingest/{name}?token={token}")
    await ws.send(json.dumps(HELLO))
    reply = json.loads(await ws.recv())
    assert reply["type"] == "hello", reply
    return ws


async def _synced(ws, messages, n=1) -> list[dict]:
    """Send ``messages`` then a ``sync`` barrier and wait for its reply (they are all handled); returns
    the replies before it."""
    for m in messages:
        await ws.send(m)
    await ws.send(json.dumps({"type": "sync", "id": n}))
    replies = []
    while True:
        reply = json.loads(await _bounded(ws.recv()))
        if reply.get("type") == "sync" and reply.get("id") == n:
            return replies
        replies.append(reply)


async def _next_frame(ws) -> dict:
    while True:
        msg = json.loads(await _bounded(ws.recv()))
        if msg["type"] == "frame":
            return msg


def test_a_viewer_token_creates_nothing_and_cannot_fill_the_table():
    with ServerThread(_settings(max_sessions=2, max_connections_per_token=8)) as srv:
        async def go():
            seen = {}
            # more subscriptions to unknown names than the table holds: each waits, none is an entry
            viewers = [await connect(f"{srv.ws_url}/v1/stream/typo{i}?token={VIEWER}") for i in range(8)]
            seen["hellos"] = [json.loads(await ws.recv()) for ws in viewers]
            seen["ninth"] = await _refused(f"{srv.ws_url}/v1/stream/typo8?token={VIEWER}")   # over its quota
            seen["waiting"] = sum(len(s) for s in srv.app.state.sessions.waiting.values())
            seen["table_waiting"], seen["ready_waiting"] = _table(srv), rest(srv.url, "GET", "/ready")[0]
            # nor through the other doors: ingest, configuration, enrolment, reading a configuration
            seen["ingest"] = await _refused(f"{srv.ws_url}/v1/ingest/by-viewer?token={VIEWER}")
            seen["put"] = rest(srv.url, "PUT", "/v1/sessions/by-viewer/config", VIEWER, {"record": False})[0]
            seen["enrol"] = rest(srv.url, "POST", "/v1/sessions/by-viewer/enrolment", VIEWER,
                                 {"segments": [{"label": "point", "start_s": 0, "end_s": 1}]})[0]
            seen["read"] = rest(srv.url, "GET", "/v1/sessions/by-viewer/config", VIEWER)[0]
            seen["table_doors"] = _table(srv)
            # the whole table is still the sources': two sessions, one of them a name a viewer waits for
            a = await _source(srv, "typo0")
            b = await _source(srv, "fresh", SOURCE2)
            seen["errors"] = await _synced(a, _messages())
            seen["first"] = await _next_frame(viewers[0])
            seen["table_full"], seen["ready_full"] = _table(srv), rest(srv.url, "GET", "/ready")[0]
            # with the table full, a viewer subscribing to another name waits too and evicts nothing
            await viewers[7].close()
            # the route releases the connection after the closing handshake, in a later turn of the server's loop
            deadline = time.monotonic() + 60.0                      # bounds a failure only
            while srv.app.state.sessions.connections.get(VIEWER, 0) >= 8 and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            async with connect(f"{srv.ws_url}/v1/stream/another?token={VIEWER}") as late:
                seen["late"] = json.loads(await late.recv())
                seen["table_late"] = _table(srv)
            for ws in (a, b, *viewers[:7]):
                await ws.close()
            return seen
        seen = asyncio.run(go())
    assert [h["waiting"] for h in seen["hellos"]] == [True] * 8
    assert seen["ninth"] == 429 and seen["waiting"] == 8
    assert seen["table_waiting"] == {} and seen["ready_waiting"] == 200
    assert (seen["ingest"], seen["put"], seen["enrol"], seen["read"]) == (403, 403, 403, 404)
    assert seen["table_doors"] == {}
    assert seen["errors"] == [] and seen["first"]["seq"] == 1
    assert set(seen["table_full"]) == {"typo0", "fresh"} and seen["ready_full"] == 503
    assert seen["late"]["waiting"] is True and set(seen["table_late"]) == {"typo0", "fresh"}


@pytest.mark.parametrize("hand_workers", [0, 1])
def test_a_viewer_cannot_close_a_session_nor_keep_it_alive(hand_workers):
    with ServerThread(_settings(hand_workers, idle_timeout_s=0.5)) as srv:
        async def go():
            seen = {}
            messages = _messages(t_m_s=4.0)
            chunks = [messages[i:i + 60] for i in range(0, len(messages), 60)]
            src = await _source(srv, "booth")
            await _synced(src, chunks[0], 1)
            # viewers come and go, one of them dropping its connection without a closing handshake;
            # each gets frames of data sent after it subscribed
            for i in range(3):
                ws = await connect(f"{srv.ws_url}/v1/stream/booth?token={VIEWER}")
                assert json.loads(await _bounded(ws.recv()))["waiting"] is False
                assert await _synced(src, chunks[1 + i], 2 + i) == []
                await _next_frame(ws)
                if i == 1:
                    ws.transport.abort()
                else:
                    await ws.close()
            # the source is still connected and its session goes on
            produced = _table(srv)["booth"]["frames_out"]
            seen["errors"] = await _synced(src, chunks[4], 5)
            seen["more_frames"] = _table(srv)["booth"]["frames_out"] > produced
            # the source leaves; a viewer watching does not keep the session in the table
            watcher = await connect(f"{srv.ws_url}/v1/stream/booth?token={VIEWER}")
            assert json.loads(await _bounded(watcher.recv()))["waiting"] is False
            await src.close()
            deadline = time.monotonic() + BOUND_S
            while "booth" in _table(srv):
                assert time.monotonic() < deadline, "a session a viewer watches was kept after its source left"
                await asyncio.sleep(0.05)
            seen["ready"] = rest(srv.url, "GET", "/ready")[0]
            # the viewer is still connected and waits: the session's next source (another token) reaches it
            src = await _source(srv, "booth", SOURCE2)
            seen["errors_again"] = await _synced(src, chunks[0] + chunks[1], 6)
            seen["again"] = await _next_frame(watcher)
            seen["sources_after"] = _table(srv)["booth"]["sources"]
            await watcher.close()
            await src.close()
            return seen
        seen = asyncio.run(go())
    assert seen["errors"] == [] and seen["more_frames"]
    assert seen["ready"] == 200
    assert seen["errors_again"] == [] and seen["again"]["seq"] == 1 and seen["sources_after"] == 1
