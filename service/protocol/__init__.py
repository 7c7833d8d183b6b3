"""Wire protocol v1 (DESIGN.md): typed messages shared by the simulator, pipeline, service and clients.

``messages``: what sources send (validated at the service's edge); ``outgoing``: what the service
sends; ``schema``: JSON Schema and AsyncAPI documents generated from both.
"""
from .messages import (  # noqa: F401
    PROTOCOL_VERSION, Calibration, Hello, Imu, ImuBatch, Pose, ProtocolError, ReferencePose, Sync, Truth,
    parse_message, parse_line, read_recording,
)
from .outgoing import (  # noqa: F401
    ERROR_CODES, ErrorMessage, Frame, FrameStatus, Gesture, GestureState, JointPose, Ray, ServerHello, SyncReply,
    parse_output,
)
