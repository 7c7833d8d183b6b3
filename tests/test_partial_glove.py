"""A glove that instruments only index and middle: ``"sensors": []`` for the other fingers. It runs
through ``estimate``, ``replay`` and a live server; the other fingers are reported untracked."""
import asyncio
import json

import numpy as np
import pytest

from clients.client import Subscription
from clients.glove import stream_glove
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.cli import main
from service.model.hand import default_calibration
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate, write_recording
from test_service import ADMIN, SOURCE, VIEWER, _wait_for, _wait_for_last_frame

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

BARE = ("thumb", "ring", "little")


def _config():
    calib = default_calibration("right").with_overrides({f: {"sensors": []} for f in BARE})
    return SimConfig(motion="sequence", noise="both", seed=3, calibration=calib,
                     finger_motion=sequence_motion(steps=(("point", 0.6), ("grasp", 0.6))))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("partial") / "partial.jsonl"
    session = simulate(_config())
    assert sorted(session.sensor_ids) == ["index.1", "index.2", "middle.1", "middle.2"]
    write_recording(session, path)
    calibration = next(json.loads(line) for line in open(path) if '"calibration"' in line)
    assert calibration["fingers"]["thumb"]["sensors"] == []
    return path


def test_estimate_reports_the_bare_fingers_untracked(recording, tmp_path, capsys):
    out = tmp_path / "est.csv"
    assert main(["estimate", str(recording), "--estimator", "chain", "--truth", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    for f in BARE:
        assert f"{f:<7} untracked" in text
    fingers = {line.split(",")[1] for line in out.read_text().splitlines()[1:]}
    assert fingers == {"index", "middle"}
    rms = [float(v) for line in text.splitlines() if line.strip().startswith("index") for v in line.split()[2::2]]
    assert len(rms) == 3 and max(rms) < 5.0          # the instrumented fingers are still tracked


def _check_frames(frames):
    assert frames
    last = frames[-1]
    for f in BARE:
        assert last["fingers"][f]["mode"] == "none"
        assert not any(j["tracked"] for n, j in last["joints"].items() if n.startswith(f) and "metacarpal" not in n)
    assert all(j["tracked"] for n, j in last["joints"].items() if n.startswith("index"))
    assert last["fingers"]["index"]["mode"] != "none"


def test_replay_runs_and_marks_them(recording, tmp_path, capsys):
    out = tmp_path / "replay.jsonl"
    assert main(["replay", str(recording), "--out", str(out)]) == 0
    frames = [json.loads(line) for line in open(out) if '"frame"' in line]
    _check_frames([m for m in frames if m["type"] == "frame"])


def test_live_server_streams_it(tmp_path):
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        async def go():
            received = []
            sub = Subscription(srv.ws_url, "partial", VIEWER)

            async def collect():
                async for m in sub:
                    received.append((None, m))

            task = asyncio.create_task(collect())
            await _wait_for(lambda: sub.server_hello is not None, "the subscription's hello")
            pub = await stream_glove(srv.url, "partial", SOURCE, _config(), speed=4.0)
            await pub.close()
            await _wait_for_last_frame(srv, "partial", received)
            await sub.close()
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            return [m for _, m in received], pub

        received, pub = asyncio.run(go())
    assert not pub.errors, list(pub.errors)
    frames = [m for m in received if m["type"] == "frame"]
    _check_frames(frames)
    t = np.array([f["t"] for f in frames])
    assert t[-1] - t[0] > 2.0
