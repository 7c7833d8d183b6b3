"""A hand session: protocol-v1 source messages in, ``frame`` messages out.

Data flow (one call of ``handle`` per message, in arrival order):

1. ``calibration`` overrides the hand geometry (estimators are rebuilt from the current estimate);
   ``pose`` goes to the ``OpticalTrack``; ``imu``/``imu_batch`` samples go to a bounded table of
   pending ticks keyed by timestamp.
2. A tick is processed when it has aged past the reorder window (``reorder_window_s`` behind the
   newest IMU time) and the optics cover it (a pose at or after it has arrived) or have timed out.
   Samples arriving for an already processed time are late; a second sample of the same sensor and
   time is a duplicate; both are dropped and counted. A jump of the IMU clock by more than
   ``clock_step_s`` is a clock step: it is counted and reported, pending ticks are discarded and the
   estimators restart from the current estimate instead of integrating across the gap.
3. Each finger's estimator gets the tick's samples of its sensors and the metacarpus kinematics at
   that time. A sensor missing from a tick is held from its last sample while younger than
   ``sensor_timeout_s``; after that it is silent: it is reported, and its finger falls back to an
   estimator over the remaining sensors, closed by the coupling plus ``PIP = fallback_coupling·MCP``
   (restarting from the current estimate; the full estimator returns with the sensor). Each finger
   sensor's readings are first turned onto its flexion axis as learned from its gyro so far
   (``mounting.py``, ``mounting_fit``); the fit learns from the raw samples while the optics track.
4. Frames are emitted on the source clock at ``output_rate_hz`` with the latest estimate of every
   finger, the 26 OpenXR joint poses and a status.

While the optics are occluded the metacarpus position is held and its orientation is carried on by
the hand's angular velocity as the finger gyros see it (``_dead_reckoned_hand``); the fingers keep
being estimated from the IMUs and the status says so. Everything here is deterministic: the same
messages give the same frames, which is what ``fingertrack replay`` relies on.
"""
from __future__ import annotations

import heapq
import math
from itertools import chain as chained, repeat
from dataclasses import dataclass, field, replace
from functools import lru_cache
from collections.abc import Mapping
from typing import Any, Iterator

import numpy as np
from scipy.spatial.transform import Rotation
from pydantic import BaseModel, ConfigDict, Field

from ..estimators.base import FingerEstimator, finger_mode
from ..estimators.chain import ChainHand
from ..estimators.registry import EstimatorSpec, make_estimator
from ..model.frames import DEFAULT_GRAVITY_WORLD
from ..model.hand import METACARPUS_SENSOR_ID, FingerGeometry, HandCalibration, MetacarpusImu, default_calibration, \
    joint_to_phalanx_angles
from ..model.frames import rot_x
from ..model.kinematics import BaseMotion
from ..model.openxr import JOINT_NAMES, FingerAngles, _packed_calibration, angles_layout, joint_pose_arrays, joint_radii, \
    joint_radii_list, joint_tracked_list
from ..model.openxr_frame_kernel import frame_poses
from ..protocol import Calibration, Hello, ReferencePose, Truth
from ..protocol.fast import IMU, IMU_BATCH, POSE, FastImuBatch, FastPose
from ..protocol.outgoing import FingerAnglesDict, FrameDict, FrameStatusDict, JointPoseDict, SensorStatusDict
from .hand_imu import HandImu
from .mounting import HandMountings
from . import optical_kernel
from .optical import OpticalTrack, motion_of
from .tick_kernel import steady_run_in, steady_tick

DEAD_RECKONING_PRIOR = 1e-2
"""Weight of the pull of the hand's angular velocity toward zero in ``_dead_reckoned_hand`` (against 1
per gyro equation): negligible where the finger gyros observe it."""


class PipelineSettings(BaseModel):
    """Hand pipeline settings (every field has a unit and a default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    estimator: str = Field("chain", description="estimator name (``fingertrack estimate --list``)")
    estimator_params: dict[str, Any] = Field(default_factory=dict, description="the estimator's settings")
    output_rate_hz: float = Field(90.0, gt=0.0, le=1000.0, description="frame rate on the source clock, Hz")
    reorder_window_s: float = Field(0.02, ge=0.0, le=1.0, description="how long a tick waits for late samples, s")
    pose_timeout_s: float = Field(0.1, gt=0.0, le=5.0, description="optics count as lost after this long without a valid pose, s")
    pose_window_s: float = Field(0.15, gt=0.0, le=2.0, description="optical derivative fit window, s")
    sensor_timeout_s: float = Field(0.08, gt=0.0, le=5.0, description="a sensor is silent after this long without samples, s")
    clock_step_s: float = Field(0.5, gt=0.0, description="an IMU time jump larger than this is a clock step, s")
    max_pending_ticks: int = Field(512, ge=8, le=100_000, description="bound of the pending-tick table (oldest dropped)")
    fallback_coupling: float = Field(1.0, ge=0.0, le=2.0, description="PIP = this x MCP when a sensor of the finger is silent")
    reference_pose_std_rad: float = Field(0.03, gt=0.0, le=1.0, description="how well a hand holds a reference_pose, per joint, rad (the std of a deviation within ±3 deg: 1.7 deg)")
    reference_pose_max_age_s: float = Field(0.5, ge=0.0, le=10.0, description="a reference_pose whose t1 is further than this behind the processed time is stale and ignored, s")
    max_pending_references: int = Field(8, ge=1, le=1000, description="bound of the reference_pose messages waiting for their t1 (oldest dropped)")
    mounting_fit: bool = Field(True, description="learn each finger sensor's flexion axis from its gyro while the finger flexes and turn its readings onto it (mounting.py)")


@dataclass
class Counters:
    duplicate: int = 0
    late: int = 0
    overflow: int = 0
    clock_steps: int = 0
    unknown_sensor: int = 0
    references_applied: int = 0
    references_stale: int = 0
    filter_resets: int = 0


class Uninstrumented:
    """Stands in for the estimator of a finger without sensors (a partially instrumented glove): it
    never starts, so the finger holds its angles (zero, or a ``reference_pose``'s) and its joints are
    reported untracked."""

    started = False
    last_t = None

    def inherit(self, previous) -> None:
        pass

    def known_configuration(self, theta, std_rad: float, hold_s=None) -> None:
        pass

    def hand_tracked(self, tracked: bool) -> None:
        pass

    def reference_lost(self, duration_s: float) -> None:
        pass


DROP_REASONS = ("late", "duplicate", "unknown_sensor", "overflow", "clock_step")
"""Why the pipeline drops input: older than what was processed, already received, a sensor the
calibration does not know, pushed out of the full pending-tick table; and a clock step (the message's
sample is kept as the new clock's first, the pending ticks before it are discarded)."""


@dataclass(frozen=True)
class Dropped:
    """What one message cost the pipeline, per reason (``DROP_REASONS``): samples, or a pose."""

    late: int = 0
    duplicate: int = 0
    unknown_sensor: int = 0
    overflow: int = 0
    clock_step: int = 0

    def __bool__(self) -> bool:
        return any(getattr(self, r) for r in DROP_REASONS)


NOTHING_DROPPED = Dropped()
"""What almost every message costs: nothing (one shared, immutable answer)."""


@dataclass(frozen=True)
class Handled:
    """The result of ``HandSession.handle``: the frames one message completes and what it dropped."""

    frames: list["HandFrame"]
    dropped: Dropped


@dataclass
class FingerState:
    geom: FingerGeometry
    estimator: FingerEstimator | Uninstrumented
    active_sensors: tuple[str, ...]
    phi: np.ndarray
    mode: str = "none"
    sensor_ids: frozenset[str] = field(init=False)
    base_matrix: np.ndarray = field(init=False)
    """The finger's base frame in the metacarpus frame (``geom.base_matrix()``, kept: the geometry is fixed)."""

    def __post_init__(self):
        self.sensor_ids = frozenset(s.id for s in self.geom.sensors)
        self.base_matrix = self.geom.base_matrix()


class JointPoses(Mapping):
    """``name -> (position, quaternion)`` of the 26 OpenXR joints over the two arrays the kernel wrote
    (rows in ``JOINT_NAMES`` order): a joint's pair is made when it is read (the gesture layer reads
    three of them), not 26 for every frame."""

    __slots__ = ("positions", "quats", "numbers", "angles")

    def __init__(self, positions: np.ndarray, quats: np.ndarray, numbers: np.ndarray | None = None,
                 angles: np.ndarray | None = None):
        self.positions, self.quats = positions, quats
        self.numbers, self.angles = numbers, angles
        """the pipeline's (``HandSession._frame``): the frame's numbers in one float64 array, its joint angles
        (``angles``, the ``FingerAngles.flat`` of the frame, a view of its start), then ``positions`` and
        ``quats`` (views of it too), what a frame's text writes in one go (``frame_text``); else ``None``"""

    def __getitem__(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        k = _JOINT_INDEX[name]
        return self.positions[k], self.quats[k]

    def __iter__(self):
        return iter(JOINT_NAMES)

    def __len__(self) -> int:
        return len(JOINT_NAMES)


_JOINT_INDEX = {n: k for k, n in enumerate(JOINT_NAMES)}
_FLOAT64 = np.dtype(np.float64)
_POSITION_NUMBERS = 3 * len(JOINT_NAMES)
_POSE_NUMBERS = 7 * len(JOINT_NAMES)
"""A frame's numbers after its joint angles: the joints' positions, then their orientations (``JointPoses``)."""

_kept_names: dict[int, tuple[HandCalibration, dict[str, tuple[str, ...]]]] = {}
_kept_constants: dict[tuple[int, int], tuple[HandCalibration, dict, tuple]] = {}


def _joint_names(calib: HandCalibration) -> dict[str, tuple[str, ...]]:
    """Each finger's joint names (``FingerGeometry.joint_names``), kept per calibration object."""
    hit = _kept_names.get(id(calib))
    if hit is not None and hit[0] is calib:
        return hit[1]
    names = {f: g.joint_names for f, g in calib.fingers.items()}
    if len(_kept_names) >= 64:
        _kept_names.clear()
    _kept_names[id(calib)] = (calib, names)
    return names


def _joint_constants(calib: HandCalibration, tracked: dict[str, bool]) -> tuple:
    """``(name, message)`` of the 26 joints in ``JOINT_NAMES`` order, ``message`` the joint's ``JointPoseDict``
    with its radius and tracked flag and without its pose (``None`` in place of position and orientation: a
    frame's message copies it and sets them, cheaper than a new dict of four), kept per calibration object and
    ``tracked`` dict (the pipeline's are shared per combination and never modified)."""
    key = (id(calib), id(tracked))
    hit = _kept_constants.get(key)
    if hit is not None and hit[0] is calib and hit[1] is tracked:
        return hit[2]
    out = tuple((n, {"position": None, "orientation": None, "radius": r, "tracked": k}) for n, r, k in
                zip(JOINT_NAMES, joint_radii_list(calib), [tracked.get(n, True) for n in JOINT_NAMES]))
    if len(_kept_constants) >= 64:
        _kept_constants.clear()
    _kept_constants[key] = (calib, tracked, out)
    return out


@dataclass
class HandFrame:
    """What the pipeline knows at one output time (source clock, s)."""

    t: float
    seq: int
    hand: str
    joint_angles: Mapping[str, np.ndarray]     # φ per finger, rad (the pipeline's: ``FingerAngles``, one array)
    modes: dict[str, str]                       # (the pipeline's: shared by the frames that have them, never modified)
    hand_rotation: np.ndarray                   # metacarpus to world
    hand_position: np.ndarray
    joints: Mapping[str, tuple[np.ndarray, np.ndarray]]
    status: FrameStatusDict
    tracked: dict[str, bool] = field(default_factory=dict)   # per joint (shared, never modified); a joint not listed is tracked

    def to_message(self, calib: HandCalibration) -> FrameDict:
        """The protocol's ``frame`` (``protocol.outgoing.Frame``), without the gesture layer's object."""
        fingers: dict[str, FingerAnglesDict] = {}
        names_of = _joint_names(calib)
        modes = self.modes
        if type(self.joint_angles) is FingerAngles:      # the pipeline's: one ``tolist`` for every finger
            flat, layout = self.joint_angles.flat.tolist(), self.joint_angles.layout
            for f, s in zip(layout.names, layout.slices):
                angles = dict(zip(names_of.get(f) or calib.finger(f).joint_names, flat[s]))
                angles["mode"] = modes[f]
                fingers[f] = angles  # type: ignore[assignment]
        else:
            for f, phi in self.joint_angles.items():
                # the finger's joint names (mcp, pip, dip; the thumb mcp, ip) are read from the calibration
                names = names_of.get(f) or calib.finger(f).joint_names
                angles = dict(zip(names, np.asarray(phi, dtype=float).tolist()))
                angles["mode"] = modes[f]
                fingers[f] = angles  # type: ignore[assignment]
        tracked = self.tracked
        if isinstance(self.joints, JointPoses):         # the pipeline's: two ``tolist`` calls for all 26
            joints: dict[str, JointPoseDict] = {}
            for (n, kept), p, q in zip(_joint_constants(calib, tracked), self.joints.positions.tolist(),
                                       self.joints.quats.tolist()):
                joint = joints[n] = kept.copy()
                joint["position"], joint["orientation"] = p, q
        else:
            radii = joint_radii(calib)
            joints = {n: {"position": p.tolist(), "orientation": q.tolist(), "radius": radii[n],
                          "tracked": tracked.get(n, True)} for n, (p, q) in self.joints.items()}
        # the message's own status (its ``dropped`` too, where a session puts its drop counts): the pipeline's is
        # shared by the frames that have it (``HandSession._frame_status``)
        status = dict(self.status)
        if type(status.get("dropped")) is dict:
            status["dropped"] = dict(status["dropped"])
        return {
            "type": "frame", "t": self.t, "seq": self.seq, "hand": self.hand, "fingers": fingers,
            "joints": joints, "status": status,
        }


class HandSession:
    """One hand (module docstring). ``handle(message)`` returns the frames it completes."""

    def __init__(self, hand: str = "right", settings: PipelineSettings | None = None,
                 calibration: HandCalibration | None = None):
        self.settings = settings or PipelineSettings()
        self.hand = hand
        self.calibration = calibration or default_calibration(hand)  # type: ignore[arg-type]
        self.optics = OpticalTrack(self.settings.pose_window_s, self.settings.pose_timeout_s)
        self.counters = Counters()
        self._pending: dict[float, dict[str, list[float]]] = {}    # t -> id -> gyr + acc (six numbers)
        self._deferred: dict[float, dict[str, list[float]]] = {}   # ready ticks held back, oldest first (``_defer``)
        self._deferred_fits = 0             # how many of them have an optical fit known to be finite (``_pose_keeps``)
        self._fit_rows = np.empty((_MAX_DEFERRED, 24))      # and those fits, ``optical_kernel.at``'s outputs,
        self._fit_status = np.empty(_MAX_DEFERRED, dtype=np.int64)  # and results, in order (``_given_fits``)
        self._samples: dict[str, tuple[float, np.ndarray, int]] = {}   # id -> t, its tick's readings (k, 2, 3), row
        self._samples_due: tuple | None = None  # the last tick's (t, ids, readings), not yet in ``_samples``
        self._processed_t: float | None = None
        self._newest_imu_t: float | None = None
        self._next_frame_t: float | None = None
        self._seq = 0
        self._hand_motion: BaseMotion | None = None
        self._tracking = False
        self._lost_since: float | None = None
        self._fingers: dict[str, FingerState] = {}
        self._together = ChainHand()        # the fingers advanced in one kernel call per tick
        self._layouts: dict[tuple, _TogetherLayout] = {}
        self._steady_kept: tuple | None = None  # the last steady tick's layout, for the next (``_steady_layout``)
        self._together_phi: tuple[np.ndarray, list[FingerState]] | None = None   # their last angles, all in one array
        self._phi_slices: tuple[list, list[slice]] | None = None   # (phalanx_start, each finger's slice of the angles)
        self._tick_ids: tuple[str, ...] | None = None          # the sensor ids of the tick being processed
        self._run_phis = self._run_totals = np.empty((0, 0))    # a steady run's angles and their sums (``_steady_run``)
        self._run_kept: tuple | None = None     # its kernel's arguments that stay the same run after run (``_run_fixed``)
        self._tick_readings: np.ndarray | None = None          # and their corrected readings (k, 2, 3)
        self._references: list[ReferencePose] = []
        self._tick_t: float | None = None
        self._hand_known = False            # the hand's acceleration is known (optics, or the back-of-hand IMU)
        self._optics_back_t = -math.inf     # when the optics last started tracking
        self._hand_imu = self._new_hand_imu(MetacarpusImu())
        self._mount_fits: HandMountings | None = None       # every finger sensor's flexion-axis fit
        self._dropped: dict[str, int] | None = None      # this message's drops (``accept``), once there is one
        self._sensor_ids_of: HandCalibration | None = None
        self._sensor_ids: frozenset[str] = frozenset()
        self._frame_fingers: tuple | None = None         # the fingers as ``_frame`` reads them, kept per ``_fingers``
        self._estimator = EstimatorSpec.of(self.settings.estimator, self.settings.estimator_params)
        self._build_fingers()

    # -- configuration ---------------------------------------------------------------------------
    def _new_hand_imu(self, placement: MetacarpusImu) -> HandImu:
        return HandImu(placement, DEFAULT_GRAVITY_WORLD, self.settings.sensor_timeout_s)

    def _make_estimator(self, geom: FingerGeometry, theta0: np.ndarray | None, extra=()) -> FingerEstimator:
        return make_estimator(self._estimator, geom, initial_theta=theta0, extra_couplings=tuple(extra))

    def _sensor_status(self, now: float, live: tuple | None = None) -> dict[str, SensorStatusDict]:
        """Every calibrated sensor's age and silence at source time ``now``. At a tick that sampled every
        one of them (all ages 0) the answer depends only on which sensors are live: one dict per set of
        live sensors is kept and shared by the frames that have it (never modified). ``live``: every
        finger's live sensors (``FingerState.active_sensors``), if the caller has them at hand."""
        complete = now == self._processed_t and self._tick_ids is not None
        if complete:
            key = (self._tick_ids, *(live if live is not None else [fs.active_sensors for fs in self._fingers.values()]))
            cached = self._sensor_status_kept.get(key)
            if cached is not None:
                return cached
        sensors: dict[str, SensorStatusDict] = {}
        samples = self._last_sample
        for fs in self._fingers.values():
            for s in fs.geom.sensors:
                last = samples.get(s.id)
                age = None if last is None else round(now - last[0], 6)
                sensors[s.id] = {"age_s": age, "silent": s.id not in fs.active_sensors}
        if complete and all(v["age_s"] == 0.0 for v in sensors.values()):
            if len(self._sensor_status_kept) > 64:
                self._sensor_status_kept.clear()
            self._sensor_status_kept[key] = sensors
        return sensors

    @property
    def estimator_name(self) -> str:
        return self._estimator.name

    def _build_fingers(self) -> None:
        new = {}
        for name, geom in self.calibration.fingers.items():
            old = self._fingers.get(name)
            phi = old.phi if old is not None else np.zeros(geom.n_phalanges)
            # continue from the current estimate, if there is one yet
            theta0 = joint_to_phalanx_angles(phi) if (old is not None and old.estimator.started) else None
            sensors = tuple(s.id for s in geom.sensors)
            if not sensors:
                new[name] = FingerState(geom, Uninstrumented(), (), phi, "none")
                continue
            estimator = self._make_estimator(geom, theta0)
            if old is not None:
                estimator.inherit(old.estimator)
            new[name] = FingerState(geom, estimator, sensors, phi, old.mode if old is not None else "none")
        self._fingers = new
        self._finger_sensor_ids = frozenset(s for fs in new.values() for s in fs.sensor_ids)
        self._sensor_status_kept: dict[tuple, dict[str, SensorStatusDict]] = {}    # per calibration (``_sensor_status``)
        self._build_mount_fits()

    mountings = HandMountings
    """The flexion-axis fits' implementation (``mounting.HandMountingsReference`` is its reference)."""

    def _build_mount_fits(self) -> None:
        """One flexion-axis fit per finger sensor; a sensor's fit is kept across rebuilds while its
        calibrated mounting and place stay the same."""
        if not self.settings.mounting_fit:
            return
        self._mount_fits = self.mountings(self.calibration, previous=self._mount_fits)

    def set_estimator(self, spec: EstimatorSpec | str, params: dict | None = None) -> None:
        """Switch the estimator of every finger live; each starts from the current estimate. A name
        and settings are validated first (``EstimatorSpec.of``): ``ValueError``/``ValidationError`` for
        an unknown name or bad settings, and nothing changes."""
        self._rebuild(self.calibration, spec if isinstance(spec, EstimatorSpec) else EstimatorSpec.of(spec, params))

    def apply_calibration(self, overrides: dict) -> None:
        """Apply a calibration's overrides; one that does not fit the hand (``ValueError``, e.g. too
        few sensors for a finger's joints) changes nothing."""
        self._rebuild(self.calibration.with_overrides(overrides), self._estimator)

    def _rebuild(self, calibration: HandCalibration, estimator: EstimatorSpec) -> None:
        """Make ``calibration`` and ``estimator`` current and rebuild every finger for them, or, if
        they do not fit together (the rebuild raises), keep the current ones and their fingers."""
        self.flush()
        before = self.calibration, self._estimator
        self.calibration, self._estimator = calibration, estimator
        try:
            self._build_fingers()            # assigns the new fingers only once all are built
        except Exception:
            self.calibration, self._estimator = before
            raise

    # -- input ---------------------------------------------------------------------------------------
    def handle(self, msg) -> Handled:
        """All frames this message completes, and what it dropped and why."""
        dropped = self.accept(msg)
        return Handled(list(self.ready_frames()), dropped)

    def accept(self, msg) -> Dropped:
        """Take one source message in (the first half of ``handle``); returns what it dropped. The
        frames it completes come from ``ready_frames``."""
        self._dropped = None
        kind = type(msg)                    # (a sample or a pose, read by the compiled parser: no call of ``_accept``)
        if kind is FastImuBatch:
            self._add_imu(msg.samples)
        elif kind is FastPose:
            self._add_pose(msg)
        else:
            self._accept(msg)
        return NOTHING_DROPPED if self._dropped is None else Dropped(**self._dropped)

    def ready_frames(self) -> Iterator[HandFrame]:
        """The frames of every tick that is ready, each yielded as soon as its tick is processed (a
        message that completes several ticks need not hold the first frame back until the last)."""
        return self._process_ready()            # (its generator itself: no generator of this call around it)

    def next_frame_covered(self) -> bool:
        """Whether the tick that makes the next frame is received and a pose at or after it has arrived: it then
        waits only for the IMU samples of the reorder window (at 1 kHz, where the frame's time falls on the tick
        grid, the very next message), not for another pose."""
        frame_t = self._next_frame_t
        if frame_t is None:
            return False
        tick = min((t for t in self._pending if t + 1e-9 >= frame_t), default=None)
        return tick is not None and self.optics.covers(tick)

    def tick_ready(self) -> bool:
        """Whether a pending tick is ready to be processed now (``ready_frames`` would process one more): ready,
        and not one that ``ready_frames`` would only hold back (``_defer``: it is then processed with the next
        frame's ticks, and nothing is left to do now; at 200 Hz IMU the tick after a pose's frame, most often)."""
        pending = self._pending
        if not pending:
            return False
        t = min(pending)
        return self._ready(t) and not self._holds_back(t)

    def ticks_ready(self, count: int) -> bool:
        """Whether the ``count`` oldest pending ticks are all ready to be processed (``ready_frames`` would process
        at least that many more)."""
        pending = self._pending
        if len(pending) < count:
            return False
        ready = self._ready
        return all(ready(t) for t in heapq.nsmallest(count, pending))

    def _drop(self, reason: str, count: int = 1) -> None:
        setattr(self.counters, reason, getattr(self.counters, reason) + count)
        if self._dropped is None:
            self._dropped = dict.fromkeys(DROP_REASONS, 0)
        self._dropped[reason] += count

    def _accept(self, msg) -> None:
        """``accept`` of any message but the compiled parser's ``imu_batch`` and ``pose`` (taken first there, by
        their exact types: no check of an ABC's registry)."""
        if isinstance(msg, IMU_BATCH):
            self._add_imu(msg.samples)
            return
        if isinstance(msg, IMU):
            self._add_imu((msg,))
            return
        if isinstance(msg, POSE):
            self._add_pose(msg)
            return
        self.flush()                        # anything else may read or change what the held-back ticks use
        if isinstance(msg, Calibration):
            self.apply_calibration(msg.overrides())
            if msg.metacarpus is not None:
                old = self._hand_imu.placement
                self._hand_imu = self._new_hand_imu(MetacarpusImu(
                    tuple(msg.metacarpus.position) if msg.metacarpus.position is not None else old.position_m,
                    tuple(msg.metacarpus.mounting) if msg.metacarpus.mounting is not None else old.mounting))
        elif isinstance(msg, Hello):
            if msg.hand != self.hand:
                self.hand = msg.hand
                self.calibration = default_calibration(msg.hand)
                self._build_fingers()
        elif isinstance(msg, ReferencePose):
            self._add_reference(msg)
        elif isinstance(msg, Truth):
            return

    def _add_pose(self, msg) -> None:
        t, latest = msg.t, self.optics.latest_t
        if latest is not None and t <= latest:
            self._drop("late")
            return
        if self._deferred and not self._pose_keeps(t):
            self.flush()                    # (which may start the optics again: read after it)
        self.optics.add(t, msg.position, msg.orientation, msg.valid)

    def _add_reference(self, msg: ReferencePose) -> None:
        """Keep a ``reference_pose`` until the tick at or after its ``t1`` is processed (it may arrive
        before the reorder window has let that tick through)."""
        if self._processed_t is not None and self._processed_t - msg.t1 > self.settings.reference_pose_max_age_s:
            self.counters.references_stale += 1
            return
        self._references.append(msg)
        self._references.sort(key=lambda r: r.t1)
        if len(self._references) > self.settings.max_pending_references:
            self._references.pop(0)
            self.counters.references_stale += 1

    def _apply_references(self, t: float) -> None:
        """Every pending reference whose ``t1`` is at or before ``t``: a known configuration now."""
        while self._references and self._references[0].t1 <= t + 1e-9:
            ref = self._references.pop(0)
            if t - ref.t1 > self.settings.reference_pose_max_age_s:
                self.counters.references_stale += 1
                continue
            for finger, phi in ref.joint_angles(self._fingers).items():
                fs = self._fingers[finger]
                fs.estimator.known_configuration(joint_to_phalanx_angles(np.asarray(phi)), self.settings.reference_pose_std_rad,
                                                 hold_s=(ref.t0, ref.t1))
                if not fs.estimator.started:
                    fs.phi = np.asarray(phi, dtype=float)
            self.counters.references_applied += 1

    def _known_sensor_ids(self) -> frozenset[str]:
        """The sensor ids the calibration places, and the back-of-hand IMU's (kept per calibration object)."""
        calibration = self.calibration
        if self._sensor_ids_of is not calibration:
            self._sensor_ids_of = calibration
            self._sensor_ids = frozenset(calibration.sensor_ids) | {METACARPUS_SENSOR_ID}
        return self._sensor_ids

    def _add_imu(self, samples) -> None:
        """Samples (each with ``t``, ``id``, ``gyr``, ``acc``) into the table of pending ticks, each as one
        list of six numbers, gyro then accelerometer (a tick's readings become one array in one step:
        numpy reads flat lists several times faster than pairs of lists)."""
        known = self._sensor_ids if self._sensor_ids_of is self.calibration else self._known_sensor_ids()
        clock_step_s, max_pending = self.settings.clock_step_s, self.settings.max_pending_ticks
        pending, newest = self._pending, self._newest_imu_t
        # the ticks held back count as processed (``_defer``): a sample at or before them is late
        processed = next(reversed(self._deferred)) if self._deferred else self._processed_t
        tick_t, tick = None, None           # the time of the last sample taken in, and its tick
        for sample in samples:
            t, sid = sample.t, sample.id
            if sid not in known:
                self._drop("unknown_sensor")
                continue
            if t == tick_t:
                # the time of the sample just taken in (a batch's samples share one): it passed the
                # checks below, which the sample taken in cannot have changed for it
                if sid in tick:
                    self._drop("duplicate")
                else:
                    tick[sid] = sample.gyr + sample.acc
                continue
            if newest is not None and abs(t - newest) > clock_step_s:
                self._clock_step()                  # clears the table (the same object) and both times
                newest = processed = None
            if processed is not None and t <= processed:
                self._drop("late")
                continue
            tick = pending.get(t)
            if tick is None:
                tick = pending[t] = {}
            elif sid in tick:
                self._drop("duplicate")
                continue
            tick[sid] = sample.gyr + sample.acc
            tick_t = t
            if newest is None or t > newest:
                newest = t
            if len(pending) > max_pending:
                oldest = min(pending)
                self._drop("overflow", len(pending.pop(oldest)))
                tick_t = None               # the oldest may be this sample's own tick
        self._newest_imu_t = newest

    def _clock_step(self) -> None:
        self.flush()                          # the ticks held back are the old clock's: processed first
        self.counters.clock_steps += 1
        if self._dropped is None:            # the message that stepped the clock is told so (``accept``)
            self._dropped = dict.fromkeys(DROP_REASONS, 0)
        self._dropped["clock_step"] += 1
        self._pending.clear()
        self._last_sample.clear()
        self._references.clear()              # a hold on the old clock: not to be applied on the new one
        self._processed_t = None
        self._newest_imu_t = None
        self._next_frame_t = None
        self._tick_t = None
        self._restart_optics()
        self._hand_known, self._lost_since = False, None    # (an outage on the old clock: not to be told the new estimators)
        self._hand_imu = self._new_hand_imu(self._hand_imu.placement)
        self._build_fingers()

    def _restart_optics(self) -> None:
        """A new optical track (after a clock step or a failed optical fit), lost until its window fills
        from its first pose on."""
        self.optics = OpticalTrack(self.settings.pose_window_s, self.settings.pose_timeout_s)
        self._tracking = False

    # -- processing ---------------------------------------------------------------------------------
    def _ready(self, t: float) -> bool:
        if self._newest_imu_t is None or self._newest_imu_t - t < self.settings.reorder_window_s - 1e-12:
            return False
        if self.optics.covers(t):
            return True
        # optics lost (or never seen): do not wait for them beyond the timeout
        return self._newest_imu_t - t >= self.settings.pose_timeout_s and \
            (self.optics.latest_valid_t is not None or self._newest_imu_t - t >= 2 * self.settings.pose_timeout_s)

    def flush(self) -> None:
        """Process the ready ticks held back (``_defer``), as they would have been when they became ready
        (they make no frame). Done before anything else may read or change the hand's state: a message
        other than IMU samples, a clock step, a new calibration or estimator, the status, the counters."""
        deferred = self._deferred
        if not deferred:
            return
        # only the held-back ticks: the pending ones after them were not ready then
        pending, self._pending, self._deferred, self._deferred_fits = self._pending, deferred, {}, 0
        try:
            for _ in self._process_ready(defer=False):
                raise AssertionError("a tick held back made a frame")
        finally:
            pending.update(self._pending)       # (none left: each was ready)
            self._pending = pending

    def _pose_keeps(self, t_new: float) -> bool:
        """Whether a pose at ``t_new`` may go into the optics before the ticks held back are processed: it
        changes none of their optical fits (``OpticalTrack.add_keeps``) and none of those fits fails (which
        would start the optics again before this pose, ``_process_tick``). Each tick's fit is checked once."""
        deferred, optics = self._deferred, self.optics
        if not optics.covers(next(reversed(deferred))):
            return False                    # a tick past the last pose (released by pose_timeout_s): a pose
            # now would be interpolated into it where it was extrapolated
        done = self._deferred_fits
        if done == len(deferred):
            return optics.add_keeps(t_new, next(iter(deferred)))
        times, rows, status = np.fromiter(deferred, float), self._fit_rows, self._fit_status
        if done:
            times, rows, status = times[done:], rows[done:], status[done:]
        # ``add_keeps``, then ``optics.at`` of each tick not checked yet and ``_finite_motion`` of what it gives, in
        # one compiled call (``optical_kernel.pose_keeps``), their outputs kept for the run that processes them
        # (``_given_fits``: by ``add_keeps``, the same as they are then; the rows after the last tick's untouched),
        # with the track's work arrays
        try:
            if optical_kernel.pose_keeps_in(float(t_new), float(next(iter(deferred))), times, *optics.kernel_args(),
                                            optics._max_poses, rows, status, optics.run_scratch()) < len(times):
                return False
        except (ValueError, np.linalg.LinAlgError):
            return False
        self._deferred_fits = done + len(times)
        return True

    def _given_fits(self) -> tuple | None:
        """The held-back ticks' optical fits that ``_pose_keeps`` computed (their times, ``at``'s outputs and
        results, the track), for the run that processes them (``_steady_run``); None if there are none."""
        if not self._deferred_fits:
            return None
        return list(self._deferred)[:self._deferred_fits], self._fit_rows, self._fit_status, self.optics

    def _may_run_steady(self, t: float) -> bool:
        """The cheap checks of a run of steady ticks from the ready tick ``t`` (``_steady_run``, ``_defer``),
        which need no other tick: ``t`` before the next frame and any reference pose due, the optics
        tracking, the fingers advanced together before, the flexion-axis fits compiled, no back-of-hand IMU
        (an occlusion or a back-of-hand IMU refuses every tick)."""
        frame_t = self._next_frame_t
        if frame_t is None or t + 1e-9 >= frame_t or (self._references and t + 1e-9 >= self._references[0].t1):
            return False
        fits = self._mount_fits
        if not (self._tracking and self._together_phi is not None and fits and fits.compiled):
            return False
        return not (METACARPUS_SENSOR_ID in self._pending[t] or self._hand_imu.live(t))

    def _defer(self, t: float) -> bool:
        """Hold the ready tick ``t`` back, to be advanced in one compiled call with the ticks after it
        (``_steady_run``), when it makes no frame and has no reference pose due, the next tick is not
        ready yet and the run looks steady (the cheap checks of ``_steady_run``). Nothing reads the hand's
        state until it is processed: the next ticks are processed after it, and whatever else could read
        or change that state processes it first (``flush``). At 200 Hz IMU and 90 Hz frames a message
        releases one tick and about half make no frame: two or three ticks per compiled call, not one."""
        if not self._holds_back(t):
            return False
        self._deferred[t] = self._pending.pop(t)
        return True

    def _holds_back(self, t: float) -> bool:
        """Whether ``_defer`` holds the ready tick ``t`` back (it changes nothing: ``tick_ready`` asks it too)."""
        if len(self._deferred) >= _MAX_DEFERRED or not self._may_run_steady(t):
            return False
        pending = self._pending
        return not (len(pending) > 1 and self._ready(sorted(pending)[1]))

    def _process_ready(self, defer: bool = True) -> Iterator[HandFrame]:
        pending = self._pending
        while pending:
            t = min(pending)
            if not self._ready(t):
                return                          # (most messages: no tick ready, no floating-point setting needed)
            given = None                        # (the held-back ticks' optical fits, when they go first)
            if defer:
                if self._defer(t):
                    return
                if self._deferred:              # they go first, in one run with this tick
                    given = self._given_fits()
                    pending.update(self._deferred)
                    self._deferred.clear()
                    self._deferred_fits = 0
                    t = min(pending)
            # a diverging filter is detected and reset, not warned about: numpy's floating-point warnings are
            # off while a tick is processed tick by tick (``_tick``; never held across a ``yield``, the caller's
            # own setting applies there); a steady run's numbers are the compiled kernels', which give none, and
            # the numpy around them allocates, copies and tests for finite values (a finger whose run diverged is
            # rebuilt with a fresh estimator, which computes nothing that warns), so it runs without that
            # setting's cost (``_steady_run``); each tick's time and readiness found once
            while True:
                frames = self._steady_run(t, given)
                given = None
                if frames is None:
                    frames = self._tick(t, pending.pop(t))
                if frames or not pending:
                    break
                t = min(pending)
                if not self._ready(t):
                    break
            if not frames:
                return
            yield from frames

    def _steady_run(self, t: float, given: tuple | None = None) -> list[HandFrame] | None:
        """The ready ticks from ``t`` on, up to the one that emits the next frame or has a reference pose
        due (included), advanced in one compiled call (``tick_kernel.steady_run``) while they are steady,
        as ``_process_tick`` makes each: every finger advanced together at the tick before, every finger
        sensor live and sampled (the same sensor ids in the same order tick after tick), no back-of-hand
        IMU, the optics tracking since before ``t`` (the kernel checks them at each tick) and nothing for
        the estimators to be told. The kernel's numbers are those of the tick by tick calls (the same
        kernels in the same order on the same values); the bookkeeping between two of the ticks, which
        only the last one's leaves behind, is done once. Returns the frames of the last tick done (then
        the next tick, if the kernel stopped before it, is processed tick by tick), or None when ``t``
        does not start such a run of two ticks or more (nothing done: one tick alone costs less tick by
        tick, whose steady tick is one call too). ``given``: the optical fits of held-back ticks computed
        already (``_given_fits``), for the first ticks of the run that are those."""
        pending = self._pending
        if len(pending) < 2 or not self._may_run_steady(t):
            return None
        fits, together, tick = self._mount_fits, self._together_phi, pending[t]
        frame_t, ref_t = self._next_frame_t, self._references[0].t1 if self._references else math.inf
        # then a second tick ready (at 200 Hz a message releases one tick: nothing more to check)
        order = sorted(pending)
        if not self._ready(order[1]):
            return None
        fingers = together[1]
        if not (self._advanced_together_again() and tick.keys() >= self._finger_sensor_ids and _all_live(fingers)):
            return None
        # the ticks of the run: ready, with the same sensors, until a frame or a reference pose is due; their
        # readings gathered into one list of numbers on the way (numpy reads a list several times faster than
        # an iterator over the ticks' lists)
        ids = tuple(tick)
        ts, flat = [t], []
        for v in tick.values():
            flat += v
        ready = self._ready
        for u in order[1:]:
            nxt = pending[u]
            if not ready(u) or tuple(nxt) != ids:
                break
            ts.append(u)
            for v in nxt.values():
                flat += v
            if u + 1e-9 >= frame_t or u + 1e-9 >= ref_t:
                break
        n = len(ts)
        if n < 2:
            return None
        shape = (n, len(ids), 2, 3)
        raw = np.fromiter(flat, float, len(flat)).reshape(shape)
        self._tick_ids = ids
        layout, off_rows = self._steady_layout(fits, fingers)
        readings = np.empty(shape)              # the kernel writes them: the sensors' last samples only then
        # the angles tick after tick and the sums of them, read only here (copied out): kept per hand and grown as a
        # run needs (the kernel uses the first n + 1 angles and n sums); the optics' motions stay the run's own (the
        # last tick's become the hand's motion, ``motion_of``'s views of them, read after the run)
        phis, totals = self._run_phis, self._run_totals
        if phis.shape[0] <= n or phis.shape[1] != together[0].shape[0]:
            phis = self._run_phis = np.empty((max(n, _MAX_DEFERRED) + 1, together[0].shape[0]))
            totals = self._run_totals = np.empty(phis.shape[0] - 1)
        phis[0] = together[0]
        motions, hands = np.empty((n, 24)), np.empty((n, 18))
        done, given_status = 0, _NO_STATUS
        if given is not None and given[3] is self.optics:
            times, rows, given_status = given[:3]
            for u, v in zip(times, ts):
                if u != v:
                    break
                done += 1
            motions[:done] = rows[:done]
        optics = self.optics
        fixed = self._run_fixed(fits, fingers, ids, layout, off_rows, phis)
        # every tick's window full is ``_hand_known`` (the kernel checks it)
        run = self._together.advance_run(
            steady_run_in, (np.array(ts), *optics.kernel_args(), self._optics_back_t,
                            self.settings.pose_window_s, self._hand_known, motions, hands, totals, done, given_status,
                            *fixed[1], raw, readings, *fixed[2]),
            ts, [fs.estimator for fs in fingers], len(layout.sensors), optics.run_scratch())
        if run is None:
            return None
        done, modes, phalanx_start, sensor_start = run
        if not done:
            return self._tick(t, pending.pop(t))
        for u in ts[:done]:
            del pending[u]
        last = ts[done - 1]
        self._processed_t, self._tick_t = last, last
        self._hand_motion = motion_of(motions[done - 1], hands[done - 1])
        finite = math.isfinite(totals[done - 1])
        self._take_together(fingers, layout, phis[done].copy(), modes, phalanx_start, sensor_start, finite)
        self._take_samples(last, ids, readings[done - 1])
        if self._references:
            with np.errstate(all="ignore"):     # (a reference pose's numbers: numpy's, as tick by tick)
                self._apply_references(last)
        frames = self._emit_frames(last)
        if done < n and finite:
            # the kernel stopped before this tick: it is not steady
            return frames + self._tick(ts[done], pending.pop(ts[done]))
        return frames

    def _tick(self, t: float, tick: dict) -> list[HandFrame]:
        """``_process_tick`` with numpy's floating-point warnings off (``_process_ready``)."""
        with np.errstate(all="ignore"):
            return self._process_tick(t, tick)

    def _process_tick(self, t: float, tick: dict) -> list[HandFrame]:
        try:
            hand, tracking = self.optics.at(t)
            usable = hand is None or _finite_motion(hand)
        except (ValueError, np.linalg.LinAlgError):
            hand, tracking, usable = None, False, False
        fits = self._mount_fits
        ids = tuple(tick)
        # gyro, accelerometer (numpy reads one flat run of numbers faster than a list of lists)
        raw = np.fromiter(chained.from_iterable(tick.values()), float, 6 * len(ids)).reshape(-1, 2, 3)
        fingers = self._fingers.values()
        again = self._advanced_together_again()
        # every finger sensor sampled in this tick and live: no finger's sensors can have changed
        settled = tick.keys() >= self._finger_sensor_ids and _all_live(fingers)
        # a steady tick (every finger advanced together again, the optics tracking, the compiled fits on):
        # its compiled calls in one (``tick_kernel``), which writes the corrected readings below
        steady = settled and again and tracking and usable and bool(fits) and fits.compiled
        if steady:
            rows = fits.rows(ids)
            readings = np.empty_like(raw)       # the kernel writes it: the sensors' last samples only then
        elif fits:
            # the tick's raw readings turned by the flexion-axis fits so far, in one call
            rows = fits.rows(ids)
            readings = fits.correct(rows, raw)
        else:
            readings = raw
        self._tick_ids, self._processed_t = ids, t
        if not steady:
            self._take_samples(t, ids, readings)
        if not usable:
            # the optical fit failed numerically (poses too far apart for their times): restart the
            # optics from the next pose rather than feed a non-finite hand to the estimators
            self.counters.filter_resets += 1
            self._restart_optics()
            return []
        if METACARPUS_SENSOR_ID in tick:
            ga = tick[METACARPUS_SENSOR_ID]
            self._hand_imu.add(t, ga[:3], ga[3:])
        if hand is None:
            return []                           # no pose seen yet: nothing to fuse with
        # the back-of-hand IMU keeps the hand's rotation and acceleration known through an occlusion
        imu_live = self._hand_imu.live(t) and (tracking or self._hand_motion is not None)
        if tracking and not self._tracking:
            self._optics_back_t = t
        # the optics give the hand's acceleration again once their fit window holds only poses since
        # they came back (before, the fit has too few poses for it and reports none, which in a fast
        # reach the accelerometers read as a tilt of tens of degrees); the angles are widened to be
        # placed again by the accelerometers then, for as long as the optics were lost
        window_full = tracking and t - self._optics_back_t >= self.settings.pose_window_s
        known = imu_live or window_full
        if fits:
            # the samples of a still hand are chosen by the optics' rate: only once it is known (``mounting.py``)
            fits.admit_still(window_full)
        if known and not self._hand_known and self._lost_since is not None:
            back = self._optics_back_t if self._optics_back_t > self._lost_since else t
            for fs in self._fingers.values():
                fs.estimator.hand_tracked(True)
                fs.estimator.reference_lost(back - self._lost_since)
            self._lost_since = None
        elif not known and self._hand_known:
            self._lost_since = t
            for fs in self._fingers.values():
                fs.estimator.hand_tracked(False)
        if imu_live:
            hand = self._hand_imu.aid(t, hand if tracking else self._hand_motion, tracking)
        elif not tracking and self._hand_motion is not None and self._tick_t is not None:
            hand = self._dead_reckoned_hand(t - self._tick_t)
        self._hand_motion, self._tracking, self._hand_known, self._tick_t = hand, tracking, known, t
        if steady:
            self._steady_tick(fits, rows, raw, readings, t, hand)
            self._take_samples(t, ids, readings)
            self._apply_references(t)
            return self._emit_frames(t)
        if tracking and fits:
            self._fit_mountings(fits, rows, raw, hand, again)
        if settled and again:
            # every finger advanced together at the last tick, so each has sensors and is taken again (the
            # loop below would find it so: ``ChainHand.takes`` of an estimator it advanced, at a later tick)
            self._update_together(self._together_phi[1], t, hand)
            self._apply_references(t)
            return self._emit_frames(t)
        together = []
        takes = ChainHand.takes
        for fs in fingers:
            if settled:
                if not fs.active_sensors:
                    fs.mode = "none"                # a finger without sensors, as ``_prepare_finger`` does
                    continue
            elif not self._prepare_finger(fs, t, tick):
                continue
            if takes(fs.estimator, t):
                together.append(fs)
            else:
                self._update_finger(fs, t, hand)
        if together:
            self._update_together(together, t, hand)
        self._apply_references(t)
        return self._emit_frames(t)

    @property
    def _last_sample(self) -> dict[str, tuple[float, np.ndarray, int]]:
        """Each sensor's last sample: sensor id -> its time, its tick's readings (k, 2, 3) (corrected) and its
        row of them; the last tick's taken in when it is read (``_take_samples``)."""
        due = self._samples_due
        if due is not None:
            self._samples_due = None
            t, ids, readings = due
            self._samples.update(zip(ids, zip(repeat(t), repeat(readings), range(len(ids)))))
        return self._samples

    def _take_samples(self, t: float, ids: tuple, readings: np.ndarray) -> None:
        """The tick's readings (corrected) as each of its sensors' last sample: its time and its row of
        ``readings``. Kept as the tick until the samples are read (``_last_sample``): a tick with the same
        sensors in the same order replaces the one before it whole (the steady ticks: nothing reads them)."""
        due = self._samples_due
        if due is not None and due[1] != ids:
            self._last_sample                       # the tick before into the samples first
        self._samples_due = (t, ids, readings)
        self._tick_readings = readings

    def _advanced_together_again(self) -> bool:
        """Whether every finger was advanced by the last ``_update_together`` (one kernel call) and still
        holds that call's angles and estimator: the steady state of a hand whose sensors are all live. (A
        finger rebuilt since has a new ``FingerState`` or angles, a diverged one ended the record.)"""
        together = self._together_phi
        if together is None:
            return False
        phi, advanced = together
        fingers = self._fingers.values()
        if len(advanced) != len(fingers):
            return False
        for fs, g in zip(fingers, advanced):
            if fs is not g or fs.phi.base is not phi:
                return False
        return True

    def _fit_mountings(self, fits: HandMountings, rows: np.ndarray, raw: np.ndarray, hand: BaseMotion,
                       again: bool) -> None:
        """Each finger sensor's raw gyro sample of this tick (``raw``, its ``rows`` in the fits) into its
        flexion-axis fit, with the hand's rate from the optics and the finger's current angles
        (``mounting.py``), every sensor in one call. ``again``: ``_advanced_together_again``."""
        fingers = self._fingers.values()
        if again:
            # every finger's angles are still the last call's, in one array already; each was advanced
            phi, started = self._together_phi[0], self._all_started(len(fingers))
        else:
            phi = np.concatenate([fs.phi for fs in fingers]).astype(float, copy=False)
            started = np.array([fs.estimator.started for fs in fingers], dtype=np.bool_)
        fits.fit(rows, raw, hand.flat, phi, started)

    @staticmethod
    @lru_cache(maxsize=8)
    def _all_started(n: int) -> np.ndarray:
        """``started`` of ``n`` fingers that all are (one array per count, which the kernel only reads; kept
        writeable: a read-only array is another type to numba, another compilation)."""
        return np.ones(n, dtype=np.bool_)

    def _dead_reckoned_hand(self, dt: float) -> BaseMotion:
        """While the optics are lost: the held pose turned by the hand's angular velocity as the finger
        gyros see it. Every live sensor ``k`` reads ``R_k ω_k = ω_M + θ̇_k x_f`` in metacarpus
        coordinates (``R_k = R_B R_x(θ_k) R_mount`` from the current estimate, ``x_f`` its finger's
        hinge axis), so each gives ``ω_M`` across its hinge axis; hinge axes that differ (the thumb's)
        give the rest. Least squares over ``ω_M`` and every ``θ̇_k``, with a weak pull of ``ω_M`` to
        zero where nothing observes it. Position and acceleration are held (unknown)."""
        prev = self._hand_motion
        assert prev is not None
        blocks, axes = [], []
        for fs in self._fingers.values():
            if not fs.active_sensors:
                continue
            theta = joint_to_phalanx_angles(fs.phi)
            rb = fs.geom.base_matrix()
            for sp in fs.geom.sensors:
                if sp.id in fs.active_sensors and sp.id in self._last_sample:
                    blocks.append(rb @ rot_x(theta[sp.phalanx]) @ sp.mounting_matrix() @ self._last_reading(sp.id)[0])
                    axes.append(rb[:, 0])
        omega_m = np.zeros(3)
        if blocks:
            k = len(blocks)
            a = np.zeros((3 * k + 3, 3 + k))
            for i, x in enumerate(axes):
                a[3 * i:3 * i + 3, :3] = np.eye(3)
                a[3 * i:3 * i + 3, 3 + i] = x
            a[3 * k:, :3] = DEAD_RECKONING_PRIOR * np.eye(3)
            b = np.concatenate(blocks + [np.zeros(3)])
            omega_m = np.linalg.lstsq(a, b, rcond=None)[0][:3]
        rot = prev.rotation @ Rotation.from_rotvec(omega_m * dt).as_matrix()
        z = np.zeros(3)
        return BaseMotion(rot, prev.position.copy(), z, z.copy(), rot @ omega_m, z.copy())

    def _last_reading(self, sensor_id: str) -> np.ndarray:
        """A sensor's last readings (2, 3): gyro and accelerometer, turned by its flexion-axis fit as it was."""
        _, readings, row = self._last_sample[sensor_id]
        return readings[row]

    def _live_sensors(self, geom: FingerGeometry, t: float) -> tuple[str, ...]:
        samples = self._last_sample
        return tuple(s.id for s in geom.sensors
                     if s.id in samples and t - samples[s.id][0] <= self.settings.sensor_timeout_s)

    def _prepare_finger(self, fs: FingerState, t: float, tick: dict) -> bool:
        """Rebuild the finger's estimator if its live sensors changed; whether it has any to update."""
        active = fs.active_sensors
        # every sensor of the finger active and sampled in this tick: nothing can have changed
        if not (len(active) == len(fs.sensor_ids) and tick.keys() >= fs.sensor_ids):
            live = self._live_sensors(fs.geom, t)
            if live != active:
                self._reconfigure(fs, live)
        if not fs.active_sensors:
            fs.mode = "none"
            return False
        return True

    def _update_finger(self, fs: FingerState, t: float, hand: BaseMotion) -> None:
        readings = np.array([self._last_reading(s) for s in fs.active_sensors])
        gyr, acc = np.ascontiguousarray(readings[:, 0]), np.ascontiguousarray(readings[:, 1])
        if fs.estimator.started and t <= fs.estimator.last_t:   # cannot happen with increasing ticks; be safe
            return
        try:
            est = fs.estimator.update_trusted(t, gyr, acc, hand)
            diverged = not _all_finite(est.phi)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            diverged = True
        if diverged:
            self._reset_finger(fs)
            return
        fs.phi = est.phi
        fs.mode = finger_mode(est.mode)

    def _update_together(self, fingers: list[FingerState], t: float, hand: BaseMotion) -> None:
        """Fingers whose estimators advance in one kernel call (``ChainHand``): the same as
        ``_update_finger`` on each."""
        layout = self._together_layout(fingers)
        readings = self._tick_readings
        if layout.rows is not None and readings is not None:
            # every sensor sampled in this tick: its corrected readings, each kind gathered in one step
            flat = readings.reshape(-1, 3)          # gyro and accelerometer rows in turn
            gyr, acc = flat.take(layout.rows_gyr, axis=0), flat.take(layout.rows_acc, axis=0)
        else:
            readings = np.array([self._last_reading(s) for s in layout.sensors])
            gyr, acc = readings[:, 0], readings[:, 1]
        fits = self._mount_fits
        chain = fingers[0].estimator.settings
        self._together.cross_offsets = layout.cross_offsets(fits, chain.gyro_angle_offset_error) \
            if fits and chain.gyro_angle_cross_offsets else None
        phi, modes, phalanx_start, sensor_start = self._together.advance(t, [fs.estimator for fs in fingers], gyr, acc, hand)
        self._take_together(fingers, layout, phi, modes, phalanx_start, sensor_start, math.isfinite(sum(phi.tolist())))

    def _steady_tick(self, fits: HandMountings, rows: np.ndarray, raw: np.ndarray, readings: np.ndarray, t: float,
                     hand: BaseMotion) -> None:
        """A steady tick (``_process_tick``): ``correct`` of the raw readings into ``readings``,
        ``_fit_mountings``, then ``_update_together`` of every finger, with their compiled calls made in
        one (``tick_kernel.steady_tick``): the same kernels in the same order on the same arrays."""
        phi_prev, fingers = self._together_phi
        layout, off_rows = self._steady_layout(fits, fingers)
        phi, modes, phalanx_start, sensor_start, total = self._together.advance_in(
            steady_tick, (fits.state, fits._meta, rows, fits._st, raw, readings, phi_prev, self._all_started(len(fingers)),
                          off_rows, layout.rows_gyr, layout.rows_acc), t, [fs.estimator for fs in fingers], hand,
            len(layout.sensors))
        self._take_together(fingers, layout, phi, modes, phalanx_start, sensor_start, math.isfinite(total))

    def _steady_layout(self, fits: HandMountings, fingers: list[FingerState]) -> tuple["_TogetherLayout", np.ndarray]:
        """The layout of a steady tick's fingers (``_together_layout``) and their sensors' rows in the fits
        whose cross-axis offsets the kernel writes, into the array set as ``ChainHand.cross_offsets`` here
        (no rows, and none set, unless the estimators take them off)."""
        chain = fingers[0].estimator.settings
        kept = self._steady_kept
        if kept is not None and kept[0] is fits and kept[1] is fingers and kept[2] is chain and kept[3] == self._tick_ids \
                and (kept[6] is None or (kept[4]._fits is fits and kept[4]._offsets is kept[6])):
            # the same fits, fingers (each with every sensor live: the callers check it), settings and tick order
            # as the last steady tick: the same layout, rows and offsets array (``offsets_of`` keeps them per fits)
            self._together.cross_offsets = kept[6]
            return kept[4], kept[5]
        layout = self._together_layout(fingers)
        if chain.gyro_angle_cross_offsets:
            off_rows, self._together.cross_offsets = layout.offsets_of(fits, chain.gyro_angle_offset_error)
        else:
            off_rows, self._together.cross_offsets = _NO_ROWS, None
        self._steady_kept = (fits, fingers, chain, self._tick_ids, layout, off_rows, self._together.cross_offsets)
        return layout, off_rows

    def _run_fixed(self, fits: HandMountings, fingers: list[FingerState], ids: tuple, layout: "_TogetherLayout",
                   off_rows: np.ndarray, phis: np.ndarray) -> tuple:
        """The arguments of a steady run's kernel that stay the same run after run (``_steady_run``): the fits'
        arrays and the tick's rows in them, then the angles' array, the fingers' ``started`` and the layout's rows;
        kept with the last steady layout (``_steady_layout``'s, the same fits, fingers and tick order) and angles'
        array they were made for."""
        kept_layout = self._steady_kept
        fixed = self._run_kept
        if fixed is None or fixed[0] is not kept_layout or fixed[2][0] is not phis:
            fixed = self._run_kept = (kept_layout, (fits.state, fits._meta, fits.rows(ids), fits._st),
                                      (phis, self._all_started(len(fingers)), off_rows, layout.rows_gyr, layout.rows_acc))
        return fixed

    def _take_together(self, fingers: list[FingerState], layout: "_TogetherLayout", phi: np.ndarray, modes: list,
                       phalanx_start: list, sensor_start: list, finite: bool) -> None:
        """The angles and modes of the fingers advanced together (``ChainHand.advance``) into their states;
        a finger whose angles are not finite is reset (``finite``: all of them are)."""
        names = layout.mode_names.get(tuple(modes))
        if names is None:
            if len(layout.mode_names) > 256:
                layout.mode_names.clear()
            names = layout.mode_names[tuple(modes)] = [
                finger_mode(modes[sensor_start[f]:sensor_start[f + 1]]) for f in range(len(fingers))]
        kept = self._phi_slices
        if kept is None or kept[0] is not phalanx_start:
            # each finger's slice of the angles, kept while the same fingers are stacked (the same list)
            kept = self._phi_slices = (phalanx_start, [slice(a, b) for a, b in zip(phalanx_start, phalanx_start[1:])])
        if finite:
            for fs, part, name in zip(fingers, kept[1], names, strict=True):
                fs.phi = phi[part]
                fs.mode = name
            self._together_phi = (phi, fingers)
            return
        for fs, part, name in zip(fingers, kept[1], names, strict=True):
            finger_phi = phi[part]
            if not _all_finite(finger_phi):
                self._reset_finger(fs)
                continue
            fs.phi = finger_phi
            fs.mode = name
        self._together_phi = None

    def _together_layout(self, fingers: list[FingerState]) -> "_TogetherLayout":
        """How this tick's readings reach the fingers advanced together, kept per tick order of sensor
        ids and per set of fingers and their live sensors (the same tick after tick)."""
        key = (self._tick_ids, *[fs.active_sensors for fs in fingers])
        layout = self._layouts.get(key)
        if layout is None:
            if len(self._layouts) > 64:
                self._layouts.clear()
            sensors = [s for fs in fingers for s in fs.active_sensors]
            ids = self._tick_ids or ()
            rows = np.array([ids.index(s) for s in sensors], dtype=np.int64) \
                if self._tick_ids is not None and set(sensors) <= set(ids) else None
            layout = self._layouts[key] = _TogetherLayout(sensors, rows)
        return layout

    def _reset_finger(self, fs: FingerState) -> None:
        """A filter that diverged (non-finite estimate, or a numerical failure) restarts from the
        reference: the last finite angles are kept and the estimator begins again at the next tick
        from the metacarpus pose and its own initialisation, instead of failing on every later tick.
        Counted in the status (``filter_resets``); the finger reports mode ``none`` (no information)
        until its estimator has a sample again."""
        self.counters.filter_resets += 1
        if not np.all(np.isfinite(fs.phi)):
            fs.phi = np.zeros_like(fs.phi)
        geom = replace(fs.geom, sensors=tuple(s for s in fs.geom.sensors if s.id in fs.active_sensors))
        extra = [] if len(fs.active_sensors) == len(fs.geom.sensors) else [(0, self.settings.fallback_coupling)]
        try:
            fs.estimator = self._make_estimator(geom, None, extra)
        except ValueError:
            fs.active_sensors = ()
        fs.mode = "none"

    def _reconfigure(self, fs: FingerState, live: tuple[str, ...]) -> None:
        fs.active_sensors = live
        if not live:
            return
        geom = replace(fs.geom, sensors=tuple(s for s in fs.geom.sensors if s.id in live))
        theta0 = joint_to_phalanx_angles(fs.phi) if fs.estimator.started else None
        extra = [] if len(live) == len(fs.geom.sensors) else [(0, self.settings.fallback_coupling)]
        try:
            estimator = self._make_estimator(geom, theta0, extra)
            estimator.inherit(fs.estimator)
            fs.estimator = estimator
        except ValueError:
            fs.active_sensors = ()           # nothing observable: hold the angles

    def _emit_frames(self, t: float) -> list[HandFrame]:
        # one frame at the first tick at or after each scheduled time, stamped with the tick's time
        # (the time of the estimate it carries); after a gap the schedule resumes from now
        step = 1.0 / self.settings.output_rate_hz
        if self._next_frame_t is None:
            self._next_frame_t = t
        if t + 1e-9 < self._next_frame_t:
            return []
        while self._next_frame_t <= t + 1e-9:
            following = self._next_frame_t + step
            if following == self._next_frame_t:     # no float64 progress at this magnitude: resume from now
                following = t + step
                if following == t:
                    break
            self._next_frame_t = following
        return [self._frame(t)]

    def _frame(self, t: float) -> HandFrame:
        hand = self._hand_motion
        assert hand is not None
        fingers = self._frame_fingers
        if fingers is None or fingers[0] is not self._fingers:
            fingers = self._frame_fingers = (self._fingers, tuple(self._fingers), list(self._fingers.values()), {})
        _, names, states, kept = fingers
        phis, modes, live = zip(*[(fs.phi, fs.mode, fs.active_sensors) for fs in states]) if states else ((), (), ())
        # every finger's angles copied into one array (``FingerAngles``: a finger's are a view of it), the start
        # of the frame's numbers (its joints' positions and orientations after them: ``JointPoses.numbers``)
        counts = tuple(map(len, phis))
        n = sum(counts)
        numbers = np.empty(n + _POSE_NUMBERS)
        flat = numbers[:n]
        if phis:
            np.concatenate(phis, out=flat)
        # what depends only on the fingers' modes, live sensors and angle counts and on the optics: one of each
        # per combination (a hand has few), shared by the frames that have it (never modified)
        key = (self._tracking, modes, live, counts)
        last = kept.get(None)               # (the frame before's: compared item by item, no hash of the key)
        if last is not None and last[0] == key:
            constants = last[1]
        else:
            constants = kept.get(key)
            if constants is None:
                if len(kept) > 64:
                    kept.clear()
                constants = kept[key] = (angles_layout(names, key[3]), dict(zip(names, modes)),
                                         _tracked_dict(self._tracking, tuple(zip(names, map(bool, live)))))
            kept[None] = (key, constants)
        layout, modes_of, tracked = constants
        angles = FingerAngles(flat, layout)
        positions = numbers[n:n + _POSITION_NUMBERS].reshape(-1, 3)
        quats = numbers[n + _POSITION_NUMBERS:].reshape(-1, 4)
        rotation, position = hand.rotation, hand.position
        # the poses written into the numbers in one call where the five fingers are padded as the kernel wants
        # them and the metacarpus pose is what it reads (``openxr_frame_kernel``), else by ``joint_pose_arrays``
        if layout.padded is None or type(rotation) is not np.ndarray or type(position) is not np.ndarray \
                or rotation.dtype is not _FLOAT64 or position.dtype is not _FLOAT64 \
                or not rotation.flags.c_contiguous or not position.flags.c_contiguous \
                or not frame_poses(_packed_calibration(self.calibration), flat, layout.padded, rotation, position,
                                   numbers):
            joint_pose_arrays(self.calibration, angles, rotation, position, positions, quats)
        self._seq += 1
        return HandFrame(t, self._seq, self.hand, angles, modes_of, rotation.copy(), position.copy(),
                         JointPoses(positions, quats, numbers, flat), self._frame_status(t, live), tracked)

    _status_kept: tuple | None = None
    """The last frame's status and what it holds (``_frame_status``)."""

    def _frame_status(self, now: float, live: tuple) -> FrameStatusDict:
        """``_status(now, live)`` for a frame: one dict per change of what it holds (the optics' state, the
        estimator, the sensors' dict, the counters; most frames hold what the frame before held), shared by the
        frames that have it and never modified (a session's drop counts go into a copy: ``FrameOutput.set_drops``,
        ``HandFrame.to_message``), whose text a hand's frames write once (``frame_text``)."""
        sensors = self._sensor_status(now, live)
        c = self.counters
        key = (self._tracking, self.optics.latest_t is None, self._estimator.name, sensors, c.duplicate, c.late,
               c.overflow, c.unknown_sensor, c.clock_steps, c.references_applied, c.references_stale, c.filter_resets)
        kept = self._status_kept
        if kept is not None and kept[0] == key:     # (item by item: the sensors' dict by identity first)
            return kept[1]
        status = self._status(now, live, sensors)
        self._status_kept = (key, status)
        return status

    def status(self, t: float | None = None) -> FrameStatusDict:
        """The frame's ``status`` (``protocol.outgoing.FrameStatus``) at source time ``t``."""
        self.flush()
        return self._status(t if t is not None else (self._processed_t or 0.0))

    def _status(self, now: float, live: tuple | None = None, sensors: dict | None = None) -> FrameStatusDict:
        """``status`` at source time ``now``; ``live``: every finger's live sensors, if known; ``sensors``: their
        ``_sensor_status(now, live)``, if known."""
        return {
            "optics": "tracking" if self._tracking else ("occluded" if self.optics.latest_t is not None else "waiting"),
            "estimator": self.estimator_name,
            "sensors": self._sensor_status(now, live) if sensors is None else sensors,
            "dropped": {"duplicate": self.counters.duplicate, "late": self.counters.late,
                        "overflow": self.counters.overflow, "unknown_sensor": self.counters.unknown_sensor},
            "clock_steps": self.counters.clock_steps,
            "reference_poses": {"applied": self.counters.references_applied, "stale": self.counters.references_stale},
            "filter_resets": self.counters.filter_resets,
        }


@dataclass
class _TogetherLayout:
    """The sensors of the fingers advanced together, finger after finger (``sensors``), their rows in the
    tick's readings (``rows``; None when the tick lacks one, which then comes from its last sample),
    and the finger modes per combination of sensor mode codes (``mode_names``)."""

    sensors: list[str]
    rows: np.ndarray | None
    mode_names: dict[tuple, list[str]] = field(default_factory=dict)
    rows_gyr: np.ndarray | None = field(init=False)
    rows_acc: np.ndarray | None = field(init=False)
    """``rows``' gyro and accelerometer rows in the tick's readings seen as (2k, 3)."""

    def __post_init__(self):
        self.rows_gyr = None if self.rows is None else 2 * self.rows
        self.rows_acc = None if self.rows is None else 2 * self.rows + 1
        self._fits = self._fit_rows = self._offsets = None

    def cross_offsets(self, fits, var: bool = False) -> np.ndarray:
        """The sensors' gyro cross-axis offsets (S, 2) as their flexion-axis fits ``fits`` estimate them now
        (``HandMountings.cross_offsets``), with ``var`` their variance as a third column, in one array kept
        per layout and rewritten each call."""
        return fits.cross_offsets(*self.offsets_of(fits, var))

    def offsets_of(self, fits, var: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The sensors' rows in ``fits`` and the array their offsets (and with ``var`` their variance) are
        written into (``cross_offsets``)."""
        if self._fits is not fits or self._offsets.shape[1] != 2 + var:
            self._fits, self._fit_rows = fits, fits.rows(tuple(self.sensors))
            self._offsets = np.zeros((len(self.sensors), 2 + var))
        return self._fit_rows, self._offsets


_NO_ROWS = np.zeros(0, dtype=np.int64)
"""No fit rows: ``tick_kernel.steady_tick`` writes no cross-axis offsets."""

_NO_STATUS = np.zeros(0, dtype=np.int64)
"""No optical results given: ``tick_kernel.steady_run`` fits the optics at every tick."""

_MAX_DEFERRED = 8
"""The most ticks held back (``HandSession._defer``)."""


@lru_cache(maxsize=64)
def _tracked_dict(optics_tracking: bool, measured: tuple[tuple[str, bool], ...]) -> dict[str, bool]:
    """``name -> tracked`` of the 26 joints (``joint_tracked_list``), one dict per combination (a hand
    has few), shared by the frames that have it: never modified."""
    return dict(zip(JOINT_NAMES, joint_tracked_list(optics_tracking, measured)))


def _all_live(fingers) -> bool:
    """Whether every finger's sensors are all live (a loop: cheaper than ``all`` over a generator)."""
    for fs in fingers:
        if len(fs.active_sensors) != len(fs.sensor_ids):
            return False
    return True


def _all_finite(*arrays: np.ndarray) -> bool:
    # a sum is non-finite if any term is (NaN and infinities propagate); cheaper than isfinite per element,
    # and on these few values plain Python sums beat numpy's per-call cost
    return math.isfinite(sum(sum(np.ravel(a).tolist()) for a in arrays if a is not None))


def _finite_motion(hand: BaseMotion) -> bool:
    # ``flat`` (rotation, acceleration, angular velocity and acceleration) is what the kernels read anyway;
    # one sum of the three (a non-finite term makes it non-finite), without ``_all_finite``'s ravel per array
    return math.isfinite(sum(hand.flat.tolist()) + sum(hand.position.tolist()) + sum(hand.velocity.tolist()))
