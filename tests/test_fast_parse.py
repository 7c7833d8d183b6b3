"""``protocol.parse_input`` (``protocol.fast``'s compiled structs, or ``orjson`` and pydantic, for
samples and poses) gives exactly what the standard path (the standard library's ``json`` through
``decode``, then ``parse_message``) gives: the same value and message (the same fields, values and
recorded form) for good input, the same error code and detail for bad input. ``protocol.encode`` (``orjson``
for JSON text where safe) writes the same values as the standard library, and exactly its text
wherever a ``null`` is written (NaN and infinity among them) or it refuses the message."""
import dataclasses
import enum
import functools
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


@functools.cache
def _recorded_outputs() -> tuple:
    """The frames and gestures of a simulated 1.5 s (simulated and replayed once for this file's tests)."""
    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=3, duration_s=1.5)
    return tuple(replay(parse_message(m) for m in simulate(config).messages(include_truth=False)))


def test_fast_encode_writes_the_standard_values_of_a_recording():
    outputs = list(_recorded_outputs())
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


def _decoded(data, binary=False):
    """``decode``'s answer as comparable text: the value's ``repr`` (an int is not a float, ``-0.0``
    is not ``0.0``, the keys' order counts) or the error's class, code and detail."""
    try:
        return ("ok", repr(decode(data, binary)))
    except ProtocolError as err:
        return ("error", err.code, err.detail)
    except (TypeError, ValueError) as err:
        return ("raised", type(err).__name__, str(err))


def _both_ways(data, binary=False):
    """``decode``'s answer with ``msgspec`` first, and the standard path's alone (``json``/``msgpack``
    and a walk of the value), and whether ``msgspec`` read it."""
    from unittest import mock

    from service.protocol import wire
    fast_read = wire._fast_decode(data, binary) is not wire._UNREAD
    fast = _decoded(data, binary)
    with mock.patch.object(wire, "_fast_decode", lambda data, binary: wire._UNREAD):
        standard = _decoded(data, binary)
    return fast, standard, fast_read


def _nest(levels, leaf="1", open_="[", close="]"):
    return open_ * levels + leaf + close * levels


_FRAME_START = '{"type":"frame","t":0.5,"seq":3,"hand":"left","status":{"age_s":null}'
DECODE_HOSTILE = [
    # integers beyond 64 bits stay integers; beyond the standard library's digit limit they are refused
    '{"seq":123456789012345678901234567890}', '[18446744073709551615,18446744073709551616,-9223372036854775809]',
    "[" + "7" * 4300 + "]", "[" + "7" * 4301 + "]", "-" + "7" * 4301,
    # non-finite numbers, as literals and by overflow; underflow to zero keeps its sign
    '{"t":NaN}', '{"t":Infinity}', "[-Infinity]", '{"t":1e400}', "[-1e400]", "[1.7976931348623159e308]",
    "[1.7976931348623157e308,-1e-400,1e-400,4.9e-324,2.4e-324]", "[1" + "0" * 400 + ".0]",
    "[0.50000000000000011102230246251565404236316680908203125,1E5,1e+5,-0,-0.0,1.0,1]",
    # strings: escapes, lone surrogates (escaped and not), non-ASCII, control characters
    '["\\ud800"]', '{"hand":"\\udc00x"}', '["\\ud83d\\ude00","\\u00e9","é","\\/","\\u0000"]', '["\ud800"]',
    '["a\tb"]', '["\x7f"]', '{"detail":"\\"quoted\\" \\\\ [[[{{"}', '{"k\\"ey":"\\\\"}',
    # keys: a duplicate keeps its first place and its last value
    '{"a":1,"b":2,"a":3}', '{"type":"frame","type":"gesture"}',
    # a type that is no string (no message's: the value, or the standard path's error where msgspec refuses)
    '{"type":[]}', '{"type":{"a":1}}', '{"type":[],"x":"\\ud800"}', '{"type":{},"t":NaN}',
    # text that is not one JSON value
    "", " ", "[1,2,]", "[1]x", "1 2", "tru", "01", "{1:2}", '\ufeff{"a":1}',
    # nesting: at the limit, one beyond it at the root, in a frame's field (refused with the path) and
    # in a list root or a sample's known field (not refused: validation refuses those), far beyond
    _FRAME_START + ',"x":' + _nest(15) + "}", _FRAME_START + ',"x":' + _nest(16) + "}",
    _FRAME_START + ',"x":' + _nest(15, "1", '{"a":', "}") + "}", _FRAME_START + ',"x":' + _nest(16, "1", '{"a":', "}") + "}",
    _FRAME_START + ',"x":' + _nest(16, "[]") + "}", _nest(16), _nest(17), _nest(3000), _nest(3000, "1", '{"a":', "}"),
    _FRAME_START + ',"x":' + _nest(5, "[]") + "}", _FRAME_START + ',"x":' + _nest(6, "[]") + "}", _nest(7), _nest(8),
    '{"type":"imu","t":0.5,"id":"index.1","gyr":' + _nest(17, "0.1") + ',"acc":[0,0,1]}',
    '{"x":"]]]]]]]]]]]]]]]]","y":' + _nest(16) + "}", '{"x":"[[[[[[[[[[[[[[[[","y":' + _nest(14) + "}",
]


@pytest.mark.parametrize("text", DECODE_HOSTILE)
def test_fast_decode_equals_the_standard_path_on_hostile_json(text):
    for data in (text, text.encode("utf-8", "surrogatepass")):
        fast, standard, _ = _both_ways(data)
        assert fast == standard


def test_fast_decode_reads_what_it_may_and_leaves_the_rest_to_the_standard_path():
    from service.protocol import wire
    read = {text: _both_ways(text)[2] for text in DECODE_HOSTILE}
    assert read['{"seq":123456789012345678901234567890}'] and read['{"a":1,"b":2,"a":3}']
    # nested to FAST_LEVELS (protocol v1's deepest is 6) by msgspec, deeper the standard way
    assert read[_FRAME_START + ',"x":' + _nest(wire.FAST_LEVELS - 2, "[]") + "}"]
    assert not read[_FRAME_START + ',"x":' + _nest(wire.FAST_LEVELS - 1, "[]") + "}"]
    for refused in ('{"t":NaN}', '{"t":1e400}', '["\\ud800"]', '["\ud800"]', "[" + "7" * 4301 + "]",
                    _FRAME_START + ',"x":' + _nest(16) + "}", _nest(17), '\ufeff{"a":1}'):
        assert not read[refused], refused
    # the standard library reads UTF-16 and a byte order mark in bytes, and a bytearray; refuses a memoryview
    for data in ('{"a":[1,"é"]}'.encode("utf-16"), b'\xef\xbb\xbf{"a":1}', bytearray(b'{"a":1}'), memoryview(b'{"a":1}')):
        fast, standard, fast_read = _both_ways(data)
        assert fast == standard and not fast_read
    assert _decoded(memoryview(b"1"))[0] == "raised"


def _packed(value, **options):
    import msgpack
    return msgpack.packb(value, **options)


DECODE_HOSTILE_PACKED = [
    _packed({"type": "frame", "t": 0.5, "seq": 2 ** 64 - 1, "x": -2 ** 63, "hand": "é", "ok": [True, None]}),
    _packed({"t": 1.5}, use_single_float=True), _packed([1.5, -0.0]),
    _packed({"t": float("nan")}), _packed({"a": [0.0, float("inf")]}, use_single_float=True), _packed([-float("inf")]),
    _packed({"note": "\xca\x7f\xff\xcb\x7f\xf8"}), _packed({1: 2}), _packed({None: 2}), _packed({"a": b"x"}),
    _packed({b"k": 1}), b"\xd6\xff\x00\x00\x00\x01", b"\x82\xa1a\x01\xa1a\x02", _packed({"a": 1}) + b"\x01",
    b"\xa2\xff\xfe", b"", b"\xc1", b"\x91" * 15 + b"\x90", b"\x91" * 16 + b"\x90", b"\x91" * 6 + b"\x90", b"\x91" * 7 + b"\x90",
    _packed({"type": "frame", "x": json.loads(_nest(15))}), _packed({"type": "frame", "x": json.loads(_nest(16))}),
    _packed({"type": "frame", "x": json.loads(_nest(16, "1", '{"a":', "}"))}),
]


@pytest.mark.parametrize("data", DECODE_HOSTILE_PACKED)
def test_fast_decode_equals_the_standard_path_on_hostile_messagepack(data):
    fast, standard, _ = _both_ways(data, binary=True)
    assert fast == standard


def test_fast_decode_reads_the_services_own_messages_and_gives_the_standard_values():
    outputs = list(_recorded_outputs()[::4])         # frames alike: every fourth of 1.5 s
    outputs += [{"type": "gesture", "t": 1.0, "hand": "right", "gesture": "pinch", "state": "start", "confidence": 0.93,
                 "ray": {"origin": [0.1, 1.2, -0.3], "direction": [0.0, 0.0, -1.0]}},
                {"type": "gesture", "t": 1.1, "ray": None, "confidence": 1e-5},
                {"type": "error", "code": "invalid_json", "detail": 'not valid JSON: "x" \\ [['},
                {"type": "hello", "protocol": 1, "session": "s", "server": "fingertrack"}, {"type": "sync", "id": 7}]
    assert {m["type"] for m in outputs} >= {"frame", "gesture"} and len(outputs) > 30
    from unittest import mock

    from service.protocol import wire

    def never(*_args, **_kwargs):
        raise AssertionError("the standard path read one of the service's own messages")
    for message in outputs:
        for binary in (False, True):
            data = encode(message, binary)
            fast, standard, fast_read = _both_ways(data, binary)
            assert fast == standard and fast_read
            with mock.patch.object(wire.json, "loads", never), mock.patch.object(wire.msgpack, "unpackb", never):
                assert repr(decode(data, binary)) == fast[1]          # decode itself takes the fast path


def test_a_type_that_is_no_string_is_an_unknown_type_not_a_crash():
    for text in ('{"type":[]}', '{"type":{"a":1}}', '{"type":[],"x":"\\ud800"}'):
        for data in (text, text.encode("utf-8", "surrogatepass")):
            with pytest.raises(ProtocolError) as err:
                parse_input(data)
            assert err.value.code == "unknown_type"
