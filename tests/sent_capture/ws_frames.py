"""Test suite only: the payloads of WebSocket data frames as a server writes them (unmasked, not
fragmented: ``service.api.outgoing.ws_frame``), for the suite's record of what the service sent
(``DrainingWebSocket.write_frames`` writes ready-made frames, past Starlette's send)."""


def payloads(data: bytes) -> list:
    """Each frame's payload in ``data``: ``str`` for a text frame, ``bytes`` for a binary one."""
    out, at = [], 0
    while at < len(data):
        opcode, n = data[at] & 0x0F, data[at + 1] & 0x7F
        at += 2
        if n >= 126:
            size = 2 if n == 126 else 8
            n, at = int.from_bytes(data[at:at + size], "big"), at + size
        payload, at = bytes(data[at:at + n]), at + n
        out.append(payload.decode("utf-8") if opcode == 1 else payload)
    return out
