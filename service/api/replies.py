"""The error replies a source message gets once it has been processed: shared by the embedded service
(``routes/ingest.py``) and the bus worker (``bus/worker.py``, whose replies the gateway passes on), so
the same input gets the same reply either way. Codes and their meaning: ``protocol.outgoing.ERROR_CODES``."""
from __future__ import annotations

import logging

from ..pipeline.hand import Dropped

log = logging.getLogger("fingertrack")


DROP_REPLIES = (
    ("late", "time_backwards", "is older than what was already processed; dropped",
     "older than what was already processed; dropped"),
    ("duplicate", "duplicate", "was already received; dropped", "already received; dropped"),
    ("unknown_sensor", "unknown_sensor", "is of a sensor id the session's calibration does not place; dropped",
     "of a sensor id the session's calibration does not place; dropped"),
    ("clock_step", "clock_step", ("jumps by more than the clock step (clock_step_s) from the newest sample "
                                                "before it: processed as a new clock (the samples still waiting were "
                                                "discarded, the estimates restart from the current ones)"),
     None),
)
"""Per drop reason of ``Dropped`` (overflow aside: samples of earlier messages, counted in the frame
status): its error code, and what it says of one message and of a batch's samples (``None``: a count
of steps, not of samples)."""


def drop_replies(msg, dropped: Dropped | None) -> list[tuple[str, str]]:
    """``(code, detail)`` per reason the pipeline dropped (part of) a message for: late, duplicate, of a
    sensor the calibration does not place; an ``imu_batch``'s detail counts its samples. Empty if it
    dropped nothing (or ``dropped`` is ``None``: a session whose hand runs elsewhere answers later)."""
    if dropped is None:
        return []
    samples = getattr(msg, "samples", None)
    out = []
    for reason, code, one, some in DROP_REPLIES:
        n = getattr(dropped, reason)
        if not n:
            continue
        if samples:
            times = [s.t for s in samples]
            counted = f"{n} of {len(samples)} samples {some}" if some else f"a sample {one}"
            out.append((code, f"{msg.type} at t={min(times)}..{max(times)}: {counted}"))
        else:
            out.append((code, f"{msg.type} at t={getattr(msg, 't', None)} {one}"))
    return out


def failure_reply(session: str, msg, err: Exception) -> tuple[str, str]:
    """``(code, detail)`` for a message whose processing raised ``err``: a ``ValueError`` is the
    input's fault (e.g. a calibration that does not fit the hand: ``invalid_message`` with its text),
    anything else a defect (``internal_error``, logged in one line; the session goes on)."""
    if isinstance(err, ValueError):
        return "invalid_message", str(err)
    log.warning("session %s: %s while processing %s: %s; message dropped", session, type(err).__name__,
                msg.type, str(err)[:200])
    return "internal_error", f"{type(err).__name__} while processing {msg.type}; message dropped"
