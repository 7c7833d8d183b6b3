"""The compiled assembly of a frame's text (``pipeline.frame_text_kernel.merge``) equals its Python definition
(``merge_reference``), byte for byte, on the parts of recorded frames and on random ones (numbers of every
spelling ``orjson`` writes, runs of one to seven numbers in any order, empty parts), and refuses what the
reference refuses (a count of numbers other than the holes', a hole beyond them, text that is no list)."""
import numpy as np
import orjson
import pytest

from service.pipeline import frame_text_kernel
from service.pipeline.frame_text_kernel import merge, merge_reference
from service.pipeline.tracked import TrackedHand
from service.protocol import parse_message
from service.sim.session import SimConfig, simulate


def _merged(numbers: bytes, small: bytes, n_head: int, n_status: int, fixed: bytes, ends, holes,
            room: int | None = None) -> bytes | None:
    """``merge``'s text, in an ``out`` of ``room`` bytes (default: room for every hole's run, even where
    they share numbers); the bytes beyond ``room`` are checked untouched."""
    if room is None:
        room = len(numbers) * len(holes) + len(small) + len(fixed)
    texts = []
    # the numbers and small parts as ``FrameOutput`` passes them (bytes) and as uint8 arrays: the same text
    for numbers_in, small_in in ((numbers, small), (np.frombuffer(numbers, np.uint8), np.frombuffer(small, np.uint8))):
        whole = np.full(room + 64, 7, dtype=np.uint8)
        out = whole[:room]
        size = merge(numbers_in, small_in, n_head, n_status, np.frombuffer(fixed, np.uint8),
                     np.asarray(ends, dtype=np.int64), np.asarray(holes, dtype=np.int64), out)
        assert (whole[room:] == 7).all()
        texts.append(None if size < 0 else out[:size].tobytes())
    assert texts[0] == texts[1]
    return texts[0]


def _both(*args) -> bytes | None:
    got, expected = _merged(*args), merge_reference(*args)
    assert got == expected
    return got


def test_recorded_frames():
    """Every frame of a simulated session, from its layout's parts: the kernel's text is the reference's (and
    ``encode``'s, which ``tests/test_frame_text.py`` checks)."""
    tracked = TrackedHand()
    checked = 0
    for m in simulate(SimConfig(motion="sequence", noise="white", seed=7, t_m_s=1.0)).messages():
        tracked.accept(parse_message(m))
        for out, _ in tracked.frame_outputs():
            assert out._text() is not None
            layout = out._layouts.last[4]
            frame = out.frame
            numbers = orjson.dumps(frame.joints.numbers, option=orjson.OPT_SERIALIZE_NUMPY)
            head, status, gesture = (orjson.dumps(x) for x in ({"type": "frame"}, frame.status, out.annotation))
            text = _both(numbers, head + status + gesture, len(head), len(status), layout.fixed.tobytes(),
                         layout.ends, layout.holes)
            assert text is not None and text.startswith(head[:-1] + b',"fingers":')
            checked += 1
    assert checked > 50


def _random_number(rng) -> float:
    kind = rng.integers(0, 6)
    if kind == 0:
        return float(rng.choice([0.0, -0.0, 1.0, -1.0, 1e-7, 1.5e-300, 1e300, 123456789.0]))
    if kind == 1:
        return float(rng.normal() * 10.0 ** rng.integers(-20, 20))
    return float(rng.normal())


@pytest.mark.parametrize("seed", range(40))
def test_random_parts(seed):
    rng = np.random.default_rng(seed)
    runs = [int(rng.integers(1, 8)) for _ in range(rng.integers(0, 12))]
    count = sum(runs) + int(rng.integers(0, 3))          # numbers no hole takes, as well
    starts = rng.permutation(count)[:len(runs)]
    holes = []
    for r, s in zip(runs, starts):
        s = min(int(s), count - r)
        holes += (s, r)
    holes.append(count)
    numbers = orjson.dumps([_random_number(rng) for _ in range(count)])
    fixed = [bytes(rng.integers(32, 127, size=rng.integers(0, 12), dtype=np.uint8)) for _ in range(len(runs) + 4)]
    ends = np.cumsum([len(p) for p in fixed])
    small = [b'{"h":1}', orjson.dumps({"s": [1, 2]}), bytes(rng.integers(32, 127, size=rng.integers(0, 9), dtype=np.uint8))]
    text = _both(numbers, b"".join(small), len(small[0]), len(small[1]), b"".join(fixed), ends, holes)
    assert text is not None and len(text) > len(small[0]) - 1 + len(small[1])


@pytest.mark.parametrize("case", ["one more number", "one fewer number", "a hole beyond them", "a hole of none",
                                  "not a list", "empty text"])
def test_refused(case):
    numbers, holes = b"[1.0,2.5,-0.0]", [0, 1, 1, 2, 3]
    if case == "one more number":
        numbers = b"[1.0,2.5,-0.0,4.0]"
    elif case == "one fewer number":
        numbers = b"[1.0,2.5]"
    elif case == "a hole beyond them":
        holes = [0, 1, 2, 2, 3]
    elif case == "a hole of none":
        holes = [0, 0, 1, 2, 3]
    elif case == "not a list":
        numbers = b"{1.0,2.5,-0.0}"
    else:
        numbers = b""
    fixed = b"abcdefgh"
    assert _both(numbers, b"{}{}{}", 2, 2, fixed, [1, 2, 3, 4, 5, 8], holes) is None
    assert _both(b"[1.0,2.5,-0.0]", b"{}{}{}", 2, 2, fixed, [1, 2, 3, 4, 5, 8], [0, 1, 1, 2, 3]) == \
        b"{a1.0b2.5,-0.0cd{}e{}fgh"


def test_warm_compiles_the_kernel_for_the_types_frames_use():
    """The pipeline's warm-up calls ``merge`` with read-only numbers, small and fixed parts (bytes), as
    ``FrameOutput`` does: its compiled code is the code frames use."""
    assert frame_text_kernel.merge in __import__("service.estimators.warm", fromlist=["_pipeline_kernels"])._pipeline_kernels()


@pytest.mark.parametrize("case", ["no numbers", "holes not of the parts", "parts out of order", "too few parts",
                                  "head beyond the small parts"])
def test_edges(case):
    numbers, small, n_head, fixed, ends, holes = b"[1.0]", b"{}{}{}", 2, b"abcdef", [1, 2, 3, 4, 6], [0, 1, 1]
    if case == "no numbers":
        numbers, ends, holes = b"[]", [1, 2, 3, 6], [0]
    elif case == "holes not of the parts":
        holes = [0, 1, 0, 1, 1]
    elif case == "parts out of order":
        ends = [1, 3, 2, 4, 6]
    elif case == "too few parts":
        ends, holes = [1, 2, 6], [1]
    else:
        n_head = 7
    text = _both(numbers, small, n_head, 2, fixed, ends, holes)
    assert (text is not None) == (case == "no numbers")


def test_an_out_too_short_is_refused_before_a_byte_is_written():
    args = (b"[1.0,2.5,-0.0]", b"{}{}{}", 2, 2, b"abcdefgh", [1, 2, 3, 4, 5, 8], [0, 1, 1, 2, 3])
    text = merge_reference(*args)
    assert _merged(*args, room=len(text)) == text
    assert _merged(*args, room=len(text) - 1) is None
