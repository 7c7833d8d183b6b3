"""The scripted load test (``fingertrack bench load``): a real service process, real gloves and
subscribers at a light load; its accounting and integrity checks."""
import pytest

from service.bench.load import _integrity, run_level
from service.cli import main
from service.pipeline.hand import PipelineSettings


def test_two_hands_at_once_every_frame_is_delivered_or_counted_and_stays_in_its_session():
    lv = run_level(hands=2, subscribers=2, seconds=3.0)
    assert lv["sessions_seen"] == 2
    # 3 s of a hand is a few hundred frames; each one reaches both subscribers of its session, or the
    # service counted it as dropped for a subscriber that fell behind (its queue holds 64 frames: on a
    # busy machine a subscriber may fall that far behind; dropping is then the promised behaviour)
    assert lv["frames_produced"] > 2 * 3.0 * 50
    assert lv["frames_delivered"] == lv["frames_expected"] - lv["frames_dropped"]
    assert lv["frames_dropped"] < lv["frames_expected"] / 2
    assert lv["integrity_violations"] == 0 and lv["source_errors"] == 0
    # how far behind schedule the frames arrive is a speed figure: `fingertrack bench load` reports it
    assert lv["schedule_delay_ms"] is not None and lv["schedule_delay_ms"]["p50"] > 0.0
    assert lv["service_cpu_share"] is None or 0.0 < lv["service_cpu_share"] < 2.0


def test_the_load_spread_over_two_generator_processes_is_accounted_for_as_from_one():
    """Two hands, one per load-generator process: every frame is delivered or counted as dropped, in
    order and in its own session, and each frame's wait is split into the pipeline's alignment wait
    (at least the reorder window: the tick's data must be that much older than the newest sample) and
    the delay beyond it."""
    lv = run_level(hands=2, subscribers=2, seconds=3.0, generators=2)
    assert lv["generator_processes"] == 2 and lv["sessions_seen"] == 2
    assert lv["frames_produced"] > 2 * 3.0 * 50
    assert lv["frames_unaccounted"] == 0
    assert lv["frames_delivered"] == lv["frames_expected"] - lv["frames_dropped"]
    assert lv["integrity_violations"] == 0 and lv["source_errors"] == 0
    assert lv["alignment_wait_ms"]["p50"] >= PipelineSettings().reorder_window_s * 1e3 - 1e-6
    assert lv["behind_schedule_beyond_alignment_ms"] is not None
    assert 0.0 < lv["generator_cpu_share_max"] and lv["generator_cpu_share"] >= lv["generator_cpu_share_max"]


def test_the_integrity_check_sees_reordering_and_cross_talk():
    ok = [(0.0, 0.001, 1, "right", 0.0), (0.0, 0.001, 2, "right", 0.01)]
    assert _integrity({("a", 0): ok}, {"a": "right"}) == 0
    swapped = [ok[1], ok[0]]                                        # seq goes backwards
    foreign = ok + [(0.0, 0.001, 3, "left", 0.02)]                  # a frame of the other hand's session
    assert _integrity({("a", 0): swapped, ("a", 1): foreign}, {"a": "right"}) == 2


def test_bad_load_arguments_are_refused(tmp_path):
    with pytest.raises(SystemExit):
        main(["bench", "load", "--hands", "1,x", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        main(["bench", "load", "--hands", "0", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        main(["bench", "load", "--subscribers", "0", "--out", str(tmp_path)])


def _frame(seq, hand, t):
    """A frame as the service sends it, down to its nested fingers and joints (skipped unread)."""
    return {"type": "frame", "t": t, "seq": seq, "hand": hand,
            "fingers": {"index": {"mcp": 0.1, "pip": 0.2, "dip": 0.2, "mode": "optical"}},
            "joints": {"palm": {"position": [0.0, 1.0, 0.0], "orientation": [0.0, 0.0, 0.0, 1.0]}},
            "status": {"imu": {"index.1": "ok"}, "latency_ms": 1.0}}


def test_the_load_subscriber_passes_every_frame_on_and_counts_what_does_not_decode():
    """A real WebSocket server sends a load-generator subscriber a repeated seq, a frame of the other
    hand, a frame without its seq, a frame in two fragments, a MessagePack frame, a ping, text that is
    not JSON and a gesture: every whole frame is passed on with its fields, the integrity check finds
    the repeated seq and the foreign hand, and the two undecodable messages are counted, not lost."""
    import asyncio
    import json

    import msgspec
    from websockets.asyncio.server import serve

    from service.bench.loadclients import LeanSubscription

    async def handler(ws):
        await ws.send(json.dumps({"type": "hello", "protocol": 1}))
        for seq, hand in [(1, "right"), (2, "right"), (2, "right"), (3, "left")]:
            await ws.send(json.dumps(_frame(seq, hand, seq / 90)))
        await ws.send(json.dumps({k: v for k, v in _frame(4, "right", 0.0).items() if k != "seq"}))
        text = json.dumps(_frame(5, "right", 5 / 90))
        await ws.send([text[:40], text[40:]])                          # two fragments
        await ws.send(msgspec.msgpack.encode(_frame(6, "right", 6 / 90)))
        await ws.ping()
        await ws.send("{not json")
        await ws.send(json.dumps({"type": "gesture", "t": 0.1, "gesture": "point", "event": "start"}))
        await ws.wait_closed()

    async def main():
        async with serve(handler, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            rows = []
            sub = LeanSubscription(f"http://127.0.0.1:{port}", "a", "token",
                                   lambda m, arrival: rows.append((arrival, 0.0, m.seq, m.hand, m.t)))
            sub.start()
            while sub.gestures < 1 and sub.reconnects == 0:            # the gesture comes last
                await asyncio.sleep(0.01)
            await sub.close()
            return rows, sub

    rows, sub = asyncio.run(asyncio.wait_for(main(), 60))
    assert [r[2] for r in rows] == [1, 2, 2, 3, 5, 6]
    assert [r[3] for r in rows] == ["right", "right", "right", "left", "right", "right"]
    assert rows[-1][4] == 6 / 90 and sub.server_hello is not None and sub.reconnects == 0
    assert _integrity({("a", 0): rows}, {"a": "right"}) == 2         # the repeated seq, the left hand's frame
    assert sub.malformed_count == 2 and sub.others == 0


def test_a_load_subscriber_refused_by_the_service_says_so_when_closed():
    import asyncio

    from websockets.asyncio.server import serve

    from service.bench.loadclients import LeanSubscription

    async def main():
        async with serve(lambda ws: ws.wait_closed(), "127.0.0.1", 0,
                         process_request=lambda conn, request: conn.respond(403, "bad token\n")) as server:
            port = server.sockets[0].getsockname()[1]
            sub = LeanSubscription(f"http://127.0.0.1:{port}", "a", "token", lambda m, arrival: None)
            sub.start()
            while sub.failure is None:
                await asyncio.sleep(0.01)
            with pytest.raises(ConnectionRefusedError, match="HTTP 403"):
                await sub.close()

    asyncio.run(asyncio.wait_for(main(), 60))
