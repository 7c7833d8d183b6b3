"""The shared estimator interface, input containers, validation and the lost-optics policy.

Every finger estimator estimates the phalanx angles ``θ`` of one finger (relative to the
metacarpus, paper section 2.1) from that finger's IMU samples and the metacarpus kinematics, and
reports all joint angles ``φ``. It runs in two modes with the same numbers:

* streaming: ``update(t, gyr, acc, hand)`` with one sample, for the live service;
* batch: ``run(samples)`` over whole arrays, for benchmarks and replays.

Arrays may carry leading batch dimensions ``B`` (independent runs processed together, as
``dlaidig/qmt`` does): a sample is ``gyr (*B, S, 3)``, a batch ``gyr (N, *B, S, 3)``, where ``S`` is
the number of sensors of the finger in the order of ``FingerGeometry.sensors``.

The metacarpus kinematics (``BaseMotion``) come from the optical tracker: rotation (metacarpus to
world), angular velocity, angular acceleration and the acceleration of its origin, world frame.
"""
from __future__ import annotations

import copy
import functools
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, model_validator

from ..model.frames import DEFAULT_GRAVITY_WORLD
from ..model.hand import FingerGeometry
from ..model.kinematics import BaseMotion
from .observations import ChainClosure, FingerObservations

MODE_SLOW, MODE_FAST, MODE_FUSED, MODE_NO_INFO = 0, 1, 2, 3
OBSERVE_BLOCK_SENSOR_SAMPLES = 200_000
"""Batch mode evaluates vectorised observations in blocks of at most this many sensor-samples, so a
long batch (a 1000 s replay of many runs) needs bounded memory."""
LOST_RATE_RAD_S = 1.0
"""While the optics are lost, an estimator's angle uncertainty grows at this rate (a hand turning
unseen at 1 rad/s), rad/s: the shared lost-optics policy behind ``reference_lost``."""
LOST_MAX_STD_RAD = np.pi / 3
"""The growth of the angle std while the optics are lost stops here, rad."""
MODE_NAMES = ("slow", "fast", "fused", "none")
"""Per-sensor modes: ``slow`` (vector observation), ``fast`` (gyro integration), ``fused`` (a filter
that uses both), ``none`` (no information: the estimate is held)."""


class EstimatorSettings(BaseModel):
    """Base of every estimator's settings: frozen, unknown names are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _nested_groups_keep_their_defaults(cls, data):
        """A nested settings group given as a mapping (``--param core.tau_acc_s=2``, a JSON config)
        changes only the fields it names: the others keep *this estimator's* default for the group,
        which may differ from the group class's own defaults."""
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, field in cls.model_fields.items():
            given = out.get(name)
            if isinstance(given, dict):
                default = field.get_default(call_default_factory=True)
                if isinstance(default, BaseModel):
                    out[name] = {**default.model_dump(), **given}
        return out


@dataclass(frozen=True)
class FingerSamples:
    """A batch of samples of one finger: ``t`` (N,) s; ``gyr``, ``acc`` (N, *B, S, 3) rad/s and
    m/s² (specific force); ``hand`` metacarpus kinematics with arrays (N, *B, ...)."""

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    hand: BaseMotion

    def __len__(self) -> int:
        return len(self.t)

    def sample(self, n: int) -> tuple[float, np.ndarray, np.ndarray, BaseMotion]:
        h = self.hand
        return (float(self.t[n]), self.gyr[n], self.acc[n],
                BaseMotion(h.rotation[n], h.position[n], h.velocity[n], h.acceleration[n],
                           h.angular_velocity[n], h.angular_acceleration[n]))


@dataclass(frozen=True)
class FingerEstimate:
    """One output sample: phalanx angles ``theta`` and joint angles ``phi`` (*B, n) rad; per-sensor
    ``mode`` (*B, S) codes (``MODE_NAMES``)."""

    t: float
    theta: np.ndarray
    phi: np.ndarray
    mode: np.ndarray


@dataclass(frozen=True)
class FingerTrack:
    """Batch output: ``t`` (N,), ``theta``/``phi`` (N, *B, n) rad, ``mode`` (N, *B, S)."""

    t: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    mode: np.ndarray


def lost_optics_variance(duration_s: float, rate_rad_s: float = LOST_RATE_RAD_S) -> float:
    """Variance, rad², to add to an angle estimate after the optics were lost for ``duration_s``:
    ``min(rate · duration, LOST_MAX_STD_RAD)²`` (``LOST_RATE_RAD_S`` unless an estimator knows better)."""
    return min(rate_rad_s * duration_s, LOST_MAX_STD_RAD) ** 2


def _check_array(name: str, value: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains non-finite values (NaN or infinity)")
    return arr


class FingerEstimator:
    """Base class. Subclasses implement ``_init_state``, ``_step`` and optionally ``run``.

    ``state`` is a dict of arrays (and floats) that can be read and restored; ``_step`` must not
    modify the state it is given in place before every check has passed (validation happens first).
    """

    name: ClassVar[str] = ""
    Settings: ClassVar[type[EstimatorSettings]] = EstimatorSettings
    jit_kernels: ClassVar[bool] = False
    """True when the estimator runs numba kernels, compiled on first use (``estimators.warm``)."""
    kernels: ClassVar[tuple] = ()
    """Those kernels (numba dispatchers), so that ``estimators.warm`` can tell whether they are cached on disk."""

    @classmethod
    def whole_hand_compiled(cls, settings: EstimatorSettings) -> bool:
        """Whether a hand on this estimator (with ``settings``) advances all its fingers in one compiled call
        per tick (``chain.ChainHand``): a few % of a core per hand. Every other estimator runs per finger and
        sample through Python (8-140 % of a core per hand, ``fingertrack bench cpu --estimator NAME``), so
        the service runs a session on one in a hand worker process of its own (``api.hands.pool``)."""
        return False

    def __init__(self, geom: FingerGeometry, settings: EstimatorSettings | None = None,
                 initial_theta: np.ndarray | None = None, batch_shape: tuple[int, ...] = (),
                 gravity_world: np.ndarray = DEFAULT_GRAVITY_WORLD, extra_couplings: tuple = ()):
        self.geom = geom
        self.settings = settings if settings is not None else self.Settings()
        if not isinstance(self.settings, self.Settings):
            raise TypeError(f"{self.name}: settings must be {self.Settings.__name__}, got {type(self.settings).__name__}")
        self.batch_shape = tuple(batch_shape)
        self.n_sensors = len(geom.sensors)
        if self.n_sensors == 0:
            raise ValueError(f"finger {geom.name!r} has no sensors")
        self.closure = ChainClosure.of(geom, tuple(extra_couplings))
        self.obs = FingerObservations.of(geom)       # the finger's observation constants, shared by every method
        self.gravity_world = np.asarray(gravity_world, dtype=float)
        self._initial_theta = None if initial_theta is None else np.broadcast_to(
            np.asarray(initial_theta, dtype=float), self.batch_shape + (geom.n_phalanges,)).copy()
        self.reset()

    @functools.cached_property
    def vector_closure(self) -> ChainClosure:
        """The finger's own chain closure, without fallback couplings: the one the vector observation
        (2.2.2) closes with inside the estimators that blend it in (``cf``, ``switching``)."""
        return ChainClosure.of(self.geom)

    # -- state ------------------------------------------------------------------------------
    def reset(self, initial_theta: np.ndarray | None = None) -> None:
        """Forget everything; start from ``initial_theta`` (*B, n) rad if given, else from the
        constructor's, else from the first sample."""
        if initial_theta is not None:
            self._initial_theta = np.broadcast_to(np.asarray(initial_theta, dtype=float),
                                                  self.batch_shape + (self.geom.n_phalanges,)).copy()
        self._state: dict | None = None
        self._t_last: float | None = None

    @property
    def started(self) -> bool:
        """True once a sample has been processed."""
        return self._t_last is not None

    @property
    def last_t(self) -> float | None:
        """Time of the last processed sample, s."""
        return self._t_last

    @property
    def state(self) -> dict:
        """A deep copy of the internal state (restorable with the setter)."""
        return copy.deepcopy({"t_last": self._t_last, "filter": self._state})

    @state.setter
    def state(self, value: dict) -> None:
        value = copy.deepcopy(value)
        self._t_last = value["t_last"]
        self._state = value["filter"]

    def inherit(self, previous: "FingerEstimator") -> None:
        """Called right after construction when this estimator replaces ``previous`` for the same finger
        (a sensor fell silent or came back, a calibration, an estimator switch), before any sample.
        Estimators that learn something about their sensors (offsets) take it over here; the default
        keeps nothing but the configuration the pipeline passes as ``initial_theta``."""

    def known_configuration(self, theta: np.ndarray, std_rad: float, hold_s: tuple[float, float] | None = None) -> None:
        """The finger is known to be at phalanx angles ``theta`` (*B, n) rad, each joint to within
        ``std_rad`` (a ``reference_pose``, at the time of the last processed sample), and, with
        ``hold_s`` ``(t0, t1)``, to have been held so over that interval. The default, for
        estimators without an explicit uncertainty, restarts from it at the next sample as from a known
        initial configuration (paper 2.2.3); filters that carry a covariance override this with a
        measurement update that keeps what they have learned."""
        self.reset(initial_theta=theta)

    def hand_tracked(self, tracked: bool) -> None:
        """The pipeline says whether the metacarpus kinematics it passes come from the optics (True)
        or are carried on without them (False: orientation from the finger gyros, acceleration
        unknown). Filters that trust the hand's acceleration may weigh the accelerometer less while it
        is unknown; the default ignores it."""

    def reference_lost(self, duration_s: float) -> None:
        """The metacarpus pose was unavailable (held) for ``duration_s``: whatever the filter believes
        about its angles is less certain than it thinks. Filters with an explicit uncertainty widen
        it so that they re-converge quickly once the optics return; the default does nothing."""

    # -- streaming ----------------------------------------------------------------------------
    def update(self, t: float, gyr: np.ndarray, acc: np.ndarray, hand: BaseMotion) -> FingerEstimate:
        """One sample. Raises ``ValueError`` naming the bad input and leaves the state untouched."""
        t, gyr, acc, hand = self._validate(t, gyr, acc, hand)
        return self._advance(t, gyr, acc, hand)

    def update_trusted(self, t: float, gyr: np.ndarray, acc: np.ndarray, hand: BaseMotion) -> FingerEstimate:
        """``update`` for input already validated upstream (the hand pipeline gets its samples from
        the protocol models and its own optics, and keeps time increasing); skips the checks."""
        return self._advance(t, gyr, acc, hand)

    def _advance(self, t: float, gyr: np.ndarray, acc: np.ndarray, hand: BaseMotion) -> FingerEstimate:
        # state and time change together, after the step: a step that raises leaves both untouched
        if self._state is None:
            state, dt = self._init_state(gyr, acc, hand, self._initial_theta), 0.0
        else:
            state, dt = self._state, t - self._t_last  # type: ignore[operator]
        self._state, theta_sensors, mode = self._step(state, dt, gyr, acc, hand)
        self._t_last = t
        phi = self.closure.joint_angles(self._branch(theta_sensors))
        return FingerEstimate(t, ChainClosure.phalanx_angles(phi), phi, mode)

    def _validate(self, t, gyr, acc, hand):
        shape = self.batch_shape + (self.n_sensors, 3)
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise ValueError(f"t: expected a number of seconds, got {t!r}") from None
        if not np.isfinite(t):
            raise ValueError(f"t: must be finite, got {t}")
        if self._t_last is not None and t <= self._t_last:
            raise ValueError(f"t: time must increase; got {t} after {self._t_last}")
        gyr = _check_array("gyr", gyr, shape)
        acc = _check_array("acc", acc, shape)
        b = self.batch_shape
        hand = BaseMotion(
            _check_array("hand.rotation", hand.rotation, b + (3, 3)),
            np.zeros(b + (3,)) if hand.position is None else _check_array("hand.position", hand.position, b + (3,)),
            np.zeros(b + (3,)) if hand.velocity is None else _check_array("hand.velocity", hand.velocity, b + (3,)),
            _check_array("hand.acceleration", hand.acceleration, b + (3,)),
            _check_array("hand.angular_velocity", hand.angular_velocity, b + (3,)),
            _check_array("hand.angular_acceleration", hand.angular_acceleration, b + (3,)),
        )
        return t, gyr, acc, hand

    # -- batch --------------------------------------------------------------------------------
    def run(self, samples: FingerSamples) -> FingerTrack:
        """All samples in order; the same numbers as calling ``update`` on each. Validates the whole
        batch first (shapes, finiteness, increasing time)."""
        self._validate_batch(samples)
        n = len(samples)
        phi = np.empty((n,) + self.batch_shape + (self.geom.n_phalanges,))
        mode = np.empty((n,) + self.batch_shape + (self.n_sensors,), dtype=np.int8)
        for k in range(n):
            est = self._advance(*samples.sample(k))
            phi[k], mode[k] = est.phi, est.mode
        return FingerTrack(np.asarray(samples.t, dtype=float), ChainClosure.phalanx_angles(phi), phi, mode)

    def _validate_batch(self, samples: FingerSamples) -> None:
        t = np.asarray(samples.t, dtype=float)
        n = t.shape[0] if t.ndim == 1 else -1
        if t.ndim != 1 or not np.all(np.isfinite(t)):
            raise ValueError("t: expected a finite 1-D array of seconds")
        if np.any(np.diff(t) <= 0) or (self._t_last is not None and n and t[0] <= self._t_last):
            raise ValueError("t: time must increase from sample to sample")
        shape = (n,) + self.batch_shape + (self.n_sensors, 3)
        _check_array("gyr", samples.gyr, shape)
        _check_array("acc", samples.acc, shape)
        b = (n,) + self.batch_shape
        _check_array("hand.rotation", samples.hand.rotation, b + (3, 3))
        for name in ("acceleration", "angular_velocity", "angular_acceleration"):
            _check_array(f"hand.{name}", getattr(samples.hand, name), b + (3,))

    def _run_split(self, samples: FingerSamples, observe, recurse) -> FingerTrack:
        """Batch path for estimators whose work splits into an observation that depends on the
        sample, the previous sample's relative rate and ``dt`` only (vectorised over all samples:
        ``observe(gyr, acc, hand, prev_rate, dt)`` returns a tuple of arrays) and a lean recursion
        ``recurse(state, dt, *observation) -> (state, theta, mode)``; the streaming ``_step`` calls
        the same two functions on one sample. Needs ``self.obs`` and a ``"rate"`` entry in the state."""
        self._validate_batch(samples)
        n = len(samples)
        if n == 0:
            return FingerEstimator.run(self, samples)
        t = np.asarray(samples.t, dtype=float)
        if self._state is None:
            first = samples.sample(0)
            self._state = self._init_state(first[1], first[2], first[3], self._initial_theta)
            dt0 = 0.0
        else:
            dt0 = t[0] - self._t_last  # type: ignore[operator]
        dt = np.diff(t, prepend=t[0] - dt0)
        state = self._state
        per_sample = int(np.prod(self.batch_shape, dtype=int)) * self.n_sensors
        block = max(1, OBSERVE_BLOCK_SENSOR_SAMPLES // per_sample)
        theta = np.empty((n,) + self.batch_shape + (self.n_sensors,))
        mode = np.empty(theta.shape, dtype=np.int8)
        for start in range(0, n, block):
            stop = min(n, start + block)
            h = samples.hand
            hand = BaseMotion(h.rotation[start:stop], h.position[start:stop], h.velocity[start:stop],
                              h.acceleration[start:stop], h.angular_velocity[start:stop], h.angular_acceleration[start:stop])
            rate = self.obs.relative_rate(samples.gyr[start:stop], hand)
            prev = np.concatenate([state["rate"][None], rate[:-1]], axis=0)
            dt_b = dt[start:stop].reshape((stop - start,) + (1,) * (rate.ndim - 1))
            observed = observe(samples.gyr[start:stop], samples.acc[start:stop], hand, prev, dt_b)
            for k in range(stop - start):
                state, theta[start + k], mode[start + k] = recurse(state, dt[start + k], *(o[k] for o in observed))
        self._state, self._t_last = state, float(t[-1])
        return self._track(t, theta, mode)

    def _branch(self, theta_sensors: np.ndarray) -> np.ndarray:
        """Reported angles lie on each phalanx's anatomical 2π branch (``FingerObservations.to_branch``):
        a filter that has lost track never reports a joint turned by whole revolutions. Internal states
        (an integrator's running angle) are not wrapped."""
        return self.obs.to_branch(theta_sensors)

    def _track(self, t: np.ndarray, theta_sensors: np.ndarray, mode: np.ndarray) -> FingerTrack:
        phi = self.closure.joint_angles(self._branch(theta_sensors))
        return FingerTrack(np.asarray(t, dtype=float), ChainClosure.phalanx_angles(phi), phi, mode)

    # -- to implement -------------------------------------------------------------------------
    def _init_state(self, gyr, acc, hand, theta0) -> dict:
        raise NotImplementedError

    def _step(self, state: dict, dt: float, gyr, acc, hand) -> tuple[dict, np.ndarray, np.ndarray]:
        """Advance by ``dt`` (0 on the first sample) and return ``(new_state, theta (*B,S), mode (*B,S))``.
        ``theta`` here is per sensor (the phalanx angle each sensor sees)."""
        raise NotImplementedError


def samples_from_session(session, finger: str, hand: BaseMotion | None = None) -> FingerSamples:
    """The samples of ``finger`` from a ``sim.session.SimulatedSession``; the metacarpus kinematics are
    the simulator's truth unless ``hand`` is given (the paper's assumption: the metacarpus is known)."""
    idx = [session.sensor_index(s.id) for s in session.calibration.finger(finger).sensors]
    return FingerSamples(session.t, session.gyr[:, idx], session.acc[:, idx], session.base if hand is None else hand)


def finger_mode(modes: np.ndarray) -> str:
    """One word for a finger from its sensors' modes: ``fast`` if any sensor integrates, ``none`` if
    any has no information, ``slow`` if all observe, else ``fused``."""
    # a few codes: plain Python beats numpy calls
    codes = modes if isinstance(modes, list) else np.asarray(modes).ravel().tolist()
    if MODE_FAST in codes:
        return MODE_NAMES[MODE_FAST]
    if MODE_NO_INFO in codes:
        return MODE_NAMES[MODE_NO_INFO]
    if all(c == MODE_SLOW for c in codes):
        return MODE_NAMES[MODE_SLOW]
    return MODE_NAMES[MODE_FUSED]
