"""A steady tick's compiled work in one call (``HandSession._process_tick``): the flexion-axis fits' two
calls, the cross-axis offsets, the gather of the fingers' samples and ``chain_kernel.run_hand``, which
the pipeline otherwise makes one by one from Python with numpy in between. A steady tick is one whose
fingers were all advanced together at the last tick, every finger sensor live and sampled, while the
optics track: the ticks between two frames almost always. The kernels called are the same, in the same
order, on the same arrays, so the numbers are the same: ``tests/test_tick_kernel.py`` checks the one call
against the calls one by one on a recording whose readings are random for a stretch (with full-scale gyro
samples), messages and filter states to 1e-9; ``tests/test_pipeline.py``'s replay checks a faulty recording's
messages through both paths bit for bit.
"""
from __future__ import annotations

import os
import sys

from numba import njit

from .. import JIT_CACHE
from ..estimators import chain_kernel as CK
from . import mounting_kernel as MK


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
    MK.correct(m_state, m_idx, raw, readings, m_st)
    MK.fit(m_state, m_meta, m_idx, raw, hand, phi_prev, started, m_st)
    if off_idx.shape[0] > 0:
        MK.cross_offsets(m_state, off_idx, ga_off, m_st)
    flat = readings.reshape(-1, 3)
    for r in range(rows_gyr.shape[0]):
        for c in range(3):
            gyr[r, c] = flat[rows_gyr[r], c]
            acc[r, c] = flat[rows_acc[r], c]
    CK.run_hand(x, p, rates, hand_acc, dts, gyr, acc, hand, st, geo, untracked, sensor_start, phalanx_start, geo_start,
                out_theta, out_phi, out_phal, out_mode, cx, dl, pd, jp, t, log_t, log_r, log_g, log_n, ga_off)
    total = 0.0
    for i in range(out_phi.shape[0]):
        total += out_phi[i]
    return total


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


_cached_with_callees(steady_tick, sys.modules[__name__], CK, MK)
