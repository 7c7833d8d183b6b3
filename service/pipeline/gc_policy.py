"""The garbage-collector policy of a process that serves hand pipelines (the web process of
``fingertrack serve`` and its hand workers)."""
from __future__ import annotations

import contextlib
import gc


@contextlib.contextmanager
def serving_gc():
    """The garbage-collector policy of a serving process, for the duration of the block: the heap
    built so far is frozen (never scanned again) and young-generation collections are rarer. The
    per-tick work allocates many small short-lived arrays; with the default policy, collections that
    scan a large heap put pauses of 10 ms and more into the frame latency tail (measured with
    ``fingertrack bench latency``; a full collection of a hand worker's heap, about 500,000 objects
    after its kernels are loaded, took 0.3 s on a busy machine). On exit the thresholds are restored,
    and the heap is unfrozen unless it was already frozen on entry (an enclosing block keeps its
    freeze)."""
    old = gc.get_threshold()
    was_frozen = gc.get_freeze_count() > 0
    gc.freeze()
    gc.set_threshold(50_000, 20, 100)
    try:
        yield
    finally:
        gc.set_threshold(*old)
        if not was_frozen:
            gc.unfreeze()
