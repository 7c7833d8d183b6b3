"""Wire protocol v1 (DESIGN.md): typed messages shared by the simulator, pipeline, service and clients.

``messages``: what sources send (validated at the service's edge); ``outgoing``: what the service
sends; ``wire``: their encodings (JSON, the MessagePack subprotocol) and recordings; ``schema``: JSON
Schema and AsyncAPI documents generated from the models.
"""
from .messages import (  # noqa: F401
    PROTOCOL_VERSION, Calibration, Hello, Imu, ImuBatch, Pose, ProtocolError, ReferencePose, Sync, Truth,
    parse_message,
)
from .outgoing import (  # noqa: F401
    ERROR_CODES, ErrorMessage, Frame, FrameStatus, Gesture, GestureState, JointPose, Ray, ServerHello, SyncReply,
    parse_output,
)
from .wire import MSGPACK_SUBPROTOCOL, decode, encode, parse_input, parse_line, read_recording  # noqa: F401
