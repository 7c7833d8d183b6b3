"""Protocol v1: recordings round-trip through the models; bad input gets a clear error."""
import json

import pytest

from service.model.hand import default_calibration
from service.protocol import Calibration, Hello, Imu, Pose, ProtocolError, Truth, decode, encode, parse_line, read_recording
from service.protocol.fast import IMU, POSE
from service.sim.session import SimConfig, simulate, write_recording


def test_recording_round_trips_through_the_protocol_models(tmp_path):
    sess = simulate(SimConfig(motion="pinch", hand="left", hand_motion="slow-rotation", noise="both", seed=3))
    path = tmp_path / "rec.jsonl"
    n = write_recording(sess, path)
    parsed = list(read_recording(path))
    assert len(parsed) == n
    kinds = [type(m) for _, m in parsed]
    assert kinds[0] is Hello and kinds[1] is Calibration
    assert sum(isinstance(m, IMU) for _, m in parsed) == sess.gyr.shape[0] * sess.gyr.shape[1]
    assert kinds.count(Truth) == len(sess.t)
    assert sum(isinstance(m, POSE) for _, m in parsed) == len(sess.pose_t)
    # values survive exactly
    first_imu = next(m for _, m in parsed if isinstance(m, IMU))
    assert first_imu.gyr == sess.gyr[0, 0].tolist()
    # the calibration message rebuilds the same hand
    calib = default_calibration("left").with_overrides(parsed[1][1].overrides())
    assert calib == sess.calibration


GOOD_IMU = {"type": "imu", "t": 1.0, "id": "index.1", "gyr": [0, 0, 0], "acc": [0, 9.81, 0]}


@pytest.mark.parametrize("line, code, fragment", [
    ("{not json", "invalid_json", "not valid JSON"),
    ('{"type":"imu","t":NaN,"id":"index.1","gyr":[0,0,0],"acc":[0,0,0]}', "invalid_json", "non-finite"),
    ('[1, 2]', "invalid_message", "must be a JSON object"),
    ('{"type":"wave"}', "unknown_type", "unknown message type 'wave'"),
    ('{"t": 1}', "unknown_type", "unknown message type None"),
    (json.dumps({**GOOD_IMU, "gyr": [0, 0]}), "invalid_message", "gyr"),
    (json.dumps({**GOOD_IMU, "id": "index.7"}), "invalid_message", "id"),
    (json.dumps({k: v for k, v in GOOD_IMU.items() if k != "acc"}), "invalid_message", "acc: Field required"),
    (json.dumps({**GOOD_IMU, "acc": [0, 1e400, 0]}).replace("Infinity", "1e400"), "invalid_message", "acc"),
    ('{"type":"pose","t":0,"position":[0,0,0],"orientation":[0,0,0,2]}', "non_unit_quaternion", "norm is 2"),
    ('{"type":"pose","t":0,"position":[0,0,0]}', "invalid_message", "valid pose needs both"),
    ('{"type":"hello","protocol":1,"hand":"middle"}', "invalid_message", "hand"),
])
def test_invalid_lines_are_rejected_with_a_clear_error(line, code, fragment):
    with pytest.raises(ProtocolError) as exc:
        parse_line(line)
    assert exc.value.code == code
    assert fragment in exc.value.detail


def test_unknown_fields_are_ignored_and_invalid_pose_needs_no_values():
    m = parse_line(json.dumps({**GOOD_IMU, "temperature": 31.0}))
    assert isinstance(m, Imu)
    p = parse_line('{"type":"pose","t":3.0,"valid":false}')
    assert isinstance(p, Pose) and not p.valid


def test_read_recording_names_the_bad_line(tmp_path):
    path = tmp_path / "bad.jsonl"
    path.write_text(json.dumps(GOOD_IMU) + "\n" + '{"type":"imu"}\n')
    with pytest.raises(ProtocolError, match=r"bad.jsonl:2: imu"):
        list(read_recording(path))


def test_read_recording_can_skip_bad_lines_and_say_which(tmp_path):
    path = tmp_path / "mixed.jsonl"
    path.write_text(json.dumps(GOOD_IMU) + "\n{not json\n\n" + json.dumps({**GOOD_IMU, "t": 2.0}) + "\n")
    skipped = []
    read = list(read_recording(path, on_error="skip", skipped=lambda n, err: skipped.append((n, err.code))))
    assert [(n, m.t) for n, m in read] == [(1, 1.0), (4, 2.0)]
    assert skipped == [(2, "invalid_json")]
    with pytest.raises(ValueError, match="on_error"):
        list(read_recording(path, on_error="ignore"))


@pytest.mark.parametrize("binary", [False, True])
def test_the_wire_encodings_round_trip_and_refuse_garbage(binary):
    message = {"type": "imu", "t": 1.5, "id": "index.1", "gyr": [0.1, -0.2, 0.3], "acc": [0.0, 9.81, 0.0]}
    data = encode(message, binary)
    assert isinstance(data, bytes if binary else str)
    assert decode(data, binary) == message
    with pytest.raises(ProtocolError) as err:
        decode(b"\xc1" if binary else '{"t": NaN}', binary)
    assert err.value.code == ("invalid_msgpack" if binary else "invalid_json")
