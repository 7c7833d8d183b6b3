"""The garbage-collector policy of the processes that run hands (``pipeline/gc_policy.py``): a hand
worker serves under it (a full collection of a worker's heap of loaded kernels and modules paused every
session of the worker for 0.3 s on a busy machine)."""
import gc
import json
import signal
import socket
import struct
import threading

import msgpack

from service.pipeline.gc_policy import serving_gc

SERVING_THRESHOLD = 50_000


def test_serving_gc_freezes_the_heap_and_restores_the_policy():
    """On exit the thresholds are back and the heap is unfrozen, unless it was frozen on entry (then it
    stays frozen: an enclosing block's freeze is kept). Both cases, whatever this process's state was (another
    test in it may have frozen its heap: it is given back as it was)."""
    was_frozen = gc.get_freeze_count() > 0
    before = gc.get_threshold()
    try:
        gc.unfreeze()
        with serving_gc():
            assert gc.get_threshold()[0] == SERVING_THRESHOLD
            assert gc.get_freeze_count() > 0
        assert gc.get_threshold() == before
        assert gc.get_freeze_count() == 0
        gc.freeze()
        with serving_gc():
            assert gc.get_freeze_count() > 0
        assert gc.get_threshold() == before and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
        if was_frozen:
            gc.freeze()


def test_a_hand_worker_serves_under_the_serving_policy():
    """A real hand worker's main loop (``hands.worker.main``, here in this process so that its policy can
    be read) on one end of a socket pair: once it has answered a source message, the serving policy is
    in force; when the web process's end closes, the worker returns and the policy before it is back."""
    from service.api.hands import worker

    header = struct.Struct(">I")
    ours, theirs = socket.socketpair()
    seen: dict = {}

    def read_batch(buf: bytearray) -> list:
        while len(buf) < header.size or len(buf) < header.size + header.unpack_from(buf)[0]:
            chunk = ours.recv(1 << 16)
            if not chunk:
                raise EOFError("the worker closed its end")
            buf += chunk
        size = header.unpack_from(buf)[0]
        batch = msgpack.unpackb(bytes(buf[header.size:header.size + size]))
        del buf[:header.size + size]
        return batch

    def web_process() -> None:
        buf = bytearray()
        try:
            seen["first"] = read_batch(buf)[0][0]
            imu = {"type": "imu", "t": 0.0, "id": "index.1", "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 9.81, 0.0]}
            ours.sendall(worker.frame([["open", 1, "s", None], ["src", 1, 1, msgpack.packb(imu)]]))
            while not any(m[0] == "rep" for m in read_batch(buf)):
                pass                                # the reply comes from the worker's serving loop
            seen["threshold"] = gc.get_threshold()[0]
            seen["frozen"] = gc.get_freeze_count()
        finally:
            ours.close()

    before = gc.get_threshold()
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    peer = threading.Thread(target=web_process)
    peer.start()
    try:
        assert worker.main([str(theirs.detach()), json.dumps({"estimator": "chain"})]) == 0
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        peer.join(60.0)
    assert seen["first"] == "ready"
    assert seen["threshold"] == SERVING_THRESHOLD and seen["frozen"] > 0
    assert gc.get_threshold() == before
