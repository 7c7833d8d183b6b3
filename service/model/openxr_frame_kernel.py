"""A frame's 26 OpenXR joint poses written into its one array of numbers (``pipeline.hand.JointPoses.numbers``)
in one compiled call: ``openxr_kernel.joint_poses`` itself, with the frame's angles taken from its flat array
(``FingerAngles.flat``) into the kernel's zero-padded (5, 3) array and the poses written into the numbers
after the angles, which ``openxr.joint_pose_arrays`` does with three numpy calls and two new arrays.
``tests/test_openxr_kernel.py`` checks it equal to ``joint_pose_arrays`` bit for bit."""
from __future__ import annotations

import numpy as np
from numba import njit

from .. import JIT_CACHE
from .openxr_kernel import joint_poses

JOINTS = 26


@njit(cache=JIT_CACHE)
def frame_poses(packed, flat, padded, hand_rotation, hand_position, numbers):  # pragma: no cover - compiled
    """``numbers[n:n + 78]`` the positions (26, 3) and ``numbers[n + 78:n + 182]`` the quaternions (26, 4) of
    ``joint_poses`` for the angles ``flat`` (``n`` of them), angle ``i`` at ``padded[i]`` of the row-major
    zero-padded (5, 3) angles; returns False (nothing written) unless ``numbers`` holds exactly ``n + 182``
    numbers and every ``padded`` index is in (5, 3)."""
    n = flat.shape[0]
    if numbers.shape[0] != n + 7 * JOINTS or padded.shape[0] != n:
        return False
    phi = np.zeros((5, 3))
    for i in range(n):
        k = padded[i]
        if k < 0 or k >= 15:
            return False
        phi[k // 3, k % 3] = flat[i]
    joint_poses(packed, phi, hand_rotation, hand_position, numbers[n:n + 3 * JOINTS].reshape((JOINTS, 3)),
                numbers[n + 3 * JOINTS:].reshape((JOINTS, 4)))
    return True
