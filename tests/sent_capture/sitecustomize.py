"""Test suite only: lets the suite check what service processes send.

``tests/conftest.py`` puts this folder on ``PYTHONPATH`` and names a folder in
``FINGERTRACK_TEST_SENT_DIR`` for the Python processes the tests start (``fingertrack serve``,
gateways, ``service_process``). In such a process, every message sent on a Starlette WebSocket is
appended to ``<dir>/<pid>.sent`` (one ``os.write`` per record on an ``O_APPEND`` file, so nothing
waits in a buffer when the process is killed), and the suite validates the records against the
published schema after each test, as it validates the messages of in-process services.

Record: one byte ``T`` (text) or ``B`` (binary), the payload's length as 4 bytes big-endian, the
payload (UTF-8 text or the MessagePack bytes). Starlette is patched when it is first imported, so
processes that never import it (hand workers, tools) are not touched."""
import importlib.abc
import os
import struct
import sys

_DIR = os.environ.get("FINGERTRACK_TEST_SENT_DIR")
_MODULE = "starlette.websockets"


def _patch(module) -> None:
    ws_class = module.WebSocket
    if getattr(ws_class, "_sent_capture", False):
        return
    path = os.path.join(_DIR, f"{os.getpid()}.sent")
    send_text, send_bytes = ws_class.send_text, ws_class.send_bytes

    def record(kind: bytes, payload: bytes) -> None:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            os.write(fd, kind + struct.pack(">I", len(payload)) + payload)
        finally:
            os.close(fd)

    async def text(self, data):
        record(b"T", data.encode("utf-8"))
        await send_text(self, data)

    async def binary(self, data):
        record(b"B", bytes(data))
        await send_bytes(self, data)

    ws_class.send_text, ws_class.send_bytes = text, binary
    ws_class._sent_capture = True


class _PatchOnImport(importlib.abc.MetaPathFinder):
    """Finds nothing itself: wraps the loader of ``starlette.websockets`` to patch it once loaded."""

    def find_spec(self, fullname, path, target=None):
        if fullname != _MODULE:
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
            _patch(module)
        spec.loader.exec_module = exec_and_patch
        return spec


if _DIR:
    sys.meta_path.insert(0, _PatchOnImport())
