"""Protocol-v1 message models (pydantic) and the single place where raw input is validated.

Source messages (what gloves and trackers send; ``outgoing`` has what the service sends).

Rules (DESIGN.md "Wire protocol v1"): every message is a JSON object with a ``type``; unknown fields
are ignored (and dropped: a message is recorded as its validated model, ``dump_message``); unknown
types, missing fields, non-finite numbers, wrong shapes, non-unit quaternions and numbers outside
their physical range raise ``ProtocolError`` with a ``code`` and a ``detail`` naming the field, the
value and what was expected. Callers turn it into an ``error`` reply and drop the message.

Physical ranges (every number is checked before it reaches a filter):

* times ``|t| <= MAX_TIME_S`` (1e10 s: any monotonic or Unix clock in seconds; float64 then still
  resolves 2 us, far below one tick at the highest output rate);
* gyroscope ``|gyr_i| <= MAX_GYRO_RAD_S`` (100 rad/s, 1.4 x the largest MEMS range of 4000 deg/s);
* accelerometer ``|acc_i| <= MAX_ACC_M_S2`` (2000 m/s^2, 1.25 x the 160 g of the highest-range
  MEMS parts; hand impacts stay far below);
* positions of the hand ``|p_i| <= MAX_POSITION_M`` (1000 m: a venue, in stage space);
* calibration: phalanx lengths ``MIN_PHALANX_M .. MAX_PHALANX_M`` (5-120 mm, adult and child hands
  with margin), finger bases within ``MAX_BASE_OFFSET_M`` (0.25 m) of the metacarpus frame, sensor
  offsets along the phalanx 0..0.2 m.
"""
from __future__ import annotations

import json
import math
from typing import Annotated, Literal, Union

from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, Strict, TypeAdapter, ValidationError, field_validator,
                      model_validator)

PROTOCOL_VERSION = 1
QUATERNION_NORM_TOLERANCE = 1e-3
"""A quaternion is accepted as unit when ``|‖q‖ - 1| <= 1e-3``."""
MAX_BATCH_SAMPLES = 4096
"""Largest ``imu_batch`` accepted, samples."""
MAX_NESTING = 16
"""Deepest nesting of objects and arrays in a message (the message itself is level 1); protocol v1's
deepest, a calibration's sensor mounting, is at level 6. Deeper values, in unknown fields too, are refused."""

SENSOR_ID_PATTERN = r"^(thumb|index|middle|ring|little)\.[0-2]$"
IMU_ID_PATTERN = r"^((thumb|index|middle|ring|little)\.[0-2]|metacarpus)$"
"""An ``imu`` sample comes from a finger sensor or from the optional IMU on the back of the hand."""

MAX_TIME_S = 1e10
MAX_GYRO_RAD_S = 100.0
MAX_ACC_M_S2 = 2000.0
MAX_POSITION_M = 1000.0
MIN_PHALANX_M = 0.005
MAX_PHALANX_M = 0.12
MAX_BASE_OFFSET_M = 0.25


def _not_bool(value):
    if isinstance(value, bool):
        raise ValueError(f"expected an integer, got {str(value).lower()}")
    return value


Num = Annotated[float, Strict()]
"""A number: an integer or a float, never ``true``/``false`` or a string (which pydantic would otherwise
turn into 1.0/0.0 or parse)."""
Int = Annotated[int, BeforeValidator(_not_bool)]
"""An integer (``1.0`` is taken as 1), never ``true``/``false``."""


def _bounded_vec3(limit: float, unit: str):
    return Annotated[list[Annotated[Num, Field(ge=-limit, le=limit)]],
                     Field(min_length=3, max_length=3, description=f"[x, y, z], {unit}, each within +-{limit:g}")]


Vec3 = Annotated[list[Num], Field(min_length=3, max_length=3)]
Time = Annotated[Num, Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description="source clock, s")]
GyroVec = _bounded_vec3(MAX_GYRO_RAD_S, "rad/s")
AccVec = _bounded_vec3(MAX_ACC_M_S2, "m/s^2")
PositionVec = _bounded_vec3(MAX_POSITION_M, "m")
BaseOffsetVec = _bounded_vec3(MAX_BASE_OFFSET_M, "m")
Quat = Annotated[list[Num], Field(min_length=4, max_length=4, description="[x, y, z, w], unit norm")]


class ProtocolError(ValueError):
    """Invalid input at the protocol edge. ``code`` is machine-readable, ``detail`` human-readable."""

    def __init__(self, code: str, detail: str):
        super().__init__(f"{code}: {detail}")
        self.code = code
        self.detail = detail


def _check_unit(q: list[float] | None, name: str) -> list[float] | None:
    if q is None:
        return q
    if len(q) == 4:                         # (every quaternion: the sum below without its generator, in its order)
        x, y, z, w = q
        norm = math.sqrt(x * x + y * y + z * z + w * w)
    else:
        norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ValueError(f"{name} must be a unit quaternion [x, y, z, w]; its norm is {norm:.6g}")
    return q


class _Message(BaseModel):
    model_config = ConfigDict(extra="ignore", allow_inf_nan=False, frozen=True)


class Hello(_Message):
    type: Literal["hello"]
    protocol: Int
    hand: Literal["right", "left"]
    source: str = ""


class BaseFrame(_Message):
    position: BaseOffsetVec | None = None
    orientation: Quat | None = None

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q):
        return _check_unit(q, "orientation")


class SensorCalibration(_Message):
    id: Annotated[str, Field(pattern=SENSOR_ID_PATTERN)]
    phalanx: Annotated[int, Field(ge=0, le=2), BeforeValidator(_not_bool)]
    offset: Annotated[Num, Field(ge=0.0, le=0.2)] | None = None
    mounting: Quat = [0.0, 0.0, 0.0, 1.0]

    @field_validator("mounting")
    @classmethod
    def _unit(cls, q):
        return _check_unit(q, "mounting")


class FingerCalibration(_Message):
    lengths: Annotated[list[Annotated[Num, Field(ge=MIN_PHALANX_M, le=MAX_PHALANX_M)]], Field(min_length=2, max_length=3)] | None = None
    base: BaseFrame | None = None
    coupling: Annotated[Num, Field(ge=0.0, le=2.0)] | None = None
    sensors: list[SensorCalibration] | None = None


class MetacarpusCalibration(_Message):
    """Where the optional IMU on the back of the hand (sensor id ``metacarpus``) sits: its position
    and the rotation of its frame in the metacarpus frame; unset fields keep the default (the middle
    of the back of the hand, axes along the metacarpus frame's)."""

    position: BaseOffsetVec | None = None
    mounting: Quat | None = None

    @field_validator("mounting")
    @classmethod
    def _unit(cls, q):
        return _check_unit(q, "mounting")


class Calibration(_Message):
    type: Literal["calibration"]
    fingers: dict[Literal["thumb", "index", "middle", "ring", "little"], FingerCalibration] = {}
    metacarpus: MetacarpusCalibration | None = None

    def overrides(self) -> dict:
        """The ``fingers`` object with unset fields removed, for ``HandCalibration.with_overrides``."""
        return self.model_dump(exclude_none=True)["fingers"]


class Pose(_Message):
    type: Literal["pose"]
    t: Time
    position: PositionVec | None = None
    orientation: Quat | None = None
    valid: Annotated[bool, Strict()] = True

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q):
        return _check_unit(q, "orientation")

    @model_validator(mode="after")
    def _complete_when_valid(self):
        if self.valid and (self.position is None or self.orientation is None):
            raise ValueError("a valid pose needs both 'position' and 'orientation' (send \"valid\": false when occluded)")
        return self


class ImuSample(_Message):
    t: Time
    id: Annotated[str, Field(pattern=IMU_ID_PATTERN)]
    gyr: GyroVec
    acc: AccVec


class Imu(ImuSample):
    type: Literal["imu"]


class ImuBatch(_Message):
    type: Literal["imu_batch"]
    samples: Annotated[list[ImuSample], Field(min_length=1, max_length=MAX_BATCH_SAMPLES)]


class Sync(_Message):
    """A barrier: the service answers ``{"type": "sync", "id": <same id>}`` once it has handled every
    message received before it on that connection. Never recorded, never seen by the pipeline."""

    type: Literal["sync"]
    id: Annotated[int, Field(ge=0, le=2**53), BeforeValidator(_not_bool)]


FINGER_JOINTS = {"thumb": ("mcp", "ip"), "index": ("mcp", "pip", "dip"), "middle": ("mcp", "pip", "dip"),
                 "ring": ("mcp", "pip", "dip"), "little": ("mcp", "pip", "dip")}
"""Joint names per finger, as in ``frame`` messages."""


class ReferencePose(_Message):
    """The hand held a known configuration from ``t0`` to ``t1`` (source clock, s): ``"flat"`` (every
    joint at 0: fingers straight, e.g. the hand laid flat on a table) or joint angles in radians per
    finger (``{"index": {"mcp": 0.1, "pip": 0.2, "dip": 0.2}}``; every joint of a named finger, fingers
    not named are not constrained). Sent by the glove app once the hold is over (at or after ``t1``);
    the estimators take it as a measurement of the configuration at ``t1``."""

    type: Literal["reference_pose"]
    t0: Time
    t1: Time
    pose: Union[Literal["flat"], dict[Literal["thumb", "index", "middle", "ring", "little"], dict[str, Num]]]

    @model_validator(mode="after")
    def _consistent(self):
        if self.t1 < self.t0:
            raise ValueError(f"t1 ({self.t1}) must not be before t0 ({self.t0})")
        if isinstance(self.pose, dict):
            if not self.pose:
                raise ValueError("pose: name at least one finger, or use \"flat\"")
            for finger, joints in self.pose.items():
                expected = FINGER_JOINTS[finger]
                if set(joints) != set(expected):
                    raise ValueError(f"pose.{finger}: expected the joints {list(expected)}, got {sorted(joints)}")
                for name, angle in joints.items():
                    if abs(angle) > math.pi:
                        raise ValueError(f"pose.{finger}.{name}: an angle in radians within ±pi, got {angle}")
        return self

    def joint_angles(self, fingers) -> dict[str, list[float]]:
        """Joint angles (rad) per finger in joint order, for the fingers the pose constrains among
        ``fingers`` (names)."""
        if self.pose == "flat":
            return {f: [0.0] * len(FINGER_JOINTS[f]) for f in fingers}
        return {f: [j[n] for n in FINGER_JOINTS[f]] for f, j in self.pose.items() if f in fingers}


class Truth(_Message):
    """Simulator ground truth; the pipeline ignores it."""

    type: Literal["truth"]
    t: Time
    fingers: dict[str, dict[str, Num]]
    position: Vec3
    orientation: Quat


SourceMessage = Annotated[Union[Hello, Calibration, Pose, Imu, ImuBatch, ReferencePose, Truth, Sync], Field(discriminator="type")]
_ADAPTER: TypeAdapter = TypeAdapter(SourceMessage)
SOURCE_TYPES = ("hello", "calibration", "pose", "imu", "imu_batch", "reference_pose", "truth", "sync")


def _shown(value) -> str:
    """The first 60 characters of a refused value as JSON (``{...}`` for an object), without writing
    all of a long list: the first items alone give them when they fill the 60 characters."""
    if isinstance(value, dict):
        return "{...}"
    if isinstance(value, list) and len(value) > 8:
        head = json.dumps(value[:8], default=str)
        if len(head) > 60:                    # the same first 60 characters as the whole list's text
            return head[:60]
    return json.dumps(value, default=str)[:60]


def _describe(err: ValidationError) -> str:
    parts = []
    for e in err.errors(include_url=False)[:3]:
        loc = ".".join(str(p) for p in e["loc"][1:]) or "message"
        parts.append(f"{loc}: {e['msg']} (got {_shown(e.get('input'))})")
    more = len(err.errors()) - 3
    return "; ".join(parts) + (f"; and {more} more" if more > 0 else "")


class SamplesRefused(ProtocolError):
    """Some samples of an ``imu_batch`` are invalid: they are refused (``refused``: their indexes in
    ``samples``, in order), the others are kept as ``kept``, a valid ``ImuBatch`` to process. The
    reply is the ``invalid_samples`` error naming the refused samples; a caller that handles only
    ``ProtocolError`` refuses the whole batch instead."""

    def __init__(self, kept: "ImuBatch", refused: list[int], detail: str):
        super().__init__("invalid_samples", detail)
        self.kept = kept
        self.refused = refused


def _refuse_samples(obj: dict, err: ValidationError) -> SamplesRefused | None:
    """The per-sample rule of ``imu_batch``: when every problem lies inside single samples and at
    least one sample is valid, the valid ones are kept; ``None`` when the batch as a whole is bad."""
    samples = obj.get("samples")
    bad: set[int] = set()
    for e in err.errors(include_url=False):
        loc = e["loc"]
        if len(loc) < 3 or loc[:2] != ("imu_batch", "samples") or not isinstance(loc[2], int):
            return None                       # e.g. no samples, too many, or a problem outside them
        bad.add(loc[2])
    if not isinstance(samples, list) or len(bad) >= len(samples):
        return None
    try:
        kept = _ADAPTER.validate_python({**obj, "samples": [x for i, x in enumerate(samples) if i not in bad]})
    except ValidationError:
        return None
    refused = sorted(bad)
    shown = ", ".join(map(str, refused[:10])) + (", ..." if len(refused) > 10 else "")
    return SamplesRefused(kept, refused, f"imu_batch: {len(refused)} of {len(samples)} samples refused (samples "
                                         f"{shown}), the other {len(samples) - len(refused)} processed: {_describe(err)}")


def parse_message(obj: object) -> Hello | Calibration | Pose | Imu | ImuBatch | ReferencePose | Truth | Sync:
    """Validate a decoded JSON value as a source message; raises ``ProtocolError``, or its
    ``SamplesRefused`` for an ``imu_batch`` whose invalid samples are refused one by one while its
    valid ones are kept (``err.kept``)."""
    if not isinstance(obj, dict):
        raise ProtocolError("invalid_message", f"a message must be a JSON object, got {type(obj).__name__}")
    kind = obj.get("type")
    if kind not in SOURCE_TYPES:
        raise ProtocolError("unknown_type", f"unknown message type {kind!r}; expected one of {list(SOURCE_TYPES)}")
    if kind == "imu_batch" and type(samples := obj.get("samples")) is list and len(samples) > MAX_BATCH_SAMPLES:
        # refused before its samples are validated: a batch too long costs no more than a valid one (it
        # cost 45 times as much, 0.54 s for 4100 samples: pydantic validates every sample first)
        raise ProtocolError("invalid_message", f"imu_batch: samples: at most {MAX_BATCH_SAMPLES} samples per "
                                               f"batch, got {len(samples)} (got {_shown(samples)})")
    try:
        return _ADAPTER.validate_python(obj)
    except ValidationError as err:
        if kind == "imu_batch" and (partial := _refuse_samples(obj, err)) is not None:
            raise partial from None
        quaternion = any("unit quaternion" in e["msg"] for e in err.errors(include_url=False, include_input=False))
        code = "non_unit_quaternion" if quaternion else "invalid_message"
        raise ProtocolError(code, f"{kind}: {_describe(err)}") from None


def dump_message(msg: _Message) -> dict:
    """A validated message as a JSON-safe dict with only its known fields, as the client set them:
    what a recording stores, so that a replay parses exactly what was processed live."""
    if isinstance(msg, _Message):
        return msg.model_dump(mode="json", exclude_unset=True)
    return msg.dump()                          # a sample or pose read by ``fast``: the same dict
