"""The ``reference_pose`` message end to end: protocol, estimators, pipeline, recordings, the Python
client and a live service (recording then replay gives the frames streamed live)."""
import asyncio
import json

import numpy as np
import pytest

from clients.client import Publisher, Subscription, rest
from clients.glove import stream_glove
from gestures.stream import replay
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.estimators.base import samples_from_session
from service.estimators.chain import Chain
from service.model.hand import joint_to_phalanx_angles
from service.pipeline.hand import HandSession
from service.pipeline.offline import load_recording, run_with_references
from service.protocol import ProtocolError, ReferencePose, parse_line, parse_message
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate, write_recording

SOURCE, VIEWER, ADMIN = "src-ref", "view-ref", "admin-ref"


def test_protocol_accepts_flat_and_joint_angles_and_names_what_is_wrong():
    flat = parse_message({"type": "reference_pose", "t0": 0.0, "t1": 2.0, "pose": "flat"})
    assert flat.joint_angles(["index", "thumb"]) == {"index": [0.0, 0.0, 0.0], "thumb": [0.0, 0.0]}
    given = parse_message({"type": "reference_pose", "t0": 1.0, "t1": 1.5,
                           "pose": {"index": {"mcp": 0.1, "pip": 0.2, "dip": 0.3}}})
    assert given.joint_angles(["index", "middle"]) == {"index": [0.1, 0.2, 0.3]}
    for bad, words in [({"t0": 2.0, "t1": 1.0, "pose": "flat"}, "t1"),
                       ({"t0": 0.0, "t1": 1.0, "pose": {"index": {"mcp": 0.0}}}, "pose.index"),
                       ({"t0": 0.0, "t1": 1.0, "pose": {"thumb": {"mcp": 0.0, "ip": 4.0}}}, "pose.thumb.ip"),
                       ({"t0": 0.0, "t1": 1.0, "pose": "fist"}, "pose"),
                       ({"t0": 0.0, "pose": "flat"}, "t1")]:
        with pytest.raises(ProtocolError) as err:
            parse_message({"type": "reference_pose", **bad})
        assert words in err.value.detail


def test_chain_takes_a_known_configuration_as_a_measurement():
    """A still finger whose vector observation is biased by accelerometer offsets: a reference with a
    tight std moves the angle to the reference, and the offset to what explains the reading."""
    sess = simulate(SimConfig(motion="open", noise="offset", seed=3, duration_s=3.0, fingers=("index",)))
    samples = samples_from_session(sess, "index")
    est = Chain(sess.calibration.finger("index"))
    est.run(samples)
    truth = joint_to_phalanx_angles(sess.joint_angles["index"][-1])
    before = est.state["filter"]["x"][:, 0] - truth[[1, 2]]
    p = est.state["filter"]["P"][:, 0, 0]
    std = np.radians(0.1)
    est.known_configuration(truth, std)
    after = est.state["filter"]["x"][:, 0] - truth[[1, 2]]
    r = np.array([2, 3]) * std**2
    # scalar Kalman update: the error shrinks by r / (p + r)
    np.testing.assert_allclose(after, before * r / (p + r), atol=1e-12)
    assert np.abs(before).max() > 1e-3 and np.all(np.abs(after) < np.abs(before))


def _recording_with_hold(tmp_path, seed=4):
    config = SimConfig(motion="sequence", noise="both", seed=seed, reference_hold_s=2.0,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8))))
    sess = simulate(config)
    path = tmp_path / "ref.jsonl"
    write_recording(sess, path)
    return sess, path


def test_recording_carries_the_reference_to_estimate_and_the_pipeline(tmp_path):
    sess, path = _recording_with_hold(tmp_path)
    rec = load_recording(path)
    assert [(r.t0, r.t1, r.pose) for r in rec.references] == [(0.0, 2.0, "flat")]
    geom = rec.calibration.finger("index")
    samples, _ = rec.finger_samples("index")
    after = samples.t > 2.0
    truth = sess.joint_angles["index"][after]
    with_ref = run_with_references(Chain(geom), samples, "index", rec.references, 0.05).phi
    without = Chain(geom).run(samples).phi
    # applied at t1 and nowhere else: identical before, different after
    np.testing.assert_array_equal(with_ref[~after], without[~after])
    assert np.abs(with_ref[after] - without[after]).max() > 1e-4
    # the hold is flat to within 3 deg per joint (its std is 0.05 rad): the estimate stays inside that
    assert np.degrees(np.sqrt(np.mean((with_ref[after] - truth) ** 2))) < 3.0
    # live pipeline: the same message, applied once, reported in the status
    hs = HandSession()
    frames = [f for line in open(path) for f in hs.handle(parse_line(line))]
    assert frames[-1].status["reference_poses"] == {"applied": 1, "stale": 0}


def test_a_reference_older_than_the_processed_time_is_stale(tmp_path):
    sess, path = _recording_with_hold(tmp_path, seed=5)
    hs = HandSession()
    msgs = [parse_line(line) for line in open(path)]
    ref = next(m for m in msgs if isinstance(m, ReferencePose))
    frames = [f for m in msgs if m is not ref for f in hs.handle(m)]
    hs.handle(ref)                                           # arrives after the whole recording
    assert hs.status()["reference_poses"] == {"applied": 0, "stale": 1} and frames


def test_client_rejects_a_malformed_reference_before_sending():
    pub = Publisher("http://127.0.0.1:9", "s", "t")
    with pytest.raises(ProtocolError):
        asyncio.run(pub.send_reference_pose(0.0, 1.0, {"index": {"mcp": 0.0}}))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    rec = tmp_path_factory.mktemp("recordings")
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    record_dir=str(rec))
    with ServerThread(settings) as srv:
        yield srv


def test_round_trip_client_service_recording_replay(server):
    """The glove streams a flat hold and its reference_pose through the Python client; the live frames
    equal the frames of replaying the service's recording, and the reference was applied."""
    config = SimConfig(motion="sequence", noise="both", seed=7, reference_hold_s=1.0,
                       finger_motion=sequence_motion(steps=(("point", 0.6), ("grasp", 0.6))))
    assert rest(server.url, "PUT", "/v1/sessions/ref/config", ADMIN, {"record": True})[0] == 200

    async def go():
        received = []
        sub = Subscription(server.ws_url, "ref", VIEWER)

        async def collect():
            async for m in sub:
                received.append(m)

        task = asyncio.create_task(collect())
        await asyncio.sleep(0.3)
        pub = await stream_glove(server.url, "ref", SOURCE, config, speed=4.0)
        await asyncio.sleep(0.4)
        await pub.close()
        await sub.close()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return received, pub

    received, pub = asyncio.run(go())
    assert not pub.errors
    live = [m for m in received if m["type"] in ("frame", "gesture")]
    _, sessions = rest(server.url, "GET", "/v1/sessions", ADMIN)
    path = next(s for s in sessions if s["session"] == "ref")["recording"]
    assert rest(server.url, "PUT", "/v1/sessions/ref/config", ADMIN, {"record": False})[0] == 200
    lines = open(path).read().splitlines()
    assert sum(json.loads(line)["type"] == "reference_pose" for line in lines) == 1
    replayed = list(replay(parse_line(line) for line in lines))
    for m in live:
        if m["type"] == "frame":
            del m["status"]["dropped"]["subscriber_frames"]
    first = next(m["seq"] for m in live if m["type"] == "frame")
    start = next(i for i, m in enumerate(replayed) if m["type"] == "frame" and m["seq"] == first)
    assert len(live) > 100
    assert [json.dumps(m, sort_keys=True) for m in replayed[start:start + len(live)]] == \
        [json.dumps(m, sort_keys=True) for m in live]
    assert live[-1 if live[-1]["type"] == "frame" else -2]["status"]["reference_poses"]["applied"] == 1
