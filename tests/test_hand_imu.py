"""The optional IMU on the back of the hand (sensor id ``metacarpus``): simulated readings against
rigid-body physics, the protocol accepting it, and the pipeline's hand kinematics with it against the
simulator's truth (better than the optics alone while tracking, and through an occlusion)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.hand import MetacarpusImu
from service.model.kinematics import BaseMotion, metacarpus_imu
from service.pipeline.hand import HandSession, PipelineSettings
from service.protocol import ProtocolError, parse_message
from service.sim.errors import OpticalModel
from service.sim.session import SimConfig, simulate

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

G = np.array([0.0, -9.81, 0.0])


def test_readings_follow_rigid_body_physics():
    """A hand turning at a constant rate about a fixed axis through the wrist: the gyro reads the rate
    in its own frame, the accelerometer the centripetal acceleration of its lever minus gravity."""
    n, w = 50, np.array([0.0, 2.0, 1.0])
    t = np.arange(n) / 200.0
    rot = Rotation.from_rotvec(t[:, None] * w).as_matrix()
    z = np.zeros((n, 3))
    base = BaseMotion(rot, z, z, z, np.tile(w, (n, 1)), z)
    mount = Rotation.from_euler("xyz", [10, -20, 30], degrees=True)
    placement = MetacarpusImu((0.01, 0.06, -0.02), tuple(mount.as_quat()))
    r = placement.mounting_matrix()
    out = metacarpus_imu(placement, base, G)
    for k in (0, n // 2, n - 1):
        rho = rot[k] @ np.array(placement.position_m)
        a = np.cross(w, np.cross(w, rho))
        np.testing.assert_allclose(out.gyr[k], (rot[k] @ r).T @ w, atol=1e-12)
        np.testing.assert_allclose(out.acc[k], (rot[k] @ r).T @ (a - G), atol=1e-12)


def test_the_other_draws_do_not_change_with_it():
    for noise in ("both", "realistic"):
        a = simulate(SimConfig(motion="random", noise=noise, seed=4, hand_motion="random", duration_s=1.0))
        b = simulate(SimConfig(motion="random", noise=noise, seed=4, hand_motion="random", duration_s=1.0,
                               metacarpus_imu=True))
        np.testing.assert_array_equal(a.gyr, b.gyr)
        np.testing.assert_array_equal(a.acc, b.acc)
        np.testing.assert_array_equal(a.pose_orientation, b.pose_orientation)
        assert b.metacarpus_gyr.shape == (len(b.t), 3)
        ids = {m.get("id") for m in b.messages() if m["type"] == "imu"}
        assert "metacarpus" in ids and "metacarpus" not in {m.get("id") for m in a.messages() if m["type"] == "imu"}


def test_protocol_accepts_it_and_names_what_is_wrong():
    parse_message({"type": "imu", "t": 0.0, "id": "metacarpus", "gyr": [0, 0, 0], "acc": [0, 9.81, 0]})
    cal = parse_message({"type": "calibration", "metacarpus": {"position": [0.0, 0.05, -0.015], "mounting": [0, 0, 0, 1]}})
    assert cal.metacarpus.position == [0.0, 0.05, -0.015]
    with pytest.raises(ProtocolError, match="mounting"):
        parse_message({"type": "calibration", "metacarpus": {"mounting": [0, 0, 0, 2]}})
    with pytest.raises(ProtocolError):
        parse_message({"type": "imu", "t": 0.0, "id": "metacarpus.1", "gyr": [0, 0, 0], "acc": [0, 9.81, 0]})


def _hand_track(session, with_imu: bool):
    """The pipeline's metacarpus kinematics per processed tick: (t, rotation, angular velocity, tracking)."""
    hs = HandSession(settings=PipelineSettings())
    out, last = [], None
    for m in session.messages(include_truth=False):
        if m["type"] == "imu" and m["id"] == "metacarpus" and not with_imu:
            continue
        hs.handle(parse_message(m))
        if hs._tick_t is not None and hs._tick_t != last and hs._hand_motion is not None:
            last = hs._tick_t
            h = hs._hand_motion
            out.append((last, h.rotation.copy(), h.angular_velocity.copy(), hs.status(last)["optics"] == "tracking"))
    t = np.array([o[0] for o in out])
    idx = np.round((t - session.t[0]) * session.config.rate_hz).astype(int)
    rot_err = np.degrees(np.array([Rotation.from_matrix(o[1].T @ session.base.rotation[i]).magnitude()
                                   for o, i in zip(out, idx)]))
    w_err = np.linalg.norm(np.array([o[2] for o in out]) - session.base.angular_velocity[idx], axis=1)
    return t, rot_err, w_err, np.array([o[3] for o in out])


@pytest.fixture(scope="module")
def rotating_hand():
    """Realistic errors (the IMU mounted up to 5 deg off, scale and cross-axis errors, offsets), a hand
    turning and translating, 0.6 s without optics."""
    return simulate(SimConfig(motion="random", noise="realistic", seed=11, hand_motion="random", duration_s=6.0,
                              fingers=("index",), metacarpus_imu=True, optical=OpticalModel(occlusions_s=((4.0, 4.6),))))


def test_angular_velocity_while_tracking_beats_the_optical_fit(rotating_hand):
    """The optics' rate is a derivative fit over 0.15 s of jittery poses; the calibrated gyro measures it.
    After 2 s of calibration the IMU's rate error must be below half the optics'."""
    t, _, w_imu, tracking = _hand_track(rotating_hand, True)
    t0, _, w_opt, tracking0 = _hand_track(rotating_hand, False)
    rms = lambda e, m: float(np.sqrt(np.mean(e[m] ** 2)))       # noqa: E731
    with_imu, optics = rms(w_imu, tracking & (t > 2.0)), rms(w_opt, tracking0 & (t0 > 2.0))
    assert with_imu < 0.5 * optics, (with_imu, optics)


def test_orientation_through_an_occlusion(rotating_hand):
    """Through 0.6 s without optics the gyro carries the orientation: a calibrated gyro (residual rate
    error well under 0.03 rad/s) drifts less than 1 deg; the finger gyros alone cannot see the hand's
    rotation about the fingers' common hinge axis as well."""
    t, rot_imu, _, tracking = _hand_track(rotating_hand, True)
    t0, rot_opt, _, tracking0 = _hand_track(rotating_hand, False)
    lost, lost0 = ~tracking & (t > 3.0), ~tracking0 & (t0 > 3.0)
    assert lost.sum() > 50 and lost0.sum() > 50
    assert rot_imu[lost].max() < 1.0, rot_imu[lost].max()
    assert rot_imu[lost].max() < rot_opt[lost0].max()


def test_linear_map_fit_recovers_a_known_map():
    """Noise-free observations y = M x + c over varied x: the recursive fit with a weak prior recovers
    M and c (a closed form: the least-squares solution of an exactly consistent system)."""
    from service.pipeline.hand_imu import LinearMapFit
    rng = np.random.default_rng(3)
    m = Rotation.from_rotvec([0.05, -0.03, 0.08]).as_matrix() @ np.diag([1.02, 0.97, 1.01])
    c = np.array([0.1, -0.2, 0.05])
    fit = LinearMapFit(np.eye(3), noise_std=1e-3, map_std=0.05, offset_std=0.1)
    for _ in range(400):
        x = rng.normal(0.0, 1.0, 3)
        fit.update(x, 1.0, m @ x + c, forget=1.0)
    np.testing.assert_allclose(fit.map, m, atol=1e-5)
    np.testing.assert_allclose(fit.offset, c, atol=1e-5)


def test_a_live_server_uses_it_and_its_recording_replays_to_the_live_frames(tmp_path):
    """A glove with a back-of-hand IMU streams to a live server that records, through an occlusion:
    no error, no sample dropped as from an unknown sensor; the live frames equal those of replaying
    the service's recording, and differ from replaying it without the IMU's messages (the service
    used them)."""
    import asyncio
    import json

    from clients.client import Subscription, rest
    from clients.glove import stream_glove
    from service.api.config import ServiceSettings
    from service.api.server import ServerThread
    from service.pipeline.tracked import replay
    from service.protocol import parse_line
    from service.sim.motions import sequence_motion
    from test_service import ADMIN, SOURCE, VIEWER, _wait_for, _wait_for_last_frame

    config = SimConfig(motion="sequence", noise="both", seed=5, hand_motion="slow-rotation", metacarpus_imu=True,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8))),
                       optical=OpticalModel(occlusions_s=((1.5, 2.1),)))
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN,
                                    record_dir=str(tmp_path))
    with ServerThread(settings) as srv:
        assert rest(srv.url, "PUT", "/v1/sessions/backimu/config", ADMIN, {"record": True})[0] == 200

        async def go():
            received = []
            sub = Subscription(srv.ws_url, "backimu", VIEWER)

            async def collect():
                async for m in sub:
                    received.append((None, m))

            task = asyncio.create_task(collect())
            await _wait_for(lambda: sub.server_hello is not None, "the subscription's hello")
            pub = await stream_glove(srv.url, "backimu", SOURCE, config, speed=4.0)
            await pub.close()
            await _wait_for_last_frame(srv, "backimu", received)
            await sub.close()
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            return [m for _, m in received], pub

        received, pub = asyncio.run(go())
        path = next(s for s in rest(srv.url, "GET", "/v1/sessions", ADMIN)[1] if s["session"] == "backimu")["recording"]
        assert rest(srv.url, "PUT", "/v1/sessions/backimu/config", ADMIN, {"record": False})[0] == 200
    assert not pub.errors, list(pub.errors)
    frames = [m for m in received if m["type"] == "frame"]
    assert len(frames) > 100 and frames[-1]["status"]["dropped"]["unknown_sensor"] == 0
    assert any(f["status"]["optics"] == "occluded" for f in frames)
    with open(path) as fh:
        recorded = [json.loads(line) for line in fh]

    def samples(m):
        return m["samples"] if m["type"] == "imu_batch" else [m] if m["type"] == "imu" else []

    assert sum(s["id"] == "metacarpus" for m in recorded for s in samples(m)) > 100
    stripped = []                              # the same recording without the back-of-hand IMU
    for m in recorded:
        if m["type"] == "imu_batch":
            m = {**m, "samples": [s for s in m["samples"] if s["id"] != "metacarpus"]}
            if not m["samples"]:
                continue
        elif m["type"] == "imu" and m["id"] == "metacarpus":
            continue
        stripped.append(m)

    def angles(msgs):
        return {m["seq"]: json.dumps(m["fingers"], sort_keys=True) for m in msgs if m["type"] == "frame"}

    live = angles(frames)
    replayed = angles(replay(parse_line(json.dumps(m)) for m in recorded))
    without = angles(replay(parse_line(json.dumps(m)) for m in stripped))
    assert all(replayed[seq] == a for seq, a in live.items())
    assert any(without.get(seq) != a for seq, a in live.items())
