"""A steady tick's compiled work in one call (``HandSession._process_tick``): the flexion-axis fits' two
calls, the cross-axis offsets, the gather of the fingers' samples and ``chain_kernel.run_hand``, which
the pipeline otherwise makes one by one from Python with numpy in between. A steady tick is one whose
fingers were all advanced together at the last tick, every finger sensor live and sampled, while the
optics track: the ticks between two frames almost always. The kernels called are the same, in the same
order, on the same arrays, so the numbers are the same: ``tests/test_tick_kernel.py`` checks the one call
against the calls one by one on a recording whose readings are random for a stretch (with full-scale gyro
samples), messages and filter states to 1e-9; ``tests/test_pipeline.py``'s replay checks a faulty recording's
messages through both paths bit for bit.

``steady_run`` takes the ticks a message releases together (a pose releases the ~11 ticks before it at
1 kHz) up to the one that emits the next frame in one call: for each, the optics at the tick
(``optical_kernel.at``) and then ``steady_tick``, the pipeline's Python between two ticks done once for the
run (``HandSession._steady_run``). It stops before the first tick that is not steady in a way only the
optics tell (not tracking, non-finite, their window filling), and after one whose angles are not finite;
``tests/test_tick_kernel.py`` checks it against the general path tick by tick on a 1 kHz recording with
random readings, clipped gyro samples, missing samples and an optical loss.
"""
from __future__ import annotations

import math
import os
import sys

from numba import njit

from .. import JIT_CACHE
from ..estimators import chain_kernel as CK
from . import mounting_kernel as MK
from . import optical_kernel as OK


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=False)
def steady_tick(m_state, m_meta, m_idx, m_st, raw, readings, phi_prev, started, off_idx, rows_gyr, rows_acc,
                x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start, geo_start,
                out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off):
    """One steady tick: the raw readings ``raw`` (k, 2, 3) turned by the flexion-axis fits into
    ``readings`` (``HandMountings.correct``), the raw gyro samples into the fits with the hand's motion
    ``hand`` and the fingers' angles of the last tick ``phi_prev`` (``HandMountings.fit``), the stacked
    sensors' cross-axis offsets (and their variance where it has a third column) into ``ga_off`` where ``off_idx`` (their fits' rows) is not empty
    (``HandMountings.cross_offsets``), the stacked sensors' gyro and accelerometer rows of ``readings``
    seen as (2k, 3) (``rows_gyr``, ``rows_acc``) into ``gyr`` and ``acc``, then ``run_hand`` with
    them (its arguments from ``x`` on, ``ChainHand.advance_in``). Returns the sum of the joint angles
    ``out_phi`` in order (non-finite where one is)."""
    return steady_tick_in(m_state, m_meta, m_idx, m_st, raw, readings, phi_prev, started, off_idx, rows_gyr, rows_acc,
                          x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start,
                          geo_start, out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n,
                          ga_off, CK.hand_scratch(sensor_start, phalanx_start))


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=False)
def steady_tick_in(m_state, m_meta, m_idx, m_st, raw, readings, phi_prev, started, off_idx, rows_gyr, rows_acc,
                   x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start, geo_start,
                   out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off, ws):
    """``steady_tick`` with ``run_hand``'s work arrays ``ws`` given (``chain_kernel.hand_scratch``), compiled
    without reference counts as ``chain_kernel.run_hand_in`` is."""
    MK.correct(m_state, m_idx, raw, readings, m_st)
    MK.fit(m_state, m_meta, m_idx, raw, hand, phi_prev, started, m_st)
    if off_idx.shape[0] > 0:
        MK.cross_offsets(m_state, off_idx, ga_off, m_st)
    flat = readings.reshape(-1, 3)
    for r in range(rows_gyr.shape[0]):
        for c in range(3):
            gyr[r, c] = flat[rows_gyr[r], c]
            acc[r, c] = flat[rows_acc[r], c]
    CK.run_hand_in(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start,
                   geo_start, out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off,
                   ws)
    total = 0.0
    for i in range(out_phi.shape[0]):
        total += out_phi[i]
    return total


@njit(cache=JIT_CACHE, error_model="numpy", fastmath=False)
def steady_run(ts, pose_t, pose_valid, pose_position, pose_orientation, pose_lo, pose_hi, held_t, held_p, held_q,
               pose_window_s, pose_timeout_s, back_t, window_s, known, motions, hands, totals, given, given_status,
               m_state, m_meta, m_idx, m_st, raw, readings, phis, started, off_idx, rows_gyr, rows_acc, gap0,
               x, p, rates, hand_acc, dts, gyr, acc, st, geo, untracked, sensor_start, phalanx_start, geo_start,
               out_theta, out_phal, out_mode, cx, dl, pd, jp, log_t, log_r, log_g, log_n, ga_off):
    """The steady ticks ``ts`` (n,) released together, each as ``HandSession._process_tick`` makes a steady
    one, in one call: the optics at the tick (``optical_kernel.at`` on the track's arrays, ``OpticalTrack.at``)
    into ``motions[i]`` (24; for the first ``given`` ticks it is there already, ``optical_kernel.usable``'s, with
    ``at``'s result in ``given_status[i]``), then ``steady_tick`` with its ``BaseMotion.flat`` (``hands[i]``, 18), the tick's
    raw readings ``raw[i]`` (k, 2, 3) corrected into ``readings[i]``, the angles of the tick before
    ``phis[i]`` and its own written into ``phis[i + 1]``, the sum of its angles into ``totals[i]``.

    A tick is steady here only while the optics track at it, their kinematics are finite (the sum
    ``_finite_motion`` takes) and whether their window is full (``t - back_t >= window_s``) is ``known``
    (nothing to tell the estimators; the still samples admitted as it says): the first tick that is not is left undone,
    with no state moved, for the tick by tick path. ``dts`` holds the fingers' steps to the first tick and
    ``gap0`` δ's (``ChainHand._begin``); after it every finger and δ step from the tick before. A tick whose
    angles are not finite is the last one done (its fingers are reset then). Returns the number of ticks done."""
    return steady_run_in(ts, pose_t, pose_valid, pose_position, pose_orientation, pose_lo, pose_hi, held_t, held_p,
                         held_q, pose_window_s, pose_timeout_s, back_t, window_s, known, motions, hands, totals, given,
                         given_status, m_state, m_meta, m_idx, m_st, raw, readings, phis, started, off_idx, rows_gyr,
                         rows_acc, gap0, x, p, rates, hand_acc, dts, gyr, acc, st, geo, untracked, sensor_start,
                         phalanx_start, geo_start, out_theta, out_phal, out_mode, cx, dl, pd, jp, log_t, log_r, log_g,
                         log_n, ga_off, CK.hand_scratch(sensor_start, phalanx_start), OK.at_scratch(pose_t.shape[0]))


@njit(cache=JIT_CACHE, _nrt=False, error_model="numpy", fastmath=False)
def steady_run_in(ts, pose_t, pose_valid, pose_position, pose_orientation, pose_lo, pose_hi, held_t, held_p, held_q,
                  pose_window_s, pose_timeout_s, back_t, window_s, known, motions, hands, totals, given, given_status,
                  m_state, m_meta, m_idx, m_st, raw, readings, phis, started, off_idx, rows_gyr, rows_acc, gap0,
                  x, p, rates, hand_acc, dts, gyr, acc, st, geo, untracked, sensor_start, phalanx_start, geo_start,
                  out_theta, out_phal, out_mode, cx, dl, pd, jp, log_t, log_r, log_g, log_n, ga_off, ws, at_ws):
    """``steady_run`` with ``run_hand``'s work arrays ``ws`` (``chain_kernel.hand_scratch``) and the optics' ``at_ws``
    (``optical_kernel.at_scratch``) given, compiled without reference counts (``chain_kernel.run_hand_in``): the
    pipeline keeps both from one run to the next (``ChainHand.advance_run``, ``OpticalTrack.run_scratch``), where
    ``steady_run`` allocates them per call."""
    n = ts.shape[0]
    for i in range(n):
        t = ts[i]
        out = motions[i]
        if i < given:
            status = given_status[i]
        else:
            status = OK.at_in(t, pose_t, pose_valid, pose_position, pose_orientation, pose_lo, pose_hi, held_t, held_p,
                              held_q, pose_window_s, pose_timeout_s, out, at_ws)
        if status != OK.TRACKING:
            return i
        if not math.isfinite(OK.motion_sum(out)):   # ``_finite_motion``'s sum, in its order
            return i
        if (t - back_t >= window_s) != known:
            return i
        hand = hands[i]
        for k in range(9):
            hand[k] = out[k]
        for k in range(9):
            hand[9 + k] = out[15 + k]
        if i == 0:
            m_st[MK.ST_STILL_ON] = 1.0 if known else 0.0      # ``HandMountings.admit_still`` at every tick
            jp[3] = gap0
        else:
            step = t - ts[i - 1]
            for f in range(dts.shape[0]):
                dts[f] = step
            jp[3] = step
        total = steady_tick_in(m_state, m_meta, m_idx, m_st, raw[i], readings[i], phis[i], started, off_idx, rows_gyr,
                               rows_acc, x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start,
                               phalanx_start, geo_start, out_theta, phis[i + 1], out_phal, out_mode, cx, dl, pd, jp, t,
                               log_t, log_r, log_g, log_n, ga_off, ws)
        totals[i] = total
        if not math.isfinite(total):
            return i + 1
    return n


def _sources_stamp(*modules) -> tuple:
    """The modification time and size of each module's source file: what numba's on-disk cache checks, for
    its own file only, before it uses a kernel's cached code."""
    return tuple((st.st_mtime, st.st_size) for st in (os.stat(m.__file__) for m in modules))


def _cached_with_callees(kernel, *callees) -> None:
    """Let ``kernel``'s cached code count as stale when the source of a module it calls into changes, not only
    its own: numba keeps the callees' code inside the caller's and checks only the caller's file, so a cached
    ``steady_tick`` would go on running an old ``run_hand`` or fit. Its cache index takes the stamp of all the
    files instead (numba's own check then compares that). Without an on-disk cache there is nothing to do."""
    cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
    if cache_file is not None and hasattr(cache_file, "_source_stamp"):
        cache_file._source_stamp = _sources_stamp(*callees)


for _kernel in (steady_tick, steady_tick_in):
    _cached_with_callees(_kernel, sys.modules[__name__], CK, MK)
for _kernel in (steady_run, steady_run_in):
    _cached_with_callees(_kernel, sys.modules[__name__], CK, MK, OK)
