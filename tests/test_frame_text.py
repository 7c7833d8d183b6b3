"""A frame's JSON text written from the pipeline's arrays (``pipeline.frame_text``) is ``encode``'s text of its
message, byte for byte: on simulated sessions with faults (occlusions, missing and silent sensors, a clock
step), with the live service's seq and drop counts, and where the arrays hold what ``encode`` writes
otherwise (a NaN, an infinity) or the fixed parts cannot be laid out."""
import math

import numpy as np
import pytest

from service.pipeline import frame_text
from service.pipeline.frame_text import FrameOutput
from service.model.hand import FingerGeometry
from service.pipeline import hand as hand_module
from service.pipeline.hand import HandFrame
from service.pipeline.tracked import TrackedHand
from service.protocol import parse_message
from service.protocol.wire import encode
from service.sim.errors import OpticalModel
from service.sim.session import SimConfig, simulate


def _outputs(messages, hand="right"):
    tracked = TrackedHand(hand)
    for m in messages:
        tracked.accept(parse_message(m))
        for out, events in tracked.frame_outputs():
            yield out, events


def _checked(outputs, seed=0):
    """Every output's text against ``encode`` of its message (with a seq offset and drop counts as a hand
    worker sets them); how many were written from the arrays."""
    rng = np.random.default_rng(seed)
    fast = 0
    for out, _ in outputs:
        out.seq += int(rng.integers(0, 3))
        out.set_drops(int(rng.integers(0, 5)), int(rng.integers(0, 5)))
        written = out._text()
        expected = encode(out.message(), binary=False)
        assert out.text() == expected
        if written is not None:
            assert written == expected
            fast += 1
    return fast


@pytest.mark.parametrize("config,written", [
    (SimConfig(motion="sequence", noise="white", seed=3), 0.8),
    (SimConfig(motion="random", t_m_s=3.0, noise="white", hand_motion="slow-rotation", seed=2,
               optical=OpticalModel(occlusions_s=((0.8, 1.1), (2.0, 2.4)))), 0.8),
    # the sensors of the fingers without any are never sampled: their age is null, written from the message
    (SimConfig(motion="pinch", noise="both", seed=4, fingers=("thumb", "index", "middle")), 0.0),
    (SimConfig(motion="grasp", noise="white", seed=6, metacarpus_imu=True, hand_motion="slow-rotation"), 0.8),
], ids=["sequence", "occlusions", "partial-glove", "back-of-hand-imu"])
def test_the_text_is_encodes_text_of_the_message(config, written):
    outputs = list(_outputs(simulate(config).messages()))
    assert len(outputs) > 100 and _checked(outputs) >= written * len(outputs)


def test_left_hand_and_a_clock_step_and_silent_sensor():
    msgs = list(simulate(SimConfig(motion="point", noise="white", seed=5, t_m_s=1.0, hand="left")).messages())
    # a sensor falls silent half way, and the clock steps forward by 10 s for the last quarter
    half, quarter = len(msgs) // 2, 3 * len(msgs) // 4
    edited = []
    for i, m in enumerate(msgs):
        if i > half and m.get("id") == "index.1":
            continue
        if i > quarter:
            m = dict(m)
            if "t" in m:
                m["t"] += 10.0
        edited.append(m)
    outputs = list(_outputs(edited, hand="left"))
    assert _checked(outputs, seed=1) > 0


def _one_output():
    msgs = list(simulate(SimConfig(motion="sequence", noise="white", seed=3, t_m_s=0.5)).messages())
    return [out for out, _ in _outputs(msgs)][-1]


@pytest.mark.parametrize("where", ["angles", "positions", "quats", "t", "status", "gesture"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_non_finite_number_is_written_as_encode_writes_it(where, value):
    out = _one_output()
    frame = out.frame
    if where == "angles":
        frame.joint_angles.flat[2] = value
    elif where == "positions":
        frame.joints.positions[7, 1] = value
    elif where == "quats":
        frame.joints.quats[25, 3] = value
    elif where == "t":
        frame.t = value
    elif where == "status":
        frame.status["dropped"]["late"] = value
    else:
        out.annotation["grab_strength"] = value
    assert out._text() is None
    text = out.text()
    assert text == encode(out.message(), binary=False) and "invalid" in text and "null" in text


def test_a_sensor_never_sampled_and_a_frame_not_of_the_pipeline_are_written_from_the_message():
    out = _one_output()
    out.frame.status["sensors"] = {**out.frame.status["sensors"], "ring.2": {"age_s": None, "silent": True}}
    assert out._text() is None and out.text() == encode(out.message(), binary=False)
    frame = out.frame
    plain = HandFrame(frame.t, frame.seq, frame.hand, {f: frame.joint_angles[f] for f in frame.joint_angles},
                      frame.modes, frame.hand_rotation, frame.hand_position, dict(frame.joints), frame.status, frame.tracked)
    other = FrameOutput(plain, out.calibration, out.annotation)
    assert other._text() is None and other.text() == encode(other.message(), binary=False)


def test_fingers_whose_angles_outnumber_their_joint_names_are_written_from_the_message(monkeypatch):
    out = _one_output()
    monkeypatch.setattr(out, "_layouts", {})
    monkeypatch.setattr(hand_module, "_kept_names", {})
    monkeypatch.setattr(FingerGeometry, "joint_names", property(lambda self: ("mcp",)))
    assert out._text() is None
    assert out.text() == encode(out.message(), binary=False) and '"pip"' not in out.text()


@pytest.mark.parametrize("where", ["mode", "estimator", "hand"])
def test_text_beyond_ascii_is_written_as_encode_writes_it(where):
    """``encode`` writes a message with text beyond ASCII by the standard library (escaped): so does ``text``
    (a mode in the fixed parts, an estimator in the status, a hand in the head)."""
    out = _one_output()
    frame = out.frame
    if where == "mode":
        frame.modes = {**frame.modes, "index": "f\u00fcsed"}
    elif where == "estimator":
        frame.status["estimator"] = "ch\u00e4in"
    else:
        frame.hand = "r\u00efght"
    assert out._text() is None
    text = out.text()
    assert text == encode(out.message(), binary=False) and text.isascii() and "\\u00" in text


def test_a_layout_keeps_its_key_objects_so_a_new_dict_with_an_old_id_is_laid_out_again():
    """The fixed parts are kept under the ids of their calibration, modes and tracked flags: a modes dict
    made after an old one was dropped may get its id, and must not be written with the old one's modes."""
    import dataclasses

    out = _one_output()
    frame, layouts = out.frame, {}
    other = {f: ("slow" if m != "slow" else "fast") for f, m in frame.modes.items()}
    for _ in range(50):                     # (a dict freed is most often the next one's memory)
        modes = dict(frame.modes)
        FrameOutput(dataclasses.replace(frame, modes=modes), out.calibration, out.annotation, layouts).text()
        old = id(modes)
        del modes
        new = dict(other)
        o = FrameOutput(dataclasses.replace(frame, modes=new), out.calibration, out.annotation, layouts)
        assert o.text() == encode(o.message(), binary=False)
        if id(new) == old:
            break


def test_each_hand_keeps_its_own_layouts():
    """A hand's frames keep their fixed parts in the hand's own dict (``TrackedHand``), not in one shared
    by every hand of a worker (which, cleared when full, laid them out again and again at 25 hands)."""
    msgs = list(simulate(SimConfig(motion="sequence", noise="white", seed=3, t_m_s=0.5)).messages())
    hands = [TrackedHand("right") for _ in range(3)]
    before = dict(frame_text._layouts)
    for m in msgs:
        for tracked in hands:
            tracked.accept(parse_message(m))
            for out, _ in tracked.frame_outputs():
                assert out.text() == encode(out.message(), binary=False)
    assert frame_text._layouts == before
    assert all(tracked._layouts for tracked in hands)
    assert not set(hands[0]._layouts) & set(hands[1]._layouts)


def _same_layout(a, b) -> bool:
    if a.fixed is None or b.fixed is None:
        return a.fixed is None and b.fixed is None
    return a.fixed.tobytes() == b.fixed.tobytes() and a.ends.tolist() == b.ends.tolist() \
        and a.holes.tolist() == b.holes.tolist() and a.size == b.size and a.n_angles == b.n_angles


@pytest.mark.parametrize("tracked_all", [True, False])
def test_a_layout_of_new_modes_from_the_layout_without_modes_is_the_one_written_whole(tracked_all):
    """``Layouts.laid_out`` (the modes put into the hand's parts without modes, ``_Modeless``) gives the
    layout ``_layout_of`` writes from the whole message, for every combination of the pipeline's modes and for
    modes it cannot put in (not a plain str, a stand-in's or a hole's text, beyond ASCII, ``null``, quotes)."""
    out = _one_output()
    frame = out.frame
    names = frame.joint_angles.layout.names
    tracked = frame.tracked if tracked_all else {n: i % 3 != 0 for i, n in enumerate(frame_text.JOINT_NAMES)}
    rng = np.random.default_rng(5)
    odd = ["fast", "fused", "", 'say "hi"', "\x01", "\x02", "\\u0002", "null", "an\u00e9", 3, None, "\ud800",
           "nul", "l"]
    layouts = frame_text.Layouts()
    for k in range(60):
        pool = ["fast", "fused", "slow", "held"] if k < 30 else odd
        modes = {f: pool[int(rng.integers(len(pool)))] for f in names}
        key = (out.calibration, frame.joint_angles.layout, modes, tracked)
        assert _same_layout(layouts.laid_out(*key), frame_text._layout_of(*key)), modes
    assert all(m.pieces is not None for m in layouts.modeless.values())


def _faulty_session():
    """A session whose status changes now and then: occlusions, a sensor falling silent, a clock step."""
    msgs = list(simulate(SimConfig(motion="random", t_m_s=3.0, noise="white", hand_motion="slow-rotation", seed=2,
                                   optical=OpticalModel(occlusions_s=((0.8, 1.1), (2.0, 2.4))))).messages())
    half, quarter = len(msgs) // 2, 3 * len(msgs) // 4
    edited = []
    for i, m in enumerate(msgs):
        if i > half and m.get("id") == "index.1":
            continue
        if i > quarter and "t" in m:
            m = {**m, "t": m["t"] + 10.0}
        edited.append(m)
    return edited


def test_a_frames_status_is_the_one_made_for_it_though_shared_until_what_it_holds_changes(monkeypatch):
    """``HandSession._frame_status`` hands the frames one status dict while what it holds stays the same: every
    frame's status equals the one ``_status`` makes for it alone, and most frames share the one before's."""
    msgs = _faulty_session()
    outputs = list(_outputs(msgs))
    statuses = [out.frame.status for out, _ in outputs]
    assert sum(a is b for a, b in zip(statuses, statuses[1:])) > len(statuses) / 2
    monkeypatch.setattr(hand_module.HandSession, "_frame_status", lambda self, now, live: self._status(now, live))
    reference = [out.frame.status for out, _ in _outputs(msgs)]
    assert len(reference) == len(statuses) and len({s["optics"] for s in reference}) >= 2
    assert statuses == reference


def test_the_drop_counts_go_into_a_copy_of_the_shared_status_and_each_message_has_its_own():
    """A worker's drop counts (the same for many frames, then others) put into frames sharing a status: the text is
    ``encode``'s, the shared status is left as it was, and a message's status is its own."""
    import copy

    outputs = list(_outputs(_faulty_session()))
    shared = [out.frame.status for out, _ in outputs]
    before = copy.deepcopy(shared)
    fast = 0
    for k, (out, _) in enumerate(outputs):
        out.set_drops(k // 100, 0 if k < 200 else 3)
        written = out._text()
        expected = encode(out.message(), binary=False)
        assert out.text() == expected and (written is None or written == expected)
        fast += written is not None
        assert out.message()["status"] == out.frame.status and out.message()["status"] is not out.frame.status
        out.message()["status"]["dropped"]["late"] = -1        # (a session's own edits of its message)
    assert fast >= 0.75 * len(outputs)
    assert shared == before
    with_drops = [out.frame.status for out, _ in outputs]
    assert sum(a is b for a, b in zip(with_drops, with_drops[1:])) > len(with_drops) / 2
    assert all(s["dropped"]["late"] != -1 for s in with_drops)
