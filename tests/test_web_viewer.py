"""The web viewer (``clients/web``): served by the service, and its module run in Node
(``tests/web_viewer_check.mjs``) on the pipeline's own frames and against a live server beside a
Python subscriber. The Node parts skip where ``node`` (with a WebSocket) is missing; the drawing
code that needs a browser canvas is not run here."""
import asyncio
import json
import math
import shutil
import subprocess
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.pipeline.tracked import replay
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.protocol import parse_message
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate

from test_service import ADMIN, SOURCE, VIEWER, _stream_and_collect

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

CHECK = Path(__file__).resolve().parent / "web_viewer_check.mjs"
OPENXR_JOINTS = {"palm", "wrist"} | {f"thumb_{j}" for j in ("metacarpal", "proximal", "distal", "tip")} | {
    f"{f}_{j}" for f in ("index", "middle", "ring", "little") for j in ("metacarpal", "proximal", "intermediate", "distal", "tip")}


@pytest.fixture(scope="module")
def server():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        yield srv


@pytest.fixture(scope="module")
def node():
    exe = shutil.which("node")
    if exe is None:
        pytest.skip("needs Node.js to run the viewer's module")
    for flags in ([], ["--experimental-websocket"]):
        probe = subprocess.run([exe, *flags, "-e", "process.exit(typeof WebSocket === 'function' ? 0 : 1)"],
                               capture_output=True)
        if probe.returncode == 0:
            return [exe, *flags]
    pytest.skip("this Node.js has no WebSocket (needs 20.10+)")


def _node(node, *args, timeout=60):
    done = subprocess.run([*node, str(CHECK), *args], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]


def test_the_service_serves_the_viewer_without_a_token(server):
    with urllib.request.urlopen(server.url + "/viewer/") as r:
        assert r.status == 200 and r.headers["content-type"].startswith("text/html")
        assert '<script type="module" src="viewer.js">' in r.read().decode()
    with urllib.request.urlopen(server.url + "/viewer/viewer.js") as r:
        assert r.headers["content-type"].startswith("text/javascript")
        assert "export function subscribe" in r.read().decode()


def test_the_viewer_module_on_the_pipelines_frames(node, tmp_path):
    sess = simulate(SimConfig(motion="sequence", noise="white", seed=5, hand_motion="slow-rotation",
                              finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8)))))
    out = list(replay(parse_message(m) for m in sess.messages(include_truth=False)))
    frames = [m for m in out if m["type"] == "frame"][::40]
    gestures = [m for m in out if m["type"] == "gesture"]
    (tmp_path / "msgs.json").write_text(json.dumps(frames + gestures))
    got = _node(node, "pure", str(tmp_path / "msgs.json"))
    head, rest = got[0], got[1:]
    edges = head["bones"]
    assert len(edges) == 25 and {j for e in edges for j in e} == OPENXR_JOINTS
    assert head["url"] == "wss://example.org:8765/v1/stream/right%20hand?token=a%20b%26c"
    for f, g in zip(frames, rest):
        assert g["seq"] == f["seq"]
        deg = lambda r: math.floor(math.degrees(r) + 0.5)                          # JavaScript's Math.round
        idx = f["fingers"]["index"]
        assert f"mcp {deg(idx['mcp']):4d} pip {deg(idx['pip']):4d} dip {deg(idx['dip']):4d}" in g["lines"][1]
        assert g["lines"][0].startswith("thumb ") and f"ip {deg(f['fingers']['thumb']['ip']):4d}" in g["lines"][0]
        center = np.array(f["joints"]["palm"]["position"])
        for (yaw, pitch), projected in zip(g["views"], g["projected"]):
            # an orthographic camera turned by yaw about +Y, then pitched about its x axis
            cam = Rotation.from_euler("X", pitch).as_matrix() @ Rotation.from_euler("Y", yaw).as_matrix()
            for name, joint in f["joints"].items():
                v = cam @ (np.array(joint["position"]) - center)
                np.testing.assert_allclose(projected[name], [280 + 1000 * v[0], 240 - 1000 * v[1], v[2]], atol=1e-9)
    lines = [g["event"] for g in got if "event" in g]
    assert gestures and lines == [f"t={m['t']:.3f}  {m['gesture']} {m['event']}  (confidence {m['confidence']:.2f})"
                                  for m in gestures]


def test_the_viewer_subscribes_to_a_live_session_beside_a_python_client(node, server):
    cmd = [*node, str(CHECK), "subscribe", server.url, "web1", VIEWER, "stdin"]
    js = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert json.loads(js.stdout.readline()) == {"type": "connected"}
    config = SimConfig(motion="sequence", noise="white", seed=6,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8), ("rest", 0.6))))
    received, _ = asyncio.run(_stream_and_collect(server, "web1", config, speed=2.0))
    py_frames = {m["seq"]: m for _, m in received if m["type"] == "frame"}
    # the module stops after the last frame the Python subscriber got (which stops on a clock)
    out, err = js.communicate(f"{max(py_frames)}\n", timeout=120)
    got = [json.loads(line) for line in out.splitlines() if line.strip()]
    js_frames = {g["seq"]: g for g in got if g["type"] == "frame" and g["seq"] <= max(py_frames)}
    assert len(py_frames) > 100 and js_frames.keys() == py_frames.keys(), err
    for seq in list(py_frames)[::50]:
        assert js_frames[seq]["tip"] == py_frames[seq]["joints"]["index_tip"]["position"]
    py_events = [(m["gesture"], m["event"]) for _, m in received if m["type"] == "gesture"]
    assert py_events and [(g["gesture"], g["event"]) for g in got if g["type"] == "gesture"] == py_events
    assert got[-1] == {"type": "summary", "frames": sum(g["type"] == "frame" for g in got)}


@pytest.mark.parametrize("token, reason", [("wrong-token", "HTTP 401"), (SOURCE, "HTTP 403: role 'source' may not read")])
def test_a_refused_token_is_reported_and_not_retried(node, server, token, reason):
    got = _node(node, "subscribe", server.url, "web2", token, "refused")
    refusals = [g for g in got if g["type"] == "refused"]
    assert len(refusals) == 1 and reason in refusals[0]["why"]
    assert got[-1] == {"type": "summary", "frames": 0}


def test_the_angle_plot_on_the_pipelines_frames(node, tmp_path):
    sess = simulate(SimConfig(motion="sequence", noise="white", seed=8,
                              finger_motion=sequence_motion(steps=(("grasp", 0.5), ("point", 0.5)))))
    frames = [m for m in replay(parse_message(m) for m in sess.messages(include_truth=False)) if m["type"] == "frame"]
    frames = frames[::3]
    del frames[-5]["fingers"]["thumb"]                        # a frame without the thumb breaks its lines
    (tmp_path / "frames.json").write_text(json.dumps(frames))
    for window_s, max_points in ((1.0, 60), (1.0, 8)):      # the window binds, then the point limit
        _check_plot(node, tmp_path, frames, window_s, max_points)


def _check_plot(node, tmp_path, frames, window_s, max_points):
    plot, restarted = _node(node, "plot", str(tmp_path / "frames.json"), str(window_s), str(max_points))
    t_end = frames[-1]["t"]
    in_window = [f for f in frames if f["t"] >= t_end - window_s]
    assert 8 < len(in_window) < 60 < len(frames)
    kept = in_window[-max_points:]
    assert plot["t"] == [f["t"] for f in kept] and plot["tEnd"] == t_end
    keys = [f"thumb.{j}" for j in ("mcp", "ip")] + [f"{f}.{j}" for f in ("index", "middle", "ring", "little") for j in ("mcp", "pip", "dip")]
    assert [line["key"] for line in plot["lines"]] == keys
    angles = {k: [math.degrees(f["fingers"][k.split(".")[0]][k.split(".")[1]]) if k.split(".")[0] in f["fingers"] else None
                  for f in kept] for k in keys}
    present = [a for values in angles.values() for a in values if a is not None]
    lo, hi = min(-10, 10 * math.floor(min(present) / 10)), max(100, 10 * math.ceil(max(present) / 10))
    assert (plot["lo"], plot["hi"]) == (lo, hi) and hi - lo >= 110
    for line in plot["lines"]:
        for f, a, point in zip(kept, angles[line["key"]], line["points"]):
            if a is None:
                assert point is None
                continue
            # the right edge is the newest frame, the left edge window_s before it; lo at the bottom
            np.testing.assert_allclose(point, [40 + 900 * (f["t"] - (t_end - window_s)) / window_s, 8 + 200 * (hi - a) / (hi - lo)],
                                       atol=1e-9)
    assert sum(p is None for line in plot["lines"] for p in line["points"]) == 2
    assert restarted == {"restarted": [frames[0]["t"] - 1]}


def test_the_pages_address_status_and_session_list(node, tmp_path):
    hashes, states, items = _node(node, "page")
    assert hashes["hashes"] == [{"session": "lab 1", "token": "a&b"}, {"session": "x", "token": None},
                                {"session": None, "token": "t"}, {"session": None, "token": None}, {"session": None, "token": None}]
    assert hashes["hashFor"] == "#session=lab%201" and hashes["back"] == {"session": "lab 1", "token": None}
    assert [s["state"] for s in states["states"]] == ["offline", "refused", "connected", "waiting", "starting", "live",
                                                       "live", "waiting", "stalled", "offline"]
    texts = [s["text"] for s in states["states"]]
    assert "waiting for a source" in texts[3] and "the source has left" in texts[7] and texts[8] == "connected; no frame for 3 s"
    assert texts[1] == "refused: HTTP 401: no" and texts[9].startswith("disconnected")
    assert items["items"] == [{"name": "a", "current": False, "text": "left hand, 1 source, 2 viewers, 1 frame sent"},
                              {"name": "b", "current": True, "text": "right hand, 0 sources, 0 viewers, 0 frames sent"}]
