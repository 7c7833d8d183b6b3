"""The gesture recogniser on synthetic frames: hysteresis, dwell, priorities, continuous values."""
import numpy as np
import pytest

from gestures.recognizer import GestureRecognizer, GestureSettings
from service.model.hand import default_calibration
from service.model.openxr import joint_poses
from service.pipeline.hand import HandFrame

CALIB = default_calibration("right")
# a relaxed hand at rest (as the simulator's rest poses: MCP 15-28 deg, PIP 20-32 deg): no gesture
RELAXED = {"thumb": (15, 15), "index": (20, 25, 25), "middle": (20, 25, 25), "ring": (20, 25, 25), "little": (20, 25, 25)}


def frame(t, **angles_deg):
    ang = dict(RELAXED)
    ang.update(angles_deg)
    phi = {f: np.radians(np.array(v, dtype=float)) for f, v in ang.items()}
    rot = np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]])
    pos = np.array([0.0, 1.1, -0.3])
    return HandFrame(t, 0, "right", phi, {f: "fused" for f in phi}, rot, pos, joint_poses(CALIB, phi, rot, pos), {})


FIST = dict(index=(85, 90, 90), middle=(85, 90, 90), ring=(85, 90, 90), little=(85, 90, 90), thumb=(45, 50))
POINT = dict(index=(0, 5, 5), middle=(80, 90, 90), ring=(80, 90, 90), little=(80, 90, 90), thumb=(40, 40))
PINCH = dict(index=(40, 40, 40), thumb=(40, 30), middle=(20, 25, 25), ring=(20, 25, 25), little=(20, 25, 25))


def run(frames, settings=None):
    rec = GestureRecognizer(settings or GestureSettings())
    events, annotations = [], []
    for f in frames:
        a, e = rec.update(f)
        annotations.append(a)
        events += [(x["gesture"], x["event"], round(x["t"], 4)) for x in e]
    return events, annotations


def test_each_pose_is_recognised_after_the_dwell_time():
    dt = 1 / 90
    for pose, name in ((FIST, "grasp"), (POINT, "point"), (PINCH, "pinch"),
                       (dict(index=(0, 0, 0), middle=(0, 0, 0), ring=(0, 0, 0), little=(0, 0, 0), thumb=(0, 0)), "open")):
        events, ann = run([frame(k * dt, **pose) for k in range(10)])
        assert events == [(name, "start", round(2 * dt, 4))], name    # 0.02 s dwell = 2 frames after the first
        assert ann[-1]["active"] == name


def test_hysteresis_holds_a_gesture_between_the_thresholds():
    # index curl oscillating between point's enter (0.2) and exit (0.35) thresholds: one start, no end
    dt = 1 / 90
    frames = [frame(k * dt, **POINT) for k in range(5)]
    for k in range(5, 60):
        index = (25, 25, 20) if k % 2 else (0, 5, 5)          # curl 70/250 = 0.28 inside the band
        frames.append(frame(k * dt, **{**POINT, "index": index}))
    events, _ = run(frames)
    assert events == [("point", "start", round(2 * dt, 4))]


def test_short_blips_do_not_flicker():
    dt = 1 / 90
    frames = [frame(k * dt) for k in range(5)]
    frames += [frame((5 + k) * dt, **FIST) for k in range(1)]     # one frame (11 ms) of fist: shorter than the dwell
    frames += [frame((6 + k) * dt) for k in range(10)]
    events, _ = run(frames)
    assert events == []
    # and a held gesture survives a one-frame dropout
    frames = [frame(k * dt, **FIST) for k in range(10)] + [frame(10 * dt)] + [frame((11 + k) * dt, **FIST) for k in range(10)]
    events, _ = run(frames)
    assert events == [("grasp", "start", round(2 * dt, 4))]


def test_grab_overrides_pinch():
    dt = 1 / 90
    fist_tips_close = {**FIST, "thumb": (60, 60)}
    frames = [frame(k * dt, **PINCH) for k in range(10)] + [frame((10 + k) * dt, **fist_tips_close) for k in range(10)]
    events, ann = run(frames)
    assert [e[:2] for e in events] == [("pinch", "start"), ("pinch", "end"), ("grasp", "start")]
    assert ann[-1]["pinch_strength"] == 0.0 and ann[-1]["grab_strength"] > 0.9


def test_continuous_values_and_ray():
    _, ann = run([frame(0.0, **POINT)] * 1 + [frame(k / 90, **POINT) for k in range(1, 5)])
    a = ann[-1]
    assert a["curl"]["index"] < 0.1 and a["curl"]["middle"] > 0.9
    assert 0.0 <= a["pinch_strength"] <= 1.0
    # the hand is palm down, fingers forward (world -Z): the extended index (PIP/DIP 5 deg) points
    # along -Z, tipped down (world -Y) by the flexion
    d = np.array(a["ray"]["direction"])
    assert np.degrees(np.arccos(-d[2])) < 5.0 and d[1] < 0
    np.testing.assert_allclose(np.linalg.norm(d), 1.0)
    _, ann = run([frame(0.0, **PINCH)])
    assert ann[0]["pinch_strength"] > 0.9


def test_per_user_thresholds_and_validation():
    strict = GestureSettings(grasp_curl_enter=0.99, grasp_curl_exit=0.9)
    events, _ = run([frame(k / 90, **{**FIST, "index": (80, 80, 80)}) for k in range(10)], strict)   # index curl 0.96
    assert events == []
    from pydantic import ValidationError
    with pytest.raises(ValidationError):
        GestureSettings(grasp_curl_enter=1.5)
    with pytest.raises(ValidationError):
        GestureSettings(grasp_enter=0.5)
