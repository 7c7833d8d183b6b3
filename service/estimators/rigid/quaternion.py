"""Vectorised quaternion algebra for the filter cores (``[w, x, y, z]`` internally, because the
Madgwick equations are written that way; public APIs convert to ``[x, y, z, w]`` with
``to_xyzw``/``from_xyzw``). A quaternion ``q`` maps sensor to world: ``v_E = q ⊗ v_S ⊗ q*``.

scipy's ``Rotation`` is the reference these are tested against; it is not used in the per-sample
loops because constructing ``Rotation`` objects costs more than the arithmetic itself.
"""
from __future__ import annotations

import numpy as np


def to_xyzw(q: np.ndarray) -> np.ndarray:
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def from_xyzw(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (..., 4)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], axis=-1)


def multiply_vector(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``q ⊗ [0, v]`` (..., 4): the quaternion derivative kernel of eq. 9."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    vx, vy, vz = np.moveaxis(v, -1, 0)
    return np.stack([
        -x * vx - y * vy - z * vz,
        w * vx + y * vz - z * vy,
        w * vy - x * vz + z * vx,
        w * vz + x * vy - y * vx,
    ], axis=-1)


def normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions ``[w, x, y, z]`` (sensor to world)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def from_matrix(m: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[w, x, y, z]`` with ``w >= 0`` from rotation matrices (..., 3, 3)."""
    from scipy.spatial.transform import Rotation
    m = np.asarray(m, dtype=float)
    q = Rotation.from_matrix(m.reshape(-1, 3, 3)).as_quat(canonical=True)
    return from_xyzw(q.reshape(m.shape[:-2] + (4,)))


def exp_rotvec(v: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector ``v`` (..., 3), rad: ``[cos(|v|/2), sin(|v|/2) v/|v|]``."""
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x)/x series below 1e-8 avoids 0/0; exact to double precision there
    scale = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), scale * v], axis=-1)


def rotate_into_sensor(q: np.ndarray, v_world: np.ndarray) -> np.ndarray:
    """``q* ⊗ v_E ⊗ q``: a world vector (..., 3) in sensor coordinates."""
    return np.einsum("...ji,...j->...i", to_matrix(q), v_world)
