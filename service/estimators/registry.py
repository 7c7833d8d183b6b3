"""Estimator names (the ``--estimator`` values), the typed choice of one, and its construction.

An estimator is chosen at the edge (``fingertrack estimate --estimator NAME --param ...``, the
service's ``PUT /v1/sessions/{session}/config``, a pipeline's settings) as a name plus settings;
``EstimatorSpec.of`` validates both once, and ``make_estimator`` builds a finger's estimator from
the result, wherever that happens (the pipeline, the command line, the benchmarks).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..model.frames import DEFAULT_GRAVITY_WORLD
from ..model.hand import FingerGeometry
from .base import EstimatorSettings, FingerEstimator
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


@dataclass(frozen=True)
class EstimatorSpec:
    """An estimator by name with its validated, frozen settings."""

    name: str
    settings: EstimatorSettings

    @classmethod
    def of(cls, name: str, params: Mapping[str, Any] | None = None) -> "EstimatorSpec":
        """Validate ``name`` and ``params`` (the settings as keyword values; strings are converted):
        ``ValueError`` naming the known estimators for an unknown name, pydantic's ``ValidationError``
        naming the field for bad settings."""
        return cls(name, estimator_class(name).Settings(**dict(params or {})))


def make_estimator(spec: EstimatorSpec, geom: FingerGeometry, *, initial_theta: np.ndarray | None = None,
                   batch_shape: tuple[int, ...] = (), gravity_world: np.ndarray = DEFAULT_GRAVITY_WORLD,
                   extra_couplings: tuple = ()) -> FingerEstimator:
    """The estimator ``spec`` names, for one finger (``FingerEstimator`` arguments)."""
    return estimator_class(spec.name)(geom, settings=spec.settings, initial_theta=initial_theta,
                                      batch_shape=batch_shape, gravity_world=gravity_world,
                                      extra_couplings=extra_couplings)
