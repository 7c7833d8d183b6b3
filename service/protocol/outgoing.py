"""Protocol-v1 messages the service sends (DESIGN.md "Wire protocol v1", service -> client).

The service builds these messages and clients read them: the hello reply, the ``sync`` reply,
``frame``, ``gesture`` and ``error``. The models are the published contract: ``service.protocol.schema``
turns them into the JSON Schema documents under ``docs/schema/``, served at ``/v1/schema``. Like
every protocol-v1 reader, they ignore unknown fields, so a field added later (always optional) does
not break an older client.

Each model has a ``TypedDict`` twin (``...Dict``, written under it) that spells the same fields in the
same order: what the service actually builds and sends is a plain dict typed with it, so the hot path
pays nothing for validation (a ``TypedDict`` is only an annotation) and a type checker holds every
construction site to the contract. A test keeps each twin equal to its model (names, order, which
fields are always present); the service's tests validate everything it sends against the schema.

Units: SI (seconds, metres, radians); quaternions ``[x, y, z, w]``; positions and directions in the
world frame (OpenXR stage space, +Y up).
"""

from typing import Annotated, Literal, Optional, Union

from pydantic import Field, TypeAdapter, ValidationError
from typing_extensions import NotRequired, TypedDict

from .messages import FINGER_JOINTS, PROTOCOL_VERSION, SENSOR_ID_PATTERN, ProtocolError, Quat, Vec3, _describe, _Message

FINGERS = tuple(FINGER_JOINTS)
JOINT_NAMES: tuple[str, ...] = (
    "palm", "wrist", "thumb_metacarpal", "thumb_proximal", "thumb_distal", "thumb_tip",
    *(f"{f}_{j}" for f in FINGERS[1:] for j in ("metacarpal", "proximal", "intermediate", "distal", "tip")),
)
"""The 26 joints of OpenXR ``XR_EXT_hand_tracking`` in the enum's order (the protocol's copy of
``service.model.openxr.JOINT_NAMES``: the protocol is a ground floor and imports no model; a test
keeps the two equal)."""
FingerName = Literal[FINGERS]  # type: ignore[valid-type]
GestureName = Literal["point", "grasp", "pinch", "open"]
EstimatorMode = Literal["slow", "fast", "fused", "none"]
Unit = Annotated[float, Field(ge=0.0, le=1.0)]

ERROR_CODES: dict[str, str] = {
    "invalid_json": "the text is not valid JSON (non-finite literals such as NaN included)",
    "invalid_msgpack": "the binary message is not valid MessagePack",
    "invalid_message": "a field is missing, has the wrong type or shape, or is out of range",
    "unknown_type": "the message's type is not a source message type",
    "non_unit_quaternion": "a quaternion's norm differs from 1 by more than 1e-3",
    "message_too_large": "the message exceeds the service's size limit",
    "rate_limited": "the source sends more messages per second than allowed",
    "unsupported_protocol": "the hello names a protocol version the service does not speak",
    "expected_hello": "a source message came before the hello",
    "time_backwards": "a sample is older than what the session has already processed",
    "duplicate": "the same sensor and time was already received",
    "unknown_sensor": "a sample of a sensor id the session's calibration does not place",
    "overloaded": "the service cannot keep up with this source: its backlog of received, unprocessed messages is "
                  "full, so the data message was dropped (counted in the frame status; send less, or pace with sync)",
    "invalid_samples": "some samples of an imu_batch are invalid or out of range: those (listed in 'samples') are "
                       "dropped, the batch's other samples are processed",
    "internal_error": "processing the message failed inside the service (a defect; logged); the message is dropped",
    "clock_step": "a notice, the message is processed: its time jumps by more than the clock step (the pipeline's "
                  "clock_step_s, 0.5 s) forward or back from the newest sample, so it starts a new clock (the samples "
                  "still waiting are discarded, the estimates restart from the current ones; counted in the frame "
                  "status as clock_steps)",
}
"""Every error code the service sends, with its meaning."""


class ServerHello(_Message):
    """The service's reply to a source's ``hello`` on ``/v1/ingest``, and the first message on
    ``/v1/stream``."""

    type: Literal["hello"]
    protocol: int = Field(description=f"protocol version the service speaks ({PROTOCOL_VERSION})")
    server: str = Field("", description="server name")
    session: str = Field("", description="the session this connection belongs to")
    waiting: Optional[bool] = Field(None, description="on /v1/stream: true while no source has created the session "
                                    "yet (the subscriber waits for it and gets its frames from its start; it creates nothing)")


class ServerHelloDict(TypedDict):
    type: Literal["hello"]
    protocol: int
    server: str
    session: str
    waiting: NotRequired[bool]

class SyncReply(_Message):
    """The answer to a source's ``sync``: every message the source sent before it has been handled."""

    type: Literal["sync"]
    id: Annotated[int, Field(ge=0, le=2**53)] = Field(description="the id of the source's sync")


class SyncReplyDict(TypedDict):
    type: Literal["sync"]
    id: int

class ErrorMessage(_Message):
    """A source message was refused and dropped (with ``invalid_samples``: only the samples listed);
    the connection and the session go on."""

    type: Literal["error"] = "error"
    code: str = Field(description="machine-readable reason, one of: " + ", ".join(ERROR_CODES))
    detail: str = Field(description="human-readable reason naming the field, the value and what was expected")
    samples: Optional[list[Annotated[int, Field(ge=0)]]] = Field(
        None, description="invalid_samples: the indexes (from 0) in the imu_batch's samples of the samples refused; "
                          "the other samples of the batch were processed")


class ErrorMessageDict(TypedDict):
    type: Literal["error"]
    code: str
    detail: str
    samples: NotRequired[list[int]]


class FingerAngles(_Message):
    """Joint angles of one finger, rad, flexion positive (DESIGN.md "Conventions")."""

    mcp: float = Field(description="metacarpophalangeal joint angle phi_0, rad")
    pip: Optional[float] = Field(None, description="proximal interphalangeal joint angle phi_1, rad (long fingers)")
    dip: Optional[float] = Field(None, description="distal interphalangeal joint angle phi_2, rad (long fingers)")
    ip: Optional[float] = Field(None, description="interphalangeal joint angle, rad (thumb)")
    mode: EstimatorMode = Field(description="what the estimator relied on: slow (vector observation), fast (gyro "
                                            "integration), fused (a filter using both), none (no information, held)")


class FingerAnglesDict(TypedDict):
    mcp: float
    pip: NotRequired[float]
    dip: NotRequired[float]
    ip: NotRequired[float]
    mode: str

class JointPose(_Message):
    """One OpenXR hand joint in the world frame: -Z toward the fingertip, +Y out of the back of the hand."""

    position: Vec3 = Field(description="joint position, m")
    orientation: Quat = Field(description="joint orientation [x, y, z, w], unit norm")
    radius: Optional[Annotated[float, Field(ge=0.0)]] = Field(None, description="joint centre to skin, m")
    tracked: bool = Field(True, description="false: the pose is held or inferred, not measured now")


class JointPoseDict(TypedDict):
    position: list[float]
    orientation: list[float]
    radius: Optional[float]
    tracked: bool

JointName = Literal[JOINT_NAMES]  # type: ignore[valid-type]
Joints = Annotated[dict[JointName, JointPose], Field(  # type: ignore[valid-type]
    min_length=len(JOINT_NAMES), max_length=len(JOINT_NAMES),
    description="all 26 joints of OpenXR XR_EXT_hand_tracking by their snake_case names "
                "(palm, wrist, thumb_metacarpal ... little_tip), world frame")]


class SensorStatus(_Message):
    age_s: Optional[float] = Field(description="time since the sensor's last sample, s (null before the first)")
    silent: bool = Field(description="true when the sensor has been silent longer than the sensor timeout")


class SensorStatusDict(TypedDict):
    age_s: Optional[float]
    silent: bool

class DroppedCounts(_Message):
    """Source samples dropped so far, by reason."""

    duplicate: int = Field(ge=0, description="samples of a sensor and time already received")
    late: int = Field(ge=0, description="samples older than what was already processed")
    overflow: int = Field(ge=0, description="samples pushed out of the bounded pending table")
    unknown_sensor: int = Field(ge=0, description="samples of a sensor the calibration does not have")
    subscriber_frames: Optional[int] = Field(None, ge=0, description="frames dropped for subscribers of this "
                                             "session that fell behind (the live service only)")
    overloaded: Optional[int] = Field(None, ge=0, description="source messages refused with an 'overloaded' error: "
                                      "the service could not keep up with the source (the live service only)")


class DroppedCountsDict(TypedDict):
    duplicate: int
    late: int
    overflow: int
    unknown_sensor: int
    subscriber_frames: NotRequired[int]
    overloaded: NotRequired[int]

class ReferencePoseCounts(_Message):
    applied: int = Field(ge=0, description="reference_pose messages applied as a known configuration")
    stale: int = Field(ge=0, description="reference_pose messages ignored: too old, or pushed out of the bounded queue")


class ReferencePoseCountsDict(TypedDict):
    applied: int
    stale: int

class FrameStatus(_Message):
    optics: Literal["tracking", "occluded", "waiting"] = Field(
        description="optical pose: tracking, occluded (pose held), or waiting (none seen yet)")
    estimator: str = Field(description="the estimator's name")
    sensors: dict[Annotated[str, Field(pattern=SENSOR_ID_PATTERN)], SensorStatus] = Field(
        description="per IMU, by sensor id <finger>.<phalanx>")
    dropped: DroppedCounts
    clock_steps: int = Field(ge=0, description="jumps of the source clock seen so far")
    reference_poses: Optional[ReferencePoseCounts] = None
    filter_resets: Optional[int] = Field(None, ge=0, description="estimators and optical fits restarted from the "
                                         "reference after diverging (a non-finite estimate or a numerical failure)")


class FrameStatusDict(TypedDict):
    optics: Literal["tracking", "occluded", "waiting"]
    estimator: str
    sensors: dict[str, SensorStatusDict]
    dropped: DroppedCountsDict
    clock_steps: int
    reference_poses: ReferencePoseCountsDict
    filter_resets: int

class Ray(_Message):
    origin: Vec3 = Field(description="the index fingertip, m, world frame")
    direction: Vec3 = Field(description="unit vector from the index MCP joint to the fingertip, world frame")


class RayDict(TypedDict):
    origin: list[float]
    direction: list[float]

class GestureState(_Message):
    """The gesture layer's continuous values at this frame (``gestures/recognizer.py``)."""

    active: Optional[GestureName] = Field(description="the gesture in progress, or null")
    curl: dict[FingerName, Unit] = Field(description="per finger, total flexion over a full curl, 0..1")
    grab_strength: Unit = Field(description="mean curl of the four long fingers, 0..1")
    pinch_strength: Unit = Field(description="1 with the thumb and index tips touching, 0 from 7 cm apart; 0 while grasping")
    ray: Optional[Ray] = Field(None, description="the pointing ray, while pointing")


class GestureStateDict(TypedDict):
    active: Optional[str]
    curl: dict[str, float]
    grab_strength: float
    pinch_strength: float
    ray: NotRequired[Optional[RayDict]]

class Frame(_Message):
    """Service -> client: the hand at one time of the source clock."""

    type: Literal["frame"]
    t: float = Field(description="time of the estimate, s, on the source's clock")
    seq: int = Field(ge=1, description="frame number in this session, counting from 1")
    hand: Literal["right", "left"]
    fingers: dict[FingerName, FingerAngles] = Field(description="joint angles per finger")
    joints: Joints
    status: FrameStatus
    gesture: Optional[GestureState] = Field(None, description="gesture layer values (absent without the recogniser)")


class FrameDict(TypedDict):
    type: Literal["frame"]
    t: float
    seq: int
    hand: str
    fingers: dict[str, FingerAnglesDict]
    joints: dict[str, JointPoseDict]
    status: FrameStatusDict
    gesture: NotRequired[GestureStateDict]

class Gesture(_Message):
    """A gesture started or ended (sent right after the frame that caused it)."""

    type: Literal["gesture"]
    t: float = Field(description="time of the frame that caused the event, s, source clock")
    gesture: GestureName
    event: Literal["start", "end"]
    confidence: Unit = Field(description="how far inside its threshold band the decisive quantity is, 0..1")
    ray: Optional[Ray] = Field(None, description="the pointing ray (point events)")


class GestureDict(TypedDict):
    type: Literal["gesture"]
    t: float
    gesture: str
    event: Literal["start", "end"]
    confidence: float
    ray: NotRequired[Optional[RayDict]]

ServiceMessage = Annotated[Union[ServerHello, SyncReply, Frame, Gesture, ErrorMessage], Field(discriminator="type")]
"""Any message the service sends on ``/v1/ingest`` or ``/v1/stream``."""
OutputMessage = Annotated[Union[Frame, Gesture, ErrorMessage], Field(discriminator="type")]
_OUTPUT_ADAPTER: TypeAdapter = TypeAdapter(OutputMessage)
SERVICE_TYPES = ("hello", "sync", "frame", "gesture", "error")
WIRE_SHAPES: dict[type, type] = {
    ServerHello: ServerHelloDict, SyncReply: SyncReplyDict, ErrorMessage: ErrorMessageDict, Frame: FrameDict,
    Gesture: GestureDict, FingerAngles: FingerAnglesDict, JointPose: JointPoseDict, SensorStatus: SensorStatusDict,
    DroppedCounts: DroppedCountsDict, ReferencePoseCounts: ReferencePoseCountsDict, FrameStatus: FrameStatusDict,
    Ray: RayDict, GestureState: GestureStateDict,
}
"""Each model and the ``TypedDict`` the service builds it as. (No postponed annotations in this module:
they would hide ``NotRequired`` from the ``TypedDict``s.)"""


def parse_output(obj: object) -> Frame | Gesture | ErrorMessage:
    """Validate a ``frame``, ``gesture`` or ``error`` from the service (for clients); raises ``ProtocolError``."""
    try:
        return _OUTPUT_ADAPTER.validate_python(obj)
    except ValidationError as err:
        raise ProtocolError("invalid_message", _describe(err)) from None

