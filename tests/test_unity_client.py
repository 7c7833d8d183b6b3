"""The Unity C# client (``clients/unity``), compiled with Mono's ``mcs`` into a console harness
(``Tests~/Harness*.cs``) and run against the Python service's own output and a real server. Needs
``mcs``, ``mono`` and a Newtonsoft.Json assembly (Debian: ``mono-mcs mono-runtime
libnewtonsoft-json5.0-cil``; or ``FINGERTRACK_NEWTONSOFT_DLL``); skipped where they are missing.
The XR Hands provider is compiled against ``Tests~/XRHandsApiSurface.cs`` (the XR Hands package's
API surface, for compilation only) and ``Tests~/UnityEngineApiSurface.cs`` (UnityEngine's); the
Unity components (``FingertrackHand.cs``, ``FingertrackXRHands.cs``) are only type-checked against
those surfaces: they have not run in Unity."""
import asyncio
import glob
import json
import os
import shutil
import socket
import struct
import subprocess
from pathlib import Path

import msgpack
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.pipeline.tracked import replay
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig, simulate
from service.protocol import parse_message

from test_service import ADMIN, SOURCE, VIEWER, _stream_and_collect

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

UNITY = Path(__file__).resolve().parents[1] / "clients" / "unity"
MIRROR_Z = np.diag([1.0, 1.0, -1.0])


def _newtonsoft() -> str | None:
    env = os.environ.get("FINGERTRACK_NEWTONSOFT_DLL")
    if env:
        return env if Path(env).is_file() else None
    found = sorted(glob.glob("/usr/lib/cli/Newtonsoft.Json*/Newtonsoft.Json.dll"))
    return found[-1] if found else None


def _mono_or_skip() -> str:
    dll = _newtonsoft()
    if shutil.which("mcs") is None or shutil.which("mono") is None or dll is None:
        pytest.skip("needs Mono (mcs, mono) and Newtonsoft.Json to build the C# client")
    return dll


def test_the_unity_components_type_check_against_the_unity_api_surface(tmp_path):
    dll = _mono_or_skip()
    sources = sorted(str(p) for p in (UNITY / "Runtime").rglob("*.cs")) + \
        [str(UNITY / "Tests~" / "UnityEngineApiSurface.cs"), str(UNITY / "Tests~" / "XRHandsApiSurface.cs")]
    build = subprocess.run(["mcs", "-warnaserror+", "-target:library", "-define:UNITY_5_3_OR_NEWER",
                            "-define:FINGERTRACK_XR_HANDS", f"-out:{tmp_path / 'Components.dll'}", f"-r:{dll}", *sources],
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    dll = _mono_or_skip()
    out = tmp_path_factory.mktemp("cs")
    shutil.copy(dll, out / "Newtonsoft.Json.dll")
    sources = sorted(str(p) for p in (UNITY / "Runtime").rglob("*.cs")) + \
        sorted(str(p) for p in (UNITY / "Tests~").glob("*.cs"))
    build = subprocess.run(["mcs", "-warnaserror+", "-define:FINGERTRACK_XR_HANDS", f"-out:{out / 'Harness.exe'}",
                            f"-r:{out / 'Newtonsoft.Json.dll'}", *sources], capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    return out / "Harness.exe"


def _run(harness, *args, timeout=60):
    done = subprocess.run(["mono", str(harness), *args], stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]


def _write_framed(path, messages):
    """MessagePack messages as the service sends them (msgpack.packb), each after a 4-byte length."""
    with open(path, "wb") as f:
        for m in messages:
            b = m if isinstance(m, bytes) else msgpack.packb(m)
            f.write(struct.pack(">I", len(b)) + b)


@pytest.fixture(scope="module")
def pipeline_output():
    sess = simulate(SimConfig(motion="sequence", noise="white", seed=2, hand_motion="slow-rotation",
                              finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8), ("open", 0.6)))))
    return list(replay(parse_message(m) for m in sess.messages(include_truth=False)))


def test_it_reads_the_services_messages_and_converts_poses_to_unitys_frame(harness, tmp_path, pipeline_output):
    out = pipeline_output
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
            assert g["unity_joints"][name]["radius"] == pose["radius"] and g["unity_joints"][name]["tracked"] == pose["tracked"]
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
    # a joint without radius and tracked (an older service): radius unknown, tracked
    old = dict(frames[0][0], joints={"palm": {"position": [0, 0, 0], "orientation": [0, 0, 0, 1]}})
    (tmp_path / "old.jsonl").write_text(json.dumps(old) + "\n")
    _write_framed(tmp_path / "old.bin", [old])
    for got_old in (_run(harness, "parse", str(tmp_path / "old.jsonl")), _run(harness, "parse-msgpack", str(tmp_path / "old.bin"))):
        assert got_old[0]["unity_joints"]["palm"]["radius"] is None and got_old[0]["unity_joints"]["palm"]["tracked"] is True


def _approx_tree(a, b) -> bool:
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), (a, b)
        return all(_approx_tree(a[k], b[k]) for k in a)
    if isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b)
        return all(_approx_tree(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and not isinstance(b, bool):
        assert a == pytest.approx(b, rel=1e-14, abs=1e-300)
        return True
    assert a == b
    return True


def test_messagepack_reads_the_same_as_json(harness, tmp_path, pipeline_output):
    out = pipeline_output
    (tmp_path / "m.jsonl").write_text("\n".join(json.dumps(m) for m in out) + "\n")
    _write_framed(tmp_path / "m.bin", out)
    from_json = _run(harness, "parse", str(tmp_path / "m.jsonl"))
    from_msgpack = _run(harness, "parse-msgpack", str(tmp_path / "m.bin"))
    assert len(from_msgpack) == len(out) and len(from_json) == len(out)
    for a, b in zip(from_msgpack, from_json):       # the same, up to the last digit of JSON number parsing
        assert _approx_tree(a, b)
    # MessagePack floats are the service's doubles, bit for bit
    frames = [(m, g) for m, g in zip(out, from_msgpack) if m["type"] == "frame"]
    assert all(g["fingers"]["middle"]["mcp"] == m["fingers"]["middle"]["mcp"] for m, g in frames)
    assert any(g.get("unity_ray_direction") for g in from_msgpack if g["type"] == "frame")
    frame = next(m for m in out if m["type"] == "frame")
    bad = [b"\x92\x01\x02",                                                   # an array, not a map
           msgpack.packb({"type": "mystery"}),
           msgpack.packb({"t": 1.0}),
           msgpack.packb(dict(frame, t=float("nan"))),
           msgpack.packb(dict(frame, joints={"palm": {"position": [0, 1], "orientation": [0, 0, 0, 1]}})),
           msgpack.packb(dict(frame, joints={"palm": {"position": [0, 0, 0], "orientation": [0, 0, 0, 1], "tracked": 1}})),
           msgpack.packb(frame)[:-7],                                          # cut short
           msgpack.packb({"type": "gesture", "t": 1.0, "gesture": "point", "event": "start"})]
    _write_framed(tmp_path / "bad.bin", bad)
    problems = [g.get("problem", "") for g in _run(harness, "parse-msgpack", str(tmp_path / "bad.bin"))]
    assert problems[0] == "not a MessagePack map"
    assert "unknown message type 'mystery'" in problems[1]
    assert "missing text field 'type'" in problems[2]
    assert problems[3] == "t: not finite"
    assert "palm: expected 3 numbers" in problems[4]
    assert "palm.tracked: expected true or false" in problems[5]
    assert "ends early" in problems[6]
    assert "missing number 'confidence'" in problems[7]


def test_a_messagepack_frame_allocates_at_most_5_kb(harness, tmp_path, pipeline_output):
    frames = [m for m in pipeline_output if m["type"] == "frame"]
    _write_framed(tmp_path / "f.bin", frames)
    got = _run(harness, "alloc", str(tmp_path / "f.bin"), "3", timeout=300)[0]
    print(f"\nC# client, bytes allocated per frame parsed (Mono, {got['frames']} frames x {got['repeats']}): "
          f"MessagePack {got['msgpack_bytes_per_frame']:.0f}, JSON {got['json_bytes_per_frame']:.0f} "
          f"(message {got['msgpack_message_bytes']:.0f} bytes)")
    assert got["frames"] == len(frames)
    assert got["msgpack_bytes_per_frame"] <= 5 * 1024
    # the measurement can fail: the JSON DOM path allocates many times more for the same frames
    assert got["json_bytes_per_frame"] > 5 * got["msgpack_bytes_per_frame"]

    # the client's whole path per frame: read and queued, drained into the interpolator, the hand
    # sampled at a render time; the frames repeated as a longer stream (later times and seqs)
    span = frames[-1]["t"] - frames[0]["t"] + 1.0
    stream = [dict(f, t=f["t"] + k * span, seq=f["seq"] + k * len(frames)) for k in range(4) for f in frames]
    _write_framed(tmp_path / "s.bin", stream)
    whole = _run(harness, "alloc-client", str(tmp_path / "s.bin"), str(len(frames)), timeout=300)[0]
    print(f"C# client, bytes allocated per frame from the received bytes to the sampled hand: "
          f"{whole['client_bytes_per_frame']:.0f} ({whole['frames']} frames)")
    assert whole["frames"] == 3 * len(frames) and whole["bad_messages"] == 0 and whole["newest_seq"] == stream[-1]["seq"]
    assert whole["interpolated"] > 0.9 * whole["frames"]          # sampled between frames, not held
    assert got["msgpack_bytes_per_frame"] <= whole["client_bytes_per_frame"] <= 5 * 1024


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
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        yield srv


@pytest.mark.parametrize("wire", ["msgpack", "json"])
def test_it_subscribes_to_a_live_session_beside_a_python_client(harness, server, wire):
    session = f"unity-{wire}"
    # the C# client listens until told the session's last frame (300 s only bounds a failure)
    cs = subprocess.Popen(["mono", str(harness), "subscribe", server.url, session, VIEWER, "300",
                           *(["json"] if wire == "json" else [])],
                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert json.loads(cs.stdout.readline()) == {"type": "ready", "subscribed": True}

    config = SimConfig(motion="sequence", noise="white", seed=3,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8), ("rest", 0.8))))
    received, _ = asyncio.run(_stream_and_collect(server, session, config, speed=2.0))
    py = [m for _, m in received]
    last = max(m["seq"] for m in py if m["type"] == "frame")
    out, err = cs.communicate(f"until {last}\n", timeout=300)
    got = [json.loads(line) for line in out.splitlines() if line.strip()]
    summary = got[-1]
    assert summary["type"] == "summary" and summary["hello_session"] == session
    assert summary["refused"] is None and summary["bad_messages"] == 0 and summary["reconnects"] == 0, err
    assert summary["states"] == ["Connecting", "Connected", "Stopped"]
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
    got = _run(harness, "subscribe", server.url, "unity2", token, "60", timeout=120)
    assert reason in got[-1]["refused"]
    assert got[-1]["states"] == ["Connecting", "Refused"]                    # refused once, never retried


def test_frames_are_interpolated_to_the_render_time_with_the_estimated_clock_offset(harness, tmp_path):
    """Closed form: each joint moves at constant velocity and turns at a constant rate about a fixed
    axis, so linear interpolation and slerp between frames are exact; frames arrive 10 s + a
    transport delay (>= 1 ms, exactly 1 ms for one frame) after their source time, so the offset
    estimate is 10.001 s."""
    rng = np.random.default_rng(5)
    names = ["palm", "wrist", "index_tip"]
    a, v = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    axes = rng.normal(size=(3, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rates = np.array([0.7, -2.0, 3.5])                       # rad/s
    q0 = Rotation.random(3, random_state=6)

    def truth(t):
        rot = Rotation.from_rotvec(axes * (rates * t)[:, None]) * q0
        return a + v * t, rot

    t_k = 0.5 + np.arange(20) / 90.0
    delay = 0.001 + rng.exponential(0.004, size=t_k.size)
    delay[3] = 0.001
    lines, expect = [], []
    render_delay = 1.5 / 90.0
    for k, t in enumerate(t_k):
        pos, rot = truth(t)
        joints = {n: {"position": pos[i].tolist(), "orientation": rot[i].as_quat().tolist(),
                      "radius": 0.01 + 0.001 * t, "tracked": not (n == "index_tip" and k == 12)} for i, n in enumerate(names)}
        lines.append({"type": "frame", "t": t, "seq": k, "hand": "right", "fingers": {}, "joints": joints,
                      "arrival": t + 10.0 + delay[k]})
        if k >= 5:
            s = t_k[k - 2] + rng.uniform(0.1, 0.9) * (t_k[k - 1] - t_k[k - 2])
            lines.append({"query": 10.001 + s + render_delay, "delay": render_delay})
            expect.append((s, k - 2))
    lines.append({"query": 10.001 + t_k[-1] + 0.5, "delay": render_delay})   # past the newest frame
    (tmp_path / "i.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    got = _run(harness, "interp", str(tmp_path / "i.jsonl"))
    assert len(got) == len(expect) + 1
    for g, (s, before) in zip(got, expect):
        assert g["ok"] and not g["held"]
        assert g["offset"] == pytest.approx(10.001, abs=1e-9)
        assert g["source_t"] == pytest.approx(s, abs=1e-9)
        pos, rot = truth(s)
        for i, n in enumerate(names):
            np.testing.assert_allclose(g["joints"][n]["position"], pos[i], atol=1e-9)
            q = np.array(g["joints"][n]["orientation"])
            assert abs(np.dot(q, rot[i].as_quat())) == pytest.approx(1.0, abs=1e-9)
            assert g["joints"][n]["radius"] == pytest.approx(0.01 + 0.001 * s, abs=1e-12)
        # untracked in frame 12: so is everything interpolated from it
        assert g["joints"]["index_tip"]["tracked"] == (before not in (11, 12))
    held = got[-1]
    newest = [x for x in lines if x.get("type") == "frame"][-1]
    assert held["held"] and held["joints"]["index_tip"]["position"] == newest["joints"]["index_tip"]["position"]


@pytest.fixture(scope="module")
def two_hands():
    def run(hand, drop=()):
        sess = simulate(SimConfig(motion="sequence", noise="white", seed=7, hand=hand, hand_motion="slow-rotation",
                                  finger_motion=sequence_motion(steps=(("point", 0.6), ("grasp", 0.6)))))
        msgs = [m for m in sess.messages(include_truth=False) if not (m["type"] == "imu" and m["id"] in drop and m["t"] > 0.6)]
        return [m for m in replay(parse_message(m) for m in msgs) if m["type"] == "frame"]
    return run("left"), run("right", drop=("ring.1", "ring.2"))


XR_HANDS_JOINT_IDS = ["Wrist", "Palm", "ThumbMetacarpal", "ThumbProximal", "ThumbDistal", "ThumbTip"] + [
    f"{f}{b}" for f in ("Index", "Middle", "Ring", "Little") for b in ("Metacarpal", "Proximal", "Intermediate", "Distal", "Tip")]
OPENXR_NAME = {xr: ("wrist" if xr == "Wrist" else "palm" if xr == "Palm" else
                    xr.replace("Metacarpal", "_metacarpal").replace("Proximal", "_proximal").replace("Intermediate", "_intermediate")
                      .replace("Distal", "_distal").replace("Tip", "_tip").lower()) for xr in XR_HANDS_JOINT_IDS}
POSE, RADIUS, HIGH_FIDELITY = 1 << 1, 1 << 0, 1 << 5          # XRHandJointTrackingState


def test_the_xr_hands_provider_writes_each_frames_joints(harness, tmp_path, two_hands):
    left, right = two_hands
    assert [f["t"] for f in left] == [f["t"] for f in right]
    _write_framed(tmp_path / "left.bin", left)
    _write_framed(tmp_path / "right.bin", right)
    got = _run(harness, "xrhands", str(tmp_path / "left.bin"), str(tmp_path / "right.bin"), timeout=300)
    assert got[0]["registered"] == [{"id": "fingertrack-hands", "provider": "Fingertrack.XRHands.FingertrackHandProvider",
                                     "subsystem": "Fingertrack.XRHands.FingertrackHandSubsystem"}]
    assert got[1] == {"layout": 26}
    updates = got[2:-1]
    assert len(updates) == len(right)
    untracked_seen = 0
    for u, fl, fr in zip(updates, left, right):
        assert u["flags"] == 0b1111                                  # both hands: root pose and joints
        for side, frame in (("left", fl), ("right", fr)):
            joints = u[side]["joints"]
            assert [j["id"] for j in joints] == XR_HANDS_JOINT_IDS
            assert all(j["handedness"] == side.capitalize() for j in joints)
            for j in joints:
                sent = frame["joints"][OPENXR_NAME[j["id"]]]
                np.testing.assert_allclose(j["position"], MIRROR_Z @ np.array(sent["position"]), atol=1e-6)
                r_unity = MIRROR_Z @ Rotation.from_quat(sent["orientation"]).as_matrix() @ MIRROR_Z
                np.testing.assert_allclose(Rotation.from_quat(j["rotation"]).as_matrix(), r_unity, atol=1e-5)
                assert j["radius"] == pytest.approx(sent["radius"], rel=1e-6)
                assert j["state"] == POSE | RADIUS | (HIGH_FIDELITY if sent["tracked"] else 0)
                untracked_seen += not sent["tracked"]
            wrist = frame["joints"]["wrist"]
            np.testing.assert_allclose(u[side]["root"][:3], MIRROR_Z @ np.array(wrist["position"]), atol=1e-6)
    assert untracked_seen > 0, "the right hand's ring finger loses its sensors, so some joints are untracked"
    assert got[-1] == {"stale_flags": 0}


def test_dispose_does_not_wait_for_a_connection_that_hangs(harness):
    # a listener that accepts TCP connections and never answers the WebSocket handshake
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)
        port = silent.getsockname()[1]
        got = _run(harness, "dispose", f"http://127.0.0.1:{port}", timeout=60)[0]
    assert got["states"] == ["Connecting", "Stopped"] and got["final"] == "Stopped"


def test_every_asset_of_the_package_has_a_meta_file_with_a_stable_unique_guid():
    """A package installed from a git URL is immutable: Unity ignores every asset without a committed
    .meta file. Folders ending in ~ (Tests~) and hidden files are not assets."""
    assets, metas = set(), set()
    for path in UNITY.rglob("*"):
        rel = path.relative_to(UNITY)
        if any(part.endswith("~") or part.startswith(".") for part in rel.parts):
            continue
        (metas if path.suffix == ".meta" else assets).add(rel)
    missing = sorted(str(a) for a in assets if a.with_name(a.name + ".meta") not in metas)
    assert not missing, f"assets without a .meta file (write one with a new GUID): {missing}"
    orphans = sorted(str(m) for m in metas if m.with_name(m.name[:-len(".meta")]) not in assets)
    assert not orphans, f".meta files without their asset: {orphans}"
    guids = {}
    importers = {".cs": "MonoImporter", ".asmdef": "AssemblyDefinitionImporter", ".md": "TextScriptImporter"}
    for m in sorted(metas):
        text = (UNITY / m).read_text()
        lines = dict(line.split(":", 1) for line in text.splitlines() if ":" in line and not line.startswith(" "))
        guid = lines["guid"].strip()
        assert lines["fileFormatVersion"].strip() == "2"
        assert len(guid) == 32 and all(c in "0123456789abcdef" for c in guid), (m, guid)
        assert guid not in guids, f"{m} repeats the GUID of {guids.get(guid)}"
        guids[guid] = m
        asset = UNITY / m.with_name(m.name[:-len(".meta")])
        if asset.is_dir():
            assert lines.get("folderAsset", "").strip() == "yes", m
        elif asset.name == "package.json":
            assert "PackageManifestImporter" in lines, m
        else:
            assert importers[asset.suffix] in lines, m
    manifest = json.loads((UNITY / "package.json").read_text())
    assert manifest["name"] == "com.fingertrack.client" and manifest["unity"] == "2021.3"
    import tomllib
    project = tomllib.loads((UNITY.parents[1] / "pyproject.toml").read_text())["project"]
    assert manifest["license"] == project["license"]["text"]                # the project's licence
    for asmdef in UNITY.rglob("*.asmdef"):
        json.loads(asmdef.read_text())                                      # valid JSON
