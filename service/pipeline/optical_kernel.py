"""Compiled (numba) kernel of ``OpticalTrack.at``: the metacarpus kinematics at one time from the
stored poses, in one call. ``OpticalTrack.at_reference`` (numpy and scipy's ``Rotation``) is the
reference; ``tests/test_optical_kernel.py`` checks the two against each other. ``add`` stores a pose
(``OpticalTrack._add_array``, its reference; ``tests/test_optical_add.py``).

The poses are the track's arrays ``t`` (cap,), ``valid`` (cap,) 0/1, ``position`` (cap, 3) and
``orientation`` (cap, 4, ``[x, y, z, w]``) between ``lo`` and ``hi`` (the reference's deque), plus
the newest pruned valid pose (``held``: t, position, orientation; ``t`` NaN when there is none).
The rotation formulas are scipy's (``from_quat`` normalises; ``as_rotvec`` and ``from_rotvec`` with
their series below 1e-3 rad); the fit is the least-squares solution ``lstsq`` gives, by Householder QR
(``_least_squares``: the design has full column rank, so both give the one solution, to rounding).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import JIT_CACHE, KERNEL_FASTMATH

NONE, HELD, TRACKING = 0, 1, 2
"""``at`` results: no valid pose yet; the last valid pose held (optics lost); tracked."""


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _unit(x, y, z, w):
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return x / n, y / n, z / n, w / n


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _matrix(x, y, z, w, out, o):
    """Rotation matrix of a unit ``[x, y, z, w]`` quaternion into ``out[o:o+9]`` (row-major)."""
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    out[o + 0] = x2 - y2 - z2 + w2
    out[o + 1] = 2.0 * (xy - zw)
    out[o + 2] = 2.0 * (xz + yw)
    out[o + 3] = 2.0 * (xy + zw)
    out[o + 4] = -x2 + y2 - z2 + w2
    out[o + 5] = 2.0 * (yz - xw)
    out[o + 6] = 2.0 * (xz - yw)
    out[o + 7] = 2.0 * (yz + xw)
    out[o + 8] = -x2 - y2 + z2 + w2


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _exp(vx, vy, vz):
    """``Rotation.from_rotvec`` as a unit quaternion."""
    angle = math.sqrt(vx * vx + vy * vy + vz * vz)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
    else:
        scale = math.sin(angle / 2.0) / angle
    return _unit(vx * scale, vy * scale, vz * scale, math.cos(angle / 2.0))


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def _reflect(v, vv, j, mat, c):
    """Apply the Householder reflection ``I - 2 v vᵀ / vv`` (``v`` nonzero from row ``j``) to column
    ``c`` of ``mat``, in place."""
    f = 0.0
    for i in range(j, mat.shape[0]):
        f += v[i] * mat[i, c]
    f *= 2.0 / vv
    for i in range(j, mat.shape[0]):
        mat[i, c] -= f * v[i]


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _least_squares(a, b, k, x, v):
    """Least squares ``min |a[:, :k] x - b|`` for ``b`` (m, 3) by Householder QR (Golub and Van Loan,
    algorithm 5.3.2), into ``x[:k]``; ``a`` and ``b`` are overwritten, ``v`` (m,) is scratch. ``a``
    must have full column rank (distinct pose times)."""
    m = a.shape[0]
    for j in range(k):
        norm = 0.0
        for i in range(j, m):
            norm += a[i, j] * a[i, j]
        norm = math.sqrt(norm)
        alpha = -norm if a[j, j] > 0.0 else norm
        vv = 0.0
        for i in range(j, m):
            v[i] = a[i, j]
        v[j] -= alpha
        for i in range(j, m):
            vv += v[i] * v[i]
        if vv == 0.0:
            continue
        for c in range(j, k):
            _reflect(v, vv, j, a, c)
        for c in range(3):
            _reflect(v, vv, j, b, c)
    for c in range(3):
        for j in range(k - 1, -1, -1):
            r = b[j, c]
            for q in range(j + 1, k):
                r -= a[j, q] * x[q, c]
            x[j, c] = r / a[j, j]


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def at(t, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, out):
    """The metacarpus kinematics at ``t`` (``OpticalTrack.at_reference``): returns ``NONE``, ``HELD``
    or ``TRACKING`` and fills ``out`` (24: rotation row-major, position, velocity, acceleration,
    angular velocity, angular acceleration; world frame) for the last two."""
    return at_in(t, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, out,
                 at_scratch(ts.shape[0]))


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def at_scratch(cap):
    """``at_in``'s work arrays for a track of ``cap`` poses (its fit window holds at most those, or the held
    pose alone), to be used by one call after another on the same track: the window's pose indices, its
    times (relative and absolute) and the QR's reflection, its positions, rotation vectors, design and their
    copies (m, 3), the fits' coefficients (3, 3), two rotation matrices (9) and the window whose absolute
    times, positions and rotation vectors are there from the call before (its size, newest valid pose and
    indices; none yet)."""
    m = cap + 1
    key = np.empty(m + 2, np.int64)
    key[0] = -1
    return (np.empty(m, np.int64), np.empty((3, m)), np.empty((6, m, 3)), np.empty((2, 3, 3)), np.empty((2, 9)),
            key)


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def at_in(t, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, out, ws):
    """``at`` with its work arrays ``ws`` (``at_scratch``) given, compiled without reference counts (it
    allocates nothing; the numbers are ``at``'s, which allocated them at every call). The fit window's poses
    turned into times, positions and rotation vectors relative to its newest (an ``atan2`` and a ``sin``
    each) are kept in ``ws`` for the next call: the ticks between two poses at 1 kHz have the same window,
    whose numbers are then taken as they are (the same poses give the same numbers; ``ws`` serves one track
    as it is: ``steady_run`` and ``usable`` allocate theirs per call)."""
    # the poses up to the first at or after t
    end = hi
    for i in range(lo, hi):
        if ts[i] >= t:
            end = i + 1
            break
    last = -1
    for i in range(end - 1, lo - 1, -1):
        if valid[i]:
            last = i
            break
    if last < 0 and math.isnan(held_t):
        return NONE
    if last >= 0:
        last_t = ts[last]
        lx, ly, lz, lw = orientation[last, 0], orientation[last, 1], orientation[last, 2], orientation[last, 3]
        lp0, lp1, lp2 = position[last, 0], position[last, 1], position[last, 2]
    else:
        last_t = held_t
        lx, ly, lz, lw = held_q[0], held_q[1], held_q[2], held_q[3]
        lp0, lp1, lp2 = held_p[0], held_p[1], held_p[2]
    qx, qy, qz, qw = _unit(lx, ly, lz, lw)
    if (end > lo and not valid[end - 1]) or t - last_t > timeout_s:
        _matrix(qx, qy, qz, qw, out, 0)
        out[9], out[10], out[11] = lp0, lp1, lp2
        for k in range(12, 24):
            out[k] = 0.0
        return HELD

    # the fit window: the valid poses within window_s before t (at least the newest)
    m = 0
    if last >= 0:
        for i in range(lo, end):
            if valid[i] and ts[i] >= t - window_s:
                m += 1
    w_idx, w_t, w_m3, w_coef, w_rot, w_key = ws
    if m == 0:
        m = 1
        idx = w_idx[:1]
        idx[0] = last
    else:
        idx = w_idx[:m]
        j = 0
        for i in range(lo, end):
            if valid[i] and ts[i] >= t - window_s:
                idx[j] = i
                j += 1
    tau = w_t[0, :m]
    tabs = w_t[1, :m]
    pos = w_m3[0, :m]
    rv = w_m3[1, :m]
    kept = w_m3[5, :m]
    same = w_key[0] == m and w_key[1] == last
    if same:
        for j in range(m):
            if w_key[2 + j] != idx[j]:
                same = False
                break
    # rotation vectors relative to the newest: log(R_ref⁻¹ R_i), scipy's as_rotvec (the call before's when its
    # window was this one)
    for j in range(0 if same else m):
        i = idx[j]
        if i >= 0:
            tj = ts[i]
            px, py, pz = position[i, 0], position[i, 1], position[i, 2]
            ix, iy, iz, iw = _unit(orientation[i, 0], orientation[i, 1], orientation[i, 2], orientation[i, 3])
        else:
            tj = held_t
            px, py, pz = held_p[0], held_p[1], held_p[2]
            ix, iy, iz, iw = _unit(held_q[0], held_q[1], held_q[2], held_q[3])
        tabs[j] = tj
        kept[j, 0], kept[j, 1], kept[j, 2] = px, py, pz
        # conj(q_ref) ⊗ q_i
        ax, ay, az, aw = -qx, -qy, -qz, qw
        cx = aw * ix + ax * iw + ay * iz - az * iy
        cy = aw * iy - ax * iz + ay * iw + az * ix
        cz = aw * iz + ax * iy - ay * ix + az * iw
        cw = aw * iw - ax * ix - ay * iy - az * iz
        if cw < 0.0:
            cx, cy, cz, cw = -cx, -cy, -cz, -cw
        angle = 2.0 * math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), cw)
        if angle <= 1e-3:
            a2 = angle * angle
            scale = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
        else:
            scale = angle / math.sin(angle / 2.0)
        rv[j, 0], rv[j, 1], rv[j, 2] = scale * cx, scale * cy, scale * cz
    if not same:
        w_key[0], w_key[1] = m, last
        for j in range(m):
            w_key[2 + j] = idx[j]
    for j in range(m):
        tau[j] = tabs[j] - t
        pos[j, 0], pos[j, 1], pos[j, 2] = kept[j, 0], kept[j, 1], kept[j, 2]     # (the fit overwrites pos)

    coef_p = w_coef[0]
    coef_r = w_coef[1]
    for r in range(3):
        for c in range(3):
            coef_p[r, c] = 0.0
            coef_r[r, c] = 0.0
    if m >= 3:      # MIN_POSES_QUADRATIC (8) and more: position, rate and acceleration; 3 to 7: rates only
        k = 3 if m >= 8 else 2
        design = w_m3[2, :m]
        design_copy = w_m3[3, :m]
        rv_copy = w_m3[4, :m]
        scratch = w_t[2, :m]
        for j in range(m):
            design[j, 0], design[j, 1], design[j, 2] = 1.0, tau[j], 0.5 * tau[j] ** 2
            for c in range(3):
                design_copy[j, c] = design[j, c]
                rv_copy[j, c] = rv[j, c]
        _least_squares(design_copy, pos, k, coef_p, scratch)
        _least_squares(design, rv_copy, k, coef_r, scratch)         # rv is read again below
    else:
        for k in range(3):
            coef_p[0, k] = pos[m - 1, k]
            coef_r[0, k] = rv[m - 1, k]

    ref = w_rot[0]
    _matrix(qx, qy, qz, qw, ref, 0)
    t_last = tabs[m - 1]
    t_prev = tabs[m - 2] if m >= 2 else 0.0
    if m >= 2 and t_prev <= t <= t_last and t_last > t_prev:
        s = (t_last - t) / (t_last - t_prev)
        ex, ey, ez, ew = _exp(s * rv[m - 2, 0], s * rv[m - 2, 1], s * rv[m - 2, 2])
    elif t_last == t:
        ex, ey, ez, ew = 0.0, 0.0, 0.0, 1.0
    else:
        d = t - t_last
        ex, ey, ez, ew = _exp(coef_r[1, 0] * d, coef_r[1, 1] * d, coef_r[1, 2] * d)
    rel = w_rot[1]
    _matrix(ex, ey, ez, ew, rel, 0)
    for r in range(3):
        for c in range(3):
            out[3 * r + c] = ref[3 * r] * rel[c] + ref[3 * r + 1] * rel[3 + c] + ref[3 * r + 2] * rel[6 + c]
    for k in range(3):
        out[9 + k] = coef_p[0, k]
        out[12 + k] = coef_p[1, k]
        out[15 + k] = coef_p[2, k]
    # body-frame rates to the world frame: R_ref ω, R_ref α
    w0, w1, w2 = coef_r[1, 0], coef_r[1, 1], coef_r[1, 2]
    a0, a1, a2 = coef_r[2, 0], coef_r[2, 1], coef_r[2, 2]
    for r in range(3):
        out[18 + r] = ref[3 * r] * w0 + ref[3 * r + 1] * w1 + ref[3 * r + 2] * w2
        out[21 + r] = ref[3 * r] * a0 + ref[3 * r + 1] * a1 + ref[3 * r + 2] * a2
    return TRACKING


@njit(cache=JIT_CACHE, inline="always", error_model="numpy", fastmath=KERNEL_FASTMATH)
def motion_sum(out):
    """The sum ``HandSession._finite_motion`` takes of ``at``'s output ``out``, in its order (non-finite where a
    number of it is): ``BaseMotion.flat`` (rotation, acceleration, angular velocity and acceleration), then the
    position, then the velocity."""
    s_flat = 0.0
    for k in range(9):
        s_flat += out[k]
    for k in range(15, 24):
        s_flat += out[k]
    s_pos = out[9] + out[10] + out[11]
    s_vel = out[12] + out[13] + out[14]
    return s_flat + s_pos + s_vel


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def usable(times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, outs, statuses):
    """How many of ``times``, from the first on, ``at`` gives no kinematics at (``NONE``) or finite ones at
    (``motion_sum``): the optical fits of the ticks a pipeline holds back (``HandSession._pose_keeps``), in one
    call. Each time's ``at`` output goes to ``outs[i]`` (24) and its result to ``statuses[i]``, up to the
    first that is not usable (included)."""
    return usable_in(times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, outs,
                     statuses, at_scratch(ts.shape[0]))


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def usable_in(times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, outs,
              statuses, ws):
    """``usable`` with ``at_in``'s work arrays ``ws`` given (``at_scratch``; ``OpticalTrack.run_scratch``)."""
    for i in range(times.shape[0]):
        status = at_in(times[i], ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s,
                       outs[i], ws)
        statuses[i] = status
        if status != NONE and not math.isfinite(motion_sum(outs[i])):
            return i
    return times.shape[0]


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def keeps(t_new, t0, ts, valid, lo, hi, max_poses, window_s, timeout_s):
    """``OpticalTrack.add_keeps`` on the track's arrays ``ts``, ``valid`` (entries ``lo..hi-1``, at most
    ``max_poses``): whether a pose added at ``t_new`` leaves ``at`` the same at every time from ``t0`` on that a
    pose covers now."""
    start = t0 - window_s
    if t_new - max(4.0 * window_s, 2.0 * timeout_s) >= start:
        return False
    if hi - lo >= max_poses and ts[lo] >= start:
        return False
    for i in range(hi - 1, lo - 1, -1):
        u = ts[i]
        if u < start:
            return False
        if u < t0 and valid[i]:
            return True
    return False


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def pose_keeps(t_new, t0, times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s,
               max_poses, outs, statuses):
    """``keeps`` (a pose at ``t_new`` leaves ``at`` the same from ``t0`` on) and, if it does, ``usable`` of ``times``
    (with ``outs`` and ``statuses``): the checks ``HandSession._pose_keeps`` makes of a pose in one call. Returns -1
    where ``keeps`` says no, else ``usable``'s count."""
    return pose_keeps_in(t_new, t0, times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s,
                         timeout_s, max_poses, outs, statuses, at_scratch(ts.shape[0]))


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def pose_keeps_in(t_new, t0, times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s,
                  timeout_s, max_poses, outs, statuses, ws):
    """``pose_keeps`` with ``at_in``'s work arrays ``ws`` given (``at_scratch``; ``OpticalTrack.run_scratch``: the
    pipeline's call allocates none)."""
    if not keeps(t_new, t0, ts, valid, lo, hi, max_poses, window_s, timeout_s):
        return -1
    return usable_in(times, ts, valid, position, orientation, lo, hi, held_t, held_p, held_q, window_s, timeout_s, outs,
                     statuses, ws)


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def add(t, valid, px, py, pz, qx, qy, qz, qw, horizon, ts, valids, position, orientation, lo, hi, max_poses, held_p,
        held_q, held_t):
    """``OpticalTrack._add_array`` in one call: the pose at ``t`` (its position ``px, py, pz`` and orientation
    ``qx, qy, qz, qw`` stored where ``valid``) into the track's arrays (entries ``lo..hi-1``, moved to the start
    when the arrays are full), the oldest dropped beyond ``max_poses``, and those whose successor is older than
    ``horizon`` pruned, the newest pruned valid one into ``held_p`` and ``held_q`` (written in place). Returns the
    new ``lo``, ``hi`` and held time ``held_t`` (the one given when none was pruned valid)."""
    if hi == ts.shape[0]:
        n = hi - lo
        for j in range(n):           # (forward: the source is at or after the destination)
            k = lo + j
            ts[j] = ts[k]
            valids[j] = valids[k]
            for c in range(3):
                position[j, c] = position[k, c]
            for c in range(4):
                orientation[j, c] = orientation[k, c]
        lo, hi = 0, n
    ts[hi] = t
    valids[hi] = valid
    if valid:
        position[hi, 0], position[hi, 1], position[hi, 2] = px, py, pz
        orientation[hi, 0], orientation[hi, 1], orientation[hi, 2], orientation[hi, 3] = qx, qy, qz, qw
    hi += 1
    if hi - lo > max_poses:
        lo += 1
    while hi - lo > 2 and ts[lo + 1] < horizon:
        if valids[lo]:
            held_t = ts[lo]
            for c in range(3):
                held_p[c] = position[lo, c]
            for c in range(4):
                held_q[c] = orientation[lo, c]
        lo += 1
    return lo, hi, held_t
