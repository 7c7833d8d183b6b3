"""Vectorised quaternion algebra for the filter cores and the pipeline's optics.

Two orders, one rule (``frames`` states the public one):

* public APIs, the wire and recordings: ``[x, y, z, w]`` (OpenXR, scipy), ``model.frames``;
* inside the filter cores and this module: ``[w, x, y, z]``, because the Madgwick and VQF equations
  are written that way. Convert at the boundary with ``to_xyzw``/``from_xyzw``, nowhere else.

A quaternion ``q`` maps sensor to world: ``v_E = q ⊗ v_S ⊗ q*``. All functions broadcast over
leading dimensions ``(..., 4)``.

scipy's ``Rotation`` is the reference these are tested against; it is not used in the per-sample
loops because constructing ``Rotation`` objects costs more than the arithmetic itself.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def to_xyzw(q: np.ndarray) -> np.ndarray:
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def from_xyzw(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (..., 4)."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(np.broadcast_shapes(p.shape, q.shape))
    out[..., 0] = pw * qw - px * qx - py * qy - pz * qz
    out[..., 1] = pw * qx + px * qw + py * qz - pz * qy
    out[..., 2] = pw * qy - px * qz + py * qw + pz * qx
    out[..., 3] = pw * qz + px * qy - py * qx + pz * qw
    return out


def multiply_vector(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``q ⊗ [0, v]`` (..., 4): the quaternion derivative kernel of eq. 9."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    out = np.empty(np.broadcast_shapes(q.shape, v.shape[:-1] + (4,)))
    out[..., 0] = -x * vx - y * vy - z * vz
    out[..., 1] = w * vx + y * vz - z * vy
    out[..., 2] = w * vy - x * vz + z * vx
    out[..., 3] = w * vz + x * vy - y * vx
    return out


def normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions ``[w, x, y, z]`` (sensor to world)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - w * z)
    m[..., 0, 2] = 2 * (x * z + w * y)
    m[..., 1, 0] = 2 * (x * y + w * z)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - w * x)
    m[..., 2, 0] = 2 * (x * z - w * y)
    m[..., 2, 1] = 2 * (y * z + w * x)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def from_matrix(m: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[w, x, y, z]`` with ``w >= 0`` from rotation matrices (..., 3, 3)."""
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


def tilt_from_accelerometer(acc: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``[w,x,y,z]`` quaternions (..., 4) of the smallest rotation taking the measured specific force
    direction (sensor frame) onto ``up`` (world): an initial attitude with an arbitrary heading."""
    a = np.asarray(acc, dtype=float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    u = np.broadcast_to(np.asarray(up, dtype=float), a.shape)
    c = np.sum(a * u, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + c, np.cross(a, u)], axis=-1)
    # opposite vectors: any axis perpendicular to a
    flip = (1.0 + c[..., 0]) < 1e-9
    if np.any(flip):
        perp = np.cross(a, np.eye(3)[np.argmin(np.abs(a), axis=-1)])
        q = np.where(flip[..., None], np.concatenate([np.zeros_like(c), perp], axis=-1), q)
    return normalize(q)
