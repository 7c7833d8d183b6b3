"""``protocol.parse_input`` (``protocol.fast``'s compiled structs, or ``orjson`` and pydantic, for
samples and poses) gives exactly what the standard path (the standard library's ``json`` through
``decode``, then ``parse_message``) gives: the same value and message (the same fields, values and
recorded form) for good input, the same error code and detail for bad input. ``protocol.encode`` (``orjson``
for JSON text where safe) writes the same values as the standard library, and exactly its text
wherever a ``null`` is written (NaN and infinity among them) or it refuses the message."""
import dataclasses
import enum
import json
import math

import orjson

import pytest

from service.pipeline.tracked import replay
from service.protocol import ProtocolError, decode, encode, parse_input, parse_line, parse_message
from service.protocol.fast import FastImu, FastImuBatch, FastPose
from service.protocol.messages import dump_message
from service.protocol.wire import finite_copy
from service.sim.session import SimConfig, simulate

IMU = '{"type":"imu","t":0.5,"id":"index.1","gyr":[0.1,-0.2,0.3],"acc":[0.0,9.81,0.1]%s}'
POSE = '{"type":"pose","t":0.5,"position":[0.1,1.2,0.3],"orientation":[0,0,0,1],"valid":true%s}'
HOSTILE = [
    IMU % "", POSE % "", IMU % ',"note":123456789012345678901234567890', IMU % ',"x":-9300000000000000000',
    IMU.replace("0.5", "123456789012345678901234567890") % "", IMU.replace("0.5", "1e400") % "",
    IMU.replace("0.5", "NaN") % "", IMU.replace("0.1,", "Infinity,") % "", IMU.replace("index.1", "\\ud800") % "",
    IMU.replace("index.1", "index.7") % "", IMU.replace("[0.1,-0.2,0.3]", "[0.1,-0.2]") % "",
    IMU.replace("[0.1,-0.2,0.3]", "[0.1,-0.2,1000]") % "", POSE.replace("[0,0,0,1]", "[0,0,0,2]") % "",
    POSE.replace("true", "1") % "", POSE.replace("true", "123456789012345678901") % "",
    '{"type":"imu_batch","samples":[' + IMU % "" + "," + IMU.replace("0.1,", "500,") % "" + "]}",
    '{"type":"imu_batch","samples":[' + IMU % "" + "," + IMU.replace("0.5", "0.505") % "" + "]}",
    '{"type":"hello","protocol":123456789012345678901234567890,"hand":"right"}', '{"type":"hello","protocol":1,"hand":"left"}',
    '{"type":"imu","t":0.5', "[1,2,3]", "17", '"imu"', '{"type":"nope"}', '{"type":"imu","t":0.5} trailing', "",
    '{"type":"imu","type":"pose","t":0.5,"position":[0,0,0],"orientation":[0,0,0,1],"valid":false}',
    "[" * 3000 + "]" * 3000,
    # depth bombs: an object nested 3,000 levels, and one in an unknown field of a sample
    '{"a":' * 3000 + "1" + "}" * 3000, IMU % (',"x":' + '{"a":' * 3000 + "1" + "}" * 3000),
    # what the compiled path must refuse or read exactly as pydantic does
    IMU.replace("index.1", "index.1\\n") % "", IMU.replace("index.1", "index.1\n") % "",
    IMU.replace("index.1", "ind\\u0065x.1") % "", IMU.replace('"t"', '"\\u0074"') % "",
    IMU.replace("0.5", "true") % "", IMU.replace("0.5", '"0.5"') % "", IMU.replace("0.5", "1") % "",
    IMU.replace("0.5", "-0.0") % "", IMU.replace("0.5", "1E-5") % "", IMU.replace("0.5", "0.50000000000000011102230246251565404236316680908203125") % "",
    IMU.replace("0.5", "1e10") % "", IMU.replace("0.5", "10000000001") % "", IMU.replace("0.1,", "100,") % "",
    IMU.replace("0.1,", "100.00000000000001,") % "", IMU.replace("0.1,", "-1e-400,") % "",
    IMU % ',"t":0.75', IMU.replace('"type":"imu",', "") % ',"type":"imu"', ' \n' + IMU % "" + '\n ',
    POSE.replace(',"valid":true', "") % "", POSE.replace("true", "false") % "",
    '{"type":"pose","t":0.5,"position":null,"orientation":null,"valid":false}',
    '{"type":"pose","t":0.5,"position":null,"orientation":[0,0,0,1],"valid":true}',
    POSE.replace("[0,0,0,1]", "[0,0,0,1.0009]") % "", POSE.replace("[0,0,0,1]", "[0,0,0,1.0011]") % "",
    POSE.replace("[0,0,0,1]", "[0,0,1]") % "", POSE.replace("[0.1,1.2,0.3]", "[0.1,1.2,1000.5]") % "",
    '{"type":"imu_batch","samples":[]}', '{"type":"imu_batch","samples":[' + IMU % "" + "]}",
    '{"type":"imu_batch","samples":[' + IMU.replace('"type":"imu",', "") % "" + "]}",
    '{"type":"imu_batch","samples":[' + IMU.replace('"type":"imu",', "") % ',"x":1' + "]}",
    '{"type":"imu_batch","samples":[' + ",".join([IMU.replace('"type":"imu",', "") % ""] * 4097) + "]}",
    '{"type":"imu_batch","samples":[' + IMU.replace('"type":"imu",', "") % "" + '],"samples":[]}',
    '{"type":"imu_batch","samples":{"t":1}}', '{"type":"imu_batch"}',
]


def _view(msg):
    """A message as the service reads it: its kind, each field's value with its Python type (an
    ``imu_batch``'s samples field by field), and its recorded text (``dump_message``)."""
    def fields(m, names):
        return {n: (repr(getattr(m, n)), type(getattr(m, n))) for n in names}
    kind = msg.type
    names = [n for n in type(parse_message({"type": kind, "t": 0, "id": "thumb.0", "gyr": [0] * 3, "acc": [0] * 3,
                                             "samples": [{"t": 0, "id": "thumb.0", "gyr": [0] * 3, "acc": [0] * 3}],
                                             "valid": False})).model_fields if n != "samples"] \
        if kind in ("imu", "imu_batch", "pose") else None
    if names is None:
        return ("model", msg)
    samples = [fields(s, ("t", "id", "gyr", "acc")) for s in getattr(msg, "samples", ())]
    return (kind, fields(msg, names), samples, json.dumps(dump_message(msg)))


def _standard(text):
    try:
        raw = decode(text)
        return ("ok", raw, _view(parse_message(raw)))
    except ProtocolError as err:
        return ("error", type(err).__name__, err.code, err.detail, getattr(err, "kept", None))


def _fast(text):
    try:
        raw, msg = parse_input(text)
        assert parse_line(text) is not msg and _view(parse_line(text)) == _view(msg)
        return ("ok", raw, _view(msg))
    except ProtocolError as err:
        with pytest.raises(ProtocolError) as again:
            parse_line(text)
        assert (again.value.code, again.value.detail) == (err.code, err.detail)
        return ("error", type(err).__name__, err.code, err.detail, getattr(err, "kept", None))


def test_samples_and_poses_are_read_by_the_compiled_path():
    sample = IMU.replace('"type":"imu",', "") % ""
    assert type(parse_input(IMU % "")[1]) is FastImu and type(parse_line(POSE % "")) is FastPose
    batch = parse_line('{"type":"imu_batch","samples":[' + sample + "," + sample.replace("0.5", "0.505") + "]}")
    assert type(batch) is FastImuBatch and [s.t for s in batch.samples] == [0.5, 0.505]
    assert batch.samples[1].gyr == [0.1, -0.2, 0.3] and batch.samples[1].id == "index.1"
    # what it refuses goes the pydantic way: unknown fields dropped, a pose without all its fields
    assert type(parse_line(IMU % ',"note":1')).__name__ == "Imu"
    assert type(parse_line('{"type":"pose","t":3.0,"valid":false}')).__name__ == "Pose"


@pytest.mark.parametrize("text", HOSTILE)
def test_fast_parse_equals_the_standard_path_on_hostile_input(text):
    for data in (text, text.encode("utf-8", "surrogatepass")):
        fast, standard = _fast(data), _standard(data)
        assert fast == standard
        if fast[0] == "ok":            # the same types too (an int stays an int)
            assert json.dumps(fast[1]) == json.dumps(standard[1])


def test_fast_parse_equals_the_standard_path_on_a_recording():
    session = simulate(SimConfig(motion="grasp", noise="realistic", seed=2, duration_s=0.3))
    texts = [json.dumps(m) for m in session.messages()]
    assert {json.loads(t)["type"] for t in texts} >= {"imu", "pose", "hello", "calibration", "truth"}
    for text in texts:
        assert _fast(text) == _standard(text)


def _standard_text(message):
    return json.dumps(finite_copy(message), separators=(",", ":"), allow_nan=False)


def test_fast_encode_writes_the_standard_values_of_a_recording():
    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=3, duration_s=1.5)
    outputs = list(replay(parse_message(m) for m in simulate(config).messages(include_truth=False)))
    outputs.append({"type": "gesture", "t": 1.0, "ray": None, "confidence": 1e-5})
    assert len(outputs) > 100 and any("null" in _standard_text(m) for m in outputs)
    for message in outputs:          # every one finite: written by orjson, with the standard values
        text = encode(message, False)
        assert text == orjson.dumps(message).decode()
        assert json.loads(text) == json.loads(_standard_text(message))


class _Colour(str, enum.Enum):
    RED = "red"


@dataclasses.dataclass
class _Point:
    x: float


@pytest.mark.parametrize("message", [
    {"type": "frame", "joints": {"palm": {"position": [0.0, math.nan, 1e-7], "orientation": [0.0, 0.0, 0.0, 1.0]}}},
    {"type": "gesture", "ray": {"origin": [math.inf, 0.0, 0.0], "direction": [-math.inf, 1.0, 0.0]}},
    {"type": "frame", "t": 1e-5, "status": {"age_s": None}, "fingers": {"index": {"mcp": -math.nan}}},
    {"type": "hello", "note": "caf\u00e9"},
    {"type": "x", 1: 2.0, "big": 123456789012345678901234567890},
    {"type": "x", "colour": _Colour.RED},
    # a null that is never a number beside one that is a NaN (the shortcut for the first must not hide the second)
    {"type": "frame", "gesture": {"active": None, "curl": {"index": math.nan}}},
    {"type": "gesture", "ray": None, "confidence": math.inf},
    {"type": "error", "detail": '"active":null "ray":null', "t": math.nan},
    {"type": "x", 'a"ray': math.nan, "gesture": {"active": None}},
    {"type": "x", "xactive": -math.inf, "gesture": {"active": None}},
])
def test_fast_encode_gives_the_standard_text_where_it_could_differ(message):
    assert encode(message, False) == _standard_text(message)


def test_fast_encode_refuses_what_the_standard_library_refuses():
    for message in ({"type": "x", "point": _Point(1.0)}, {"type": "x", "values": {1.5}}):
        with pytest.raises(TypeError):
            json.dumps(message)
        with pytest.raises(TypeError):
            encode(message, False)
