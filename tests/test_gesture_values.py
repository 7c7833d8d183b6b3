"""The compiled gesture values (``gestures.values.frame_values``) equal the numpy reference
(``reference_values``) on random frames, degenerate ones, and the frames of a recording through the
pipeline (realistic sensor errors, a saturated and a dropped sample, an optical loss), for the
pipeline's ``JointPoses`` and for a plain mapping of joints; and the recogniser's output is the same
whichever computes its values."""
import math

import numpy as np
import pytest

from gestures import recognizer as rec_module
from gestures.recognizer import GestureRecognizer, GestureSettings
from gestures.values import frame_values, reference_values, round4_into
from service.model.hand import default_calibration
from service.model.openxr import JOINT_NAMES, FingerAngles, angles_layout, joint_poses
from service.pipeline.hand import HandFrame, HandSession, JointPoses
from service.protocol import parse_message
from service.sim.errors import OpticalModel
from service.sim.session import SimConfig, simulate

S = GestureSettings()
FULL = (S.curl_full_long_rad, S.curl_full_thumb_rad)


def _close(a, b):
    """Equal to 1e-9 (NaN where the other is NaN), and in fact to the last bit."""
    if isinstance(a, dict) or isinstance(b, dict):
        assert (a is None) == (b is None) and a.keys() == b.keys()
        for k in a:
            _close(a[k], b[k])
        return
    if isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _close(x, y)
        return
    assert (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9
    assert np.array_equal(np.float64(a), np.float64(b), equal_nan=True)


def _same(fast, ref):
    _close(fast.curl, ref.curl)
    _close(fast.pinch_distance_m, ref.pinch_distance_m)
    _close(fast.grab_strength, ref.grab_strength)
    assert (fast.ray is None) == (ref.ray is None)
    if ref.ray is not None:
        _close(fast.ray, ref.ray)


def _check(angles, joints):
    _same(frame_values(angles, joints, *FULL), reference_values(angles, joints, *FULL))


def test_random_frames_equal_the_reference_for_both_joint_containers():
    rng = np.random.default_rng(7)
    calib = default_calibration("right")
    for k in range(300):
        scale = (0.5, 3.0, 1e-6)[k % 3]
        angles = {f: rng.normal(0.6, scale, g.n_phalanges) for f, g in calib.fingers.items()}
        positions = rng.normal(0.0, (0.1, 1e-10, 10.0)[k % 3], (len(JOINT_NAMES), 3))
        quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(JOINT_NAMES), 1))
        _check(angles, JointPoses(positions, quats))
        _check(angles, {n: (positions[i], quats[i]) for i, n in enumerate(JOINT_NAMES)})


def test_degenerate_frames_equal_the_reference():
    calib = default_calibration("right")
    rot, pos = np.eye(3), np.zeros(3)
    flat = {f: np.zeros(g.n_phalanges) for f, g in calib.fingers.items()}
    cases = [flat, {**flat, "index": np.array([np.nan, 0.1, 0.1])}, {**flat, "thumb": np.array([np.inf, 0.0])},
             {**flat, "ring": np.array([-0.0, -0.0, -0.0])}, {f: np.full(g.n_phalanges, 3.0) for f, g in calib.fingers.items()}]
    for angles in cases:
        _check(angles, joint_poses(calib, angles if angles is cases[-1] else flat, rot, pos))
    # the index finger without length (no ray), a non-finite tip (no ray), an infinite MCP (NaN direction)
    positions = np.zeros((len(JOINT_NAMES), 3))
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(JOINT_NAMES), 1))
    tip, base = JOINT_NAMES.index("index_tip"), JOINT_NAMES.index("index_proximal")
    assert frame_values(flat, JointPoses(positions, quats), *FULL).ray is None
    _check(flat, JointPoses(positions, quats))
    positions[tip] = [np.nan, 0.0, 0.0]
    _check(flat, JointPoses(positions, quats))
    positions[tip], positions[base] = [0.0, 0.0, 0.1], [np.inf, 0.0, 0.0]
    _check(flat, JointPoses(positions, quats))
    with pytest.raises(KeyError):
        frame_values({"thumb": np.zeros(2)}, JointPoses(positions, quats), *FULL)


def _recorded_frames():
    config = SimConfig(motion="sequence", hand_motion="random", noise="realistic", seed=5, duration_s=4.0,
                       optical=OpticalModel(occlusions_s=((1.5, 1.8),)))
    session, frames = HandSession("right"), []
    for k, m in enumerate(simulate(config).messages(include_truth=False)):
        if m["type"] == "imu" and m["id"] == "index.2":
            if k % 97 == 0:
                continue                                        # a dropped sample
            if k % 89 == 0:
                m = {**m, "gyr": [34.9, -34.9, 34.9]}           # a saturated one (2000 deg/s)
        frames.extend(session.handle(parse_message(m)).frames)
    return frames


def test_recorded_frames_equal_the_reference_and_the_recogniser_output_is_unchanged(monkeypatch):
    frames = _recorded_frames()
    assert len(frames) > 300
    for f in frames:
        _check(f.joint_angles, f.joints)
    fast = GestureRecognizer()
    fast_out, kernel_rounded = [], 0
    for f in frames:
        fast_out.append(fast.update(f))
        kernel_rounded += fast._frame_values[1].rounded is not None    # the annotation as the kernel rounded it
    assert kernel_rounded == len(frames)

    def reference(joint_angles, joints, long_rad, thumb_rad, *pinch):
        return reference_values(joint_angles, joints, long_rad, thumb_rad)

    ruled = GestureRecognizer()               # every rule asked through its GestureRule (no rule table)
    assert [ruled.update_reference(f) for f in frames] == fast_out
    monkeypatch.setattr(rec_module, "frame_values", reference)
    monkeypatch.setattr(GestureRecognizer, "_step", lambda self, frame: None)     # (values through frame_values)
    slow = GestureRecognizer()
    slow_out = [slow.update(f) for f in frames]
    assert fast_out == slow_out
    assert {e["gesture"] for _, events in slow_out for e in events} >= {"point", "grasp"}


_SCRIPT = (   # curls (index, middle, ring, little, thumb), tip distance m, frames to reach the pose, frames held,
    #            and the frame from which the tips are 5 mm apart instead (None: never)
    ((0.05, 0.05, 0.05, 0.05, 0.1), 0.05, 20, 20, None),      # open
    ((0.9, 0.9, 0.9, 0.9, 0.6), 0.05, 40, 10, None),          # grasp
    ((0.35, 0.2, 0.2, 0.2, 0.4), 0.005, 40, 20, None),        # closing tips while it opens slowly: handed over to a pinch
    ((0.05, 0.05, 0.05, 0.05, 0.6), 0.05, 30, 15, None),      # open but for the thumb
    ((0.95, 0.2, 0.2, 0.2, 0.4), 0.05, 40, 25, 50),           # the tips close with the index curled past a pinch
    ((0.1, 0.0, 0.0, 0.0, 0.4), 0.05, 30, 10, None),          # the others straight ...
    ((0.1, 0.35, 0.35, 0.35, 0.4), 0.05, 12, 15, 3),          # ... closing fast as the tips close: a pinch once they slow
    ((0.05, 0.8, 0.8, 0.8, 0.5), 0.05, 40, 10, None),         # point
)
_POSES = ((0.9, 0.9, 0.9, 0.9, 0.6), (0.05, 0.8, 0.8, 0.8, 0.5), (0.35, 0.2, 0.2, 0.2, 0.4),
          (0.05, 0.05, 0.05, 0.05, 0.1), (0.4, 0.55, 0.6, 0.65, 0.5))


def _random_frames(rng, n: int, fingers=("thumb", "index", "middle", "ring", "little")):
    """Frames that move between poses (``_SCRIPT``, then poses of ``_POSES`` at random, each reached in
    40 frames and held for 8), with noise, the tips now close now apart, two late ones with a NaN angle:
    every enter condition of every rule the only one that fails on some frames, and a grasp handed over
    to a pinch."""
    calib = default_calibration("right")
    full = np.array([S.curl_full_long_rad] * 4 + [S.curl_full_thumb_rad])
    column = {f: k for k, f in enumerate(("index", "middle", "ring", "little", "thumb"))}
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(JOINT_NAMES), 1))
    tip_t, tip_i = JOINT_NAMES.index("thumb_tip"), JOINT_NAMES.index("index_tip")
    frames, curls = [], np.array(_POSES[3])
    segments = list(_SCRIPT)
    while len(frames) < n:
        if not segments:
            pick = rng.integers(len(_POSES))
            apart = (0.01, 0.028, 0.05)[rng.integers(3)] if pick != 2 else (0.005, 0.01, 0.028)[rng.integers(3)]
            segments.append((_POSES[pick], apart, 40, 8, None))
        target, apart, ramp, hold, closes_at = segments.pop(0)
        start, target = curls, np.array(target)
        jitter = rng.normal(0.0, 0.002, 3)                         # (held: the tips' rate settles)
        for j in range(ramp + hold):
            k = len(frames)
            offset = jitter + [apart if closes_at is None or j < closes_at else 0.005, 0.0, 0.0]
            curls = start + (target - start) * min(1.0, (j + 1) / ramp)
            angles = {}
            for f in fingers:
                n_ph = calib.finger(f).n_phalanges
                angles[f] = np.full(n_ph, curls[column[f]] * full[column[f]] / n_ph) + rng.normal(0.0, 0.005, n_ph)
            if k in (n - 30, n - 10):             # (a NaN stays in the low-passed rates: late in the sequence)
                angles["index"][1] = np.nan
            positions = rng.normal(0.0, 0.05, (len(JOINT_NAMES), 3))
            positions[tip_t] = positions[tip_i] + offset
            frames.append(HandFrame(k / 90, k, "right", angles, {}, np.eye(3), np.zeros(3), JointPoses(positions, quats), {}))
    return frames[:n]


def _alone_failing(history, settings_of) -> dict:
    """How many frames of a recogniser's ``history`` each enter condition ``(gesture, index)`` was the only
    one of its rule to fail on (``settings_of(k)``: the settings of frame ``k``)."""
    counts = {}
    for k, entry in enumerate(history):
        x = rec_module.Features.from_history(entry)
        for g, rule in rec_module.RULES.items():
            s = settings_of(k)
            failing = [i for i, c in enumerate(rule.conditions) if not c.holds(x, getattr(s, c.enter))]
            if len(failing) == 1:
                counts[(g, failing[0])] = counts.get((g, failing[0]), 0) + 1
    return counts


def _outcome(update, frame):
    try:
        return update(frame)
    except KeyError as e:
        return "KeyError", str(e)


def test_the_rule_table_equals_the_rules_on_random_frames():
    """``update`` (each quantity computed once, the thresholds from a table per settings object) against
    ``update_reference`` (every condition through ``GestureRule``): the same annotations, events and
    state, with the settings changed midway (enrolled thresholds), NaN angles, and frames without a
    thumb (the quantities then left to the rules, which raise ``KeyError`` where they read its curl). The
    frames make every enter condition the only failing one of its rule somewhere (checked through the
    rules themselves), and hand a grasp over to a pinch."""
    rng = np.random.default_rng(11)
    enrolled = GestureSettings(grasp_curl_enter=0.55, pinch_enter_m=0.03, pinch_exit_m=0.04, open_curl_enter=0.2,
                               pinch_others_curl_max=0.7, start_dwell_s=0.03)
    for fingers in (("thumb", "index", "middle", "ring", "little"), ("index", "middle", "ring", "little")):
        frames = _random_frames(rng, 1000, fingers)
        fast, ruled = GestureRecognizer(), GestureRecognizer()
        out_fast, out_ruled = [], []
        for k, f in enumerate(frames):
            if k == 500:
                fast.settings = ruled.settings = enrolled
            out_fast.append(_outcome(fast.update, f))
            out_ruled.append(_outcome(ruled.update_reference, f))
        assert repr(out_fast) == repr(out_ruled)        # (a float's repr is exact; NaN is written as NaN)
        assert repr(fast.history) == repr(ruled.history) and fast.active == ruled.active
        started = {e["gesture"] for out in out_ruled if out[0] != "KeyError" for e in out[1] if e["event"] == "start"}
        if "thumb" in fingers:
            assert started == {"grasp", "point", "pinch", "open"}
            handovers = [k for k, (_, events) in enumerate(out_ruled)
                         if [(e["gesture"], e["event"]) for e in events] == [("grasp", "end"), ("pinch", "start")]]
            assert handovers
            alone = _alone_failing(ruled.history, lambda k: GestureSettings() if k < 500 else enrolled)
            assert {(g, i) for g, rule in rec_module.RULES.items() for i in range(len(rule.conditions))} <= alone.keys()
        else:
            assert ("KeyError", "'thumb'") in out_ruled and started >= {"grasp", "point"}
    # each quantity as QUANTITIES defines it, NaN included
    for k in range(200):
        curl = dict(zip(rec_module.FINGER_ORDER, rng.uniform(-0.2, 1.2, 5)))
        if k % 7 == 0:
            curl["ring"] = np.nan
        x = rec_module.Features(curl, float(rng.uniform(0.0, 0.1)), 0.5, float(rng.normal()), float(rng.normal()))
        q = rec_module._quantities(x)
        assert np.array_equal(q, [f(x) for f in rec_module.QUANTITIES.values()], equal_nan=True)


def test_a_truth_frame_with_plain_joints_gives_the_pipeline_values():
    calib = default_calibration("right")
    rng = np.random.default_rng(3)
    angles = {f: rng.uniform(0.0, 1.2, g.n_phalanges) for f, g in calib.fingers.items()}
    rot, pos = np.eye(3), np.array([0.1, 1.2, -0.3])
    joints = joint_poses(calib, angles, rot, pos)
    frame = HandFrame(0.0, 1, "right", angles, {}, rot, pos, joints, {})
    ray = GestureRecognizer.ray(frame)
    tip, base = joints["index_tip"][0], joints["index_proximal"][0]
    assert ray["origin"] == tip.tolist()
    assert np.allclose(ray["direction"], (tip - base) / np.linalg.norm(tip - base), atol=1e-12)


def _bits(values) -> list:
    return np.asarray(values, dtype=np.float64).view(np.int64).tolist()


def test_round4_into_gives_pythons_round_or_leaves_the_value_to_it():
    """``round4_into`` writes ``round(x, 4)`` to the bit (a zero's sign included) wherever it rounds, and
    leaves to Python's ``round`` only values near a halfway point, huge ones and non-finite ones: random
    values of the annotation's range and of every magnitude, every halfway point k + 1/2 of the last decimal
    in [0, 1] and its neighbours a few ulps away, exact ties (odd multiples of 1/32, half of 10⁻⁴·625·2k+1)."""
    rng = np.random.default_rng(5)
    halfway = (np.arange(10001) + 0.5) / 1e4
    near = [halfway]
    for steps in (1, 2, 3, 40):
        up, down = halfway.copy(), halfway.copy()
        for _ in range(steps):
            up, down = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
        near += [up, down]
    xs = np.concatenate([
        rng.uniform(0.0, 1.0, 20000),
        rng.uniform(-1.0, 1.0, 5000) * 10.0 ** rng.integers(-12, 8, 5000),
        *near, -halfway,
        np.arange(1, 64, 2) / 32.0, -np.arange(1, 64, 2) / 32.0,
        [0.0, -0.0, 4e-5, -4e-5, 5e-5, -5e-5, 1e-300, -1e-300, 999.99994, 999.99996, 1e3, 1e20, -1e20,
         np.nan, np.inf, -np.inf]])
    sentinel = 0.12345                  # not the float nearest any k/10⁴: never a result
    out = np.full_like(xs, sentinel)
    assert round4_into(xs, out) is False
    done = _bits(out) != np.float64(sentinel).view(np.int64)
    left = ~done
    for x, r in zip(xs[done].tolist(), out[done].tolist()):
        assert _bits([r]) == _bits([round(x, 4)]), (x, r, round(x, 4))
    y = xs[left] * 1e4
    with np.errstate(invalid="ignore"):
        assert np.all(~np.isfinite(y) | (np.abs(y) >= 1e7) | (np.abs(y - np.floor(y) - 0.5) < 1e-9))
    assert done[:20000].sum() > 0.999 * 20000        # the annotation's range: all but a rare one near a halfway point
    assert not done[np.isin(xs, np.arange(1, 64, 2) / 32.0)].any()      # exact ties are left to round
    assert _bits(out[np.isin(xs, [-4e-5])]) == _bits([-0.0])            # a zero keeps the value's sign
    one = np.array([0.123456789, -4e-5, 0.5])
    assert round4_into(one, one) is True and _bits(one) == _bits([0.1235, -0.0, 0.5])


def test_the_annotation_rounded_by_the_kernel_equals_pythons_round_at_ties_and_nans(monkeypatch):
    """Frames of the pipeline's kind (``FingerAngles``, ``JointPoses``) whose curls, grab strength or pinch band
    are exactly halfway between two 4-decimal values, a hair off it, zero or NaN: the kernel rounds what it can
    and leaves the rest, and every annotation is the one Python's ``round`` gives (the reference path)."""
    calib = default_calibration("right")
    names = tuple(calib.fingers)
    layout = angles_layout(names, tuple(g.n_phalanges for g in calib.fingers.values()))
    full = {f: S.curl_full_thumb_rad if f == "thumb" else S.curl_full_long_rad for f in names}
    rng = np.random.default_rng(9)
    frames, kinds = [], []
    for k in range(120):
        curls = {f: float(rng.choice([0.03125, 0.09375, 0.00015, 0.5, 0.0, rng.uniform()])) for f in names}
        flat = np.concatenate([np.array([curls[f] * full[f]] + [0.0] * (layout.counts[i] - 1))
                               for i, f in enumerate(names)])
        if k % 4 == 1:
            flat[3] = np.nextafter(flat[3], np.inf)              # a hair above a tie
        if k % 10 == 7:
            flat[5] = np.nan
        positions = rng.normal(0.0, 0.05, (len(JOINT_NAMES), 3))
        tip_t, tip_i = JOINT_NAMES.index("thumb_tip"), JOINT_NAMES.index("index_tip")
        # the tip distance such that the pinch band is 0.25 + 1/32 (a tie) on some frames
        band = (0.25 + 0.03125) if k % 3 == 0 else rng.uniform()
        gap = S.pinch_zero_m + band * (S.pinch_full_m - S.pinch_zero_m)
        positions[tip_t] = positions[tip_i] + [gap, 0.0, 0.0]
        angles = FingerAngles(flat, layout)
        frames.append(HandFrame(k / 90, k, "right", angles, {}, np.eye(3), np.zeros(3),
                                JointPoses(positions, np.tile([0.0, 0.0, 0.0, 1.0], (len(JOINT_NAMES), 1))), {}))
    fast = GestureRecognizer()
    fast_out = []
    for f in frames:
        fast_out.append(fast.update(f))
        kinds.append(fast._frame_values[1].rounded is None)
    assert any(kinds) and not all(kinds)          # some frames left to round, most rounded by the kernel
    monkeypatch.setattr(rec_module, "frame_values", lambda a, j, long_rad, thumb_rad, *pinch:
                        reference_values(a, j, long_rad, thumb_rad))
    monkeypatch.setattr(GestureRecognizer, "_step", lambda self, frame: None)     # (values through frame_values)
    slow = GestureRecognizer()
    assert repr([slow.update(f) for f in frames]) == repr(fast_out)   # (repr: exact, a zero's sign and NaN too)


def _pipeline_kind(frame):
    """``frame`` with its angles as the pipeline's ``FingerAngles`` (one array, finger after finger)."""
    names = tuple(frame.joint_angles)
    layout = angles_layout(names, tuple(len(frame.joint_angles[f]) for f in names))
    flat = np.concatenate([np.asarray(frame.joint_angles[f], dtype=np.float64) for f in names])
    return HandFrame(frame.t, frame.seq, frame.hand, FingerAngles(flat, layout), frame.modes, frame.hand_rotation,
                     frame.hand_position, frame.joints, frame.status, frame.tracked)


def _state(rec):
    return repr((rec.active, rec._candidate, rec._candidate_since, rec._failing_since, rec._confidence, rec._previous,
                 rec._rate, rec._index_rate, rec._tips_rate, rec._handover_since, list(rec.history)))


def test_the_step_kernel_equals_the_rules_on_random_frames(monkeypatch):
    """``update`` on the pipeline's frames (``FingerAngles``: values, rates, quantities and rules in one
    ``step_kernel`` call, ``_step``) against ``update_reference`` (values by ``frame_values``, every condition
    through its ``GestureRule``): the same annotations, events and state after every frame (a float's repr is
    exact), on the frames of ``test_the_rule_table_equals_the_rules_on_random_frames`` (every enter condition
    the only failing one somewhere, a grasp handed over to a pinch, NaN angles), with the settings changed
    midway; a frame whose fingers lack the thumb is left to ``_update`` (and raises as the rules do)."""
    stepped = []
    step = GestureRecognizer._step

    def counted(self, frame):
        out = step(self, frame)
        stepped.append(out is not None)
        return out

    monkeypatch.setattr(GestureRecognizer, "_step", counted)
    rng = np.random.default_rng(12)
    enrolled = GestureSettings(grasp_curl_enter=0.55, pinch_enter_m=0.03, pinch_exit_m=0.04, open_curl_enter=0.2,
                               pinch_others_curl_max=0.7, start_dwell_s=0.03, handover_rate_max=2.5)
    for fingers in (("thumb", "index", "middle", "ring", "little"), ("index", "thumb", "little", "middle", "ring"),
                    ("index", "middle", "ring", "little")):
        frames = [_pipeline_kind(f) for f in _random_frames(rng, 1000, fingers)]
        fast, ruled = GestureRecognizer(), GestureRecognizer()
        del stepped[:]
        started = set()
        for k, f in enumerate(frames):
            if k == 500:
                fast.settings = ruled.settings = enrolled
            a, b = _outcome(fast.update, f), _outcome(ruled.update_reference, f)
            assert repr(a) == repr(b)
            assert _state(fast) == _state(ruled)
            if a[0] != "KeyError":
                started |= {e["gesture"] for e in a[1] if e["event"] == "start"}
        if "thumb" in fingers:
            assert all(stepped) and len(stepped) == len(frames)
            assert started == {"grasp", "point", "pinch", "open"}
        else:
            assert not any(stepped) and started >= {"grasp", "point"}


def test_a_recording_steps_as_it_updates_through_the_rules():
    """The frames of a recording through the pipeline: ``update`` (``_step``) and ``update_reference`` give the
    same outputs and state, frame after frame."""
    frames = _recorded_frames()
    fast, ruled = GestureRecognizer(), GestureRecognizer()
    for f in frames:
        assert type(f.joint_angles) is FingerAngles
        assert repr(fast.update(f)) == repr(ruled.update_reference(f))
        assert _state(fast) == _state(ruled)
    assert fast._steps
