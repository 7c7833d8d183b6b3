"""Conventions of DESIGN.md checked against scipy's Rotation (an independent reference)."""
import numpy as np
from scipy.spatial.transform import Rotation

from service.model.frames import FINGER_TO_OPENXR, MIRROR_X, phalanx_axis, palmar_axis, quat_to_matrix, rot_x


def test_rot_x_matches_scipy_and_flexion_turns_y_toward_z():
    angles = np.linspace(-3, 3, 13)
    ref = Rotation.from_euler("x", angles[:, None]).as_matrix()
    np.testing.assert_allclose(rot_x(angles), ref, atol=1e-15)
    # +theta turns y toward z (flexion positive, DESIGN.md)
    y = rot_x(0.1) @ np.array([0.0, 1.0, 0.0])
    assert y[2] > 0
    np.testing.assert_allclose(phalanx_axis(angles), ref[:, :, 1], atol=1e-15)
    np.testing.assert_allclose(palmar_axis(angles), ref[:, :, 2], atol=1e-15)


def test_finger_to_openxr_mapping():
    # paper (x, y, z) = OpenXR (-X, -Z, -Y): columns of the matrix are X, Y, Z in finger coordinates
    assert np.isclose(np.linalg.det(FINGER_TO_OPENXR), 1.0)
    X, Y, Z = FINGER_TO_OPENXR.T
    np.testing.assert_array_equal(X, [-1, 0, 0])   # X = -x
    np.testing.assert_array_equal(Z, [0, -1, 0])   # Z = -y: -Z toward the fingertip
    np.testing.assert_array_equal(Y, [0, 0, -1])   # Y = -z: +Y out of the back of the hand


def test_quaternion_order_is_xyzw():
    q = np.array([np.sin(0.25), 0.0, 0.0, np.cos(0.25)])   # 0.5 rad about x
    np.testing.assert_allclose(quat_to_matrix(q), rot_x(0.5), atol=1e-15)


def test_mirror_keeps_rotations_proper(rng):
    r = Rotation.random(5, random_state=1).as_matrix()
    m = MIRROR_X @ r @ MIRROR_X
    np.testing.assert_allclose(np.linalg.det(m), 1.0)
