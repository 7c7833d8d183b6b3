"""Wire protocol v1 (DESIGN.md): typed messages shared by the simulator, pipeline, service and clients."""
from .messages import (  # noqa: F401
    PROTOCOL_VERSION, Calibration, ErrorMessage, Hello, Imu, ImuBatch, Pose, ProtocolError, ReferencePose, Sync, Truth,
    parse_message, parse_line, read_recording, Frame, Gesture, ServerHello, parse_output,
)
