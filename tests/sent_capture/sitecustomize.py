"""Test suite only: lets the suite check what service processes send.

``tests/conftest.py`` puts this folder on ``PYTHONPATH`` and names a folder in
``FINGERTRACK_TEST_SENT_DIR`` for the Python processes the tests start (``fingertrack serve``,
gateways, ``service_process``). In such a process, every message sent on a Starlette WebSocket is
appended to ``<dir>/<pid>.sent`` (one ``os.write`` per record on an ``O_APPEND`` file, so nothing
waits in a buffer when the process is killed), and the suite validates the records against the
published schema after each test, as it validates the messages of in-process services.

Ready-made frames written past Starlette (``service.api.server.DrainingWebSocket.write_frames``) are
recorded too, each frame's payload as one record.

Record: one byte ``T`` (text) or ``B`` (binary), the payload's length as 4 bytes big-endian, the
payload (UTF-8 text or the MessagePack bytes). Starlette and the server module are patched when they are
first imported, so processes that never import them (hand workers, tools) are not touched."""
import importlib.abc
import os
import struct
import sys

_DIR = os.environ.get("FINGERTRACK_TEST_SENT_DIR")
_HERE = os.path.dirname(os.path.abspath(__file__))     # now: a test may change the working directory later
_MODULE = "starlette.websockets"


def _record(kind: bytes, payload: bytes) -> None:
    fd = os.open(os.path.join(_DIR, f"{os.getpid()}.sent"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        os.write(fd, kind + struct.pack(">I", len(payload)) + payload)
    finally:
        os.close(fd)


def _patch(module) -> None:
    ws_class = module.WebSocket
    if getattr(ws_class, "_sent_capture", False):
        return
    send_text, send_bytes = ws_class.send_text, ws_class.send_bytes
    record = _record

    async def text(self, data):
        record(b"T", data.encode("utf-8"))
        await send_text(self, data)

    async def binary(self, data):
        record(b"B", bytes(data))
        await send_bytes(self, data)

    ws_class.send_text, ws_class.send_bytes = text, binary
    ws_class._sent_capture = True


def _patch_wire(module) -> None:
    # ws_frames beside this file, loaded by its path (``import ws_frames`` failed in the suite's test
    # processes on a clean clone, its folder not found on sys.path by then)
    import importlib.util
    spec = importlib.util.spec_from_file_location("_sent_capture_ws_frames", os.path.join(_HERE, "ws_frames.py"))
    frames = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(frames)
    payloads = frames.payloads

    protocol = module.DrainingWebSocket
    write_frames = protocol.write_frames

    def written(self, data):
        done = write_frames(self, data)
        if done:
            for payload in payloads(data):
                _record(b"T", payload.encode("utf-8")) if isinstance(payload, str) else _record(b"B", payload)
        return done
    protocol.write_frames = written


_PATCHES = {_MODULE: _patch, "service.api.server": _patch_wire}


class _PatchOnImport(importlib.abc.MetaPathFinder):
    """Finds nothing itself: wraps the loader of each module in ``_PATCHES`` to patch it once loaded."""

    def find_spec(self, fullname, path, target=None):
        patch = _PATCHES.get(fullname)
        if patch is None:
            return None
        sys.meta_path.remove(self)
        try:
            import importlib.util
            spec = importlib.util.find_spec(fullname)
        finally:
            sys.meta_path.insert(0, self)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_and_patch(module):
            exec_module(module)
            patch(module)
        spec.loader.exec_module = exec_and_patch
        return spec


if _DIR:
    sys.meta_path.insert(0, _PatchOnImport())
