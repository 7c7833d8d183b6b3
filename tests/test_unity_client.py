"""The Unity C# client (``clients/unity``), compiled with Mono's ``mcs`` into a console harness
(``Tests~/Harness.cs``) and run against the Python service's own output and a real server. Needs
``mcs``, ``mono`` and a Newtonsoft.Json assembly (Debian: ``mono-mcs mono-runtime
libnewtonsoft-json5.0-cil``; or ``FINGERTRACK_NEWTONSOFT_DLL``); skipped where they are missing.
The Unity component itself (``FingertrackHand.cs``) needs UnityEngine and is not compiled here."""
import asyncio
import glob
import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gestures.stream import replay
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate
from service.protocol import parse_message

from test_service import SOURCE, VIEWER, _stream_and_collect

UNITY = Path(__file__).resolve().parents[1] / "clients" / "unity"
MIRROR_Z = np.diag([1.0, 1.0, -1.0])


def _newtonsoft() -> str | None:
    env = os.environ.get("FINGERTRACK_NEWTONSOFT_DLL")
    if env:
        return env if Path(env).is_file() else None
    found = sorted(glob.glob("/usr/lib/cli/Newtonsoft.Json*/Newtonsoft.Json.dll"))
    return found[-1] if found else None


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    dll = _newtonsoft()
    if shutil.which("mcs") is None or shutil.which("mono") is None or dll is None:
        pytest.skip("needs Mono (mcs, mono) and Newtonsoft.Json to build the C# client")
    out = tmp_path_factory.mktemp("cs")
    shutil.copy(dll, out / "Newtonsoft.Json.dll")
    sources = sorted(str(p) for p in (UNITY / "Runtime").glob("*.cs")) + [str(UNITY / "Tests~" / "Harness.cs")]
    build = subprocess.run(["mcs", "-warnaserror+", f"-out:{out / 'Harness.exe'}", f"-r:{out / 'Newtonsoft.Json.dll'}",
                            *sources], capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    return out / "Harness.exe"


def _run(harness, *args, timeout=60):
    done = subprocess.run(["mono", str(harness), *args], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]


def test_it_reads_the_services_messages_and_converts_poses_to_unitys_frame(harness, tmp_path):
    sess = simulate(SimConfig(motion="sequence", noise="white", seed=2, hand_motion="slow-rotation",
                              finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8), ("open", 0.6)))))
    out = list(replay(parse_message(m) for m in sess.messages(include_truth=False)))
    bad = ['{"type":"frame"}', "not json", '{"type":"mystery"}',
           '{"type":"gesture","t":1,"gesture":"point","event":"start","confidence":NaN}',
           '{"type":"frame","t":1,"seq":1,"hand":"right","fingers":{},"joints":{"palm":{"position":[0,1],"orientation":[0,0,0,1]}}}']
    lines = [json.dumps(m) for m in out] + bad
    (tmp_path / "msgs.jsonl").write_text("\n".join(lines) + "\n")
    got = _run(harness, "parse", str(tmp_path / "msgs.jsonl"))
    assert len(got) == len(lines)
    frames = [(m, g) for m, g in zip(out, got) if m["type"] == "frame"]
    assert frames and all(g["type"] == "frame" and g["seq"] == m["seq"] and g["t"] == m["t"] for m, g in frames)
    for m, g in frames[::25]:
        assert g["fingers"]["index"]["mcp"] == m["fingers"]["index"]["mcp"]
        assert g["fingers"]["thumb"]["second"] == m["fingers"]["thumb"]["ip"]
        for name, pose in m["joints"].items():
            p, q = np.array(pose["position"]), np.array(pose["orientation"])
            pu, qu = np.array(g["unity_joints"][name]["position"]), np.array(g["unity_joints"][name]["orientation"])
            np.testing.assert_allclose(pu, MIRROR_Z @ p, atol=1e-12)
            # the mirrored rotation is M R M: what turns mirrored vectors as R turns the originals
            np.testing.assert_allclose(Rotation.from_quat(qu).as_matrix(),
                                       MIRROR_Z @ Rotation.from_quat(q).as_matrix() @ MIRROR_Z, atol=1e-9)
    pointing = [(m, g) for m, g in frames if m["gesture"].get("ray")]
    assert pointing, "the sequence points, so some frames carry a ray"
    m, g = pointing[len(pointing) // 2]
    np.testing.assert_allclose(g["unity_ray_direction"], MIRROR_Z @ np.array(m["gesture"]["ray"]["direction"]), atol=1e-12)
    events = [(m["gesture"], m["event"]) for m in out if m["type"] == "gesture"]
    assert [(g["gesture"], g["event"]) for g in got if g.get("type") == "gesture"] == events and events
    problems = [g.get("problem", "") for g in got[-len(bad):]]
    assert "missing number 't'" in problems[0]
    assert problems[1].startswith("not a JSON object")
    assert "unknown message type 'mystery'" in problems[2]
    assert "confidence" in problems[3]
    assert "palm: expected 3 numbers" in problems[4]


def test_a_slow_reader_loses_the_oldest_frames_never_an_event(harness, tmp_path):
    frame = {"type": "frame", "t": 0.0, "seq": 0, "hand": "right", "fingers": {}, "joints": {}, "status": {}}
    msgs = [dict(frame, t=0.01 * k, seq=k) for k in range(1, 9)]
    msgs.insert(2, {"type": "gesture", "t": 0.02, "gesture": "point", "event": "start", "confidence": 0.9})
    msgs.insert(6, {"type": "gesture", "t": 0.05, "gesture": "point", "event": "end", "confidence": 0.0})
    (tmp_path / "q.jsonl").write_text("\n".join(json.dumps(m) for m in msgs) + "\n")
    got = _run(harness, "queue", str(tmp_path / "q.jsonl"))
    # room for 5: both events stay, in place; of the 8 frames the newest 3 remain, in order
    assert [(g["type"], g.get("seq", g.get("event"))) for g in got] == \
        [("gesture", "start"), ("gesture", "end"), ("frame", 6), ("frame", 7), ("frame", 8)]


@pytest.fixture(scope="module")
def server():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token="unity-admin")
    with ServerThread(settings) as srv:
        yield srv


def test_it_subscribes_to_a_live_session_beside_a_python_client(harness, server):
    seconds = 9.0
    cs = subprocess.Popen(["mono", str(harness), "subscribe", server.url, "unity1", VIEWER, str(seconds)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert json.loads(cs.stdout.readline()) == {"type": "ready", "subscribed": True}

    started = time.monotonic()
    config = SimConfig(motion="sequence", noise="white", seed=3,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8), ("relaxed", 0.8))))
    received, _ = asyncio.run(_stream_and_collect(server, "unity1", config, speed=2.0))
    py = [m for _, m in received]
    assert time.monotonic() - started < seconds - 1.0, "the stream must end before the C# client stops listening"
    out, err = cs.communicate(timeout=30)
    got = [json.loads(line) for line in out.splitlines() if line.strip()]
    summary = got[-1]
    assert summary["type"] == "summary" and summary["hello_session"] == "unity1"
    assert summary["refused"] is None and summary["bad_messages"] == 0 and summary["reconnects"] == 0, err
    py_frames = {m["seq"]: m for m in py if m["type"] == "frame"}
    cs_frames = {g["seq"]: g for g in got if g["type"] == "frame"}
    assert len(py_frames) > 100 and cs_frames.keys() == py_frames.keys()        # every frame, both clients
    seqs = [g["seq"] for g in got if g["type"] == "frame"]
    assert seqs == sorted(seqs)
    for seq in list(py_frames)[::40]:
        tip = np.array(py_frames[seq]["joints"]["index_tip"]["position"])
        np.testing.assert_allclose(cs_frames[seq]["unity_joints"]["index_tip"]["position"], MIRROR_Z @ tip, atol=1e-12)
    py_events = [(m["gesture"], m["event"]) for m in py if m["type"] == "gesture"]
    assert py_events and [(g["gesture"], g["event"]) for g in got if g["type"] == "gesture"] == py_events


@pytest.mark.parametrize("token, reason", [("wrong-token", "HTTP 401"), (SOURCE, "HTTP 403: role 'source' may not read")])
def test_a_refused_token_stops_the_client_with_the_services_reason(harness, server, token, reason):
    started = time.monotonic()
    got = _run(harness, "subscribe", server.url, "unity2", token, "8", timeout=30)
    assert reason in got[-1]["refused"]
    assert time.monotonic() - started < 6.0                                   # no retrying a refusal
