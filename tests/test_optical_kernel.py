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
