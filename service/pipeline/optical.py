"""Metacarpus kinematics at IMU times from the optical pose stream, two ways:

* ``OpticalTrack``: causal, from the poses received so far; the live pipeline (and so ``replay``)
  uses it;
* ``hand_kinematics_acausal``: from a whole recording, past and future poses alike; ``estimate`` and
  the benchmarks use it. The two give different angles for one recording, by design.

Acausal (whole recordings): each position axis and each quaternion component (signs made continuous)
is fitted with a cubic smoothing spline (``scipy.interpolate.make_smoothing_spline``, smoothing
chosen by generalised cross-validation), so the derivatives are smooth instead of a double difference
of jittery samples. With ``q(t)`` the unit quaternion (metacarpus to world):

* angular velocity (world frame): ``ω = 2 q̇ ⊗ q*`` (vector part);
* angular acceleration: ``α = 2 q̈ ⊗ q*`` (vector part; ``q̇ ⊗ q̇*`` is a scalar for unit ``q``);
* acceleration: the second derivative of the position splines.

Poses marked ``valid: false`` are left out; the splines bridge the gaps.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.spatial.transform import Rotation

from ..model import quaternion as quat
from ..model.kinematics import BaseMotion
from . import optical_kernel

MIN_POSES = 5
MIN_POSES_QUADRATIC = 8
"""Fewer poses in the fit window (e.g. right after the optics start or return) fit rates only."""


def _continuous_signs(q: np.ndarray) -> np.ndarray:
    q = q.copy()
    flips = np.cumsum(np.sum(q[1:] * q[:-1], axis=1) < 0) % 2
    q[1:][flips == 1] *= -1.0
    return q


def hand_kinematics_acausal(pose_t: np.ndarray, position: np.ndarray, orientation_xyzw: np.ndarray,
                            valid: np.ndarray, query_t: np.ndarray) -> BaseMotion:
    """Metacarpus kinematics at ``query_t`` from the valid poses (module docstring)."""
    pose_t = np.asarray(pose_t, dtype=float)
    keep = np.asarray(valid, dtype=bool)
    if keep.sum() < MIN_POSES:
        raise ValueError(f"need at least {MIN_POSES} valid optical poses to derive the hand's motion, got {int(keep.sum())}")
    t = pose_t[keep]
    pos = np.asarray(position, dtype=float)[keep]
    q = _continuous_signs(quat.from_xyzw(np.asarray(orientation_xyzw, dtype=float)[keep]))
    n = len(query_t)
    p, v, a = (np.empty((n, 3)) for _ in range(3))
    for j in range(3):
        spl = make_smoothing_spline(t, pos[:, j])
        p[:, j], v[:, j], a[:, j] = spl(query_t), spl(query_t, 1), spl(query_t, 2)
    qs, dq, ddq = (np.empty((n, 4)) for _ in range(3))
    for j in range(4):
        spl = make_smoothing_spline(t, q[:, j])
        qs[:, j], dq[:, j], ddq[:, j] = spl(query_t), spl(query_t, 1), spl(query_t, 2)
    norm = np.linalg.norm(qs, axis=1, keepdims=True)
    qs, dq, ddq = qs / norm, dq / norm, ddq / norm
    conj = qs * np.array([1.0, -1.0, -1.0, -1.0])
    omega = 2.0 * quat.multiply(dq, conj)[:, 1:]
    alpha = 2.0 * quat.multiply(ddq, conj)[:, 1:]
    return BaseMotion(quat.to_matrix(qs), p, v, a, omega, alpha)



_BASE_MOTION, _new_motion = BaseMotion, object.__new__

_FLAT = np.r_[0:9, 15:24]
"""Where ``BaseMotion.flat`` (rotation, acceleration, angular velocity and acceleration) lies in the
kernel's output (rotation, position, velocity, acceleration, angular velocity and acceleration)."""

def motion_of(out: np.ndarray, flat: np.ndarray) -> BaseMotion:
    """The ``BaseMotion`` of ``optical_kernel.at``'s output ``out`` (24), its fields views of it, with
    ``flat`` (18: ``out[_FLAT]``) as ``BaseMotion.flat``: the frozen dataclass's fields set as its
    ``__init__`` would (one ``object.__setattr__`` call each there), and ``flat`` in one step (the kernels
    read it)."""
    motion = _new_motion(_BASE_MOTION)
    motion.__dict__.update(rotation=out[:9].reshape(3, 3), position=out[9:12], velocity=out[12:15],
                           acceleration=out[15:18], angular_velocity=out[18:21], angular_acceleration=out[21:24],
                           flat=flat)
    return motion


def _pose_numbers(position, orientation_xyzw) -> list:
    """A pose's position and orientation as seven floats, as numpy stores them in a row of the track's arrays
    (``OpticalTrack._add_array``: converted and broadcast, or refused with its error)."""
    row = np.empty(7)
    row[:3] = position
    row[3:] = orientation_xyzw
    return row.tolist()


class OpticalTrack:
    """Causal metacarpus kinematics from a live pose stream (the hand pipeline's view of the optics).

    Poses (valid or not) are kept in time order for a bounded time. A query at time ``t`` uses the
    poses up to the first one at or after ``t`` (the one that *covers* ``t``), or all of them when
    none has arrived yet, so the answer does not depend on when the query is made:

    * orientation: slerp between the valid poses around ``t`` (or the newest valid pose rotated on
      by the fitted angular velocity when ``t`` is past it);
    * angular velocity and acceleration: a quadratic least-squares fit of the rotation vectors of the
      valid poses within ``window_s`` before ``t`` relative to the newest of them (body frame, valid
      for the small rotations of one window), turned into the world frame; position, velocity and
      acceleration: the same fit of the positions. A fit over ``window_s`` instead of a double
      difference keeps the optical jitter out of the derivatives; with fewer than
      ``MIN_POSES_QUADRATIC`` poses in the window only the rates are fitted (accelerations zero).
    * occlusion: when the last pose up to the covering one says ``valid: false``, or the newest valid
      pose is older than ``timeout_s``, the last valid orientation and position are held with zero
      rates, and ``at`` reports it.
    """

    def __init__(self, window_s: float = 0.15, timeout_s: float = 0.1, max_poses: int = 512, reference: bool = False):
        self.window_s = window_s
        self.timeout_s = timeout_s
        self.reference = reference          # the poses kept for ``at_reference`` too (its tests; the pipeline reads ``at``)
        self._poses: deque = deque(maxlen=max_poses)      # (t, valid, position, quaternion xyzw)
        self.latest_t: float | None = None
        self.latest_valid_t: float | None = None
        self._pruned_valid: tuple | None = None
        # the same poses as arrays for the compiled ``at`` (``optical_kernel``): entries lo..hi-1
        self._max_poses = max_poses
        cap = 2 * max_poses + 2
        self._t = np.zeros(cap)
        self._valid = np.zeros(cap, dtype=np.bool_)
        self._position = np.zeros((cap, 3))
        self._orientation = np.zeros((cap, 4))
        self._lo = self._hi = 0
        self._held_t = math.nan                           # the newest pruned valid pose (``optical_kernel.add``
        self._held_position = np.zeros(3)                 # writes it into these two arrays)
        self._held_orientation = np.array([0.0, 0.0, 0.0, 1.0])
        self._scratch: tuple | None = None                # ``run_scratch``'s work arrays, made at its first call

    def add(self, t: float, position, orientation_xyzw, valid: bool) -> None:
        """The pose at ``t`` (after the one before) into the track, in one compiled call (``optical_kernel.add``,
        ``_add_array``'s steps) with its seven numbers: a message's lists unpacked as they are, anything else as
        numpy stores it in a row (converted and broadcast, or refused with its error before anything is stored)."""
        if self.latest_t is not None and t <= self.latest_t:
            raise ValueError(f"pose time must increase: {t} after {self.latest_t}")
        self.latest_t = t
        horizon = t - max(4 * self.window_s, 2 * self.timeout_s)
        if self.reference:
            self._add_reference(t, position, orientation_xyzw, valid, horizon)
        if not valid:
            px = py = pz = qx = qy = qz = qw = 0.0
        elif type(position) is list and type(orientation_xyzw) is list and len(position) == 3 and len(orientation_xyzw) == 4:
            px, py, pz = position                   # (a message's: lists of floats)
            qx, qy, qz, qw = orientation_xyzw
        else:
            px, py, pz, qx, qy, qz, qw = _pose_numbers(position, orientation_xyzw)
        self._lo, self._hi, self._held_t = optical_kernel.add(
            float(t), bool(valid), px, py, pz, qx, qy, qz, qw, horizon, self._t, self._valid, self._position,
            self._orientation, self._lo, self._hi, self._max_poses, self._held_position, self._held_orientation,
            self._held_t)
        if valid:
            self.latest_valid_t = t          # once the pose is stored (a position that is no vector is not)

    def _add_reference(self, t: float, position, orientation_xyzw, valid: bool, horizon: float) -> None:
        """``add`` on the deque ``at_reference`` reads."""
        if valid:
            self._poses.append((t, True, np.asarray(position, dtype=float), np.asarray(orientation_xyzw, dtype=float)))
        else:
            self._poses.append((t, False, None, None))
        while len(self._poses) > 2 and self._poses[1][0] < horizon:
            old = self._poses.popleft()
            if old[1]:
                self._pruned_valid = old       # still the held pose during a long occlusion

    def _add_array(self, t: float, position, orientation_xyzw, valid: bool, horizon: float) -> None:
        """``add`` on the arrays, step for step as on the deque (its ``maxlen`` drops silently), in Python: the
        reference of the compiled ``optical_kernel.add``, which ``add`` calls."""
        if self._hi == len(self._t):
            n = self._hi - self._lo
            for a in (self._t, self._valid, self._position, self._orientation):
                a[:n] = a[self._lo:self._hi]
            self._lo, self._hi = 0, n
        i = self._hi
        self._t[i], self._valid[i] = t, bool(valid)
        if valid:
            self._position[i] = position
            self._orientation[i] = orientation_xyzw
        self._hi += 1
        if self._hi - self._lo > self._max_poses:
            self._lo += 1
        while self._hi - self._lo > 2 and self._t[self._lo + 1] < horizon:
            if self._valid[self._lo]:
                self._held_t = float(self._t[self._lo])
                self._held_position = self._position[self._lo].copy()
                self._held_orientation = self._orientation[self._lo].copy()
            self._lo += 1

    def add_keeps(self, t_new: float, t0: float) -> bool:
        """Whether adding a pose at ``t_new`` leaves ``at`` unchanged at every time from ``t0`` on that is
        covered now (the new pose comes after the one covering it): every pose the add drops (``_add_array``)
        is older than the fit window before ``t0``, and a valid pose within that window before ``t0`` stays,
        so such a time's newest valid pose up to its covering one stays stored. One compiled call
        (``optical_kernel.keeps``)."""
        return optical_kernel.keeps(float(t_new), float(t0), self._t, self._valid, self._lo, self._hi, self._max_poses,
                                    float(self.window_s), float(self.timeout_s))

    def covers(self, t: float) -> bool:
        """True when ``t`` can be evaluated now: a pose at or after ``t`` has arrived."""
        return self.latest_t is not None and self.latest_t >= t

    def _relevant(self, t: float) -> list:
        out = []
        for entry in self._poses:
            out.append(entry)
            if entry[0] >= t:
                break
        return out

    def at(self, t: float) -> tuple[BaseMotion | None, bool]:
        """``(kinematics, tracking)``; ``None`` before the first valid pose. One compiled call
        (``optical_kernel.at``, as ``at_in`` with the track's work arrays, ``run_scratch``), equal to ``at_reference``."""
        out = np.empty(24)
        status = optical_kernel.at_in(float(t), *self.kernel_args(), out, self.run_scratch())
        if status == optical_kernel.NONE:
            return None, False
        return motion_of(out, out[_FLAT]), status == optical_kernel.TRACKING

    def kernel_args(self) -> tuple:
        """``optical_kernel.at``'s arguments between the time and the output: the stored poses (``at``; the
        pipeline's run of steady ticks calls the kernel itself, ``tick_kernel.steady_run``)."""
        return (self._t, self._valid, self._position, self._orientation, self._lo, self._hi, self._held_t,
                self._held_position, self._held_orientation, float(self.window_s), float(self.timeout_s))

    def run_scratch(self) -> tuple:
        """``optical_kernel.at_in``'s work arrays for this track's capacity (``optical_kernel.at_scratch``), one set
        kept per track and handed to one compiled call after another (``at``, ``optical_kernel.pose_keeps_in``,
        ``tick_kernel.steady_run_in``), each time with no fit window kept from the call before (its key cleared):
        the call computes what it would with arrays of its own, without allocating them (some 180 kB)."""
        ws = self._scratch
        if ws is None:
            ws = self._scratch = optical_kernel.at_scratch(self._t.shape[0])
        ws[5][0] = -1
        return ws

    def at_reference(self, t: float) -> tuple[BaseMotion | None, bool]:
        """``at`` in numpy and scipy (the reference of the compiled kernel), for a track made with
        ``reference=True``."""
        if not self.reference:
            raise ValueError("at_reference needs a track that keeps its poses for it: OpticalTrack(..., reference=True)")

        poses = self._relevant(t)
        valid = [p for p in poses if p[1]] or ([self._pruned_valid] if self._pruned_valid is not None else [])
        if not valid:
            return None, False
        last_valid = valid[-1]
        if not poses[-1][1] or t - last_valid[0] > self.timeout_s:
            r = Rotation.from_quat(last_valid[3]).as_matrix()
            z = np.zeros(3)
            return BaseMotion(r, last_valid[2].copy(), z, z.copy(), z.copy(), z.copy()), False
        window = [p for p in valid if p[0] >= t - self.window_s] or [last_valid]
        ts = np.array([p[0] for p in window])
        pos = np.array([p[2] for p in window])
        quats = np.array([p[3] for p in window])
        r_ref = Rotation.from_quat(quats[-1])
        tau = ts - t
        rv = (r_ref.inv() * Rotation.from_quat(quats)).as_rotvec()
        if len(window) >= MIN_POSES_QUADRATIC:
            design = np.stack([np.ones_like(tau), tau, 0.5 * tau**2], axis=1)
            coef_p = np.linalg.lstsq(design, pos, rcond=None)[0]
            coef_r = np.linalg.lstsq(design, rv, rcond=None)[0]
        elif len(window) >= 3:
            # too few poses for a second derivative that is not mostly jitter: rates only
            design = np.stack([np.ones_like(tau), tau], axis=1)
            coef_p = np.vstack([np.linalg.lstsq(design, pos, rcond=None)[0], np.zeros(3)])
            coef_r = np.vstack([np.linalg.lstsq(design, rv, rcond=None)[0], np.zeros(3)])
        else:
            coef_p = np.stack([pos[-1], np.zeros(3), np.zeros(3)])
            coef_r = np.stack([rv[-1], np.zeros(3), np.zeros(3)])
        r_ref_m = r_ref.as_matrix()
        if len(window) >= 2 and ts[-2] <= t <= ts[-1] and ts[-1] > ts[-2]:
            # slerp between the bracketing poses: R_ref · Exp(s · rv_prev), rv_prev = log(R_ref⁻¹ R_prev)
            s = (ts[-1] - t) / (ts[-1] - ts[-2])
            rot_m = r_ref_m @ Rotation.from_rotvec(s * rv[-2]).as_matrix()
        elif ts[-1] == t:
            rot_m = r_ref_m
        else:
            rot_m = r_ref_m @ Rotation.from_rotvec(coef_r[1] * (t - ts[-1])).as_matrix()
        return BaseMotion(rot_m, coef_p[0], coef_p[1], coef_p[2], r_ref_m @ coef_r[1], r_ref_m @ coef_r[2]), True
