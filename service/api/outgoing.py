"""Output messages encoded once for all their subscribers.

A frame streamed to many subscribers is serialised at most once per wire format (JSON text,
MessagePack bytes), on first use, and the same bytes go to every subscriber that asked for that
format. Encoding used to be done per subscriber and was a measurable share of a session's CPU.
"""
from __future__ import annotations

from ..protocol.outgoing import FrameDict, GestureDict
from ..protocol.wire import encode


class Outgoing:
    """A ``frame`` or ``gesture`` message with its encodings cached."""

    __slots__ = ("message", "_text", "_packed")

    def __init__(self, message: FrameDict | GestureDict):
        self.message = message
        self._text: str | None = None
        self._packed: bytes | None = None

    @property
    def type(self) -> str:
        return self.message["type"]

    def text(self) -> str:
        """Compact JSON text (the default format)."""
        if self._text is None:
            self._text = encode(self.message, binary=False)     # never NaN or infinity
        return self._text

    def packed(self) -> bytes:
        """MessagePack bytes (subprotocol ``fingertrack.msgpack``)."""
        if self._packed is None:
            self._packed = encode(self.message, binary=True)
        return self._packed
