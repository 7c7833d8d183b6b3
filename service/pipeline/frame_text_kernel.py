"""Compiled (numba) assembly of a frame's JSON text (``frame_text.FrameOutput.text``): the numbers as
``orjson`` wrote them, in one run, put between the frame's fixed parts in one call.

``orjson`` writes every number of a frame (its joint angles, then its joints' positions, then their
orientations: one float64 array) as one list; ``merge`` cuts that text at its commas and copies each run of
numbers a hole of the fixed parts takes (an angle alone, a joint's position or orientation as three or four
numbers with their commas) into place, with the frame's head, status and gesture annotation (written by
``orjson`` too) around them. It copies bytes, never writes a number: the text is the one ``frame_text``'s
parts and splits made before (``tests/test_frame_text.py`` checks it against ``encode`` of the message).
"""
from __future__ import annotations

import numba
import numpy as np

from .. import JIT_CACHE

COMMA = 44              # ","
OPEN, CLOSE = 91, 93    # "[", "]"


@numba.njit(cache=JIT_CACHE, inline="always")
def _copy(out, w, src, a, b):  # pragma: no cover - compiled
    """``out[w:w + b - a] = src[a:b]``, returning ``w + b - a``: a loop over two views (several times
    cheaper here than numba's slice assignment or a loop indexing the whole arrays)."""
    n = b - a
    o = out[w:w + n]
    s = src[a:b]
    for i in range(n):
        o[i] = s[i]
    return w + n


@numba.njit(cache=JIT_CACHE)
def merge(numbers, small, n_head, n_status, fixed, ends, holes, out):  # pragma: no cover - compiled
    """Write the frame's text into ``out`` and return its length; -1 if ``numbers`` is not a list of
    ``holes``' count of numbers (``holes[-1]``: their count) or ``out`` is too short.

    ``numbers``: ``orjson``'s text of one list of numbers (``[a,b,...]``, bytes, or as uint8); ``small``: the
    frame's head object, its status object and its gesture object, one after the other (``n_head`` and
    ``n_status`` bytes the first two); ``fixed``: the fixed parts one after the other, part ``k`` up to
    ``ends[k]`` (from ``ends[k - 1]``, the first from 0); ``holes[2k]``, ``holes[2k + 1]``: the first number
    and the count of numbers hole ``k`` takes, ``len(ends) - 4`` holes (``holes`` has one more item, the
    count of numbers). The text: the head without its closing brace, fixed part 0, hole 0, fixed part 1,
    ..., the last hole, then the fixed part after it, fixed part ``K + 1`` (``,"status":``), the status,
    fixed part ``K + 2`` (``,"gesture":``), the gesture annotation, fixed part ``K + 3`` (``}``)."""
    k_holes = ends.shape[0] - 4
    if k_holes < 0 or holes.shape[0] != 2 * k_holes + 1:
        return -1
    for k in range(ends.shape[0]):
        if ends[k] < (ends[k - 1] if k else 0):
            return -1
    count = holes[2 * k_holes]
    size = len(numbers)
    if count < 0 or size < 2 or numbers[0] != OPEN or numbers[size - 1] != CLOSE:
        return -1
    # where each number's text starts (``starts[i]``) and ends (``starts[i + 1] - 1``, at its comma)
    commas = 0
    for p in range(1, size - 1):                 # (no branch per byte: one pass to count, one to place)
        commas += numbers[p] == COMMA
    if commas != count - 1 if size > 2 else count != 0:      # (``[]``: no number)
        return -1
    starts = np.empty(count + 1, dtype=np.int64)
    starts[0] = 1
    i = 1
    for p in range(1, size - 1):
        starts[i] = p + 1                        # (overwritten until the comma: the last write is a number's)
        i += numbers[p] == COMMA
    starts[count] = size
    need = n_head - 1 + len(small) - n_head + fixed.shape[0]     # (every byte written counted first)
    for k in range(k_holes):
        first, n = holes[2 * k], holes[2 * k + 1]
        if first < 0 or n < 1 or first + n > count:
            return -1
        need += starts[first + n] - 1 - starts[first]
    if out.shape[0] < need or n_head < 1 or n_status < 0 or n_head + n_status > len(small) \
            or ends[ends.shape[0] - 1] > fixed.shape[0]:
        return -1
    w = _copy(out, 0, small, 0, n_head - 1)     # the head without its "}"
    begin = 0
    for k in range(k_holes):
        w = _copy(out, w, fixed, begin, ends[k])
        begin = ends[k]
        first, n = holes[2 * k], holes[2 * k + 1]
        w = _copy(out, w, numbers, starts[first], starts[first + n] - 1)     # the run with its inner commas
    # the fixed part after the last hole and ``,"status":``, the status, ``,"gesture":``, the annotation, ``}``
    w = _copy(out, w, fixed, begin, ends[k_holes + 1])
    w = _copy(out, w, small, n_head, n_head + n_status)
    w = _copy(out, w, fixed, ends[k_holes + 1], ends[k_holes + 2])
    w = _copy(out, w, small, n_head + n_status, len(small))
    return _copy(out, w, fixed, ends[k_holes + 2], ends[k_holes + 3])


def merge_reference(numbers: bytes, small: bytes, n_head: int, n_status: int, fixed: bytes, ends, holes) -> bytes | None:
    """``merge`` in Python (bytes in, bytes out; ``None`` for its -1): the numbers' text split at its commas,
    each hole's run joined again with its commas, and the parts put in order. The definition ``merge`` is
    tested equal to (``tests/test_frame_text_kernel.py``)."""
    ends, holes = [int(e) for e in ends], [int(h) for h in holes]
    if len(ends) < 4 or len(holes) != 2 * (len(ends) - 4) + 1 or any(b < a for a, b in zip([0, *ends], ends)):
        return None
    count = holes[-1]
    if count < 0 or len(numbers) < 2 or numbers[:1] != b"[" or numbers[-1:] != b"]":
        return None
    if n_head < 1 or n_status < 0 or n_head + n_status > len(small) or ends[-1] > len(fixed):
        return None
    items = numbers[1:-1].split(b",") if len(numbers) > 2 else []
    if len(items) != count:
        return None
    parts = [fixed[a:b] for a, b in zip([0, *ends[:-1]], ends)]
    out = [small[:n_head - 1]]
    for k in range(len(ends) - 4):
        first, n = holes[2 * k], holes[2 * k + 1]
        if first < 0 or n < 1 or first + n > count:
            return None
        out += (parts[k], b",".join(items[first:first + n]))
    k = len(ends) - 4
    out += (parts[k], parts[k + 1], small[n_head:n_head + n_status], parts[k + 2], small[n_head + n_status:], parts[k + 3])
    return b"".join(out)
