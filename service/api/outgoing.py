"""Output messages encoded once for all their subscribers.

A frame streamed to many subscribers is serialised at most once per wire format (JSON text,
MessagePack bytes), on first use, and the same bytes go to every subscriber that asked for that
format. Encoding used to be done per subscriber and was a measurable share of a session's CPU.
A message a hand worker encoded already (``encoded``) is passed on as those bytes, decoded only if a
subscriber asks for a format the worker did not write.
"""
from __future__ import annotations

import orjson

from ..protocol.outgoing import FrameDict, GestureDict
from ..protocol.wire import decode, encode


class Outgoing:
    """A ``frame`` or ``gesture`` message with its encodings cached."""

    __slots__ = ("_message", "type", "_text", "_packed")

    def __init__(self, message: FrameDict | GestureDict):
        self._message: FrameDict | GestureDict | None = message
        self.type: str = message["type"]
        self._text: str | None = None
        self._packed: bytes | None = None

    @classmethod
    def encoded(cls, kind: str, text: str, packed: bytes | None = None) -> "Outgoing":
        """A message of type ``kind`` that arrives encoded: its JSON ``text`` (as ``text()`` writes it)
        and, if given, its MessagePack bytes."""
        out = cls.__new__(cls)
        out._message, out.type, out._text, out._packed = None, kind, text, packed
        return out

    @property
    def message(self) -> FrameDict | GestureDict:
        if self._message is None:
            self._message = orjson.loads(self._text) if self._text is not None else decode(self._packed, binary=True)
        return self._message

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
