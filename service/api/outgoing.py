"""Output messages encoded once for all their subscribers.

A frame streamed to many subscribers is serialised at most once per wire format (JSON text,
MessagePack bytes), on first use, and the same bytes go to every subscriber that asked for that
format. Encoding used to be done per subscriber and was a measurable share of a session's CPU.
A message a hand worker encoded already (``encoded``) is passed on as those bytes, decoded only if a
subscriber asks for a format the worker did not write. Its WebSocket frame (``wire``: the header and the
payload as a server sends them) is built once per format too, and written as it is to every subscriber's
connection (``server.DrainingWebSocket.write_frames``).
"""
from __future__ import annotations

import struct

import orjson

from ..protocol.outgoing import FrameDict, GestureDict
from ..protocol.wire import decode, encode

WIRE_EXTENSION = "fingertrack.wire"
"""The ASGI scope extension under which the server's WebSocket protocol offers the app a write of ready-made
frames (``server.DrainingWebSocket.write_frames``)."""


class Outgoing:
    """A ``frame`` or ``gesture`` message with its encodings cached."""

    __slots__ = ("_message", "type", "_text", "_packed", "_wire_text", "_wire_packed")

    def __init__(self, message: FrameDict | GestureDict):
        self._message: FrameDict | GestureDict | None = message
        self.type: str = message["type"]
        self._text: str | None = None
        self._packed: bytes | None = None
        self._wire_text = self._wire_packed = None

    @classmethod
    def encoded(cls, kind: str, text: str, packed: bytes | None = None) -> "Outgoing":
        """A message of type ``kind`` that arrives encoded: its JSON ``text`` (as ``text()`` writes it)
        and, if given, its MessagePack bytes."""
        out = cls.__new__(cls)
        out._message, out.type, out._text, out._packed = None, kind, text, packed
        out._wire_text = out._wire_packed = None
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

    def wire(self, binary: bool) -> bytes:
        """The whole WebSocket frame of the message in one format (``packed`` if ``binary``, else ``text``)
        as a server sends it (``ws_frame``), built once."""
        if binary:
            if self._wire_packed is None:
                self._wire_packed = ws_frame(self.packed(), binary=True)
            return self._wire_packed
        if self._wire_text is None:
            self._wire_text = ws_frame(self.text().encode(), binary=False)
        return self._wire_text


_LENGTH_16 = struct.Struct("!BBH")
_LENGTH_64 = struct.Struct("!BBQ")


def ws_frame(payload: bytes, binary: bool) -> bytes:
    """One unfragmented, unmasked, uncompressed WebSocket data frame (RFC 6455 section 5.2): FIN and the
    opcode (text 1, binary 2), the payload length in 7, 7+16 or 7+64 bits, the payload; what the
    protocol library writes for a server's ``send_text``/``send_binary`` without extensions."""
    head = 0x82 if binary else 0x81
    n = len(payload)
    if n < 126:
        return bytes((head, n)) + payload
    if n < 1 << 16:
        return _LENGTH_16.pack(head, 126, n) + payload
    return _LENGTH_64.pack(head, 127, n) + payload


def joined_frames(messages, binary: bool) -> bytes:
    """The ready-made WebSocket frames of ``messages`` (``Outgoing``), in order, as one write."""
    return messages[0].wire(binary) if len(messages) == 1 else b"".join(m.wire(binary) for m in messages)
