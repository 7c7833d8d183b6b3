"""Protocol v1: recordings round-trip through the models; bad input gets a clear error."""
import json

import pytest

from service.model.hand import default_calibration
from service.protocol import Calibration, Hello, Imu, Pose, ProtocolError, Truth, decode, encode, parse_line, read_recording
from service.protocol.messages import MAX_BATCH_SAMPLES
from service.protocol.wire import parse_input
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
    (json.dumps({**GOOD_IMU, "acc": [0, 1e400, 0]}).replace("Infinity", "1e400"), "invalid_json", "non-finite number at acc.1"),
    # non-finite anywhere, unknown fields included (a JSON literal that overflows a float64)
    (json.dumps({**GOOD_IMU, "note": [1, {"x": 1e400}]}).replace("Infinity", "1e400"), "invalid_json",
     "non-finite number at note.1.x"),
    (json.dumps({**GOOD_IMU, "note": -1e400}).replace("-Infinity", "-1" + "9" * 309 + ".5"), "invalid_json", "at note"),
    # booleans and strings are not numbers (pydantic would take true as 1.0 and "1.5" as 1.5)
    (json.dumps({**GOOD_IMU, "gyr": [True, 0, 0]}), "invalid_message", "gyr.0: Input should be a valid number (got true)"),
    (json.dumps({**GOOD_IMU, "t": "1.5"}), "invalid_message", "t: Input should be a valid number"),
    ('{"type":"pose","t":true,"position":[0,0,0],"orientation":[0,0,0,1]}', "invalid_message", "t: Input should be a valid number"),
    ('{"type":"pose","t":0,"position":[0,0,0],"orientation":[0,0,0,1],"valid":"yes"}', "invalid_message", "valid"),
    ('{"type":"hello","protocol":true,"hand":"right"}', "invalid_message", "protocol"),
    ('{"type":"pose","t":0,"position":[0,0,0],"orientation":[0,0,0,2]}', "non_unit_quaternion", "norm is 2"),
    ('{"type":"pose","t":0,"position":[0,0,0]}', "invalid_message", "valid pose needs both"),
    ('{"type":"hello","protocol":1,"hand":"middle"}', "invalid_message", "hand"),
])
def test_invalid_lines_are_rejected_with_a_clear_error(line, code, fragment):
    with pytest.raises(ProtocolError) as exc:
        parse_line(line)
    assert exc.value.code == code
    assert fragment in exc.value.detail


def test_a_float_literal_that_overflows_is_found_in_text_and_bytes_and_one_digit_less_is_not():
    """1.8e308 is the largest float64: a float literal of 309 digits before its point overflows to
    infinity, one of 308 nines does not (the prefilter finds digit runs by a byte table)."""
    for digits, refused in ((309, True), (308, False)):
        text = json.dumps({**GOOD_IMU, "note": 0.0}).replace("0.0}", "9" * digits + ".5}")
        for data in (text, text.encode(), text.replace('"note"', '"n\u00f6te"')):   # bytes; text beyond ASCII
            if refused:
                with pytest.raises(ProtocolError, match="non-finite number at n"):
                    parse_input(data)
            else:
                assert isinstance(parse_input(data)[1], Imu)


def test_a_batch_longer_than_the_limit_is_refused_for_its_length_before_its_samples_are_read():
    sample = {k: v for k, v in GOOD_IMU.items() if k != "type"}
    batch = {"type": "imu_batch", "samples": [sample] * MAX_BATCH_SAMPLES + [{"t": "bad"}]}
    with pytest.raises(ProtocolError) as exc:
        parse_line(json.dumps(batch))
    assert exc.value.code == "invalid_message"
    assert exc.value.detail.startswith(f"imu_batch: samples: at most {MAX_BATCH_SAMPLES} samples per batch, "
                                       f"got {MAX_BATCH_SAMPLES + 1} (got [")
    assert len(exc.value.detail) < 200                     # the samples are not all written into it
    assert len(parse_line(json.dumps({**batch, "samples": batch["samples"][:MAX_BATCH_SAMPLES]})).samples) == MAX_BATCH_SAMPLES


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


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("width", [64, 32])
def test_a_messagepack_non_finite_number_is_refused_in_an_unknown_field_too(value, width):
    import msgpack
    message = {**GOOD_IMU, "note": {"deep": [1.0, value]}}
    data = msgpack.packb(message, use_single_float=width == 32)
    with pytest.raises(ProtocolError) as err:
        decode(data, True)
    assert err.value.code == "invalid_msgpack" and "non-finite number at note.deep.1" in err.value.detail
    # finite numbers and bytes that only look like a NaN's (inside a string) pass
    fine = {**GOOD_IMU, "note": {"deep": [1.0, 0.5, "\xca\x7f\xff\xcb\x7f\xf8"]}}
    packed = msgpack.packb(fine, use_single_float=width == 32)
    assert decode(packed, True) == msgpack.unpackb(packed)


@pytest.mark.parametrize("binary", [False, True])
def test_nesting_beyond_the_limit_is_refused_in_an_unknown_field_too(binary):
    import msgpack
    from service.protocol.messages import MAX_NESTING
    from service.protocol.wire import parse_input

    def nested(levels):
        value = 1
        for _ in range(levels):
            value = {"a": value}
        return value
    at_limit = {**GOOD_IMU, "deep": nested(MAX_NESTING - 1)}         # the message is level 1
    over = {**GOOD_IMU, "deep": nested(MAX_NESTING)}
    pack = msgpack.packb if binary else json.dumps
    assert isinstance(parse_input(pack(at_limit), binary)[1], Imu)
    with pytest.raises(ProtocolError) as err:
        parse_input(pack(over), binary)
    assert err.value.code == ("invalid_msgpack" if binary else "invalid_json")
    assert f"nested deeper than {MAX_NESTING} levels at deep" + ".a" * (MAX_NESTING - 1) in err.value.detail
    # the protocol's own deepest field (a sensor's mounting, level 6) is far within it
    cal = {"type": "calibration", "fingers": {"index": {"sensors": [{"id": "index.1", "phalanx": 1,
                                                                      "mounting": [0.0, 0.0, 0.0, 1.0]}]}}}
    assert parse_input(pack(cal), binary)[1].fingers["index"].sensors[0].phalanx == 1
