"""A calibration's constants made once and shared by every hand on it (``model.hand.default_calibration``,
``HandCalibration.with_overrides``, ``FingerObservations.of``, ``ChainClosure.of``, ``HandMountings``): the same
numbers as made afresh, never changed by a hand, and a hand that changes its calibration or estimator leaves
the others' outputs as they are."""
from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest

from service.bench.cpu import recording_lines
from service.estimators import chain_kernel as K
from service.estimators.chain import Chain, ChainSettings
from service.estimators.observations import ChainClosure, FingerObservations
from service.model.frames import quat_to_matrix
from service.model.hand import FrozenFingers, HandCalibration, default_calibration, rotation_matrix
from service.pipeline import mounting_kernel as MK
from service.pipeline.mounting import HandMountings
from service.pipeline.tracked import TrackedHand
from service.protocol import encode, parse_line


def _own_copy(calib: HandCalibration) -> HandCalibration:
    """The same calibration as a new, unshared object (its constants made afresh)."""
    return HandCalibration(calib.hand, {name: replace(geom) for name, geom in calib.fingers.items()})


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_a_default_calibration_is_one_shared_frozen_object():
    calib = default_calibration("left")
    assert default_calibration("left") is calib and default_calibration("right") is not calib
    assert type(calib.fingers) is FrozenFingers
    for change in (lambda f: f.__setitem__("index", f["ring"]), lambda f: f.pop("index"), lambda f: f.clear(),
                   lambda f: f.update(index=f["ring"]), lambda f: f.__delitem__("index")):
        with pytest.raises(TypeError):
            change(calib.fingers)
    assert calib == _own_copy(calib)
    again = pickle.loads(pickle.dumps(calib))
    assert again == calib and type(again.fingers) is FrozenFingers
    # another hand length: its own calibration, not the shared one of the default length
    assert default_calibration("left", 0.2) is not calib and default_calibration("left", 0.2) != calib


def test_overrides_of_a_shared_calibration_give_one_shared_calibration_equal_to_a_fresh_one():
    calib = default_calibration("right")
    overrides = {"index": {"lengths": [0.05, 0.03, 0.02], "sensors": [
        {"id": "index.1", "phalanx": 1, "offset": 0.01, "mounting": [0.0, 0.0, 0.0, 1.0]},
        {"id": "index.2", "phalanx": 2, "offset": 0.01, "mounting": [-0.0, 0.0, 0.0, 1.0]}]}}
    shared = calib.with_overrides(overrides)
    assert calib.with_overrides({"index": dict(overrides["index"])}) is shared
    assert type(shared.fingers) is FrozenFingers
    fresh = _own_copy(calib).with_overrides(overrides)
    assert type(fresh.fingers) is dict and fresh == shared
    assert shared.fingers["middle"] is calib.fingers["middle"]
    # -0.0 and 0.0 are different overrides (their text), as their numbers may differ
    positive = calib.with_overrides({"index": {"sensors": [dict(s, mounting=[0.0, 0.0, 0.0, 1.0])
                                                           for s in overrides["index"]["sensors"]]}})
    negative = calib.with_overrides({"index": {"sensors": overrides["index"]["sensors"]}})
    assert positive is not negative
    # what a repr does not tell apart (a numpy array) is not shared
    assert calib.with_overrides({"index": {"lengths": np.array([0.05, 0.03, 0.02])}}).fingers.__class__ is dict
    with pytest.raises(ValueError):
        calib.with_overrides({"index": {"lengths": [0.05, 0.03]}})


def test_a_placement_matrix_is_the_quaternion_matrix_to_the_bit_and_a_new_array_each_time():
    rng = np.random.default_rng(4)
    for q in [(0.0, 0.0, 0.0, 1.0), (-0.0, 0.0, 0.0, 1.0), (0.0, 0.0, -0.0, -1.0), (0, 0, 0, 1),
              *(tuple(float(v) for v in x / np.linalg.norm(x)) for x in rng.normal(size=(20, 4)))]:
        first = rotation_matrix(q)
        assert _same_bits(first, quat_to_matrix(np.asarray(q)))
        first[:] = 7.0                              # the caller's own array
        assert _same_bits(rotation_matrix(q), quat_to_matrix(np.asarray(q)))


@pytest.mark.parametrize("hand", ["right", "left"])
def test_shared_finger_constants_equal_fresh_ones_and_are_read_only(hand):
    calib = default_calibration(hand)
    for geom in calib.fingers.values():
        obs, fresh = FingerObservations.of(geom), FingerObservations(geom)
        assert FingerObservations.of(geom) is obs
        for name, value in vars(fresh).items():
            if isinstance(value, np.ndarray):
                assert _same_bits(getattr(obs, name), value), name
                assert not getattr(obs, name).flags.writeable
                with pytest.raises(ValueError):
                    getattr(obs, name)[...] = 0
        for extra in [(), ((0, 0.5),), ((0, -0.0),)]:
            closure = ChainClosure.of(geom, extra)
            assert ChainClosure.of(geom, extra) is closure
            assert _same_bits(closure.matrix, ChainClosure(geom, extra_couplings=list(extra)).matrix)
            assert not closure.matrix.flags.writeable
        # a chain of this finger: the kernel's geometry vector as made from fresh constants, its own array
        est = Chain(geom, ChainSettings())
        want = K.geometry_vector(fresh, ChainClosure(geom), est.gravity_world)
        assert _same_bits(est._geometry_vector, want) and est._geometry_vector.flags.writeable
        assert Chain(geom, ChainSettings())._geometry_vector is not est._geometry_vector


def test_the_flexion_axis_fits_of_a_shared_calibration_start_as_made_afresh_and_keep_what_they_learned():
    calib = default_calibration("right")
    shared, fresh = HandMountings(calib), HandMountings(_own_copy(calib))
    assert _same_bits(shared.state, fresh.state) and _same_bits(shared._meta, fresh._meta)
    assert _same_bits(shared._st, fresh._st) and shared.places == fresh.places
    assert shared.state.flags.writeable and HandMountings(calib).state is not shared.state
    # what one hand's fits learn stays its own, and a rebuild hands it over as before
    shared.state[:, MK.C0:] += 0.25
    assert _same_bits(HandMountings(calib).state, fresh.state)
    moved = calib.with_overrides({"index": {"sensors": [
        {"id": "index.1", "phalanx": 1, "mounting": [0.0, 0.0, 0.08715574274765817, 0.9961946980917455]},
        {"id": "index.2", "phalanx": 2}]}})
    rebuilt, rebuilt_fresh = HandMountings(moved, previous=shared), HandMountings(_own_copy(moved), previous=shared)
    assert _same_bits(rebuilt.state, rebuilt_fresh.state)
    kept = rebuilt.places["middle.1"][0]
    assert _same_bits(rebuilt.state[kept, MK.C0:], shared.state[shared.places["middle.1"][0], MK.C0:])
    assert not np.array_equal(rebuilt.state[rebuilt.places["index.1"][0], MK.C0:],
                              shared.state[shared.places["index.1"][0], MK.C0:])


def _outputs(hand: TrackedHand, lines: list[str], change=None) -> list[str]:
    """Every output of ``lines`` through ``hand`` as JSON text; ``change(hand, k)`` before line ``k``."""
    out = []
    for k, line in enumerate(lines):
        if change is not None:
            change(hand, k)
        out.extend(encode(m, False) for m in hand.handle(parse_line(line)))
    return out


def _fresh_constants(monkeypatch) -> None:
    """From here on, every hand's constants made afresh for it (nothing shared or kept)."""
    from service.estimators import chain, observations
    from service.pipeline import mounting

    monkeypatch.setattr(observations, "_kept", lambda kind, geom, detail, build: build())
    monkeypatch.setattr(chain, "_geometry_vector", K.geometry_vector)
    monkeypatch.setattr(mounting, "_FRESH", {})
    monkeypatch.setattr(mounting, "FrozenFingers", type("NeverShared", (dict,), {}))


def _change(hand: TrackedHand, k: int, third: int) -> None:
    if k == third:
        hand._session.apply_calibration({"index": {"lengths": [0.06, 0.03, 0.02]}, "thumb": {"coupling": 0.7}})
    elif k == 2 * third:
        hand.set_estimator("chain", {"acc_noise_m_s2": 0.9})


def test_a_hand_that_changes_its_calibration_or_estimator_leaves_another_hand_on_the_shared_one_as_a_fresh_hand():
    lines = recording_lines(1.0, seed=5, batched=True)
    third = len(lines) // 3
    with pytest.MonkeyPatch.context() as monkeypatch:
        _fresh_constants(monkeypatch)
        alone = _outputs(TrackedHand("right"), lines)
        changed_alone = _outputs(TrackedHand("right"), lines, lambda hand, k: _change(hand, k, third))
    assert changed_alone != alone
    # the same recording through a hand whose calibration is an unshared copy: the same outputs
    unshared = TrackedHand("right")
    unshared._session._rebuild(_own_copy(unshared._session.calibration), unshared._session._estimator)
    assert _outputs(unshared, lines) == alone

    # two hands on the shared constants, interleaved message by message as a hand worker runs its sessions;
    # one changes its calibration, then its estimator
    other, changing = TrackedHand("right"), TrackedHand("right")
    got_other, got_changing = [], []
    for k, line in enumerate(lines):
        _change(changing, k, third)
        got_changing.extend(encode(m, False) for m in changing.handle(parse_line(line)))
        got_other.extend(encode(m, False) for m in other.handle(parse_line(line)))
    assert got_other == alone
    assert got_changing == changed_alone
    # and the shared constants are still those of a fresh calibration
    calib = default_calibration("right")
    for geom in calib.fingers.values():
        fresh = FingerObservations(geom)
        assert all(_same_bits(getattr(FingerObservations.of(geom), n), v)
                   for n, v in vars(fresh).items() if isinstance(v, np.ndarray))
    assert _same_bits(HandMountings(calib).state, HandMountings(_own_copy(calib)).state)
