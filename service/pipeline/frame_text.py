"""A frame's JSON text written from the pipeline's arrays (``FrameOutput.text``), with the message's fixed
parts laid out once: the same text as ``protocol.wire.encode`` of the frame's message, without the message.

A frame message is about 7 kB of JSON, most of it the 26 joints' poses (182 numbers) between keys, radii and
flags that stay the same frame after frame. Built as dicts (``HandFrame.to_message``, 26 joint dicts and a
list per number pair) and then encoded (``orjson``, then ``encode``'s scan for ``null``), it cost a hand
worker about as much as its compiled tick. Here the numbers are written by ``orjson`` (the encoder
``encode`` uses, each number written as it writes it anywhere: the same bytes) from one list per kind
(the joint angles, the positions, the orientations), cut at their separators, and put between the fixed
parts, which ``orjson`` wrote once per calibration, finger layout and tracked flags, each finger's mode put
in once per combination of modes (``_Modeless``, ``_Layout``); the frame's head, status and gesture
annotation are small dicts, written by ``orjson`` as they are. The parts are put together in one compiled call
(``frame_text_kernel.merge``: the texts as ``orjson`` gave them, into a buffer kept per hand).

The text is ``encode``'s only where ``encode`` itself writes ``orjson``'s text: every part is ASCII and every
``null`` in it is one ``encode`` knows holds no number (``_nulls_all_known``: the fixed parts have none,
the numbers are checked finite, ``orjson`` writes a NaN or an infinity as ``null``). Anything else (a
non-finite number, a sensor never sampled, a frame not built by the pipeline) is written from the message,
by ``encode`` (``FrameOutput.text``'s fallback). ``tests/test_frame_text.py`` checks the two equal.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import orjson

from ..model.openxr import JOINT_NAMES, FingerAngles, joint_radii_list
from ..protocol.wire import _ORJSON_STRICT, _nulls_all_known, encode
from .frame_text_kernel import merge
from .hand import JointPoses

_HOLE = "\x01"
"""Where a number goes in the fixed parts while they are written (a string no key or value of a frame holds)."""
_HOLE_TEXT = orjson.dumps(_HOLE)
_NUMPY = orjson.OPT_SERIALIZE_NUMPY
_POSITIONS, _QUATS = (len(JOINT_NAMES), 3), (len(JOINT_NAMES), 4)


class _Layout:
    """The fixed parts of a frame's ``fingers`` and ``joints`` for one calibration, finger layout, modes and
    tracked flags, as ``frame_text_kernel.merge`` reads them: ``fixed`` the parts one after the other (uint8),
    part ``k`` up to ``ends[k]``; a hole between each two for a run of numbers (``holes``: its first number
    and its count in the frame's numbers, the joint angles, then the 26 positions, then the 26 orientations;
    the angles one hole each, then per joint its position and its orientation), and after the last one
    ``,"status":``, ``,"gesture":`` and ``}`` around the frame's status and gesture annotation. ``fixed`` is
    ``None`` where the frame cannot be laid out so (``_layout_of``)."""

    __slots__ = ("key", "fixed", "ends", "holes", "n_angles", "size")

    def __init__(self, key: tuple, parts: list | None, n_angles: int):
        self.key = key          # (the objects themselves: while kept, no other object has their ids)
        self.n_angles = n_angles
        self.fixed = self.ends = self.holes = None
        self.size = 0
        if parts is not None:
            parts = [*parts, b',"status":', b',"gesture":', b"}"]
            self.fixed = np.frombuffer(b"".join(parts), dtype=np.uint8)
            self.ends = np.cumsum([len(p) for p in parts], dtype=np.int64)
            self.holes = _holes(n_angles)
            self.size = len(self.fixed)


@lru_cache(maxsize=16)
def _holes(n_angles: int) -> np.ndarray:
    """``_Layout.holes`` of a frame with ``n_angles`` joint angles (shared by its layouts: ``merge`` only
    reads it)."""
    n, joints = n_angles, len(JOINT_NAMES)
    holes = [(k, 1) for k in range(n)]
    for j in range(joints):
        holes += ((n + 3 * j, 3), (n + 3 * joints + 4 * j, 4))
    return np.array([x for h in holes for x in h] + [n + 7 * joints], dtype=np.int64)


def _layout_of(calib, layout, modes: dict, tracked: dict) -> _Layout:
    """The frame's fixed parts (``_Layout``); ``fixed`` is ``None`` where they cannot be laid out so (a finger
    whose angle count differs from its joint names, a joint without a radius: ``to_message``'s message then)."""
    pieces = _pieces(calib, layout, modes, tracked)
    return _Layout((calib, layout, modes, tracked), pieces, layout.n if pieces is not None else 0)


def _pieces(calib, layout, modes: dict, tracked: dict) -> list[bytes] | None:
    """The fixed parts between the holes of a frame's ``fingers`` and ``joints``, or ``None`` where they cannot
    be laid out so (``_layout_of``)."""
    names_of = {f: g.joint_names for f, g in calib.fingers.items()}
    if any(len(names_of.get(f) or calib.finger(f).joint_names) != c for f, c in zip(layout.names, layout.counts)):
        return None
    fingers = {}
    for f in layout.names:
        angles = dict.fromkeys(names_of.get(f) or calib.finger(f).joint_names, _HOLE)
        angles["mode"] = modes[f]
        fingers[f] = angles
    # a joint's position and orientation each one hole, for the run of its numbers
    joints = {n: {"position": [_HOLE], "orientation": [_HOLE], "radius": r, "tracked": tracked.get(n, True)}
              for n, r in zip(JOINT_NAMES, joint_radii_list(calib))}
    try:
        text = orjson.dumps({"fingers": fingers, "joints": joints}, option=_ORJSON_STRICT)
    except (orjson.JSONEncodeError, TypeError):      # (e.g. a mode or radius that is no plain str or float)
        return None
    pieces = (b"," + text[1:-1]).split(_HOLE_TEXT)
    if not all(p.isascii() and b"null" not in p for p in pieces) or len(pieces) != layout.n + 2 * len(JOINT_NAMES) + 1:
        return None
    return pieces


_MODE = "\x02"
"""Where a finger's mode goes in a ``_Modeless`` layout's parts while they are written (a string no key or value
of a frame holds)."""
_MODE_TEXT = orjson.dumps(_MODE)


class _Modeless:
    """The fixed parts of a frame's ``fingers`` and ``joints`` for one calibration, finger layout and tracked
    flags, with each finger's mode still to be put in (``laid_out``): a hand's fingers change modes often (a
    hand has some 30 combinations of them), and each combination's parts are then these with five strings
    put in, not the whole message written again. ``pieces`` is ``None`` where the parts cannot be made so
    (``_layout_of`` then lays out each combination)."""

    __slots__ = ("key", "pieces", "moded")

    def __init__(self, key: tuple):
        self.key = key          # (the objects themselves: while kept, no other object has their ids)
        calib, layout, tracked = key
        self.pieces = self.moded = None
        pieces = _pieces(calib, layout, dict.fromkeys(layout.names, _MODE), tracked)
        if pieces is None:
            return
        # the parts with modes: (its index, its text around each mode, the fingers whose modes go there)
        moded, finger = [], 0
        for k, p in enumerate(pieces):
            count = p.count(_MODE_TEXT)
            if count:
                moded.append((k, p.split(_MODE_TEXT), range(finger, finger + count)))
                finger += count
        if finger != len(layout.names):       # (a key that is the mode's stand-in too)
            return
        self.pieces, self.moded = pieces, moded

    def laid_out(self, modes: dict) -> _Layout:
        """``_layout_of(*key, modes)``: the parts with the fingers' modes put in."""
        calib, layout, tracked = self.key
        key = (calib, layout, modes, tracked)
        texts = []
        for f in layout.names:
            mode = modes[f]
            if type(mode) is not str:
                return _layout_of(*key)
            try:
                text = orjson.dumps(mode)
            except orjson.JSONEncodeError:      # (e.g. a lone surrogate)
                return _layout_of(*key)
            if _HOLE_TEXT in text or not text.isascii() or b"null" in text:
                return _layout_of(*key)
            texts.append(text)
        pieces = self.pieces.copy()
        for k, around, fingers in self.moded:
            parts = [around[0]]
            for f, after in zip(fingers, around[1:]):
                parts += (texts[f], after)
            pieces[k] = b"".join(parts)       # (no ``null`` across a mode's ends: its quotes are)
        return _Layout(key, pieces, layout.n)


class Layouts(dict):
    """Frame layouts (``_Layout``) by the ids of what they depend on, and the last one used with those objects
    (``last``: most frames have the same as the frame before, found then by four identity checks); the
    layouts without their modes (``modeless``: ``_Modeless`` by the ids of calibration, finger layout and
    tracked flags), each new combination of modes laid out from one of them; where a frame's text is
    written before it becomes a ``str`` (``buffer``: one hand's frames are written one at a time, by one
    thread); and the last status the hand's frames had, with its text (``status``: ``(status, its text or
    None)``, ``None`` where ``encode`` would not write it so), and with the session's drop counts put in
    (``drops``: ``(status, subscriber frames, overloaded, the status with them)``): a hand's frames share one
    status dict until what it holds changes (``HandSession._frame_status``), written once."""

    __slots__ = ("last", "modeless", "buffer", "status", "drops")

    def __init__(self):
        super().__init__()
        self.last: tuple | None = None
        self.modeless: dict = {}
        self.buffer = np.empty(0, dtype=np.uint8)
        self.status: tuple | None = None
        self.drops: tuple | None = None

    def laid_out(self, calib, layout, modes: dict, tracked: dict) -> _Layout:
        """``_layout_of``, from the layout without modes of ``calib``, ``layout`` and ``tracked``."""
        kept = self.modeless
        ids = (id(calib), id(layout), id(tracked))
        modeless = kept.get(ids)
        if modeless is None:
            if len(kept) > 16:                  # bounded: a hand has few
                kept.clear()
            modeless = kept[ids] = _Modeless((calib, layout, tracked))
        if modeless.pieces is None:
            return _layout_of(calib, layout, modes, tracked)
        return modeless.laid_out(modes)


_layouts = Layouts()
"""The layouts of frames made without a hand's own (``FrameOutput``'s ``layouts``)."""


class FrameOutput:
    """A frame and its gesture annotation as the pipeline makes them (``TrackedHand.frame_outputs``): its
    protocol message (``message``) built when asked, its JSON text (``text``) written from its arrays."""

    __slots__ = ("frame", "calibration", "annotation", "seq", "_message", "_layouts")

    def __init__(self, frame, calibration, annotation: dict, layouts: dict | None = None):
        """``layouts``: where the fixed parts of the hand's frames are kept (a dict per hand, ``TrackedHand``'s:
        its keys are the hand's own calibration, modes and tracked flags, 10-30 of them in a session; one dict
        for many hands, cleared when full, would lay them out again and again)."""
        self.frame, self.calibration, self.annotation = frame, calibration, annotation
        self._layouts = _layouts if layouts is None else layouts
        self.seq: int = frame.seq
        """the frame's ``seq`` in its message (a worker continuing a session sets its own)"""
        self._message = None

    @property
    def t(self) -> float:
        return self.frame.t

    @property
    def hand(self) -> str:
        return self.frame.hand

    def message(self) -> dict:
        """The ``frame`` message (``HandFrame.to_message`` with the annotation as its ``gesture``), with
        ``seq``; built once (the same dict at every call: its status a copy of the frame's, with the session's
        drop counts where ``set_drops`` put them in)."""
        msg = self._message
        if msg is None:
            msg = self._message = self.frame.to_message(self.calibration)
            msg["gesture"] = self.annotation
        msg["seq"] = self.seq
        return msg

    def set_drops(self, subscriber_frames: int, overloaded: int) -> None:
        """The session's counts for ``status.dropped`` (frames dropped for slow subscribers, source messages
        refused as overload: the live service's), put into a copy of the frame's status (the pipeline's is
        shared by the hand's frames that have it: ``HandSession._frame_status``), one per status and counts
        while they stay the same (``Layouts.drops``)."""
        frame, layouts = self.frame, self._layouts
        status = frame.status
        own = type(layouts) is Layouts and layouts is not _layouts      # (a hand's own: written by one thread)
        kept = layouts.drops if own else None
        if kept is not None and kept[0] is status and kept[1] == subscriber_frames and kept[2] == overloaded \
                and type(subscriber_frames) is int and type(overloaded) is int:
            frame.status = kept[3]
        else:
            frame.status = {**status, "dropped": {**status["dropped"], "subscriber_frames": subscriber_frames,
                                                  "overloaded": overloaded}}
            if own:
                layouts.drops = (status, subscriber_frames, overloaded, frame.status)
        if self._message is not None:
            self._message["status"]["dropped"].update(frame.status["dropped"])

    def text(self) -> str:
        """``encode(self.message(), binary=False)``, written from the frame's arrays where it can be."""
        fast = self._text()
        return fast if fast is not None else encode(self.message(), binary=False)

    def _text(self) -> str | None:
        frame = self.frame
        angles, joints = frame.joint_angles, frame.joints
        if type(angles) is not FingerAngles or type(joints) is not JointPoses:
            return None
        calibration, modes, tracked = self.calibration, frame.modes, frame.tracked
        layouts = self._layouts
        last = getattr(layouts, "last", None)    # (the frame before's, ``Layouts``; a plain dict has none)
        if last is not None and last[0] is calibration and last[1] is angles.layout and last[2] is modes \
                and last[3] is tracked:
            layout = last[4]
        else:
            key = (calibration, angles.layout, modes, tracked)
            ids = (id(key[0]), id(key[1]), id(key[2]), id(key[3]))
            layout = layouts.get(ids)
            if layout is None:
                if len(layouts) > 64:           # bounded: a hand has few combinations
                    layouts.clear()
                layout = layouts[ids] = layouts.laid_out(*key) if type(layouts) is Layouts else _layout_of(*key)
            if type(layouts) is Layouts:
                layouts.last = (*key, layout)   # (its objects held there: no other object takes their ids meanwhile)
        if layout.fixed is None:
            return None
        try:
            # the small parts first: one that ``encode`` would write otherwise (e.g. a sensor's age ``null``)
            # sends the frame to ``encode`` before the arrays are written; the status written once for the hand's
            # frames that share it (``Layouts.status``)
            status = frame.status
            own = type(layouts) is Layouts and layouts is not _layouts      # (a hand's own)
            kept = layouts.status if own else None
            if kept is not None and kept[0] is status:
                status = kept[1]
            else:
                text = orjson.dumps(status, option=_ORJSON_STRICT)
                if not (text.isascii() and _nulls_all_known(text)):
                    text = None
                if own:
                    layouts.status = (status, text)     # (its object held there: no other object takes its id)
                status = text
            if status is None:
                return None
            head = orjson.dumps({"type": "frame", "t": frame.t, "seq": self.seq, "hand": frame.hand}, option=_ORJSON_STRICT)
            gesture = orjson.dumps(self.annotation, option=_ORJSON_STRICT)
            # (the head and annotation asked at once: no ``null`` can span two of the small parts, each a whole object)
            if not ((rest := head + gesture).isascii() and _nulls_all_known(rest)):
                return None
            small = head + status + gesture
            numbers = joints.numbers
            if numbers is None or joints.angles is not angles.flat:     # (not one array: made one)
                positions, quats = joints.positions, joints.quats
                if positions.shape != _POSITIONS or quats.shape != _QUATS:
                    return None
                numbers = np.concatenate((angles.flat, positions.ravel(), quats.ravel()), dtype=np.float64)
            numbers = orjson.dumps(numbers, option=_NUMPY)
        except (orjson.JSONEncodeError, TypeError, ValueError):
            return None
        # ``orjson`` writes a non-finite number as ``null``: a list of numbers without an ``n`` has none
        if b"n" in numbers:
            return None
        need = layout.size + len(small) + len(numbers)
        if type(layouts) is Layouts and layouts is not _layouts:    # (a hand's own: written by one thread)
            out = layouts.buffer
            if len(out) < need:
                out = layouts.buffer = np.empty(need + 1024, dtype=np.uint8)
        else:
            out = np.empty(need, dtype=np.uint8)
        size = merge(numbers, small, len(head), len(status), layout.fixed, layout.ends, layout.holes, out)
        if size < 0:                            # (numbers not of the layout's count)
            return None
        return str(out[:size], "ascii")
