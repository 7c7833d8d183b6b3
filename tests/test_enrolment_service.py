"""Per-user enrolment through a live service: a glove streams the enrolment procedure of a person
whose pinch is wide, then ``POST /v1/sessions/{session}/enrolment`` fits and applies the thresholds."""
import asyncio

import numpy as np
import pytest

from clients.client import Publisher, rest
from clients.glove import source_messages
from gestures.recognizer import GestureSettings
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.gesture_script import Subject, Trial, enrolment_steps
from service.sim.session import SimConfig

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE, VIEWER, ADMIN = "src-token-e", "view-token-e", "admin-token-e"


@pytest.fixture(scope="module")
def server():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        yield srv


def test_enrolment_over_rest_fits_a_wide_pinch_and_names_bad_segments(server):
    subject = Subject(pinch_aperture_m=0.035)
    steps = enrolment_steps(subject, 0.5, np.random.default_rng(3))
    trial = Trial(3, subject, tuple(steps), "slow-rotation", steps[-1].end_s)
    config = SimConfig(motion="sequence", noise="white", seed=3, calibration=trial.calibration(),
                       finger_motion=trial.finger_motion(), hand_trajectory=trial.hand_trajectory())

    async def stream():
        # as fast as the service takes it: a sync every 0.5 s of data keeps its backlog short (a
        # backlog longer than the keepalive timeout would close the connection on a busy machine)
        pub = Publisher(server.url, "enrol1", SOURCE)
        for k, (_, m) in enumerate(await asyncio.to_thread(source_messages, config)):
            await pub.send(m)
            if k % 100 == 99:
                await pub.sync()
        await pub.close()
    asyncio.run(stream())
    segments = [{"label": s.intent if s.intent != "none" else "rest",
                 "start_s": s.start_s + s.transition_s + 0.2, "end_s": s.end_s - 0.1} for s in steps]
    status, body = rest(server.url, "POST", "/v1/sessions/enrol1/enrolment", ADMIN, {"segments": segments})
    assert status == 200, body
    assert body["gestures"]["pinch_enter_m"] > 0.035 and body["changes"]["pinch_enter_m"]["old"] == GestureSettings().pinch_enter_m
    status, config_now = rest(server.url, "GET", "/v1/sessions/enrol1/config", ADMIN)
    assert config_now["gestures"]["pinch_enter_m"] == body["gestures"]["pinch_enter_m"]
    # bad requests: clear reasons, nothing changed
    status, body = rest(server.url, "POST", "/v1/sessions/enrol1/enrolment", ADMIN,
                        {"segments": [{**segments[0], "label": "wave"}]})
    assert status == 422 and "'wave'" in body["detail"]
    status, body = rest(server.url, "POST", "/v1/sessions/enrol1/enrolment", ADMIN, {"segments": segments[:1]})
    assert status == 422 and "'grasp' has 0 frames" in body["detail"]
    status, body = rest(server.url, "POST", "/v1/sessions/enrol1/enrolment", VIEWER, {"segments": segments})
    assert status == 403
    assert rest(server.url, "GET", "/v1/sessions/enrol1/config", ADMIN)[1]["gestures"] == config_now["gestures"]
