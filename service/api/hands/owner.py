"""What a worker that owns a session keeps so that another worker can continue it: the frames' ``seq``
continued across a change of owner and the last joint angles (both kinds of worker: the embedded
service's hand processes, ``hands.worker``, and the NATS bus workers, ``bus.worker``).

A session's compact state (the bus lease's value, and what the embedded service sends a restarted
hand process): ``{"session", "worker", "seq", "t", "angles", "hello", "calibration", "config"}``;
the new owner replays ``hello`` and ``calibration``, applies ``config``, and applies ``angles`` as a
``reference_pose`` at the first sample it handles (``resume_reference``), so the filters restart from
the last estimate."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..outgoing import Outgoing


def first_time(raw: dict) -> float | None:
    """The source time of a message, if it carries one."""
    if "t" in raw:
        return float(raw["t"])
    if raw.get("type") == "imu_batch" and raw.get("samples"):
        return float(raw["samples"][0]["t"])
    return None


def resume_reference(angles: dict, raw: dict) -> dict | None:
    """The ``reference_pose`` that restarts a taken-over session from ``angles`` (the previous owner's
    last joint angles) at the time of the source message ``raw``; ``None`` if ``raw`` has no time."""
    t = first_time(raw)
    return None if t is None else {"type": "reference_pose", "t0": t, "t1": t, "pose": angles}


@dataclass(eq=False)
class OutputSink:
    """The owned session's subscriber: frames and events are kept (``pending``) for the transport with
    the session's ``seq`` (continued across a change of owner), and the last frame for the state."""

    rate_hz: float
    resume_after: tuple[int, float] | None = None   # (seq, t) of the previous owner's last state
    seq_offset: int = 0
    last_seq: int = 0
    last_t: float | None = None
    last_fingers: dict | None = None
    """the last frame's ``fingers`` (its ``last_angles`` made from it when asked)"""
    pending: list = field(default_factory=list)
    binary: bool = True
    dropped: int = 0
    packed: bool = True
    """keep each message as MessagePack bytes (the bus publishes them), else as the message dict"""

    def put(self, item: Outgoing, t_ingest: float) -> int:
        msg = item.message
        if msg["type"] == "frame":
            msg["seq"] = self.frame_seq(msg["seq"], msg["t"])
            self.last_fingers = msg["fingers"]
        self.pending.append(item.packed() if self.packed else msg)
        return 0

    def frame_seq(self, seq: int, t: float) -> int:
        """The session's ``seq`` of its hand's frame ``seq`` at source time ``t`` (continued across a change
        of owner), kept as the last frame's with ``t`` (``put`` of a frame; a hand worker's frames, whose
        session state the web process keeps, take only this)."""
        if self.resume_after is not None:
            seq0, t0 = self.resume_after
            # the previous owner may have sent frames after its last state: every one of them lies
            # on its frame grid before this frame's time, so this seq is above all of theirs
            self.seq_offset = seq0 + max(1, math.ceil((t - t0) * self.rate_hz)) + 1 - seq
            self.resume_after = None
        seq += self.seq_offset
        self.last_seq, self.last_t = seq, t
        return seq

    @property
    def last_angles(self) -> dict:
        """The last frame's joint angles per finger (without the modes): the session's state for its next
        owner, made when that is asked for, not at every frame."""
        fingers = self.last_fingers or {}
        return {f: {j: v for j, v in a.items() if j != "mode"} for f, a in fingers.items()}
