"""The worker link's framing (``hands.worker.frame``): one packer per thread, reused, gives the bytes of
``msgpack.packb`` for every batch, also right after a batch it could not pack and from several threads."""
import sys
import threading

import msgpack
import numpy as np
import pytest

from service.api.hands import worker as hands_worker


def _expected(messages) -> bytes:
    data = msgpack.packb(messages, default=hands_worker._plain)
    return hands_worker.HEADER.pack(len(data)) + data


def test_frame_is_packb_with_its_length_before_and_after_a_batch_it_refuses():
    batches = [[["out", 1, 5, ["frame", 3, 1.25, "right"], "x" * 3000, None], ["rep", 1, 5, []]],
               [["reps", 1, 3, 4]], [["alive"]], [["out", 2, 1, [np.float64(0.5), np.arange(3)], b"\x00\x01", None]]]
    for batch in batches:
        assert hands_worker.frame(batch) == _expected(batch)
    with pytest.raises(TypeError):
        hands_worker.frame([["reps", 1, 3, 4], ["x", object()]])
    for batch in batches:       # nothing of the refused batch left in the packer's buffer
        assert hands_worker.frame(batch) == _expected(batch)
    big = [["out", 1, 1, None, "y" * (3 << 20), None]]
    assert hands_worker.frame(big) == _expected(big)
    assert hands_worker.frame([["alive"]]) == _expected([["alive"]])


def test_frame_from_several_threads_at_once_gives_each_its_own_bytes():
    go = threading.Barrier(4)
    wrong: list = []

    def run(k: int) -> None:
        # numpy values: the packer calls back into Python (``_plain``) in the middle of each batch, where the
        # interpreter may switch threads (asked to switch often here)
        batch = [["out", k, n, ["frame", n, np.float64(n / 90), "left"], str(k) * 200, np.arange(k, k + 3)]
                 for n in range(3)]
        go.wait()
        for _ in range(300):
            if hands_worker.frame(batch) != _expected(batch):
                wrong.append(k)
                return

    threads = [threading.Thread(target=run, args=(k,)) for k in range(4)]
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    finally:
        sys.setswitchinterval(interval)
    assert wrong == []
