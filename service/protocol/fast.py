"""The per-sample messages (``imu``, ``imu_batch``, ``pose``) read straight from JSON text into compiled
``msgspec`` structs, validated while they are decoded: no intermediate dict, no pydantic model per
sample (about a quarter of the pydantic path's CPU time for a tick's ``imu_batch``).

The structs are the same messages as ``messages.Imu``, ``ImuBatch``, ``ImuSample`` and ``Pose``: the same
fields and values (every number a float, as pydantic makes them), the same ranges and rules, and each
is registered as a virtual subclass of its pydantic model, so ``isinstance(msg, ImuBatch)`` holds for
either. This path only ever accepts: whatever it refuses (other message types, unknown fields, a
missing optional field, a value pydantic would coerce such as ``"0.5"`` for a number, and every bad
message) goes through the pydantic path, whose message or ``ProtocolError`` is the answer
(``wire.parse_input``). Anything it accepts, the pydantic path accepts with equal values
(``tests/test_fast_parse.py`` checks both on hostile and recorded input):

* numbers are range-checked as in ``messages`` (inclusive bounds), so NaN, infinity and integers
  beyond 64 bits (which JSON readers may read differently) never pass;
* sensor ids are the exact strings ``messages.IMU_ID_PATTERN`` matches (an enumeration: a regular
  expression's ``$`` would let a trailing newline through);
* booleans are JSON ``true``/``false`` only; unknown fields are refused (the pydantic path drops them,
  so that a recording holds only what was validated);
* a ``pose`` is read here only with all of ``position``, ``orientation`` and ``valid`` present (then
  ``dump_message`` writes every field, as pydantic's dump of the fields set does); its quaternion is
  checked by the same function as the model's, and a valid pose needs both position and orientation.
"""
from __future__ import annotations

from typing import Annotated, ClassVar, Literal, Union

import msgspec
from msgspec import Meta

from .messages import (
    MAX_ACC_M_S2, MAX_BATCH_SAMPLES, MAX_GYRO_RAD_S, MAX_POSITION_M, MAX_TIME_S, Imu, ImuBatch, Pose,
    _check_unit,
)

_FINGERS = ("thumb", "index", "middle", "ring", "little")
_IMU_IDS = tuple(f"{f}.{i}" for f in _FINGERS for i in range(3)) + ("metacarpus",)
ImuId = Literal[_IMU_IDS]        # every string of messages.IMU_ID_PATTERN, exactly


def _vec3(limit: float):
    return Annotated[list[Annotated[float, Meta(ge=-limit, le=limit)]], Meta(min_length=3, max_length=3)]


_Time = Annotated[float, Meta(ge=-MAX_TIME_S, le=MAX_TIME_S)]
_Gyro = _vec3(MAX_GYRO_RAD_S)
_Acc = _vec3(MAX_ACC_M_S2)
_Position = _vec3(MAX_POSITION_M)
_Quat = Annotated[list[float], Meta(min_length=4, max_length=4)]
_OPTIONS = {"frozen": True, "forbid_unknown_fields": True, "gc": False}


class FastImuSample(msgspec.Struct, **_OPTIONS):
    t: _Time
    id: ImuId
    gyr: _Gyro
    acc: _Acc

    def dump(self) -> dict:
        return {"t": self.t, "id": self.id, "gyr": list(self.gyr), "acc": list(self.acc)}


class FastImu(msgspec.Struct, tag_field="type", tag="imu", **_OPTIONS):
    type: ClassVar[str] = "imu"
    t: _Time
    id: ImuId
    gyr: _Gyro
    acc: _Acc

    def dump(self) -> dict:
        """What ``messages.dump_message`` gives for the same message validated by pydantic: every
        field (all were set), in the model's order of fields (``Imu``'s ``type`` last)."""
        return {"t": self.t, "id": self.id, "gyr": list(self.gyr), "acc": list(self.acc), "type": "imu"}


class FastImuBatch(msgspec.Struct, tag_field="type", tag="imu_batch", **_OPTIONS):
    type: ClassVar[str] = "imu_batch"
    samples: Annotated[list[FastImuSample], Meta(min_length=1, max_length=MAX_BATCH_SAMPLES)]

    def dump(self) -> dict:
        return {"type": "imu_batch", "samples": [s.dump() for s in self.samples]}


class FastPose(msgspec.Struct, tag_field="type", tag="pose", **_OPTIONS):
    type: ClassVar[str] = "pose"
    t: _Time
    position: Union[_Position, None]
    orientation: Union[_Quat, None]
    valid: bool

    def __post_init__(self):
        _check_unit(self.orientation, "orientation")          # a ValueError: refused (the pydantic path answers)
        if self.valid and (self.position is None or self.orientation is None):
            raise ValueError("a valid pose needs both 'position' and 'orientation'")

    def dump(self) -> dict:
        return {"type": "pose", "t": self.t, "position": None if self.position is None else list(self.position),
                "orientation": None if self.orientation is None else list(self.orientation), "valid": self.valid}


IMU_BATCH = (ImuBatch, FastImuBatch)
IMU = (Imu, FastImu)
POSE = (Pose, FastPose)
"""Either class of each message, for ``isinstance``."""
FAST_TYPES = (FastImu, FastImuBatch, FastPose)
_DECODER = msgspec.json.Decoder(Union[FAST_TYPES])


def read(data: str | bytes) -> FastImu | FastImuBatch | FastPose | None:
    """The message of JSON text ``data`` if it is a valid ``imu``, ``imu_batch`` or ``pose`` this path
    reads (see the module's text), else ``None`` (the pydantic path then gives the message or error)."""
    try:
        return _DECODER.decode(data)
    # msgspec.ValidationError is a DecodeError; a RecursionError is a depth bomb in an unknown field
    # (msgspec skips its value recursively)
    except (msgspec.DecodeError, ValueError, RecursionError):
        return None
