"""The compiled ``OpticalTrack.add`` (``optical_kernel.add``) equals its Python reference ``_add_array`` bit for bit:
the track's arrays, its bounds and its held pose after every pose, on a recorded pose stream and on random ones
with invalid poses, the arrays' wrap, the ``max_poses`` drop and the horizon's pruning (gaps longer than it); and
``at`` reads the same from both."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.pipeline.optical import OpticalTrack
from service.protocol import parse_message

_STATE = ("_t", "_valid", "_position", "_orientation", "_lo", "_hi", "_held_t", "_held_position", "_held_orientation")


def _reference_add(track: OpticalTrack, t, position, orientation_xyzw, valid) -> None:
    """``OpticalTrack.add`` with ``_add_array`` (the Python steps) in place of the compiled kernel."""
    if track.latest_t is not None and t <= track.latest_t:
        raise ValueError(f"pose time must increase: {t} after {track.latest_t}")
    track.latest_t = t
    track._add_array(t, position, orientation_xyzw, valid, t - max(4 * track.window_s, 2 * track.timeout_s))
    if valid:
        track.latest_valid_t = t


def _same(track: OpticalTrack, ref: OpticalTrack, t: float) -> None:
    for name in _STATE:
        got, want = getattr(track, name), getattr(ref, name)
        assert type(got) is type(want) and np.array_equal(got, want, equal_nan=True), (name, t)
    assert track.latest_t == ref.latest_t and track.latest_valid_t == ref.latest_valid_t
    for u in (t - 0.2, t - 0.011, t):
        a, b = track.at(u), ref.at(u)
        assert a[1] == b[1] and (a[0] is None) == (b[0] is None)
        assert a[0] is None or np.array_equal(a[0].flat, b[0].flat) and np.array_equal(a[0].position, b[0].position) \
            and np.array_equal(a[0].velocity, b[0].velocity)


def _counts(track: OpticalTrack, before: tuple, counts: dict) -> None:
    lo, hi, held_t = before
    counts["wrap"] += hi == len(track._t)
    counts["held"] += not np.array_equal(held_t, track._held_t, equal_nan=True)
    counts["drop"] += track._hi - track._lo == track._max_poses and hi - lo == track._max_poses


def test_the_compiled_add_equals_the_reference_on_a_recorded_pose_stream():
    from service.bench.cpu import recording_lines

    poses = [m for m in (parse_message(json.loads(line)) for line in recording_lines(8.0, seed=2, batched=True))
             if m.type == "pose"]
    assert len(poses) > 600 and type(poses[0].position) is list
    counts = {"wrap": 0, "held": 0, "drop": 0}
    for max_poses in (16, 512):
        track, ref = OpticalTrack(max_poses=max_poses), OpticalTrack(max_poses=max_poses)
        for k, m in enumerate(poses):
            valid = m.valid and k % 29 not in (3, 4, 5)            # (the recording's are all valid)
            before = (track._lo, track._hi, track._held_t)
            track.add(m.t, m.position, m.orientation, valid)
            _reference_add(ref, m.t, m.position, m.orientation, valid)
            _counts(track, before, counts)
            _same(track, ref, m.t)
    assert counts["wrap"] > 10 and counts["held"] > 100 and counts["drop"] > 100


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_add_equals_the_reference_on_random_pose_streams(seed):
    """Jittery times with gaps past the horizon (pruning down to two poses), long occlusions (the held pose),
    small and large ``max_poses`` (the drop and the arrays' wrap), positions as lists, arrays and scalars."""
    rng = np.random.default_rng(seed)
    counts = {"wrap": 0, "held": 0, "drop": 0}
    for max_poses in (3, 8, 64):
        track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=max_poses)
        ref = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=max_poses)
        t = 0.0
        for k in range(400):
            t += rng.choice([1.0 / 90.0, 0.002, 0.3, 1.0], p=[0.85, 0.08, 0.05, 0.02]) + rng.uniform(0.0, 0.003)
            valid = not (100 <= k < 160 or rng.random() < 0.15)
            p, q = rng.normal(0.0, 0.3, 3), Rotation.random(random_state=rng).as_quat()
            kind = k % 4
            position = p.tolist() if kind == 0 else p if kind == 1 else float(p[0]) if kind == 2 else tuple(p)
            orientation = q.tolist() if kind != 1 else q
            if not valid and kind == 0:
                position = orientation = None
            before = (track._lo, track._hi, track._held_t)
            track.add(t, position, orientation, valid)
            _reference_add(ref, t, position, orientation, valid)
            _counts(track, before, counts)
            _same(track, ref, t)
    assert counts["wrap"] > 20 and counts["held"] > 20 and counts["drop"] > 100


def test_a_pose_the_arrays_cannot_take_is_refused_and_not_stored():
    """A valid pose whose position or orientation is no vector of its size raises numpy's error, as the reference's
    does, and leaves the stored poses as they were (``latest_valid_t`` too)."""
    track = OpticalTrack()
    track.add(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], True)
    kept = {name: np.copy(getattr(track, name)) for name in _STATE}
    for position, orientation in (([1.0, 2.0], [0.0, 0.0, 0.0, 1.0]), ([1.0, 2.0, 3.0], [0.0, 1.0]),
                                  (np.zeros(4), np.array([0.0, 0.0, 0.0, 1.0]))):
        with pytest.raises(ValueError):
            track.add(track.latest_t + 0.01, position, orientation, True)
        assert track.latest_valid_t == 0.0
        assert all(np.array_equal(getattr(track, name), kept[name], equal_nan=True) for name in _STATE)


def test_the_warm_up_compiles_the_kernel_for_a_message_s_pose():
    """``optical_kernel.add`` is one of the pipeline's kernels the warm-up compiles and checks on disk, and a pose as
    messages give it (lists of floats) takes the signature the warm-up's arrays do."""
    from service.estimators.warm import _pipeline_kernels, _warm_pipeline
    from service.pipeline import optical_kernel

    assert optical_kernel.add in _pipeline_kernels()
    _warm_pipeline()
    compiled = set(optical_kernel.add.signatures)
    OpticalTrack().add(0.5, [0.1, 0.2, 0.3], [0.0, 0.0, 0.0, 1.0], True)
    OpticalTrack().add(0.5, None, None, False)
    assert set(optical_kernel.add.signatures) == compiled
