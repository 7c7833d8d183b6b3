"""The hand pipeline with gestures on simulated recordings: events, faults, ordering, determinism."""
import json

import numpy as np
import pytest

from service.pipeline.tracked import TrackedHand, replay
from service.pipeline.hand import Dropped, HandSession, PipelineSettings
from service.protocol import parse_message
from service.sim.errors import OpticalModel
from service.sim.session import SimConfig, simulate


def _run(messages, settings=None):
    return list(replay((parse_message(m) for m in messages), settings))


def _frames(out):
    return [m for m in out if m["type"] == "frame"]


def _events(out):
    return [(m["gesture"], m["event"], m["t"]) for m in out if m["type"] == "gesture"]


@pytest.fixture(scope="module")
def sequence_clean():
    return simulate(SimConfig(motion="sequence", noise="none", seed=0))


def test_scripted_sequence_gives_exactly_those_events_in_order(sequence_clean):
    out = _run(sequence_clean.messages())
    events = _events(out)
    assert [(g, e) for g, e, _ in events] == [
        ("point", "start"), ("point", "end"), ("grasp", "start"), ("grasp", "end"),
        ("pinch", "start"), ("pinch", "end"), ("open", "start")]
    # each start falls inside (or just after) the transition into its pose: t_d = 0.5, t_m = 0.4
    transitions = {"point": 0.5, "grasp": 2.1, "pinch": 5.1, "open": 6.7}
    for g, e, t in events:
        if e == "start":
            assert transitions[g] < t < transitions[g] + 0.4 + 0.1, (g, t)
    frames = _frames(out)
    assert all(f["gesture"]["active"] != "point" or "ray" in f["gesture"] for f in frames)


def test_frames_carry_angles_joints_and_status(sequence_clean):
    frames = _frames(_run(sequence_clean.messages()))
    f = frames[len(frames) // 2]
    assert set(f["fingers"]) == {"thumb", "index", "middle", "ring", "little"}
    assert set(f["fingers"]["thumb"]) == {"mcp", "ip", "mode"}
    assert len(f["joints"]) == 26
    q = np.array(f["joints"]["index_tip"]["orientation"])
    assert abs(np.linalg.norm(q) - 1) < 1e-9
    assert f["status"]["optics"] == "tracking" and f["status"]["estimator"] == "chain"
    assert set(f["status"]["sensors"]) == set(sequence_clean.sensor_ids)
    # about 90 frames per second of source time
    t = np.array([fr["t"] for fr in frames])
    assert 85 < len(t) / (t[-1] - t[0]) < 95
    # noise-free angles follow the truth
    n = int(round(f["t"] * 200))
    assert np.degrees(abs(f["fingers"]["index"]["mcp"] - sequence_clean.joint_angles["index"][n, 0])) < 1.0


def _angle_error(frames, sess, finger="index"):
    t = np.array([f["t"] for f in frames])
    est = np.array([[f["fingers"][finger][j] for j in ("mcp", "pip", "dip")] for f in frames])
    truth = np.stack([np.interp(t, sess.t, sess.joint_angles[finger][:, j]) for j in range(3)], axis=1)
    return t, np.degrees(np.abs(est - truth)).max(axis=1)


def test_occlusion_keeps_frames_coming_and_recovers_within_half_a_second():
    optical = OpticalModel(occlusions_s=((2.0, 3.0),))
    sess = simulate(SimConfig(motion="random", t_m_s=6.0, noise="white", hand_motion="slow-rotation", seed=2, optical=optical))
    frames = _frames(_run(sess.messages()))
    t = np.array([f["t"] for f in frames])
    assert np.max(np.diff(t)) < 1 / 90 + 1 / 200 + 1e-9            # no gap in the output
    inside = [f for f in frames if 2.15 < f["t"] < 2.95]
    assert inside and all(f["status"]["optics"] == "occluded" for f in inside)
    after = [f for f in frames if f["t"] > 3.1]
    assert all(f["status"]["optics"] == "tracking" for f in after)
    reference = _frames(_run(simulate(SimConfig(motion="random", t_m_s=6.0, noise="white", hand_motion="slow-rotation",
                                                seed=2)).messages()))
    _, err_ref = _angle_error(reference, sess)
    t_occ, err_occ = _angle_error(frames, sess)
    recovered = t_occ >= 3.5
    assert err_occ[recovered].max() < max(1.0, 1.5 * err_ref[np.array([f["t"] for f in reference]) >= 3.5].max())


def test_a_silent_sensor_is_reported_and_its_finger_keeps_angles():
    sess = simulate(SimConfig(motion="sequence", noise="white", seed=3))
    msgs = [m for m in sess.messages() if not (m["type"] == "imu" and m["id"] == "index.2" and m["t"] > 2.0)]
    frames = _frames(_run(msgs))
    silent_at = min(f["t"] for f in frames if f["status"]["sensors"]["index.2"]["silent"])
    assert 2.0 < silent_at <= 2.1
    later = [f for f in frames if f["t"] > 2.1]
    assert all(f["status"]["sensors"]["index.2"]["silent"] for f in later)
    assert all(np.isfinite(f["fingers"]["index"]["mcp"]) for f in later)
    assert later[-1]["status"]["sensors"]["index.2"]["age_s"] > 5.0


def test_out_of_order_and_duplicate_samples_do_not_change_the_frames():
    sess = simulate(SimConfig(motion="pinch", noise="both", seed=4))
    msgs = list(sess.messages())
    reference = _run(msgs)
    rng = np.random.default_rng(0)
    shuffled = list(msgs)
    # reorder IMU messages by up to 10 ms (inside the 20 ms reorder window) and duplicate some
    keyed = [(m.get("t", -1.0) + (rng.uniform(0, 0.01) if m["type"] == "imu" else 0.0), i, m) for i, m in enumerate(shuffled)]
    keyed.sort(key=lambda x: (x[0], x[1]))
    disordered = []
    duplicates = 0
    for _, _, m in keyed:
        disordered.append(m)
        if m["type"] == "imu" and rng.uniform() < 0.05:
            disordered.append(dict(m))
            duplicates += 1
    hand = TrackedHand()
    out = [o for m in disordered for o in hand.handle(parse_message(m))]
    assert [f["fingers"] for f in _frames(out)] == [f["fingers"] for f in _frames(reference)]
    assert _events(out) == _events(reference)
    counters = hand.counters
    # a duplicate arriving after its tick was processed counts as late
    assert counters.duplicate + counters.late == duplicates and counters.duplicate > 0.9 * duplicates
    # a sample far behind the processed time is late: dropped and counted, frames unchanged
    old_imu = next(m for m in msgs if m["type"] == "imu" and m["t"] > 0.5)
    hand = TrackedHand()
    out_late = []
    for m in msgs:
        out_late += hand.handle(parse_message(m))
        if m["type"] == "imu" and m["t"] > 1.0 and hand.counters.late == 0:
            out_late += hand.handle(parse_message(old_imu))
    assert hand.counters.late == 1
    assert [f["fingers"] for f in _frames(out_late)] == [f["fingers"] for f in _frames(reference)]


def test_handle_says_what_a_message_dropped_and_why():
    msgs = list(simulate(SimConfig(motion="point", noise="white", seed=5, t_m_s=1.0)).messages())
    session = HandSession()
    imus = [m for m in msgs if m["type"] == "imu"]
    results = [session.handle(parse_message(m)) for m in msgs]
    assert not any(r.dropped for r in results) and sum(len(r.frames) for r in results) > 10
    again = session.handle(parse_message(imus[-1]))                 # its tick is still pending
    assert again.dropped == Dropped(duplicate=1) and again.frames == []
    processed = next(m for m in imus if m["t"] > imus[-1]["t"] - 0.2)   # processed, no clock step
    old = session.handle(parse_message(processed))
    assert old.dropped == Dropped(late=1)
    stranger = session.handle(parse_message({**imus[-1], "id": "thumb.2", "t": imus[-1]["t"] + 0.001}))
    assert stranger.dropped == Dropped(unknown_sensor=1)
    assert (session.counters.duplicate, session.counters.late, session.counters.unknown_sensor) == (1, 1, 1)


def test_a_calibration_that_does_not_fit_the_hand_changes_nothing():
    """A calibration refused by the pipeline (too few sensors for a finger's joints) leaves the hand as
    it was: the frames equal those of the same stream without it (it used to keep the new calibration
    with the old fingers, so every later sample was dropped as of an unknown sensor)."""
    msgs = [parse_message(m) for m in simulate(SimConfig(motion="grasp", noise="white", seed=11, t_m_s=1.0)).messages()]
    bad = parse_message({"type": "calibration", "fingers": {"index": {"sensors": [{"id": "index.1", "phalanx": 1}]}}})
    half = len(msgs) // 2
    hand, reference = TrackedHand(), TrackedHand()
    out = [o for m in msgs[:half] for o in hand.handle(m)]
    with pytest.raises(ValueError, match="cannot determine its 3 joint angles"):
        hand.handle(bad)
    out += [o for m in msgs[half:] for o in hand.handle(m)]
    expected = [o for m in msgs for o in reference.handle(m)]
    assert len(out) > 20 and json.dumps(out) == json.dumps(expected)


def test_replaying_twice_gives_identical_frames_with_the_steady_tick_shortcut_on_and_off(monkeypatch):
    """Two replays in one process give the same text; the second without the steady tick's shortcut
    (``_process_tick`` skipping the per-finger checks when every finger was advanced together at the last
    tick and every sensor is sampled and live), which must not change a frame: realistic sensor errors
    (the flexion-axis fits learn), a sensor silent for a while, dropped samples and an occlusion."""
    config = SimConfig(motion="sequence", hand_motion="random", noise="realistic", seed=6, duration_s=3.0,
                       optical=OpticalModel(occlusions_s=((2.1, 2.4),)))
    msgs = [m for k, m in enumerate(simulate(config).messages())
            if not (m["type"] == "imu" and ((m["id"] == "ring.1" and 1.0 < m["t"] < 1.4) or (m["id"] == "index.2" and k % 53 == 0)))]
    again = HandSession._advanced_together_again
    taken = []
    monkeypatch.setattr(HandSession, "_advanced_together_again", lambda self: taken.append(again(self)) or taken[-1])
    a = json.dumps(_run(msgs))
    assert 0.5 * len(taken) < sum(taken) < len(taken) and len(taken) > 400     # the steady state, not always
    monkeypatch.setattr(HandSession, "_advanced_together_again", lambda self: False)
    b = json.dumps(_run(msgs))
    assert a == b


def test_a_clock_step_is_reported_not_integrated():
    sess = simulate(SimConfig(motion="open", noise="white", seed=5))
    msgs = []
    for m in sess.messages():
        m = dict(m)
        if "t" in m and m["t"] > 1.0:
            m["t"] += 30.0
        msgs.append(m)
    frames = _frames(_run(msgs))
    assert frames[-1]["status"]["clock_steps"] == 1
    assert frames[-1]["t"] > 31.0
    after = [f for f in frames if f["t"] > 31.3]
    assert after and all(abs(f["fingers"]["index"]["mcp"]) < np.radians(20) for f in after)


def test_estimator_switches_live_from_the_current_estimate(sequence_clean):
    hand = TrackedHand()
    frames = []
    switched_at = None
    for m in sequence_clean.messages():
        if m["type"] == "imu" and m["t"] == 3.0 and m["id"] == "thumb.0":
            hand.set_estimator("madgwick", {"beta": 0.05})
            switched_at = len(frames)
        frames += [o for o in hand.handle(parse_message(m)) if o["type"] == "frame"]
    before, after = frames[switched_at - 1], frames[switched_at]
    assert before["status"]["estimator"] == "chain" and after["status"]["estimator"] == "madgwick"
    assert abs(after["fingers"]["index"]["pip"] - before["fingers"]["index"]["pip"]) < np.radians(2)
    with pytest.raises(ValueError, match="unknown estimator"):
        hand.set_estimator("kalman")
    assert hand.estimator_name == "madgwick"


def test_bad_pipeline_settings_are_rejected():
    from pydantic import ValidationError
    with pytest.raises(ValidationError):
        PipelineSettings(output_rate_hz=-1)
    with pytest.raises(ValidationError):
        PipelineSettings(reorder_windw_s=0.1)


def test_joints_carry_radius_and_tracked_flags_that_follow_sensors_and_optics():
    optical = OpticalModel(occlusions_s=((4.0, 5.0),))
    sess = simulate(SimConfig(motion="sequence", noise="white", seed=4, optical=optical))
    ring = ("ring.1", "ring.2")
    msgs = [m for m in sess.messages() if not (m["type"] == "imu" and m["id"] in ring and m["t"] > 2.0)]
    frames = _frames(_run(msgs))
    ring_joints = {f"ring_{b}" for b in ("proximal", "intermediate", "distal", "tip")}
    early = [f for f in frames if 0.5 < f["t"] < 2.0]
    assert early and all(all(j["tracked"] for j in f["joints"].values()) for f in early)
    silent = [f for f in frames if 2.2 < f["t"] < 3.8]
    assert silent
    for f in silent:
        untracked = {n for n, j in f["joints"].items() if not j["tracked"]}
        assert untracked == ring_joints                       # the ring's metacarpal stays with the optics
    occluded = [f for f in frames if 4.15 < f["t"] < 4.95]
    assert occluded and all(not any(j["tracked"] for j in f["joints"].values()) for f in occluded)
    radii = {n: j["radius"] for n, j in frames[-1]["joints"].items()}
    assert len(radii) == 26 and all(0.005 < r < 0.02 for r in radii.values())
    for finger in ("index", "middle", "ring", "little"):
        assert radii[f"{finger}_tip"] < radii[f"{finger}_proximal"] < radii["palm"]
    assert radii["little_proximal"] < radii["ring_proximal"] < radii["middle_proximal"]


def test_joint_radii_scale_with_the_calibrated_finger():
    from service.model.hand import default_calibration
    from service.model.openxr import joint_radii
    calib = default_calibration("right")
    index = calib.finger("index").lengths_m
    # a little finger calibrated to the index's phalanx lengths is as broad as the index
    same = calib.with_overrides({"little": {"lengths": list(index)}})
    r, r_same = joint_radii(calib), joint_radii(same)
    for bone in ("proximal", "intermediate", "distal", "tip"):
        assert r_same[f"little_{bone}"] == pytest.approx(r[f"index_{bone}"], rel=1e-12)
        assert r[f"little_{bone}"] < r[f"index_{bone}"]


def test_frames_without_radius_or_tracked_still_parse():
    from service.protocol import parse_output
    from service.model.openxr import JOINT_NAMES
    joint = {"position": [0, 0, 0], "orientation": [0, 0, 0, 1]}
    status = {"optics": "tracking", "estimator": "chain", "sensors": {},
              "dropped": {"duplicate": 0, "late": 0, "overflow": 0, "unknown_sensor": 0}, "clock_steps": 0}
    frame = {"type": "frame", "t": 0.0, "seq": 1, "hand": "right", "fingers": {},
             "joints": {name: joint for name in JOINT_NAMES}, "status": status}
    parsed = parse_output(frame)
    assert parsed.joints["palm"].radius is None and parsed.joints["palm"].tracked is True


def test_a_clock_step_is_told_to_the_message_that_made_it():
    """A jump of more than ``clock_step_s`` either way starts a new clock: the message that made it
    gets a ``clock_step`` notice (its source hears it), a message within the step gets nothing."""
    from service.api.replies import drop_replies
    hand = HandSession()

    def imu(t, sid="index.1"):
        return parse_message({"type": "imu", "t": t, "id": sid, "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, 9.81]})
    assert not hand.accept(imu(10.0)) and not hand.accept(imu(10.4))          # within the step: nothing
    back = imu(9.0)
    dropped = hand.accept(back)
    assert dropped == Dropped(clock_step=1) and hand.counters.clock_steps == 1
    [(code, detail)] = drop_replies(back, dropped)
    assert code == "clock_step" and detail.startswith("imu at t=9.0 jumps by more than the clock step")
    batch = parse_message({"type": "imu_batch", "samples": [
        {"t": 9.01, "id": "index.1", "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, 9.81]},
        {"t": 20.0, "id": "index.2", "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, 9.81]}]})
    dropped = hand.accept(batch)                                            # forward: a gap in the stream
    assert dropped == Dropped(clock_step=1) and hand.counters.clock_steps == 2
    assert drop_replies(batch, dropped)[0][0] == "clock_step"
    assert not hand.accept(imu(20.0, "middle.1"))


def test_a_batch_is_taken_in_as_its_samples_one_message_each():
    """``imu_batch`` takes a sample of the time just taken in without checking that time again: the
    same pending ticks, drops and frames as the same samples sent one ``imu`` message each, with a
    duplicate, an unknown sensor, a late sample and the pending table overflowing inside a batch."""
    def sample(t, sid, k=0.0):
        return {"t": t, "id": sid, "gyr": [0.1 + k, -0.2, 0.3], "acc": [0.0, 0.5 + k, 9.8]}

    ids = ["index.1", "index.2", "middle.1"]
    samples = [sample(1.0 + 0.005 * i, s, 0.01 * i) for i in range(12) for s in ids]
    samples.insert(4, sample(1.005, "index.2", 9.0))               # a duplicate of the tick just begun
    samples.insert(7, sample(1.01, "index.0"))                       # a sensor the calibration does not place
    samples += [sample(0.99, "index.1"), sample(0.99, "index.2")]    # older than every pending tick: pushed out
    settings = PipelineSettings(max_pending_ticks=8)
    batched, single = HandSession(settings=settings), HandSession(settings=settings)
    dropped = batched.accept(parse_message({"type": "imu_batch", "samples": samples}))
    singles = [single.accept(parse_message({"type": "imu", **s})) for s in samples]
    assert dropped == Dropped(duplicate=1, unknown_sensor=1, overflow=4 * 3 + 2)
    assert [sum(getattr(d, r) for d in singles) for r in ("duplicate", "unknown_sensor", "overflow")] == [1, 1, 14]
    assert batched._pending == single._pending and len(batched._pending) == 8
    assert batched._newest_imu_t == single._newest_imu_t == max(s["t"] for s in samples)

    # a whole recording, each tick in one batch, against one message per sample (a late sample in a batch too)
    msgs = list(simulate(SimConfig(motion="pinch", noise="both", seed=4, duration_s=2.0)).messages(include_truth=False))
    grouped, batch = [], []
    for m in msgs:
        if m["type"] == "imu" and (not batch or batch[-1]["t"] == m["t"]):
            batch.append({k: m[k] for k in ("t", "id", "gyr", "acc")})
            continue
        if batch:
            grouped.append({"type": "imu_batch", "samples": batch})
            batch = []
        if m["type"] == "imu":
            batch.append({k: m[k] for k in ("t", "id", "gyr", "acc")})
        else:
            grouped.append(m)
    if batch:
        grouped.append({"type": "imu_batch", "samples": batch})
    late = next(i for i, m in enumerate(grouped) if m["type"] == "imu_batch" and m["samples"][0]["t"] > 1.0)
    earlier = next(m for m in grouped[late - 40::-1] if m["type"] == "imu_batch")
    grouped[late]["samples"].insert(1, dict(earlier["samples"][0]))
    ungrouped = [x for m in grouped
                 for x in ([{"type": "imu", **s} for s in m["samples"]] if m["type"] == "imu_batch" else [m])]
    a, b = TrackedHand(), TrackedHand()
    out_a = [o for m in grouped for o in a.handle(parse_message(m))]
    out_b = [o for m in ungrouped for o in b.handle(parse_message(m))]
    assert len(_frames(out_a)) > 100 and out_a == out_b
    assert a.counters == b.counters and a.counters.late == 1


@pytest.mark.parametrize("event", ["clock_step", "optical_fit_failed"])
def test_still_samples_wait_for_a_full_optics_window_after_the_optics_start_again(event):
    """The offsets' still samples are taken only while the optics' fit window is full of poses since they
    last came back (``mounting.HandMountings.admit_still``): their rate is zero at the first pose and lags
    after it. A clock step, or an optical fit that failed numerically, starts the optics again from one
    pose: the window is not full then either."""
    from service.pipeline import mounting_kernel as K

    msgs = list(simulate(SimConfig(motion="pinch", noise="both", seed=4, duration_s=3.0)).messages(include_truth=False))
    session = HandSession("right", PipelineSettings())
    window, step = session.settings.pose_window_s, 1.5
    jump = 10.0 if event == "clock_step" else 0.0
    at = session.optics.at

    def failing_at(t):                                  # the old track's fit fails once, from ``step`` on
        if t >= step:
            raise np.linalg.LinAlgError("singular")
        return at(t)

    if event == "optical_fit_failed":
        session.optics.at = failing_at
        # the failure is injected into the tick by tick path's fit (``optics.at``): every tick through it,
        # none held back for a compiled run (``HandSession._defer``), and the state seen after each message
        session._defer = lambda t: False
    seen = []
    for m in msgs:
        if "t" in m and m["t"] >= step:
            m = {**m, "t": m["t"] + jump}               # (a clock step: the glove's clock jumps forward)
        session.handle(parse_message(m))
        fits, t = session._mount_fits, session._tick_t        # (the last tick that reached the fusion)
        if fits and t is not None and (not seen or seen[-1][0] != t):
            seen.append((t, fits._st[K.ST_STILL_ON] == 1.0))
    assert session.counters.clock_steps + session.counters.filter_resets == 1
    after = [(t, on) for t, on in seen if t >= step + jump]
    assert any(on for t, on in seen if t < step) and any(on for _, on in after)       # on before and after
    # the new track's poses are from ``step`` on (those before went to the old one): a full window after
    assert after and not any(on for t, on in after if t < step + jump + window - 1e-9)


def test_an_outage_on_the_old_clock_is_not_told_to_the_estimators_after_a_clock_step(monkeypatch):
    """The optics lost when the glove's clock steps: the estimators built on the new clock are not told
    an outage measured across the step (10 s forward here: their angles' uncertainty was widened for 10 s
    of drift; a step back gave a negative duration)."""
    from service.estimators.chain import Chain

    told = []
    monkeypatch.setattr(Chain, "reference_lost", lambda self, duration_s: told.append(duration_s))
    msgs = list(simulate(SimConfig(motion="pinch", noise="both", seed=4, duration_s=3.0)).messages(include_truth=False))
    session = HandSession("right", PipelineSettings())
    step, jump = 1.5, 10.0
    for m in msgs:
        if m["type"] == "pose" and (1.2 <= m["t"] < step or 2.0 <= m["t"] < 2.3):
            continue                                    # occluded before the step, and once after it
        if "t" in m and m["t"] >= step:
            m = {**m, "t": m["t"] + jump}
        session.handle(parse_message(m))
    assert session.counters.clock_steps == 1
    # the occlusion after the step is told (0.3 s of poses missing, less the optics' pose timeout; once per
    # finger), the one across it is not
    assert told and all(0.0 < d < 0.3 for d in told), told


def test_a_frames_message_from_its_one_array_of_angles_equals_the_one_from_a_dict(sequence_clean):
    """The pipeline's frames hold every finger's angles in one array (``FingerAngles``); their message is
    the same text as that of the same frame with the angles given finger by finger."""
    from dataclasses import replace as replaced
    from service.model.openxr import FingerAngles
    from service.protocol import encode

    session = HandSession()
    frames = [f for m in list(sequence_clean.messages())[:1500] for f in session.handle(parse_message(m)).frames]
    assert len(frames) > 50
    for f in frames[::7]:
        assert type(f.joint_angles) is FingerAngles
        plain = replaced(f, joint_angles={n: a.copy() for n, a in f.joint_angles.items()})
        assert encode(f.to_message(session.calibration), False) == encode(plain.to_message(session.calibration), False)


def _late_poses(msgs: list[dict], start: float, end: float) -> list[dict]:
    """``msgs`` with the poses of ``[start, end)`` (source time) arriving 0.12 s late (after the IMU of then:
    ticks past the last pose are released by ``pose_timeout_s``)."""
    late = [m for m in msgs if m["type"] == "pose" and start <= m["t"] < end]
    out, pending = [], list(late)
    for m in msgs:
        if m in late:
            continue
        t = m["samples"][-1]["t"] if m["type"] == "imu_batch" else m.get("t")
        while pending and t is not None and t >= pending[0]["t"] + 0.12:
            out.append(pending.pop(0))
        out.append(m)
    return out + pending


@pytest.mark.parametrize("poses", ["on time", "late", "a hello and a switch midway"])
def test_ticks_held_back_for_the_next_frame_change_no_output(poses):
    """A ready tick that makes no frame waits to run with the next ticks (``HandSession._defer``): the frames,
    the drops of each message and the counters are those of processing every tick as soon as it is ready,
    with a late sample for a held-back tick dropped as late; also with poses arriving after ticks past the
    last pose were released (a pose then must not go in before them)."""
    from service.bench.cpu import recording_lines

    msgs = [json.loads(line) for line in recording_lines(2.0, seed=3, batched=True)]
    if poses == "late":
        msgs = _late_poses(msgs, 0.8, 1.2)
    middle = len(msgs) // 2 if poses == "a hello and a switch midway" else None
    if middle is not None:                          # held-back ticks run before either (with the old estimator)
        msgs.insert(middle, {"type": "hello", "protocol": 1, "hand": "right", "source": "again"})
    held = HandSession("right", PipelineSettings())
    eager = HandSession("right", PipelineSettings())
    eager._defer = lambda t: False
    defer, deferred = held._defer, []

    def counting(t):
        ok = defer(t)
        deferred.append(ok)
        return ok

    held._defer = counting
    late_sent = False
    for i, m in enumerate(msgs):
        if middle is not None and i == middle + 40:
            for session in (held, eager):
                session.set_estimator("vector")
        outs = []
        for session in (held, eager):
            handled = session.handle(parse_message(m))
            outs.append(([f.to_message(session.calibration) for f in handled.frames], handled.dropped))
        assert outs[0] == outs[1]
        if held._deferred and not late_sent:           # a sample for a held-back tick's time: late in both
            t = next(iter(held._deferred))
            sample = {"type": "imu", "t": t, "id": m["samples"][0]["id"], "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, 9.81]}
            assert held.accept(parse_message(sample)) == eager.accept(parse_message(sample)) == Dropped(late=1)
            late_sent = True
    assert late_sent and sum(deferred) > 100
    assert held.counters == eager.counters
    assert held.status() == eager.status()


def test_the_fingers_stacked_together_keep_their_own_angles_when_a_finger_s_sensors_fall_silent_and_return(monkeypatch):
    """The stacked fingers' angle slices are kept while the same fingers are stacked (``_take_together``):
    with the thumb's sensors silent for 1.5 s (it leaves the stack, then comes back) the frames are the same
    as with the slices made anew at every tick."""
    import json

    from service.pipeline import hand as hand_module
    from service.pipeline.tracked import TrackedHand
    from service.protocol import parse_message
    from service.sim.session import SimConfig, simulate

    cfg = SimConfig(motion="sequence", hand_motion="random", noise="realistic", seed=6, duration_s=4.0)
    msgs = [m for m in simulate(cfg).messages()
            if not (m["type"] == "imu" and m["id"].startswith("thumb.") and 1.0 < m["t"] < 2.5)]

    def frames() -> str:
        hand, out = TrackedHand(), []
        for m in msgs:
            out += hand.handle(parse_message(m))
        return json.dumps(out)

    kept = frames()
    take = hand_module.HandSession._take_together

    def anew(self, *args):
        self._phi_slices = None
        return take(self, *args)
    monkeypatch.setattr(hand_module.HandSession, "_take_together", anew)
    assert kept == frames()


def test_a_pose_goes_in_before_the_held_back_ticks_only_if_every_unchecked_fit_of_them_is_usable(monkeypatch):
    """``HandSession._pose_keeps`` asks ``optical_kernel.pose_keeps_in`` (``add_keeps`` and ``usable`` in one call)
    about every held-back tick not checked yet (each once) and follows its answer: one failing fit, the last
    tick's included, and the pose waits for the held-back ticks (they are processed first)."""
    from service.pipeline import hand as hand_module

    from service.bench.cpu import recording_lines

    msgs = [parse_message(json.loads(line)) for line in recording_lines(2.0, seed=3, batched=True)]
    real = hand_module.optical_kernel.pose_keeps_in
    asked, refuse_last = [], [False]

    def spy(t_new, t0, times, *args):
        asked.append(list(times))
        done = real(t_new, t0, times, *args)
        return min(done, len(times) - 1) if refuse_last[0] else done

    monkeypatch.setattr(hand_module.optical_kernel, "pose_keeps_in", spy)
    for refuse in (False, True):
        refuse_last[0] = refuse
        session, checked, flushed = HandSession(), 0, 0
        for m in msgs:
            if m.type == "pose" and session._deferred:
                unchecked = list(session._deferred)[session._deferred_fits:]
                asked.clear()
                keeps = session._pose_keeps(m.t)
                if asked:
                    assert asked == [unchecked]                 # each unchecked tick, once, in order
                    checked += 1
                    assert keeps is not refuse
                flushed += not keeps
            session.accept(m)
            list(session.ready_frames())
        assert checked > 20 and (flushed >= checked if refuse else flushed < checked)


@pytest.mark.parametrize("rate_hz", [200.0, 1000.0])
def test_tick_ready_says_whether_the_frames_message_has_a_tick_to_process_now(rate_hz):
    """After each frame, ``tick_ready`` says whether ``ready_frames``, resumed, processes another tick before it ends
    (a hand worker sends the frame at once then, not with the message's reply): a ready tick it only holds back for
    the next frame's run (``_defer``) is not one. At 200 Hz IMU (90 Hz frames) a pose releases two or three ticks and
    the one after its frame's is held back, most often; at 1 kHz the ten or so after the frame are processed."""
    from clients.glove import source_messages

    config = SimConfig(motion="random", t_m_s=2, noise="both", hand_motion="slow-rotation", seed=0, rate_hz=rate_hz)
    session = HandSession("right")
    answers = {True: 0, False: 0}
    for _, raw in source_messages(config):
        session.accept(parse_message(raw))
        asked = None
        for _ in session.ready_frames():
            if asked is not None:                   # a frame made since: its ticks were processed
                assert asked[1], "a frame after a frame that had nothing to process behind it"
            asked = (session._processed_t, session.tick_ready())
            answers[asked[1]] += 1
        if asked is not None:                       # the generator's end: a tick processed since the last frame?
            assert (session._processed_t != asked[0]) == asked[1], (rate_hz, asked)
    assert answers[False] >= 10, answers
    if rate_hz == 1000.0:
        assert answers[True] >= 3 * answers[False], answers
    else:
        assert answers[False] >= 3 * answers[True], answers


def test_next_frame_covered_says_whether_the_next_frame_waits_for_a_pose():
    """After a frame made while its message has ticks left (a pose at 1 kHz), ``next_frame_covered`` says whether
    the next frame's tick is received and covered by a pose already (it then waits only for the reorder window's
    IMU samples: the hand worker does not yield its core then, ``hands.worker.hand_over``). Where it says no,
    the next frame is always made by a pose; where it says yes, by an IMU message in most cases (26 of 29 here)."""
    from clients.glove import source_messages

    config = SimConfig(motion="random", t_m_s=3, noise="both", hand_motion="slow-rotation", seed=0, rate_hz=1000.0)
    hand = TrackedHand("right")
    asked, seen = None, {True: [], False: []}
    for _, raw in source_messages(config):
        msg = parse_message(raw)
        hand.accept(msg)
        for _ in hand.outputs():
            if asked is not None:
                seen[asked].append(msg.type)
                asked = None
            if hand.tick_ready():
                asked = hand.next_frame_covered()
    assert len(seen[False]) >= 100 and set(seen[False]) == {"pose"}, seen[False][:10]
    assert len(seen[True]) >= 20 and seen[True].count("imu_batch") >= 0.8 * len(seen[True]), seen[True]
