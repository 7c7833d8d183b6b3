"""Frame and rotation conventions, written once (DESIGN.md "Conventions").

* Quaternions in public APIs are ``[x, y, z, w]`` (scipy / OpenXR order), unit norm.
  A quaternion ``q_ab`` maps vectors from frame ``b`` to frame ``a``: ``v_a = R(q_ab) v_b``.
* World frame: OpenXR stage space, right-handed, +Y up, metres. Default gravity ``[0, -9.81, 0]``.
* Finger frame (paper section 2.1): ``y`` along the phalanx, ``z`` palmar, ``x = y × z`` the hinge
  axis; a rotation about ``+x`` by ``+θ`` turns ``y`` toward ``z`` (flexion positive).
* OpenXR joint frames: paper ``(x, y, z)`` = OpenXR ``(-X, -Z, -Y)``.

All functions broadcast over leading dimensions.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

GRAVITY_M_S2 = 9.81
"""Default gravity magnitude, m/s²."""

DEFAULT_GRAVITY_WORLD = np.array([0.0, -GRAVITY_M_S2, 0.0])
"""Gravity vector in the world frame (OpenXR stage space, +Y up), m/s²."""

# Columns: OpenXR axes (X, Y, Z) expressed in the paper's finger frame (x, y, z).
# paper x = -X, paper y = -Z, paper z = -Y  =>  X = -x, Y = -z, Z = -y.
FINGER_TO_OPENXR = np.array(
    [[-1.0, 0.0, 0.0],
     [0.0, 0.0, -1.0],
     [0.0, -1.0, 0.0]]
)
"""Rotation matrix whose columns are the OpenXR joint axes in the finger frame.

Post-multiply a finger-frame orientation by it to get the OpenXR joint orientation:
``R_world_openxr = R_world_finger @ FINGER_TO_OPENXR``. It is a proper rotation (det = +1)."""

MIRROR_X = np.diag([-1.0, 1.0, 1.0])
"""Reflection through the finger frame's yz-plane: turns a right hand into a left hand."""


def rot_x(angle_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices about +x by ``angle_rad`` (paper's ``R(θ_i)``, section 2.1). Shape ``(..., 3, 3)``."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    out[..., 0, 0] = 1.0
    out[..., 1, 1] = c
    out[..., 1, 2] = -s
    out[..., 2, 1] = s
    out[..., 2, 2] = c
    return out


def phalanx_axis(theta_rad: np.ndarray) -> np.ndarray:
    """Unit vector ``y_i = R(θ_i) [0, 1, 0] = [0, cos θ, sin θ]`` in the finger base frame. Shape ``(..., 3)``."""
    t = np.asarray(theta_rad, dtype=float)
    return np.stack([np.zeros_like(t), np.cos(t), np.sin(t)], axis=-1)


def palmar_axis(theta_rad: np.ndarray) -> np.ndarray:
    """Unit vector ``z_i = R(θ_i) [0, 0, 1] = [0, -sin θ, cos θ]``; ``d y_i / dθ = z_i``. Shape ``(..., 3)``."""
    t = np.asarray(theta_rad, dtype=float)
    return np.stack([np.zeros_like(t), -np.sin(t), np.cos(t)], axis=-1)


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """``[x, y, z, w]`` quaternions ``(..., 4)`` to rotation matrices ``(..., 3, 3)`` (scipy)."""
    q = np.asarray(q_xyzw, dtype=float)
    flat = q.reshape(-1, 4)
    mats = Rotation.from_quat(flat).as_matrix()
    return mats.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(mats: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` to ``[x, y, z, w]`` quaternions with ``w >= 0`` (scipy)."""
    m = np.asarray(mats, dtype=float)
    q = Rotation.from_matrix(m.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape(m.shape[:-2] + (4,))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]×`` of vectors ``(..., 3)``, shape ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def apply(mats: np.ndarray, vecs: np.ndarray) -> np.ndarray:
    """``mats @ vecs`` for stacks of matrices ``(..., 3, 3)`` and vectors ``(..., 3)``."""
    return np.einsum("...ij,...j->...i", mats, vecs)


def apply_transpose(mats: np.ndarray, vecs: np.ndarray) -> np.ndarray:
    """``mats.T @ vecs`` for stacks: expresses world vectors in the rotated frame."""
    return np.einsum("...ji,...j->...i", mats, vecs)

