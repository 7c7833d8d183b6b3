"""Compiled (numba) kernel of ``chain``. ``chain.py`` explains the method and keeps the numpy
reference (``Chain._step_reference``); ``tests/test_chain_kernel.py`` checks the two against each
other to 1e-9 on random inputs and on a simulated recording through the hand pipeline.

Everything lives in flat float64 arrays the estimator keeps, so one call advances every sensor of a
finger (and every batch row) by any number of samples without a numpy call:

* state: ``x`` (B, S, 15) = ``[θ, b_g, b_ax, b_ay, b_az, G (9, row-major), s_g]`` per sensor, ``P``
  (B, S, 15, 15), the last
  measured relative rate ``rate`` (B, S) and the hand's optical acceleration smoothed over the fit's
  lag ``hand_acc`` (B, 3; the last one when that setting is 0), updated in place;
* inputs per sample: ``dt`` (N,), ``gyr``/``acc`` (N, B, S, 3) and the hand as ``BaseMotion.flat``
  (N, B, 18: rotation row-major, acceleration, angular velocity, angular acceleration);
* the finger's constants (``geometry_vector``) and the settings (``settings_vector``) as vectors.

One flat loop over scalars, as in ``rigid/inertial_kernel.py``: no array views or array arguments to
helpers on the per-sample path (numba reference-counts those with atomic calls), and the kernels a tick
runs (``run_hand_in`` and below) compiled without reference counts at all (``_nrt=False``: they allocate
nothing; ``run_hand`` and ``run`` allocate the work arrays and call them). No fast-math licence
(``service.KERNEL_FASTMATH``); results differ from the numpy reference by rounding only.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import JIT_CACHE, KERNEL_FASTMATH


GA_START = 5
"""Index of the accelerometer's linear-map states ``G`` (9, row-major) in the state vector."""
GS = GA_START + 9
"""Index of the gyro's scale error about the hinge axis ``s_g`` in the state vector."""
N_STATE = GS + 1
HINGE_G_YZ, HINGE_G_ZY = GA_START + 5, GA_START + 7
"""``G_yz`` and ``G_zy``: their antisymmetric combination (a turn about the hinge axis) is left to the
angle, so the random walk of ``G`` is projected off it (``chain._HINGE_FREE``)."""
HAND_SIZE = 18
"""``BaseMotion.flat``: rotation (9, row-major), acceleration, angular velocity, angular acceleration."""

# --- settings vector -------------------------------------------------------------------------
(ST_GYRO_NOISE, ST_GYRO_WALK, ST_ACC_WALK, ST_ACC_NOISE, ST_KINEMATIC, ST_GYRO_SCALE, ST_ACC_SCALE,
 ST_GYRO_RANGE, ST_ACC_RANGE, ST_FIT_LAG, ST_UNTRACKED_NOISE, ST_CAL_WALK, ST_GS_WALK, ST_CLIPPED_STD,
 ST_GS_LEARN, ST_GA_RATE_STD, ST_GA_MIN_RATE, ST_GA_MAX_FLEX, ST_GA_WINDOW) = range(19)
SETTINGS_SIZE = 19
GYRO_ANGLE_H = math.sqrt(0.5) / math.sqrt(2.0)
"""The gyro's angle ``θ - δ_m`` over a sensor's states: ``θ + GYRO_ANGLE_H (G_yz - G_zy)`` (``chain._GYRO_ANGLE_H``)."""
GYRO_ANGLE_GATE_RAD = 0.5
"""``chain._GYRO_ANGLE_GATE_RAD``."""
SATURATED_SIGMA_M_S2 = 1e6
"""Accelerometer std of a clipped sample (no update in effect), as in the reference."""
SATURATION_MARGIN = 1.0 - 1e-3
"""A reading at this fraction of full scale or beyond counts as clipped."""


def settings_vector(s) -> np.ndarray:
    """The ``ChainSettings`` the kernel reads, in the ``ST_*`` order."""
    return np.array([s.gyro_noise_density_rad_s_rthz, s.gyro_bias_walk_rad_s_rts, s.acc_bias_walk_m_s2_rts,
                     s.acc_noise_m_s2, s.kinematic_uncertainty, s.gyro_scale_uncertainty, s.acc_scale_uncertainty,
                     s.gyro_range_rad_s, s.acc_range_m_s2, s.optical_fit_lag_s, s.untracked_acc_noise_m_s2,
                     s.calibration_walk_rts, s.gyro_scale_walk_rts, s.clipped_rate_std_rad_s, 1.0,
                     s.gyro_angle_rate_std_rad_s, s.gyro_angle_min_rate_rad_s, s.gyro_angle_max_flexion_rad_s,
                     s.gyro_angle_window_s], dtype=float)
    """``ST_GS_LEARN`` is 1 where the gyro scale state learns; the estimator sets it."""


def geometry_vector(obs, closure, gravity_world: np.ndarray) -> np.ndarray:
    """One finger's constants (``FingerObservations`` and ``ChainClosure``) concatenated in the order
    the kernel reads them: sensor mountings (S, 3, 3), hinge axes in sensor coordinates (S, 3), finger
    base rotation (3, 3) and position (3), levers (S, n), prefixes (S, n), eq. 6 chain factors (S),
    closure matrix (n, S), anatomical branch starts (S), gravity (3)."""
    parts = (obs.mount, obs.hinge_in_sensor, obs.base, obs.base_position, obs._lever, obs._prefix.astype(float),
             obs._chain_factor, closure.matrix, obs.branch_low, gravity_world)
    return np.ascontiguousarray(np.concatenate([np.asarray(p, dtype=float).ravel() for p in parts]))


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def run(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, out_theta, out_phi, out_phal, out_mode):
    """One finger: ``_finger`` (below) as a compiled entry point (no shared hand acceleration error)."""
    ns = x.shape[1]
    _finger(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, out_theta, out_phi, out_phal, out_mode,
            np.zeros((ns, N_STATE, 3)), x.reshape(-1, N_STATE), np.zeros(3),
            np.zeros((3, 3)), 0, False, _scratch(ns, out_phi.shape[2], ns))


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _scratch(ns, nph, n_all):
    """``_finger``'s work arrays for fingers of up to ``ns`` sensors and ``nph`` joints, allocated once per
    call and shared by the fingers of a hand (``_finger`` names their rows), and the cross-covariance products
    held back for the hand's ``n_all`` sensors (``_settle``)."""
    return (np.empty((6, ns)), np.empty((5, nph)), np.zeros((2, 3, N_STATE)), np.empty((4, N_STATE, 3)),
            np.empty((N_STATE, N_STATE)), np.zeros((6, 3)), np.empty(N_STATE), np.empty((8, 3, 3)),
            (np.empty((n_all, 3, 3)), np.empty((n_all, 3)), np.zeros(n_all, np.int64)))


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _clear_scratch(ws):
    """The work arrays ``_scratch`` makes with zeros zeroed again, for another call: each call starts from
    what a fresh allocation held."""
    m3n, v3, held = ws[2], ws[5], ws[8][2]
    for a in range(held.shape[0]):
        held[a] = 0
    for a in range(m3n.shape[0]):
        for b in range(m3n.shape[1]):
            for c in range(m3n.shape[2]):
                m3n[a, b, c] = 0.0
    for a in range(v3.shape[0]):
        for b in range(v3.shape[1]):
            v3[a, b] = 0.0


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def run_hand(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start, geo_start,
             out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off):
    """One tick of several fingers (a hand) in one call: finger ``f`` is ``_finger`` on its rows of the
    stacked arrays, the same arithmetic as ``run`` on that finger alone. Its sensors are rows
    ``sensor_start[f]:sensor_start[f + 1]`` of ``x`` (S, 15), ``p`` (S, 15, 15), ``rates`` (S), ``gyr``
    and ``acc`` (S, 3), ``out_theta`` and ``out_mode`` (S); its joints entries
    ``phalanx_start[f]:phalanx_start[f + 1]`` of ``out_phi`` and ``out_phal``; its constants
    ``geo[geo_start[f]:geo_start[f + 1]]``; its own step ``dts[f]`` (0 right after it starts), last
    smoothed hand acceleration ``hand_acc[f]`` (F, 3), settings ``st[f]`` (F, 15) and ``untracked[f]``. The
    hand's motion ``hand`` (18) is shared, and so is the optical acceleration's error ``δ`` (``dl`` (3), its
    covariance ``pd`` (3, 3), every sensor's cross-covariance with it ``cx`` (S, 15, 3); ``jp``: its time
    constant, scale, floor and the time since ``δ`` was last advanced, ``chain.py``), updated in place; with the time constant 0 there is none and
    each finger widens its accelerometers along the fit's lag error instead. A ``δ`` made non-finite by a
    diverging finger restarts from its prior (``_keep_shared_error_finite``). Then every finger's log for a
    reference pose's hold takes the tick at ``t`` (``_log_holds``: ``log_t`` (C, F), ``log_r`` (C, S),
    ``log_g`` (C, S, 3), ``log_n`` (F), ``chain.HoldLog``). ``ga_off`` (S, 2): each gyro's cross-axis offsets
    (in the frame of its reading turned by the mounting) taken off it for the gyro's angle (``ChainHand.cross_offsets``)."""
    run_hand_in(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start, geo_start,
                out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off,
                hand_scratch(sensor_start, phalanx_start))


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=KERNEL_FASTMATH)
def hand_scratch(sensor_start, phalanx_start):
    """``run_hand_in``'s work arrays (``_scratch``) for the hand's largest finger, to be used by one call
    after another (``tick_kernel.steady_run`` allocates them once for a run of ticks)."""
    ns_max = nph_max = 0
    for f in range(sensor_start.shape[0] - 1):
        ns_max = max(ns_max, sensor_start[f + 1] - sensor_start[f])
        nph_max = max(nph_max, phalanx_start[f + 1] - phalanx_start[f])
    return _scratch(ns_max, nph_max, sensor_start[sensor_start.shape[0] - 1])


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def run_hand_in(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start, geo_start,
                out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off, ws):
    """``run_hand`` with its work arrays ``ws`` (``hand_scratch``) given. Compiled without the runtime's
    reference counts (``_nrt=False``), as are the kernels it calls: it allocates nothing, and its views and
    arguments live inside the caller's arrays. Counted, every view and every array argument of a call was
    an atomic increment and a decrement: 43 % of the compiled code's samples (``perf``) in a run of steady
    ticks of the 1 kHz stream, whose ticks took 25.6 us each then and 19.0 us without the counts."""
    _clear_scratch(ws)
    hand1 = hand.reshape(1, 1, HAND_SIZE)
    joint_tau, joint_scale, joint_floor = jp[0], jp[1], jp[2]
    joint = joint_tau > 0.0
    if joint:
        # the shared error of the optical hand acceleration: first-order Gauss-Markov over the time since
        # it was last advanced (``jp[3]``, ``ChainHand._delta_step``)
        dt = jp[3]
        lost = False
        for f in range(dts.shape[0]):
            lost = lost or untracked[f]
        q = 0.0
        for c in range(3):
            dd = hand[9 + c] - hand_acc[0, c]
            q += dd * dd
        q = joint_scale * joint_scale * q + joint_floor * joint_floor
        if lost:
            for c in range(3):
                dl[c] = 0.0
                for c2 in range(3):
                    pd[c, c2] = q if c == c2 else 0.0
            cx[:, :, :] = 0.0
        else:
            fdec = math.exp(-dt / joint_tau)
            for c in range(3):
                dl[c] *= fdec
                for c2 in range(3):
                    pd[c, c2] *= fdec * fdec
                pd[c, c] += (1.0 - fdec * fdec) * q
            for l in range(cx.shape[0]):
                for ii in range(N_STATE):
                    for c in range(3):
                        cx[l, ii, c] *= fdec
    pend = ws[8]
    for f in range(dts.shape[0]):
        s0, s1 = sensor_start[f], sensor_start[f + 1]
        q0, q1 = phalanx_start[f], phalanx_start[f + 1]
        ns, nph = s1 - s0, q1 - q0
        _settle(cx, x, pend, s0, s1)        # the earlier fingers' updates of its sensors, before its turn
        _finger(x[s0:s1].reshape(1, ns, N_STATE), p[s0:s1].reshape(1, ns, N_STATE, N_STATE), rates[s0:s1].reshape(1, ns),
                hand_acc[f:f + 1], dts[f:f + 1], gyr[s0:s1].reshape(1, 1, ns, 3), acc[s0:s1].reshape(1, 1, ns, 3), hand1,
                st[f], geo[geo_start[f]:geo_start[f + 1]], untracked[f], out_theta[s0:s1].reshape(1, 1, ns),
                out_phi[q0:q1].reshape(1, 1, nph), out_phal[q0:q1].reshape(1, 1, nph), out_mode[s0:s1].reshape(1, 1, ns),
                cx, x, dl, pd, s0, joint and not untracked[f], ws)
    _settle(cx, x, pend, 0, cx.shape[0])   # the later fingers' updates
    _keep_shared_error_finite(dl, pd, cx, joint_floor)
    _gyro_angles(hand, gyr, dts, untracked, sensor_start, geo, geo_start, st, x, p, cx, ws[6], ga_off)
    _log_holds(t, dts, rates, gyr, sensor_start, log_t, log_r, log_g, log_n)


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _keep_shared_error_finite(dl, pd, cx, floor):
    """``chain.ChainHand._keep_shared_error_finite``: a non-finite sum of ``δ`` and its covariance (a
    finger diverged into it) restarts ``δ`` from its prior ``floor² I``, its cross-covariances at 0. The
    sums in Python's order (``δ``'s, then the covariance's row by row)."""
    a = 0.0
    for c in range(3):
        a += dl[c]
    b = 0.0
    for c in range(3):
        for c2 in range(3):
            b += pd[c, c2]
    if math.isfinite(a + b):
        return
    for c in range(3):
        dl[c] = 0.0
        for c2 in range(3):
            pd[c, c2] = floor * floor if c == c2 else 0.0
    cx[:, :, :] = 0.0


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _gyro_angles(hand, gyr, dts, untracked, sensor_start, geo, geo_start, st, x, p, cx, ph, ga_off):
    """``chain.ChainHand._gyro_angles`` (its numpy reference): each sensor's angle as its gyro's cross axes
    tell it, while the hand turns across the hinge axis and the finger is nearly still on it, one scalar
    update of the sensor's own states, covariance (symmetrised) and cross-covariance with δ. The settings
    are the first finger's (``st[0]``); ``ph`` is work space (15)."""
    rate_std = st[0, ST_GA_RATE_STD]
    if rate_std <= 0.0:
        return
    min_rate, max_flex, window = st[0, ST_GA_MIN_RATE], st[0, ST_GA_MAX_FLEX], st[0, ST_GA_WINDOW]
    gyro_clip = st[0, ST_GYRO_RANGE] * SATURATION_MARGIN
    g5, g7 = GA_START + 5, GA_START + 7
    hq = GYRO_ANGLE_H
    two_pi = 2.0 * math.pi
    # the hand's rate in metacarpus coordinates, R_Mᵀ ω
    v0 = hand[0] * hand[12] + hand[3] * hand[13] + hand[6] * hand[14]
    v1 = hand[1] * hand[12] + hand[4] * hand[13] + hand[7] * hand[14]
    v2 = hand[2] * hand[12] + hand[5] * hand[13] + hand[8] * hand[14]
    for f in range(dts.shape[0]):
        s0, s1 = sensor_start[f], sensor_start[f + 1]
        ok = not untracked[f] and dts[f] > 0.0
        for s in range(s0, s1):
            for c in range(3):
                ok = ok and abs(gyr[s, c]) < gyro_clip
        if not ok:
            continue
        ns = s1 - s0
        ob = geo_start[f] + 12 * ns             # the finger's base rotation (row-major, ``geometry_vector``)
        w0 = v0 * geo[ob] + v1 * geo[ob + 3] + v2 * geo[ob + 6]
        w1 = v0 * geo[ob + 1] + v1 * geo[ob + 4] + v2 * geo[ob + 7]
        w2 = v0 * geo[ob + 2] + v1 * geo[ob + 5] + v2 * geo[ob + 8]
        w_yz2 = w1 * w1 + w2 * w2
        if not w_yz2 > min_rate * min_rate:
            continue
        seen = math.atan2(w2, w1)
        learn = st[f, ST_GS_LEARN] > 0.5          # a finger on a fallback holds its gyro scale states
        for k in range(ns):
            s = s0 + k
            m = geo_start[f] + 9 * k            # the sensor's mounting (sensor -> phalanx)
            f0 = geo[m] * gyr[s, 0] + geo[m + 1] * gyr[s, 1] + geo[m + 2] * gyr[s, 2]
            f1 = geo[m + 3] * gyr[s, 0] + geo[m + 4] * gyr[s, 1] + geo[m + 5] * gyr[s, 2] - ga_off[s, 0]
            f2 = geo[m + 6] * gyr[s, 0] + geo[m + 7] * gyr[s, 1] + geo[m + 8] * gyr[s, 2] - ga_off[s, 1]
            predicted = x[s, 0] + hq * x[s, g5] - hq * x[s, g7]
            y = (seen - math.atan2(f2, f1) - predicted + math.pi) % two_pi - math.pi
            if not (abs(f0 - w0) < max_flex and abs(y) < GYRO_ANGLE_GATE_RAD):
                continue
            var = rate_std * rate_std + (ga_off[s, 2] if ga_off.shape[1] > 2 else 0.0)
            r = var / w_yz2 * window / dts[f]
            for i in range(N_STATE):
                ph[i] = p[s, i, 0] + hq * p[s, i, g5] - hq * p[s, i, g7]
            den = ph[0] + hq * ph[g5] - hq * ph[g7] + r
            hc0 = cx[s, 0, 0] + hq * cx[s, g5, 0] - hq * cx[s, g7, 0]
            hc1 = cx[s, 0, 1] + hq * cx[s, g5, 1] - hq * cx[s, g7, 1]
            hc2 = cx[s, 0, 2] + hq * cx[s, g5, 2] - hq * cx[s, g7, 2]
            for i in range(N_STATE):
                gain = 0.0 if i == GS and not learn else ph[i] / den
                x[s, i] += gain * y
                cx[s, i, 0] -= gain * hc0
                cx[s, i, 1] -= gain * hc1
                cx[s, i, 2] -= gain * hc2
            for i in range(N_STATE):
                gi = 0.0 if i == GS and not learn else ph[i] / den
                for j in range(i, N_STATE):
                    if learn:
                        pij = 0.5 * ((p[s, i, j] - ph[i] / den * ph[j]) + (p[s, j, i] - ph[j] / den * ph[i]))
                    else:
                        # the scale's gain zeroed: the general form P - K phᵀ - ph Kᵀ + S K Kᵀ
                        gj = 0.0 if j == GS else ph[j] / den
                        pij = 0.5 * ((p[s, i, j] - gi * ph[j] - ph[i] * gj + den * gi * gj)
                                     + (p[s, j, i] - gj * ph[i] - ph[j] * gi + den * gj * gi))
                    p[s, i, j] = pij
                    p[s, j, i] = pij


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=False)      # set, or it inherits run_hand's
def _log_holds(t, dts, rates, gyr, sensor_start, log_t, log_r, log_g, log_n):
    """``chain.HoldLog.add`` for every finger of a hand at ``t``: finger ``f``'s ticks are column ``f`` of
    ``log_t``, its sensors' columns ``sensor_start[f]:sensor_start[f + 1]`` of ``log_r`` and ``log_g``, its
    count ``log_n[f]``; a full log keeps its newer half. Compiled without fused multiply-add: each sum is
    numpy's ``r + dt * rate``, rounded twice, to the last bit."""
    cap = log_t.shape[0]
    for f in range(dts.shape[0]):
        s0, s1 = sensor_start[f], sensor_start[f + 1]
        n = log_n[f]
        if n == cap:
            half = n // 2
            for i in range(half):
                log_t[i, f] = log_t[half + i, f]
                for s in range(s0, s1):
                    log_r[i, s] = log_r[half + i, s]
                    for c in range(3):
                        log_g[i, s, c] = log_g[half + i, s, c]
            n = half
        if n > 0:
            dt = dts[f]
            for s in range(s0, s1):
                log_r[n, s] = log_r[n - 1, s] + dt * rates[s]
                for c in range(3):
                    log_g[n, s, c] = log_g[n - 1, s, c] + dt * gyr[s, c]
        log_t[n, f] = t
        log_n[f] = n + 1


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _finger(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, out_theta, out_phi, out_phal, out_mode,
            cx, x_all, dl, pd, s_off, joint, ws):
    """Advance the state (``x``, ``p``, ``rates``, ``hand_acc``, in place) by every sample ``i`` of
    ``dts`` (``dt = 0`` is the first sample after initialisation: no prediction, no rate change).
    Outputs per sample: the filter's per-sensor angle ``out_theta`` (N, B, S), the joint angles on the
    anatomical branch ``out_phi`` (N, B, n), their phalanx angles ``out_phal`` (N, B, n) and the mode
    code ``out_mode`` (N, B, S) int8 (1 fast, 2 fused). All arrays C-contiguous float64."""
    nb, ns = x.shape[0], x.shape[1]
    nph = out_phi.shape[2]
    o_hinge = 9 * ns
    o_base = o_hinge + 3 * ns
    o_bpos = o_base + 9
    o_lever = o_bpos + 3
    o_prefix = o_lever + ns * nph
    o_cf = o_prefix + ns * nph
    o_clo = o_cf + ns
    o_bl = o_clo + nph * ns
    o_g = o_bl + ns
    grav0, grav1, grav2 = geo[o_g], geo[o_g + 1], geo[o_g + 2]
    fast_above = 0.5 * math.sqrt(grav0 * grav0 + grav1 * grav1 + grav2 * grav2)
    b00, b01, b02 = geo[o_base], geo[o_base + 1], geo[o_base + 2]
    b10, b11, b12 = geo[o_base + 3], geo[o_base + 4], geo[o_base + 5]
    b20, b21, b22 = geo[o_base + 6], geo[o_base + 7], geo[o_base + 8]
    bp0, bp1, bp2 = geo[o_bpos], geo[o_bpos + 1], geo[o_bpos + 2]
    q_theta = st[ST_GYRO_NOISE] ** 2
    q_bg = st[ST_GYRO_WALK] ** 2
    q_ba = st[ST_ACC_WALK] ** 2
    q_cal = st[ST_CAL_WALK] ** 2
    q_gs = st[ST_GS_WALK] ** 2
    gs_learn = st[ST_GS_LEARN] > 0.5
    gyro_range, acc_range = st[ST_GYRO_RANGE], st[ST_ACC_RANGE]
    clipped_std = st[ST_CLIPPED_STD]
    gyro_clip, acc_clip = gyro_range * SATURATION_MARGIN, acc_range * SATURATION_MARGIN
    untracked_var = (st[ST_UNTRACKED_NOISE] if untracked else 0.0) ** 2
    fit_lag = st[ST_FIT_LAG]
    two_pi = 2.0 * math.pi

    sv, pv, m3n, mn3, a, v3, ke, m33, pend = ws
    th, rate, prev, rc, meas, gxs = sv[0], sv[1], sv[2], sv[3], sv[4], sv[5]
    # predicted per-sensor angle, bias-corrected relative rate, previous relative rate (corrected with the
    # same bias), rate change, measured relative rate (the next sample's previous), raw hinge-axis reading
    th_all, w_all, dw_all, cs, sn = pv[0], pv[1], pv[2], pv[3], pv[4]
    hm, hp = m3n[0], m3n[1]             # H, H P
    pht, kg, aht, tl = mn3[0], mn3[1], mn3[2], mn3[3]   # P Hᵀ, the Kalman gain, (I - K H) P Hᵀ, K S
    # a: (I - K H) P; ke: K e
    vv, hth, yy, ee, wv, dl0 = v3[0], v3[1], v3[2], v3[3], v3[4], v3[5]
    # R_x(θ)ᵀ u, ∂f/∂θ, the innovation, (I + G) R_x(θ)ᵀ (the optical fit's lag error: R = r I + e eᵀ),
    # Mᵀ S⁻¹ y (another sensor's dx = C wv), δ when the finger's tick began
    mb, md, phd, kd, sm, si, am, td = m33[0], m33[1], m33[2], m33[3], m33[4], m33[5], m33[6], m33[7]
    # R_Bᵀ R_Mᵀ, ∂f/∂δ = (I + G) R_x(θ)ᵀ R_Bᵀ R_Mᵀ, P_δ· Hᵀ, δ's gain, S, S⁻¹, I - Mᵀ S⁻¹ (P_δ·Hᵀ)ᵀ (another
    # sensor's C ← C am), K_δ S

    for i in range(dts.shape[0]):
        dt = dts[i]
        for b in range(nb):
            h = hand[i, b]
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]
            ha0, ha1, ha2 = h[9], h[10], h[11]
            # the hand's rates and linear term in metacarpus coordinates: R_Mᵀ ω, R_Mᵀ α, R_Mᵀ (a_M - g)
            w0 = r00 * h[12] + r10 * h[13] + r20 * h[14]
            w1 = r01 * h[12] + r11 * h[13] + r21 * h[14]
            w2 = r02 * h[12] + r12 * h[13] + r22 * h[14]
            dw0 = r00 * h[15] + r10 * h[16] + r20 * h[17]
            dw1 = r01 * h[15] + r11 * h[16] + r21 * h[17]
            dw2 = r02 * h[15] + r12 * h[16] + r22 * h[17]
            la0, la1, la2 = ha0 - grav0, ha1 - grav1, ha2 - grav2
            if joint:
                # the optical acceleration corrected by the shared estimate of its error
                la0, la1, la2 = la0 + dl[0], la1 + dl[1], la2 + dl[2]
                dl0[0], dl0[1], dl0[2] = dl[0], dl[1], dl[2]
                # R_Bᵀ R_Mᵀ: world -> finger base
                for cc in range(3):
                    mb[0, cc] = b00 * h[3 * cc] + b10 * h[3 * cc + 1] + b20 * h[3 * cc + 2]
                    mb[1, cc] = b01 * h[3 * cc] + b11 * h[3 * cc + 1] + b21 * h[3 * cc + 2]
                    mb[2, cc] = b02 * h[3 * cc] + b12 * h[3 * cc + 1] + b22 * h[3 * cc + 2]
            lin0 = r00 * la0 + r10 * la1 + r20 * la2
            lin1 = r01 * la0 + r11 * la1 + r21 * la2
            lin2 = r02 * la0 + r12 * la1 + r22 * la2
            hand_rate = w0 * b00 + w1 * b10 + w2 * b20          # (R_Bᵀ R_Mᵀ ω_M)_x
            # the optical fit's predicted lag error (chain.py, "The optics' acceleration"): its change
            # over one lag, â - ā, in the finger base frame R_Bᵀ R_Mᵀ (â - ā); none with the setting at 0
            d0, d1, d2 = ha0 - hand_acc[b, 0], ha1 - hand_acc[b, 1], ha2 - hand_acc[b, 2]
            if fit_lag <= 0.0:
                d0 = d1 = d2 = 0.0
            dm0 = r00 * d0 + r10 * d1 + r20 * d2
            dm1 = r01 * d0 + r11 * d1 + r21 * d2
            dm2 = r02 * d0 + r12 * d1 + r22 * d2
            db0 = b00 * dm0 + b10 * dm1 + b20 * dm2
            db1 = b01 * dm0 + b11 * dm1 + b21 * dm2
            db2 = b02 * dm0 + b12 * dm1 + b22 * dm2

            # predicted angles (trapezoid of the bias-corrected relative rate), then the chain
            finger_sat = False
            for k in range(ns):
                g0, g1, g2 = gyr[i, b, k, 0], gyr[i, b, k, 1], gyr[i, b, k, 2]
                finger_sat = finger_sat or abs(g0) >= gyro_clip or abs(g1) >= gyro_clip or abs(g2) >= gyro_clip
                hi = o_hinge + 3 * k
                gx = geo[hi] * g0 + geo[hi + 1] * g1 + geo[hi + 2] * g2
                rm = gx - hand_rate
                # offset and scale error (s_g of the reading, the previous one's taken as equal)
                corr = x[b, k, 1] + x[b, k, GS] * gx
                gxs[k] = gx
                rate[k] = rm - corr
                prev[k] = rates[b, k] - corr
                meas[k] = rm
                th[k] = x[b, k, 0] + dt * 0.5 * (prev[k] + rate[k])
                rc[k] = (rate[k] - prev[k]) / dt if dt > 0 else 0.0
            acc_th = 0.0
            acc_w = 0.0
            acc_dw = 0.0
            for j in range(nph):
                sj_th = 0.0
                sj_w = 0.0
                sj_dw = 0.0
                for k in range(ns):
                    c = geo[o_clo + j * ns + k]
                    sj_th += c * th[k]
                    sj_w += c * rate[k]
                    sj_dw += c * rc[k]
                acc_th += sj_th
                acc_w += sj_w
                acc_dw += sj_dw
                th_all[j] = acc_th
                w_all[j] = acc_w
                dw_all[j] = acc_dw
                cs[j] = math.cos(acc_th)
                sn[j] = math.sin(acc_th)

            for k in range(ns):
                # reference force of the chain model (observations.reference_force, eqs. 1-2 with a
                # moving hand): u = R_Bᵀ [R_Mᵀ(a_M - g) + α×ρ + ω×(ω×ρ) + 2 ω×ρ' + ρ'']
                v1 = v2 = vel1 = vel2 = ac1 = ac2 = 0.0
                w_max = 0.0
                dw_max = 0.0
                for j in range(nph):
                    lev = geo[o_lever + k * nph + j]
                    v1 += lev * cs[j]
                    v2 += lev * sn[j]
                    wj, dwj = w_all[j], dw_all[j]
                    vel1 += lev * (wj * -sn[j])
                    vel2 += lev * (wj * cs[j])
                    ac1 += lev * (dwj * -sn[j] - wj * wj * cs[j])
                    ac2 += lev * (dwj * cs[j] - wj * wj * sn[j])
                    if geo[o_prefix + k * nph + j] > 0.0:
                        w_max = max(w_max, abs(wj))
                        dw_max = max(dw_max, abs(dwj))
                # finger base -> metacarpus: ρ = p_B + R_B v (v has no x component)
                rho0 = bp0 + b01 * v1 + b02 * v2
                rho1 = bp1 + b11 * v1 + b12 * v2
                rho2 = bp2 + b21 * v1 + b22 * v2
                ve0, ve1, ve2 = b01 * vel1 + b02 * vel2, b11 * vel1 + b12 * vel2, b21 * vel1 + b22 * vel2
                ar0, ar1, ar2 = b01 * ac1 + b02 * ac2, b11 * ac1 + b12 * ac2, b21 * ac1 + b22 * ac2
                # ω×ρ, then ω×(ω×ρ) + α×ρ + 2 ω×ρ'
                c0, c1, c2 = w1 * rho2 - w2 * rho1, w2 * rho0 - w0 * rho2, w0 * rho1 - w1 * rho0
                o0 = lin0 + (dw1 * rho2 - dw2 * rho1) + (w1 * c2 - w2 * c1) + 2.0 * (w1 * ve2 - w2 * ve1) + ar0
                o1 = lin1 + (dw2 * rho0 - dw0 * rho2) + (w2 * c0 - w0 * c2) + 2.0 * (w2 * ve0 - w0 * ve2) + ar1
                o2 = lin2 + (dw0 * rho1 - dw1 * rho0) + (w0 * c1 - w1 * c0) + 2.0 * (w0 * ve1 - w1 * ve0) + ar2
                u0 = b00 * o0 + b10 * o1 + b20 * o2
                u1 = b01 * o0 + b11 * o1 + b21 * o2
                u2 = b02 * o0 + b12 * o1 + b22 * o2

                # the measured force in the phalanx frame, saturation
                m = 9 * k
                a0, a1, a2 = acc[i, b, k, 0], acc[i, b, k, 1], acc[i, b, k, 2]
                f0 = geo[m] * a0 + geo[m + 1] * a1 + geo[m + 2] * a2
                f1 = geo[m + 3] * a0 + geo[m + 4] * a1 + geo[m + 5] * a2
                f2 = geo[m + 6] * a0 + geo[m + 7] * a1 + geo[m + 8] * a2
                g0, g1, g2 = gyr[i, b, k, 0], gyr[i, b, k, 1], gyr[i, b, k, 2]
                gyr_sat = abs(g0) >= gyro_clip or abs(g1) >= gyro_clip or abs(g2) >= gyro_clip
                acc_sat = abs(a0) >= acc_clip or abs(a1) >= acc_clip or abs(a2) >= acc_clip

                # predict: F = I - dt e0 e1ᵀ - dt g_x e0 e_sᵀ, P = F P Fᵀ + Q (Q from the gyro noise,
                # its scale error and saturation, and the offsets' random walks)
                scale = st[ST_GYRO_SCALE] * math.sqrt(g0 * g0 + g1 * g1 + g2 * g2) + (clipped_std if gyr_sat else 0.0)
                # a held scale state is taken as known: it corrects the rate but adds no uncertainty
                fs = dt * gxs[k] if gs_learn else 0.0
                for jj in range(N_STATE):
                    p[b, k, 0, jj] = p[b, k, 0, jj] - dt * p[b, k, 1, jj] - fs * p[b, k, GS, jj]
                for ii in range(N_STATE):
                    p[b, k, ii, 0] = p[b, k, ii, 0] - dt * p[b, k, ii, 1] - fs * p[b, k, ii, GS]
                if joint:
                    for cc in range(3):
                        cx[s_off + k, 0, cc] = cx[s_off + k, 0, cc] - dt * cx[s_off + k, 1, cc] - fs * cx[s_off + k, GS, cc]
                p[b, k, 0, 0] += q_theta * dt + (dt * scale) ** 2
                p[b, k, 1, 1] += q_bg * dt
                p[b, k, 2, 2] += q_ba * dt
                p[b, k, 3, 3] += q_ba * dt
                p[b, k, 4, 4] += q_ba * dt
                p[b, k, GS, GS] += q_gs * dt
                for ii in range(GA_START, N_STATE):
                    if ii != HINGE_G_YZ and ii != HINGE_G_ZY:
                        p[b, k, ii, ii] += q_cal * dt
                half = 0.5 * q_cal * dt
                p[b, k, HINGE_G_YZ, HINGE_G_YZ] += half
                p[b, k, HINGE_G_ZY, HINGE_G_ZY] += half
                p[b, k, HINGE_G_YZ, HINGE_G_ZY] += half
                p[b, k, HINGE_G_ZY, HINGE_G_YZ] += half

                # measurement f = (I + G) R_x(θ)ᵀ u + b_a
                c, s = math.cos(th[k]), math.sin(th[k])
                vv[0], vv[1], vv[2] = u0, c * u1 + s * u2, -s * u1 + c * u2
                h1 = -s * u1 + c * u2              # ∂v_y/∂θ
                h2 = -c * u1 - s * u2              # ∂v_z/∂θ
                for rr in range(3):
                    g = GA_START + 3 * rr
                    pred = vv[rr] + x[b, k, g] * vv[0] + x[b, k, g + 1] * vv[1] + x[b, k, g + 2] * vv[2] + x[b, k, 2 + rr]
                    hth[rr] = x[b, k, g + 1] * h1 + x[b, k, g + 2] * h2
                    yy[rr] = pred
                hth[1] += h1
                hth[2] += h2
                dv1, dv2 = c * db1 + s * db2, -s * db1 + c * db2
                for rr in range(3):
                    g = GA_START + 3 * rr
                    ee[rr] = x[b, k, g] * db0 + x[b, k, g + 1] * dv1 + x[b, k, g + 2] * dv2
                ee[0] += db0
                ee[1] += dv1
                ee[2] += dv2
                yy[0] = f0 - yy[0]
                yy[1] = f1 - yy[1]
                yy[2] = f2 - yy[2]
                mu = geo[o_cf + k] * math.sqrt(dw_max * dw_max + w_max ** 4)     # eq. 6 bound
                fnorm = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
                sigma = math.sqrt(st[ST_ACC_NOISE] ** 2 + (st[ST_KINEMATIC] * mu) ** 2 + (st[ST_ACC_SCALE] * fnorm) ** 2
                                  + untracked_var)
                if acc_sat or finger_sat:
                    # a clipped accelerometer, or a clipped gyro anywhere on the finger (the chain's
                    # kinematic terms take every sensor's rate): no usable direction, no update
                    sigma = SATURATED_SIGMA_M_S2
                    ee[0] = ee[1] = ee[2] = 0.0
                r = sigma * sigma
                # H rows i: ∂f_i/∂θ at 0, e at 2 + i, v at G_i
                for rr in range(3):
                    for ll in range(N_STATE):
                        hm[rr, ll] = 0.0
                    hm[rr, 0] = hth[rr]
                    hm[rr, 2 + rr] = 1.0
                    g = GA_START + 3 * rr
                    hm[rr, g], hm[rr, g + 1], hm[rr, g + 2] = vv[0], vv[1], vv[2]

                if joint:
                    _joint_update(k, b, s_off, ns, x, p, x_all, cx, dl, pd, th, yy, ee, r, c, s, mb, md,
                                  hm, pht, phd, kg, kd, sm, si, am, wv, tl, td, gs_learn, dl0, dt, pend)
                else:
                    # update (kalman.update): PHᵀ, S = H P Hᵀ + R, K = PHᵀ S⁻¹, Joseph form; H's row rr has
                    # entries at 0, 2 + rr and G's row (g..g + 2) only: the products sum those, in the
                    # dense sum's order (the same numbers, the other terms being exact zeros)
                    for ii in range(N_STATE):
                        for rr in range(3):
                            g = GA_START + 3 * rr
                            acc_p = 0.0
                            acc_p += p[b, k, ii, 0] * hm[rr, 0]
                            acc_p += p[b, k, ii, 2 + rr] * hm[rr, 2 + rr]
                            acc_p += p[b, k, ii, g] * hm[rr, g]
                            acc_p += p[b, k, ii, g + 1] * hm[rr, g + 1]
                            acc_p += p[b, k, ii, g + 2] * hm[rr, g + 2]
                            pht[ii, rr] = acc_p
                            acc_h = 0.0
                            acc_h += hm[rr, 0] * p[b, k, 0, ii]
                            acc_h += hm[rr, 2 + rr] * p[b, k, 2 + rr, ii]
                            acc_h += hm[rr, g] * p[b, k, g, ii]
                            acc_h += hm[rr, g + 1] * p[b, k, g + 1, ii]
                            acc_h += hm[rr, g + 2] * p[b, k, g + 2, ii]
                            hp[rr, ii] = acc_h
                    for r1 in range(3):
                        g = GA_START + 3 * r1
                        for r2 in range(3):
                            acc_s = 0.0
                            acc_s += hm[r1, 0] * pht[0, r2]
                            acc_s += hm[r1, 2 + r1] * pht[2 + r1, r2]
                            acc_s += hm[r1, g] * pht[g, r2]
                            acc_s += hm[r1, g + 1] * pht[g + 1, r2]
                            acc_s += hm[r1, g + 2] * pht[g + 2, r2]
                            sm[r1, r2] = acc_s
                    s00, s01, s02 = sm[0, 0], sm[0, 1], sm[0, 2]
                    s10, s11, s12 = sm[1, 0], sm[1, 1], sm[1, 2]
                    s20, s21, s22 = sm[2, 0], sm[2, 1], sm[2, 2]
                    s00 += r + ee[0] * ee[0]
                    s01 += ee[0] * ee[1]
                    s02 += ee[0] * ee[2]
                    s10 += ee[1] * ee[0]
                    s11 += r + ee[1] * ee[1]
                    s12 += ee[1] * ee[2]
                    s20 += ee[2] * ee[0]
                    s21 += ee[2] * ee[1]
                    s22 += r + ee[2] * ee[2]
                    # S⁻¹ by cofactors
                    i00 = s11 * s22 - s12 * s21
                    i01 = s02 * s21 - s01 * s22
                    i02 = s01 * s12 - s02 * s11
                    i10 = s12 * s20 - s10 * s22
                    i11 = s00 * s22 - s02 * s20
                    i12 = s02 * s10 - s00 * s12
                    i20 = s10 * s21 - s11 * s20
                    i21 = s01 * s20 - s00 * s21
                    i22 = s00 * s11 - s01 * s10
                    det = s00 * i00 + s01 * i10 + s02 * i20
                    for ii in range(N_STATE):
                        q0, q1, q2 = pht[ii, 0], pht[ii, 1], pht[ii, 2]
                        kg[ii, 0] = (q0 * i00 + q1 * i10 + q2 * i20) / det
                        kg[ii, 1] = (q0 * i01 + q1 * i11 + q2 * i21) / det
                        kg[ii, 2] = (q0 * i02 + q1 * i12 + q2 * i22) / det
                    if not gs_learn:
                        # the scale state is held (a finger on a fallback closure would learn its errors);
                        # the Joseph form below stays valid for any gain
                        kg[GS, 0] = kg[GS, 1] = kg[GS, 2] = 0.0
                    for ii in range(N_STATE):
                        ke[ii] = kg[ii, 0] * ee[0] + kg[ii, 1] * ee[1] + kg[ii, 2] * ee[2]
                    # A = (I - K H) P, then A (I - K H)ᵀ + K R Kᵀ = A - (A Hᵀ) Kᵀ + r K Kᵀ + (K e)(K e)ᵀ
                    for ii in range(N_STATE):
                        k0, k1, k2 = kg[ii, 0], kg[ii, 1], kg[ii, 2]
                        for jj in range(N_STATE):
                            a[ii, jj] = p[b, k, ii, jj] - (k0 * hp[0, jj] + k1 * hp[1, jj] + k2 * hp[2, jj])
                    for ii in range(N_STATE):
                        for rr in range(3):
                            g = GA_START + 3 * rr
                            acc_a = 0.0
                            acc_a += a[ii, 0] * hm[rr, 0]
                            acc_a += a[ii, 2 + rr] * hm[rr, 2 + rr]
                            acc_a += a[ii, g] * hm[rr, g]
                            acc_a += a[ii, g + 1] * hm[rr, g + 1]
                            acc_a += a[ii, g + 2] * hm[rr, g + 2]
                            aht[ii, rr] = acc_a
                    for ii in range(N_STATE):
                        k0, k1, k2 = kg[ii, 0], kg[ii, 1], kg[ii, 2]
                        c0_, c1_, c2_ = aht[ii, 0], aht[ii, 1], aht[ii, 2]
                        for jj in range(N_STATE):
                            l0, l1, l2 = kg[jj, 0], kg[jj, 1], kg[jj, 2]
                            p[b, k, ii, jj] = ((a[ii, jj] - (c0_ * l0 + c1_ * l1 + c2_ * l2)) + r * (k0 * l0 + k1 * l1 + k2 * l2)
                                               + ke[ii] * ke[jj])
                    x[b, k, 0] = th[k] + (kg[0, 0] * yy[0] + kg[0, 1] * yy[1] + kg[0, 2] * yy[2])
                    for ii in range(1, N_STATE):
                        x[b, k, ii] += kg[ii, 0] * yy[0] + kg[ii, 1] * yy[1] + kg[ii, 2] * yy[2]
                rates[b, k] = meas[k]
                out_theta[i, b, k] = x[b, k, 0]
                out_mode[i, b, k] = 1 if mu > fast_above else 2

            # ā: the optical acceleration smoothed over the fit's lag (a first-order filter)
            w_bar = dt / (fit_lag + dt) if fit_lag > 0.0 else 1.0
            hand_acc[b, 0] += w_bar * (ha0 - hand_acc[b, 0])
            hand_acc[b, 1] += w_bar * (ha1 - hand_acc[b, 1])
            hand_acc[b, 2] += w_bar * (ha2 - hand_acc[b, 2])
            # joint angles from the angles on their anatomical branch, and their phalanx angles
            phal = 0.0
            for j in range(nph):
                phi = 0.0
                for k in range(ns):
                    low = geo[o_bl + k]
                    phi += geo[o_clo + j * ns + k] * (low + (x[b, k, 0] - low) % two_pi)
                out_phi[i, b, j] = phi
                phal += phi
                out_phal[i, b, j] = phal


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _joint_update(k, b, s_off, ns, x, p, x_all, cx, dl, pd, th, yy, ee, r, c, s, mb, md,
                  hm, pht, phd, kg, kd, sm, si, am, wv, tl, td, gs_learn, dl0, dt, pend):
    """Sensor ``k``'s accelerometer update with the hand's shared acceleration error ``δ`` (world frame)
    as three more states: the measurement ``f = h(x_k) + M δ``, ``M = (I + G) R_x(θ)ᵀ R_Bᵀ R_Mᵀ``; the
    augmented covariance keeps ``P_k``, ``C_l = P_{x_l δ}`` of every sensor ``l`` of the hand and ``P_δ``
    (the cross terms between two sensors' states are dropped, as between separate filters). Every
    other sensor moves by its correlation with ``δ``: ``K_l = C_l Mᵀ S⁻¹``. The covariance update is
    the general form ``P - K (PHᵀ)ᵀ - PHᵀ Kᵀ + K S Kᵀ`` (valid for the held scale state's zeroed gain).

    The arithmetic follows the structure (the numpy reference, ``Chain._joint_step_reference``, does the
    dense products; the results differ from it by rounding only): a row of ``H`` has five entries
    (``∂f/∂θ``, ``b_a``'s 1 and ``v`` at ``G``'s row), so ``PHᵀ``, ``C Hᵀ`` and ``S`` sum only those, in
    the dense sum's order (the same numbers: the other terms are exact zeros); ``P`` is updated on and
    above its diagonal and mirrored. For another sensor ``l``, ``K_l = C_l Mᵀ S⁻¹`` (its scale row held
    at 0) and ``C_l - K_l (P_δ·Hᵀ)ᵀ - C_l Mᵀ K_δᵀ + K_l S K_δᵀ`` is ``C_l (I - Mᵀ S⁻¹ (P_δ·Hᵀ)ᵀ)`` in exact
    arithmetic (``K_l S K_δᵀ = C_l Mᵀ K_δᵀ`` on the other rows; on the held row the first and last terms
    are 0 and ``Mᵀ K_δᵀ = Mᵀ S⁻¹ (P_δ·Hᵀ)ᵀ``, ``S`` being symmetric), and ``dx_l = C_l Mᵀ S⁻¹ y`` but on the
    held row (0): a 3 x 3 matrix and a vector shared by every other sensor, where ``K_l``, ``K_l S`` and
    the update of ``C_l`` took six products of 15 x 3 each. For a sensor of another finger, nothing reads
    ``C_l`` or ``x_l`` before that finger's turn, so the products are held back there (``pend``: their
    3 x 3 matrices multiplied together, ``A_l ← A_l am``, and the vectors ``v_l ← v_l + A_l wv``; one
    product of 15 x 3 when ``_settle`` applies them, where each sensor took one per update: the same
    numbers in exact arithmetic, another order of the sums)."""
    gk = s_off + k
    ee[0] = ee[1] = ee[2] = 0.0         # the lag error is δ's now, not a widening
    for cc in range(3):
        m0, m1, m2 = mb[0, cc], c * mb[1, cc] + s * mb[2, cc], -s * mb[1, cc] + c * mb[2, cc]
        for rr in range(3):
            g = GA_START + 3 * rr
            md[rr, cc] = x[b, k, g] * m0 + x[b, k, g + 1] * m1 + x[b, k, g + 2] * m2
        md[0, cc] += m0
        md[1, cc] += m1
        md[2, cc] += m2
    # the reference force took δ as it was when the finger's tick began
    for rr in range(3):
        yy[rr] -= md[rr, 0] * (dl[0] - dl0[0]) + md[rr, 1] * (dl[1] - dl0[1]) + md[rr, 2] * (dl[2] - dl0[2])
    # PHᵀ + C Mᵀ and P_δ·Hᵀ = Cᵀ Hᵀ + P_δ Mᵀ: H's row rr has entries at 0, 2 + rr and G's row (g..g + 2)
    for ii in range(N_STATE):
        for rr in range(3):
            g = GA_START + 3 * rr
            acc_p = 0.0
            acc_p += p[b, k, ii, 0] * hm[rr, 0]
            acc_p += p[b, k, ii, 2 + rr] * hm[rr, 2 + rr]
            acc_p += p[b, k, ii, g] * hm[rr, g]
            acc_p += p[b, k, ii, g + 1] * hm[rr, g + 1]
            acc_p += p[b, k, ii, g + 2] * hm[rr, g + 2]
            for cc in range(3):
                acc_p += cx[gk, ii, cc] * md[rr, cc]
            pht[ii, rr] = acc_p
    for c1 in range(3):
        for rr in range(3):
            g = GA_START + 3 * rr
            acc_p = 0.0
            acc_p += cx[gk, 0, c1] * hm[rr, 0]
            acc_p += cx[gk, 2 + rr, c1] * hm[rr, 2 + rr]
            acc_p += cx[gk, g, c1] * hm[rr, g]
            acc_p += cx[gk, g + 1, c1] * hm[rr, g + 1]
            acc_p += cx[gk, g + 2, c1] * hm[rr, g + 2]
            for cc in range(3):
                acc_p += pd[c1, cc] * md[rr, cc]
            phd[c1, rr] = acc_p
    for r1 in range(3):
        g = GA_START + 3 * r1
        for r2 in range(3):
            acc_s = r if r1 == r2 else 0.0
            acc_s += hm[r1, 0] * pht[0, r2]
            acc_s += hm[r1, 2 + r1] * pht[2 + r1, r2]
            acc_s += hm[r1, g] * pht[g, r2]
            acc_s += hm[r1, g + 1] * pht[g + 1, r2]
            acc_s += hm[r1, g + 2] * pht[g + 2, r2]
            for cc in range(3):
                acc_s += md[r1, cc] * phd[cc, r2]
            sm[r1, r2] = acc_s
    s00, s01, s02, s10, s11, s12, s20, s21, s22 = sm[0, 0], sm[0, 1], sm[0, 2], sm[1, 0], sm[1, 1], sm[1, 2], sm[2, 0], sm[2, 1], sm[2, 2]
    si[0, 0] = s11 * s22 - s12 * s21
    si[0, 1] = s02 * s21 - s01 * s22
    si[0, 2] = s01 * s12 - s02 * s11
    si[1, 0] = s12 * s20 - s10 * s22
    si[1, 1] = s00 * s22 - s02 * s20
    si[1, 2] = s02 * s10 - s00 * s12
    si[2, 0] = s10 * s21 - s11 * s20
    si[2, 1] = s01 * s20 - s00 * s21
    si[2, 2] = s00 * s11 - s01 * s10
    det = s00 * si[0, 0] + s01 * si[1, 0] + s02 * si[2, 0]
    for r1 in range(3):
        for r2 in range(3):
            si[r1, r2] /= det
    for ii in range(N_STATE):
        for rr in range(3):
            kg[ii, rr] = pht[ii, 0] * si[0, rr] + pht[ii, 1] * si[1, rr] + pht[ii, 2] * si[2, rr]
    if not gs_learn:
        kg[GS, 0] = kg[GS, 1] = kg[GS, 2] = 0.0
    for c1 in range(3):
        for rr in range(3):
            kd[c1, rr] = phd[c1, 0] * si[0, rr] + phd[c1, 1] * si[1, rr] + phd[c1, 2] * si[2, rr]
    for c1 in range(3):
        for rr in range(3):
            td[c1, rr] = kd[c1, 0] * sm[0, rr] + kd[c1, 1] * sm[1, rr] + kd[c1, 2] * sm[2, rr]
    # every other sensor of the hand, through its correlation with δ: am = I - Mᵀ S⁻¹ (P_δ·Hᵀ)ᵀ, wv = Mᵀ S⁻¹ y
    sy0 = si[0, 0] * yy[0] + si[0, 1] * yy[1] + si[0, 2] * yy[2]
    sy1 = si[1, 0] * yy[0] + si[1, 1] * yy[1] + si[1, 2] * yy[2]
    sy2 = si[2, 0] * yy[0] + si[2, 1] * yy[1] + si[2, 2] * yy[2]
    for cc in range(3):
        wv[cc] = md[0, cc] * sy0 + md[1, cc] * sy1 + md[2, cc] * sy2
        for c1 in range(3):
            q0 = si[0, 0] * phd[c1, 0] + si[0, 1] * phd[c1, 1] + si[0, 2] * phd[c1, 2]
            q1 = si[1, 0] * phd[c1, 0] + si[1, 1] * phd[c1, 1] + si[1, 2] * phd[c1, 2]
            q2 = si[2, 0] * phd[c1, 0] + si[2, 1] * phd[c1, 1] + si[2, 2] * phd[c1, 2]
            eye = 1.0 if cc == c1 else 0.0
            am[cc, c1] = eye - (md[0, cc] * q0 + md[1, cc] * q1 + md[2, cc] * q2)
    pa, pv, held = pend
    for l in range(cx.shape[0]):
        if l == gk:
            continue
        if not s_off <= l < s_off + ns:
            # another finger's sensor: held back (the first product as it is, later ones composed)
            if held[l]:
                a = pa[l]
                for r1 in range(3):
                    pv[l, r1] += a[r1, 0] * wv[0] + a[r1, 1] * wv[1] + a[r1, 2] * wv[2]
                for r1 in range(3):
                    b0, b1, b2 = a[r1, 0], a[r1, 1], a[r1, 2]
                    for c1 in range(3):
                        a[r1, c1] = b0 * am[0, c1] + b1 * am[1, c1] + b2 * am[2, c1]
            else:
                held[l] = 1
                for r1 in range(3):
                    pv[l, r1] = wv[r1]
                    for c1 in range(3):
                        pa[l, r1, c1] = am[r1, c1]
            continue
        same = l - s_off > k
        for ii in range(N_STATE):
            e0, e1, e2 = cx[l, ii, 0], cx[l, ii, 1], cx[l, ii, 2]
            cx[l, ii, 0] = e0 * am[0, 0] + e1 * am[1, 0] + e2 * am[2, 0]
            cx[l, ii, 1] = e0 * am[0, 1] + e1 * am[1, 1] + e2 * am[2, 1]
            cx[l, ii, 2] = e0 * am[0, 2] + e1 * am[1, 2] + e2 * am[2, 2]
            if ii == GS:
                continue                   # K_l holds the scale state
            dx = e0 * wv[0] + e1 * wv[1] + e2 * wv[2]
            if ii == 0 and same:
                th[l - s_off] += dx        # not updated yet this tick: its predicted angle moves (below)
            else:
                x_all[l, ii] += dx
            if ii == 1 and same:
                # its correction is of the state before the prediction, so the predicted angle moves by
                # F dx: -dt dx_bg (the scale state's term -dt g_x dx_gs is 0: K_l holds it)
                th[l - s_off] -= dt * dx
    # the sensor itself and δ
    _cross_update(cx, gk, kg, pht, kd, phd, sm, tl)
    for ii in range(N_STATE):
        t0, t1, t2 = pht[ii, 0] - tl[ii, 0], pht[ii, 1] - tl[ii, 1], pht[ii, 2] - tl[ii, 2]
        k0, k1, k2 = kg[ii, 0], kg[ii, 1], kg[ii, 2]
        for jj in range(ii, N_STATE):
            acc_p = k0 * pht[jj, 0] + k1 * pht[jj, 1] + k2 * pht[jj, 2] + t0 * kg[jj, 0] + t1 * kg[jj, 1] + t2 * kg[jj, 2]
            v = p[b, k, ii, jj] - acc_p
            p[b, k, ii, jj] = v
            p[b, k, jj, ii] = v
    for c1 in range(3):
        for c2 in range(3):
            acc_p = 0.0
            for rr in range(3):
                acc_p += kd[c1, rr] * phd[c2, rr] + phd[c1, rr] * kd[c2, rr] - td[c1, rr] * kd[c2, rr]
            pd[c1, c2] -= acc_p
    x[b, k, 0] = th[k] + (kg[0, 0] * yy[0] + kg[0, 1] * yy[1] + kg[0, 2] * yy[2])
    for ii in range(1, N_STATE):
        x[b, k, ii] += kg[ii, 0] * yy[0] + kg[ii, 1] * yy[1] + kg[ii, 2] * yy[2]
    for c1 in range(3):
        dl[c1] += kd[c1, 0] * yy[0] + kd[c1, 1] * yy[1] + kd[c1, 2] * yy[2]


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _settle(cx, x_all, pend, s0, s1):
    """The cross-covariance products held back for sensors ``s0:s1`` (``_joint_update``'s ``pend``) applied:
    ``dx = C_l v_l`` into the states (but the scale state's: ``K_l`` holds it), then ``C_l ← C_l A_l``."""
    pa, pv, held = pend
    for l in range(s0, s1):
        if not held[l]:
            continue
        held[l] = 0
        for ii in range(N_STATE):
            e0, e1, e2 = cx[l, ii, 0], cx[l, ii, 1], cx[l, ii, 2]
            cx[l, ii, 0] = e0 * pa[l, 0, 0] + e1 * pa[l, 1, 0] + e2 * pa[l, 2, 0]
            cx[l, ii, 1] = e0 * pa[l, 0, 1] + e1 * pa[l, 1, 1] + e2 * pa[l, 2, 1]
            cx[l, ii, 2] = e0 * pa[l, 0, 2] + e1 * pa[l, 1, 2] + e2 * pa[l, 2, 2]
            if ii != GS:
                x_all[l, ii] += e0 * pv[l, 0] + e1 * pv[l, 1] + e2 * pv[l, 2]


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=KERNEL_FASTMATH)
def _cross_update(cx, row, gain, ph, kd, phd, sm, tl):
    """``C = P_{x δ}`` of sensor ``row`` after an update (gain ``gain`` for its state, ``kd`` for δ;
    ``ph``, ``phd`` their rows of ``P Hᵀ``; ``sm`` = S): ``C - K phdᵀ - ph K_δᵀ + K S K_δᵀ``, with ``tl``
    scratch for ``K S``."""
    for ii in range(N_STATE):
        for rr in range(3):
            tl[ii, rr] = gain[ii, 0] * sm[0, rr] + gain[ii, 1] * sm[1, rr] + gain[ii, 2] * sm[2, rr]
    for ii in range(N_STATE):
        for c1 in range(3):
            acc_p = 0.0
            for rr in range(3):
                acc_p += gain[ii, rr] * phd[c1, rr] + ph[ii, rr] * kd[c1, rr] - tl[ii, rr] * kd[c1, rr]
            cx[row, ii, c1] -= acc_p
