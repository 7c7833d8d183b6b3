"""One read buffer per thread for the web process's protocols (``asyncio.BufferedProtocol``)."""
from __future__ import annotations

import threading

READ_BUFFER_BYTES = 1 << 16
"""what one read of a WebSocket connection, or of a hand worker's socket, takes at most (``read_buffer``)"""
_read_buffers = threading.local()


def read_buffer() -> memoryview:
    """This thread's buffer for a protocol's reads (``asyncio.BufferedProtocol.get_buffer``): the transport reads
    into it and the protocol takes the bytes out at once, within the same callback, so one buffer serves every
    connection of the thread's event loop. asyncio gives a plain protocol each read as a new bytes object of
    256 KiB, cut to what came: that allocation (mapped and unmapped by the C allocator each time) cost about
    10 us a read here, against about 1.5 us for the read itself, and a glove's message comes in a read of its own."""
    view = getattr(_read_buffers, "view", None)
    if view is None:
        view = _read_buffers.view = memoryview(bytearray(READ_BUFFER_BYTES))
    return view
