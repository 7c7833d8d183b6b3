"""The LSL bridge with a real LSL inlet on the loopback, fed by a real service and a streaming source."""
import asyncio
import json
import re
import threading

import numpy as np
import pytest

try:
    import pylsl
except (ImportError, RuntimeError, OSError) as err:       # pylsl missing, or liblsl cannot load
    pytest.skip(f"pylsl/liblsl cannot load: {err}", allow_module_level=True)

from clients.client import Publisher, Subscription, rest
from clients.glove import source_messages
from clients.lsl import CHANNELS, ClockMap, LslBridge
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.cli import main
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE, VIEWER, ADMIN = "src-lsl-1", "view-lsl-1", "admin-lsl-1"


@pytest.fixture(scope="module")
def server():
    # every frame is compared: subscribers that fall behind an unpaced source on a busy machine must
    # not lose their oldest frames (a few hundred here, far below the queue)
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    subscriber_queue_frames=10000)
    with ServerThread(settings) as srv:
        yield srv


def test_the_clock_map_is_the_running_minimum_delay_per_source_run():
    clock = ClockMap("estimate")
    t = np.arange(6) * 0.01
    delays = [0.050, 0.030, 0.045, 0.031, 0.020, 0.090]
    stamps = [clock.frame_time(ti, 100.0 + ti + d) for ti, d in zip(t, delays)]
    expected_offsets = np.minimum.accumulate(np.asarray(delays)) + 100.0
    assert np.allclose(np.asarray(stamps) - t, expected_offsets, atol=1e-12)
    assert clock.event_time(t[-1]) == pytest.approx(t[-1] + 100.020)
    # a new run of the source clock (time going back) starts a new estimate
    assert clock.frame_time(0.0, 500.07) == pytest.approx(500.07)
    assert clock.runs == 2
    # as does a clock step the service reports
    clock.frame_time(1.0, 501.0, clock_steps=0)
    assert clock.frame_time(9.0, 600.5, clock_steps=1) == pytest.approx(600.5) and clock.runs == 3
    # a source on the LSL clock is used as is
    assert ClockMap("lsl").frame_time(12.5, 99.0) == 12.5
    with pytest.raises(ValueError, match="source clock"):
        ClockMap("ntp")


def _shifted(message, dt: float):
    """The message with every time field moved by ``dt`` seconds."""
    if isinstance(message, dict):
        return {k: (v + dt if k in ("t", "t0", "t1") else _shifted(v, dt)) for k, v in message.items()}
    if isinstance(message, list):
        return [_shifted(v, dt) for v in message]
    return message


def _latest_time(message: dict) -> float:
    """The latest sample time in a source message (a batch's samples carry theirs), or 0."""
    return max([message.get("t", 0.0)] + [x.get("t", 0.0) for x in message.get("samples", [])])


def _resolve(source_id: str) -> pylsl.StreamInlet:
    found = pylsl.resolve_byprop("source_id", source_id, 1, 30.0)
    assert found, f"no LSL stream with source_id {source_id}"
    inlet = pylsl.StreamInlet(found[0], max_buflen=360, recover=False)
    inlet.open_stream(30.0)
    return inlet


def _bridged_session(server, session: str, source_clock: str, paced: bool = False) -> dict:
    """A source stamping with the LSL clock streams point, grasp, relax into ``session`` (``paced``:
    each message sent no earlier than its time, as a live source sends); the bridge republishes it;
    what a subscriber and two LSL inlets (hand, markers) received, with the LSL time at which the
    inlet had each sample (an upper bound of when the bridge got its frame)."""
    bridge = LslBridge(server.url, VIEWER, [(session, "right")], source_clock=source_clock)
    hand_inlet = _resolve(f"fingertrack/{server.url.split('//')[1]}/{session}/right")
    marker_inlet = _resolve(f"fingertrack/{server.url.split('//')[1]}/{session}/gestures")

    loop = asyncio.new_event_loop()
    failures = []

    def follow():                                    # the bridge on its own event loop, as in its own process
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(bridge.run())
        except Exception as err:                     # reported below; a refusal would end the bridge early
            failures.append(err)
    runner = threading.Thread(target=follow)
    runner.start()
    try:
        config = SimConfig(motion="sequence", noise="white", seed=5,
                           finger_motion=sequence_motion(steps=(("point", 0.6), ("grasp", 0.6), ("rest", 0.6))))
        start = pylsl.local_clock()                  # the source stamps with the LSL clock
        messages = [_shifted(m, start) for _, m in source_messages(config)]

        async def stream():
            frames, events = [], []
            sub = Subscription(server.ws_url, session, VIEWER)

            async def collect():
                async for m in sub:
                    (frames if m["type"] == "frame" else events).append(m)
            task = asyncio.create_task(collect())
            while True:                              # the bridge and this subscriber are both listening
                # (waiting for the session's source, which creates it: the subscriber gauge counts them)
                status, text = await asyncio.to_thread(rest, server.url, "GET", "/metrics", VIEWER)
                if float(re.search(r"^fingertrack_subscribers (\S+)$", text, re.M).group(1)) >= 2:
                    break
                await asyncio.sleep(0.05)
            pub = Publisher(server.url, session, SOURCE)
            for m in messages:
                ahead = _latest_time(m) - pylsl.local_clock() if paced else 0.0
                if ahead > 0:
                    await asyncio.sleep(ahead)
                await pub.send(m)
            await pub.close()                        # syncs: every frame of the session exists now
            _, sessions = await asyncio.to_thread(rest, server.url, "GET", "/v1/sessions", VIEWER)
            total = next(s["frames_out"] for s in sessions if s["session"] == session)
            while len(frames) < total:
                await asyncio.sleep(0.05)
            await sub.close()
            task.cancel()
            return frames, events
        frames, events = asyncio.run(asyncio.wait_for(stream(), 300))

        samples, stamps, held_at = [], [], []
        while len(samples) < len(frames):
            sample, stamp = hand_inlet.pull_sample(timeout=60.0)
            assert sample is not None, f"the inlet got {len(samples)} of {len(frames)} frames"
            samples.append(sample)
            stamps.append(stamp)
            held_at.append(pylsl.local_clock())
        markers = []
        while len(markers) < len(events):
            sample, stamp = marker_inlet.pull_sample(timeout=60.0)
            assert sample is not None, f"the marker inlet got {len(markers)} of {len(events)} events"
            markers.append((json.loads(sample[0]), stamp))
        info, marker_type = hand_inlet.info(30.0), marker_inlet.info(30.0).type()
    finally:
        asyncio.run_coroutine_threadsafe(bridge.close(), loop).result(30)
        runner.join(30)
        loop.close()
    assert failures == []
    return {"frames": frames, "events": events, "samples": samples, "stamps": np.asarray(stamps),
            "held_at": np.asarray(held_at), "markers": markers, "info": info, "marker_type": marker_type}


def test_every_frame_reaches_an_lsl_inlet_in_order_at_its_source_time(server):
    got = _bridged_session(server, "lsl-a", "lsl")
    frames, events, samples, stamps, markers = (got[k] for k in ("frames", "events", "samples", "stamps", "markers"))
    assert len(frames) > 150 and [f["seq"] for f in frames] == list(range(1, len(frames) + 1))
    # every frame, in order: the angles the service sent (as float32) ...
    expected = np.array([[f["fingers"][finger][joint] for finger, joint in CHANNELS] for f in frames])
    assert np.allclose(np.asarray(samples), expected.astype(np.float32), rtol=0, atol=1e-6)
    # ... at the frame's mapped time (the source's own time on the LSL clock), within 1 ms
    t = np.array([f["t"] for f in frames])
    assert np.max(np.abs(np.asarray(stamps) - t)) <= 1e-3
    assert np.all(np.diff(stamps) > 0)
    # the gesture events as markers, at their frames' times
    assert [e["gesture"] for e, _ in markers] == [e["gesture"] for e in events]
    assert [(e["event"], e["confidence"]) for e, _ in markers] == [(e["event"], e["confidence"]) for e in events]
    assert max(abs(stamp - e["t"]) for (_, stamp), e in zip(markers, events)) <= 1e-3
    assert {e["gesture"] for e in events} >= {"point", "grasp"}
    # what a recorder reads from the stream description
    info = got["info"]
    assert (info.type(), info.channel_count(), info.nominal_srate()) == ("MoCap", 14, 90.0)
    channel = info.desc().child("channels").child("channel")
    labels, units = [], []
    while not channel.empty():
        labels.append(channel.child_value("label"))
        units.append(channel.child_value("unit"))
        channel = channel.next_sibling()
    assert labels == [f"{f}_{j}" for f, j in CHANNELS] and set(units) == {"radians"}
    assert info.desc().child_value("hand") == "right"
    assert got["marker_type"] == "Markers"


def test_estimated_lsl_times_follow_the_least_delayed_frame(server):
    """The default mapping, for a source whose clock the bridge does not know: here the source stamps
    with the LSL clock, so each frame's true LSL time is its t. An estimated time is never before it
    (delays are not negative), never after the frame was in the inlet, and lags it by the smallest
    delay seen so far, which only shrinks over the run."""
    got = _bridged_session(server, "lsl-e", "estimate", paced=True)
    frames, stamps, held_at = got["frames"], got["stamps"], got["held_at"]
    assert len(frames) > 150 and len(got["samples"]) == len(frames)
    t = np.array([f["t"] for f in frames])
    lag = stamps - t
    assert np.all(lag >= -1e-6) and np.all(stamps <= held_at + 1e-6)
    assert np.all(np.diff(lag) <= 1e-6) and lag[-1] < lag[0] + 1e-6
    # where the lag steps is timing's to decide (a backlog draining after a stall of a busy machine makes
    # every frame of it a less-delayed one): the rule itself is tested with given arrivals above
    assert "minimum-delay" in got["info"].desc().child("clock").child_value("mapping")
    # an event gets its frame's time: the frame's t moved by the frame's lag
    lag_at = dict(zip(t.tolist(), lag.tolist()))
    events = got["events"]
    assert events and [stamp for _, stamp in got["markers"]] == pytest.approx([e["t"] + lag_at[e["t"]] for e in events], abs=1e-6)


def test_the_lsl_command_refuses_bad_arguments_and_tokens_clearly(server, capsys):
    with pytest.raises(SystemExit):
        main(["lsl", "--url", server.url, "--token", VIEWER, "--session", "a:middle"])
    assert "expected NAME or NAME:HAND with HAND right or left, got 'a:middle'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["lsl", "--url", server.url, "--token", VIEWER, "--session", "a", "--rate", "0"])
    assert "expected a positive finite number, got '0'" in capsys.readouterr().err
    assert main(["lsl", "--url", server.url, "--token", "wrong-token", "--session", "lsl-refused"]) == 2
    err = capsys.readouterr().err
    assert "refused the subscription: HTTP 403" in err and "Traceback" not in err and "wrong-token" not in err
    assert main(["lsl", "--url", server.url, "--token", SOURCE, "--session", "lsl-refused"]) == 2
    assert "refused the subscription: HTTP 403; --token needs the viewer role" in capsys.readouterr().err


def test_a_restarted_bridge_is_picked_up_again_by_the_same_inlet():
    """The streams' source_id is the same whenever the bridge starts, so an inlet that recovers lost
    streams (as LabRecorder's do) goes on receiving from the new bridge without being told."""
    import gc

    url = "http://127.0.0.1:9"                       # nothing is subscribed: frames are handed in
    frame = {"type": "frame", "t": 5.0, "seq": 1, "hand": "left",
             "fingers": {f: {j: 0.1 * k for j in ("mcp", "pip", "dip", "ip")} for k, f in
                         enumerate(("thumb", "index", "middle", "ring", "little"))}}
    first = LslBridge(url, VIEWER, [("lsl-restart", "left")], source_clock="lsl")
    source_id = first.source_id("lsl-restart", "left")
    found = pylsl.resolve_byprop("source_id", source_id, 1, 30.0)
    assert found
    inlet = pylsl.StreamInlet(found[0], max_buflen=60, recover=True)
    inlet.open_stream(30.0)
    first.handle("lsl-restart", frame)
    sample, stamp = inlet.pull_sample(timeout=30.0)
    assert stamp == pytest.approx(5.0) and sample[0] == pytest.approx(0.0)
    del first                                        # the bridge stops: its outlets go away
    gc.collect()
    second = LslBridge(url, VIEWER, [("lsl-restart", "left")], source_clock="lsl")
    assert second.source_id("lsl-restart", "left") == source_id
    got = None
    for k in range(60):                              # the inlet finds the new outlet by itself;
        second.handle("lsl-restart", dict(frame, t=6.0 + k, seq=2 + k))   # frames sent before that are lost
        got = inlet.pull_sample(timeout=1.0)
        if got[0] is not None:
            break
    sample, stamp = got
    assert sample is not None, "the inlet did not pick the restarted bridge's stream up"
    assert stamp >= 6.0 and sample[2] == pytest.approx(0.1, abs=1e-6)
    del second
    gc.collect()
