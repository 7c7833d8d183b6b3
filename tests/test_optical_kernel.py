"""The compiled ``OpticalTrack.at`` (``pipeline/optical_kernel.py``) equals ``at_reference`` (numpy
and scipy) on a jittery pose stream with occlusions short and long (the held pose after pruning),
queries between, at and beyond the poses, and few poses in the fit window."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.kinematics import BaseMotion
from service.pipeline.optical import OpticalTrack


def _compare(track, t, plain):
    got, tracking = track.at(t)
    want, tracking_ref = track.at_reference(t)
    got_plain, tracking_plain = plain.at(t)             # the pipeline's kind of track: the same answer, bit for bit
    assert tracking_plain == tracking and (got_plain is None) == (got is None)
    assert got is None or np.array_equal(got_plain.flat, got.flat) and np.array_equal(got_plain.position, got.position) \
        and np.array_equal(got_plain.velocity, got.velocity)
    assert tracking == tracking_ref
    assert (got is None) == (want is None)
    if want is None:
        return 0
    for name in ("rotation", "position", "velocity", "acceleration", "angular_velocity", "angular_acceleration"):
        np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-9, atol=1e-9, err_msg=f"{name} at {t}")
    # the kernels' layout, taken from the kernel's output, is the one BaseMotion computes from the fields
    again = BaseMotion(got.rotation, got.position, got.velocity, got.acceleration, got.angular_velocity,
                       got.angular_acceleration)
    assert np.array_equal(got.flat, again.flat) and got.flat.flags.c_contiguous and got.flat.dtype == np.float64
    return 2 if tracking else 1


def test_compiled_optical_track_equals_the_reference():
    rng = np.random.default_rng(5)
    track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=64, reference=True)
    plain = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=64)
    seen = {0: 0, 1: 0, 2: 0}
    t, rot, pos = 0.0, Rotation.random(random_state=rng), rng.normal(0.0, 0.3, 3)
    omega, vel = rng.normal(0.0, 2.0, 3), rng.normal(0.0, 0.5, 3)
    seen[_compare(track, 0.0, plain)] += 1                            # nothing yet
    for k in range(700):
        t += 1.0 / 90.0 + rng.uniform(-0.002, 0.002)
        omega += rng.normal(0.0, 0.5, 3)
        rot = Rotation.from_rotvec(omega / 90.0) * rot
        pos = pos + vel / 90.0
        lost = 150 <= k < 160 or 300 <= k < 420 or (k % 37 == 5)     # short and long occlusions, single drops
        q = rot.as_quat() * (-1.0 if k % 5 == 0 else 1.0) * (1.0 + 1e-7 * rng.normal())   # either sign, not quite unit
        noisy = pos + rng.normal(0.0, 5e-4, 3)
        track.add(t, noisy, q, not lost)
        plain.add(t, noisy, q, not lost)
        for query in (t - 0.03, t - 0.011, t, t + 0.004):
            seen[_compare(track, query, plain)] += 1
    assert seen[0] >= 1 and seen[1] > 100 and seen[2] > 1000
    with pytest.raises(ValueError, match="reference=True"):
        OpticalTrack().at_reference(0.0)            # the pipeline's tracks keep no poses for it


def test_usable_counts_the_times_whose_fit_is_none_or_finite_as_the_pipeline_checks_them():
    """``optical_kernel.usable`` (the held-back ticks' fits in one call, ``HandSession._pose_keeps``) is the
    number of leading times at which ``at`` gives no kinematics or ones ``_finite_motion`` accepts: on a
    jittery stream, before the first pose, and where positions of 1e308 m make the fit non-finite."""
    from service.pipeline import optical_kernel
    from service.pipeline.hand import _finite_motion

    def expected(track, times):
        for i, t in enumerate(times):
            hand, _ = track.at(t)
            if hand is not None and not _finite_motion(hand):
                return i
        return len(times)

    rng = np.random.default_rng(7)
    track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=64)
    def usable(times):
        outs, statuses = np.full((len(times), 24), np.nan), np.full(len(times), -1)
        got = optical_kernel.usable(times, *track.kernel_args(), outs, statuses)
        for i in range(min(got + 1, len(times))):           # each time's output and result: at()'s
            out = np.empty(24)
            assert statuses[i] == optical_kernel.at(times[i], *track.kernel_args(), out)
            assert statuses[i] == optical_kernel.NONE or np.array_equal(outs[i], out, equal_nan=True)
        return got

    times = np.array([-0.02, -0.01])
    assert usable(times) == 2 == expected(track, times)
    t, rot = 0.0, Rotation.random(random_state=rng)
    finite = infinite = 0
    for k in range(300):
        t += 1.0 / 90.0 + rng.uniform(-0.002, 0.002)
        rot = Rotation.from_rotvec(rng.normal(0.0, 0.05, 3)) * rot
        huge = k in (100, 101, 200)         # positions whose sums overflow: a non-finite fit
        track.add(t, np.full(3, 1e308) if huge else rng.normal(0.0, 0.3, 3), rot.as_quat(), k % 41 != 7)
        times = np.sort(rng.uniform(t - 0.05, t, 4))
        got = usable(times)
        assert got == expected(track, times)
        finite += got == 4
        infinite += got < 4
    assert finite > 100 and infinite > 0


def test_add_keeps_holds_only_where_the_added_pose_changes_no_fit_from_t0_on():
    """``OpticalTrack.add_keeps`` (``optical_kernel.keeps``, as compiled and as Python): where it says a new pose
    keeps the fits from ``t0`` on, ``at`` gives the same bits at times from ``t0`` to the newest pose after the
    add as before it; on a stream with invalid poses, a track that drops poses when full and prunes old ones,
    new poses near and far and ``t0`` inside and before the fit window (where it says so often, and often not)."""
    import copy

    from service.pipeline import optical_kernel

    rng = np.random.default_rng(11)
    answers = {True: 0, False: 0}
    for max_poses in (8, 64):
        track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=max_poses)
        t = 0.0
        for k in range(300):
            t += 1.0 / 90.0 + rng.uniform(-0.003, 0.003)
            track.add(t, rng.normal(0.0, 0.3, 3), Rotation.random(random_state=rng).as_quat(), k % 13 not in (3, 4))
            for _ in range(3):
                t0 = t - rng.uniform(-0.01, 0.3)
                t_new = t + rng.choice([1e-3, 0.02, 0.2, 0.5])
                keeps = track.add_keeps(t_new, t0)
                assert keeps == optical_kernel.keeps.py_func(t_new, t0, track._t, track._valid, track._lo, track._hi,
                                                             max_poses, 0.15, 0.1)
                answers[keeps] += 1
                if keeps:
                    after = copy.deepcopy(track)
                    after.add(t_new, rng.normal(0.0, 0.3, 3), Rotation.random(random_state=rng).as_quat(), True)
                    for u in np.linspace(t0, t, 5) if t0 <= t else ():     # (the times covered now)
                        a, b = track.at(u), after.at(u)
                        assert a[1] == b[1] and (a[0] is None) == (b[0] is None)
                        assert a[0] is None or np.array_equal(a[0].flat, b[0].flat) and \
                            np.array_equal(a[0].position, b[0].position) and np.array_equal(a[0].velocity, b[0].velocity)
    assert answers[True] > 100 and answers[False] > 100


def test_motion_sum_is_the_sum_finite_motion_takes_and_sees_every_number():
    """``optical_kernel.motion_sum`` (``steady_run``'s and ``usable``'s check) is the very sum
    ``HandSession._finite_motion`` takes of a ``BaseMotion`` made of ``at``'s output, bit for bit, and is not
    finite where any one of the 24 numbers is not (the rotation, position, velocity, acceleration, angular
    velocity or angular acceleration)."""
    from service.pipeline import optical_kernel
    from service.pipeline.hand import _finite_motion
    from service.pipeline.optical import _FLAT, motion_of

    rng = np.random.default_rng(3)
    for _ in range(200):
        out = rng.normal(0.0, 10.0 ** rng.integers(-3, 300), 24)
        hand = motion_of(out, out[_FLAT])
        want = sum(hand.flat.tolist()) + sum(hand.position.tolist()) + sum(hand.velocity.tolist())
        assert optical_kernel.motion_sum(out) == want or (np.isnan(want) and np.isnan(optical_kernel.motion_sum(out)))
        assert np.isfinite(optical_kernel.motion_sum(out)) == _finite_motion(hand)
    for k in range(24):
        for bad in (np.nan, np.inf, -np.inf):
            out = np.ones(24)
            out[k] = bad
            assert not np.isfinite(optical_kernel.motion_sum(out))


def test_usable_equals_the_per_tick_check_on_tracks_with_gaps_and_huge_positions():
    """``usable`` against ``at`` + ``_finite_motion`` per time on random tracks: invalid poses, gaps past the
    timeout (the last valid pose held), times before the first pose and past the last, positions up to 1e308
    (sums that overflow in the position, the velocity or the acceleration); failing fits at tracked and at
    held times among them."""
    from service.pipeline import optical_kernel
    from service.pipeline.hand import _finite_motion

    rng = np.random.default_rng(11)
    kinds = {True: 0, False: 0}
    for trial in range(120):
        track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=64)
        t = rng.uniform(-5.0, 5.0)
        rot = Rotation.random(random_state=rng)
        scale = 10.0 ** rng.choice([0, 200, 306, 307, 308])
        for k in range(40):
            t += rng.choice([1 / 90, 1 / 90, 0.3]) + rng.uniform(-0.002, 0.002)
            rot = Rotation.from_rotvec(rng.normal(0.0, 0.05, 3)) * rot
            with np.errstate(over="ignore"):         # (a product past the largest float: infinite, then clipped)
                p = np.clip(rng.normal(0.0, 1.0, 3) * (scale if rng.random() < 0.3 else 1.0), -1.7e308, 1.7e308)
            track.add(t, p, rot.as_quat(), bool(rng.random() > 0.1))
            times = np.sort(rng.uniform(t - 0.4, t + 0.4, int(rng.integers(1, 6))))
            want = len(times)
            for i, u in enumerate(times):
                hand, tracking = track.at(u)
                if hand is not None and not _finite_motion(hand):
                    want = i
                    kinds[tracking] += 1
                    break
            outs, statuses = np.empty((len(times), 24)), np.empty(len(times), dtype=np.int64)
            assert optical_kernel.usable(times, *track.kernel_args(), outs, statuses) == want
    assert kinds[True] > 10 and kinds[False] > 10


def test_at_with_work_arrays_kept_from_call_to_call_gives_the_bits_of_a_fresh_call():
    """``optical_kernel.at_in`` with one set of work arrays (``at_scratch``) for many times on a track, as
    ``tick_kernel.steady_run`` and ``usable`` call it, keeps the fit window's rotation vectors from the call
    before when the window is the same: each answer is ``at``'s (fresh arrays) to the bit, on a jittery
    stream with occlusions, for times in 1 ms steps across several poses (windows that grow, shrink and
    slide by one pose at the same size), and the kept window is used (some calls find it)."""
    from service.pipeline import optical_kernel as OK

    rng = np.random.default_rng(11)
    track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=64)
    t, rot, pos = 0.0, Rotation.random(random_state=rng), rng.normal(0.0, 0.3, 3)
    omega = rng.normal(0.0, 2.0, 3)
    kept = slid = 0
    for k in range(160):
        t += 1.0 / 90.0 + rng.uniform(-0.002, 0.002)
        omega += rng.normal(0.0, 0.5, 3)
        rot = Rotation.from_rotvec(omega / 90.0) * rot
        lost = 60 <= k < 64 or k % 29 == 3
        track.add(t, pos + rng.normal(0.0, 5e-4, 3), rot.as_quat(), not lost)
        args = track.kernel_args()
        ws = OK.at_scratch(args[0].shape[0])
        windows = []
        for query in np.arange(t - 0.05, t + 0.01, 0.001):
            want, got = np.zeros(24), np.zeros(24)
            assert OK.at_in(query, *args, got, ws) == OK.at(query, *args, want)
            assert np.array_equal(got, want), (k, query)
            m = int(ws[5][0])
            window = tuple(ws[5][2:2 + m])
            kept += bool(windows) and window == windows[-1]
            slid += bool(windows) and len(window) == len(windows[-1]) and window != windows[-1]
            windows.append(window)
    assert kept > 1000 and slid > 10


def test_pose_keeps_is_keeps_then_usable_in_one_call():
    """``optical_kernel.pose_keeps`` (``HandSession._pose_keeps``' one call) answers -1 where ``keeps`` says a new pose
    changes a fit from ``t0`` on, else ``usable``'s count with the same outputs and results, on a jittery stream
    with occlusions, gaps past the fit window and positions whose fits overflow."""
    from service.pipeline import optical_kernel

    rng = np.random.default_rng(13)
    seen = {"changes": 0, "all": 0, "fewer": 0}
    for trial in range(40):
        track = OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=16)
        t = rng.uniform(-5.0, 5.0)
        rot = Rotation.random(random_state=rng)
        for k in range(60):
            t += rng.choice([1 / 90, 1 / 90, 1 / 90, 0.2]) + rng.uniform(-0.002, 0.002)
            rot = Rotation.from_rotvec(rng.normal(0.0, 0.05, 3)) * rot
            p = np.full(3, 1e308) if rng.random() < 0.03 else rng.normal(0.0, 0.3, 3)
            track.add(t, p, rot.as_quat(), bool(rng.random() > 0.1))
            times = np.sort(rng.uniform(t - 0.1, t, int(rng.integers(1, 5))))
            t0, t_new = float(times[0]), t + rng.choice([1 / 90, 0.5])
            args = track.kernel_args()
            want_outs, want_st = np.full((len(times), 24), np.nan), np.full(len(times), -7)
            if optical_kernel.keeps(t_new, t0, track._t, track._valid, track._lo, track._hi, track._max_poses,
                                    track.window_s, track.timeout_s):
                want = optical_kernel.usable(times, *args, want_outs, want_st)
            else:
                want = -1
            outs, st = np.full((len(times), 24), np.nan), np.full(len(times), -7)
            got = optical_kernel.pose_keeps(t_new, t0, times, *args, track._max_poses, outs, st)
            assert got == want
            assert np.array_equal(outs, want_outs, equal_nan=True) and np.array_equal(st, want_st)
            seen["changes" if want < 0 else "all" if want == len(times) else "fewer"] += 1
    assert all(n > 5 for n in seen.values()), seen


def test_a_tracks_kept_work_arrays_give_the_bits_of_fresh_ones_from_call_to_call():
    """``OpticalTrack.run_scratch`` (one set of ``at_in``'s work arrays per track, handed to ``at``, ``pose_keeps_in``
    and ``usable_in`` call after call, as the pipeline does) gives each call the bits of a call with arrays of its own
    (``optical_kernel.at``, ``pose_keeps``, ``usable``): two tracks of the same pose times (the same window indices)
    and other poses, called in turn, on small tracks whose arrays are moved to their start every few poses, with
    occlusions and gaps past the timeout."""
    from service.pipeline import optical_kernel as OK

    rng = np.random.default_rng(17)
    tracks = [OpticalTrack(window_s=0.15, timeout_s=0.1, max_poses=4) for _ in range(2)]
    rots = [Rotation.random(random_state=rng) for _ in tracks]
    t, compared = 0.0, 0
    for k in range(400):
        t += rng.choice([1 / 90, 1 / 90, 1 / 90, 0.12]) + rng.uniform(-0.002, 0.002)
        valid = bool(rng.random() > 0.15)
        for j, track in enumerate(tracks):
            rots[j] = Rotation.from_rotvec(rng.normal(0.0, 0.3, 3)) * rots[j]
            track.add(t, rng.normal(0.0, 0.3, 3), rots[j].as_quat(), valid)
        queries = np.sort(rng.uniform(t - 0.2, t + 0.05, 3))
        times = np.sort(rng.uniform(t - 0.1, t, 3))
        for query in queries:
            for track in tracks:
                want = np.zeros(24)
                status = OK.at(query, *track.kernel_args(), want)
                got, tracking = track.at(query)
                assert (got is None) == (status == OK.NONE) and tracking == (status == OK.TRACKING)
                assert got is None or np.array_equal(np.concatenate([got.rotation.ravel(), got.position, got.velocity,
                                                                     got.acceleration, got.angular_velocity,
                                                                     got.angular_acceleration]), want), (k, query)
                compared += got is not None
        for track in tracks:
            args = track.kernel_args()
            outs, statuses = np.zeros((3, 24)), np.zeros(3, dtype=np.int64)
            outs_k, statuses_k = np.zeros((3, 24)), np.zeros(3, dtype=np.int64)
            assert OK.usable_in(times, *args, outs_k, statuses_k, track.run_scratch()) == \
                OK.usable(times, *args, outs, statuses)
            assert np.array_equal(outs_k, outs) and np.array_equal(statuses_k, statuses)
            t_new = t + 1 / 90
            assert OK.pose_keeps_in(t_new, times[0], times, *args, track._max_poses, outs_k, statuses_k,
                                    track.run_scratch()) == \
                OK.pose_keeps(t_new, times[0], times, *args, track._max_poses, outs, statuses)
            assert np.array_equal(outs_k, outs) and np.array_equal(statuses_k, statuses)
    assert compared > 1200
