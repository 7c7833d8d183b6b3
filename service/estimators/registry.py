"""Estimator names (the ``--estimator`` values) and construction."""
from __future__ import annotations

from .base import FingerEstimator
from .cf import Complementary
from .chain import Chain
from .ekf import Ekf
from .inertial import InertialFinger
from .integration import GyroIntegration
from .madgwick import Madgwick
from .switching import Switching
from .vector import VectorObservation

REGISTRY: dict[str, type[FingerEstimator]] = {
    cls.name: cls for cls in (VectorObservation, GyroIntegration, Switching, Madgwick, Ekf, Complementary, Chain, InertialFinger)
}


def estimator_class(name: str) -> type[FingerEstimator]:
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; expected one of {sorted(REGISTRY)}") from None
