"""Kalman predict and update over stacks of independent filters (leading dimensions ``...``).

The same equations as ``filterpy.kalman.ExtendedKalmanFilter`` (``predict``: ``P = F P Fᵀ + Q``;
``update``: ``S = H P Hᵀ + R``, ``K = P Hᵀ S⁻¹``, ``x += K y`` and the Joseph form
``P = (I - K H) P (I - K H)ᵀ + K R Kᵀ``, which keeps ``P`` symmetric positive definite even when
``K`` is not exactly optimal, e.g. after rounding), evaluated for many filters at once so that a
batch of sensors and runs costs one numpy call per operation. ``tests/test_estimators_ekf.py``
checks them against filterpy itself.
"""
from __future__ import annotations

import numpy as np


def predict(P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``F P Fᵀ + Q`` for stacks (..., n, n)."""
    return F @ P @ np.swapaxes(F, -1, -2) + Q


def update(P: np.ndarray, H: np.ndarray, R: np.ndarray, y: np.ndarray,
           held: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Measurement update of error states that are zero before it: returns ``(dx (..., n), P)``.

    ``H`` (..., m, n), ``R`` (..., m, m), innovation ``y = z - h(x)`` (..., m). ``held`` (n,) marks states
    taken as known: their gain rows are zero, so they and their variances stay as they were (the Joseph
    form below holds for any gain)."""
    pht = P @ np.swapaxes(H, -1, -2)
    s = H @ pht + R
    k = pht @ np.linalg.inv(s)
    if held is not None:
        k = np.where(held[:, None], 0.0, k)
    dx = np.einsum("...ij,...j->...i", k, y)
    i_kh = np.eye(P.shape[-1]) - k @ H
    P = i_kh @ P @ np.swapaxes(i_kh, -1, -2) + k @ R @ np.swapaxes(k, -1, -2)
    return dx, P
