"""Whole recordings as arrays, for the ``estimate`` command and benchmarks: offline, so the hand's
motion comes from all of a recording's poses at once (``optical.hand_kinematics_acausal``), not from
the causal ``OpticalTrack`` of the live pipeline and ``replay``.

A recording (DESIGN.md) is read with the protocol models; every line must be valid. IMU samples
are grouped by timestamp: a finger's sample at time ``t`` needs all of that finger's sensors (a tick
where one is missing is dropped for that finger and counted).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..estimators.base import FingerEstimator, FingerSamples, FingerTrack
from ..model.hand import HandCalibration, default_calibration, joint_to_phalanx_angles
from ..model.kinematics import BaseMotion
from ..protocol import Calibration, Hello, ReferencePose, Truth, read_recording
from ..protocol.fast import IMU, IMU_BATCH, POSE
from .optical import hand_kinematics_acausal


@dataclass
class Recording:
    calibration: HandCalibration
    imu: dict[float, dict[str, tuple[list[float], list[float]]]] = field(default_factory=dict)
    pose_t: list[float] = field(default_factory=list)
    pose_position: list[list[float]] = field(default_factory=list)
    pose_orientation: list[list[float]] = field(default_factory=list)
    pose_valid: list[bool] = field(default_factory=list)
    truth: dict[float, dict[str, dict[str, float]]] = field(default_factory=dict)
    references: list[ReferencePose] = field(default_factory=list)

    def instrumented(self, finger: str) -> bool:
        """True if ``finger`` has sensors and at least one complete IMU sample (a partially
        instrumented glove leaves the others out: ``"sensors": []`` or no samples)."""
        ids = [s.id for s in self.calibration.finger(finger).sensors]
        return bool(ids) and any(all(i in group for i in ids) for group in self.imu.values())

    def finger_samples(self, finger: str) -> tuple[FingerSamples, int]:
        """``(samples, dropped_ticks)`` of ``finger``; hand kinematics from the optical poses."""
        ids = [s.id for s in self.calibration.finger(finger).sensors]
        times = sorted(t for t, group in self.imu.items() if all(i in group for i in ids))
        dropped = sum(1 for group in self.imu.values() if any(i in group for i in ids)) - len(times)
        if not times:
            raise ValueError(f"the recording has no complete IMU sample of finger {finger!r} (sensors {ids})")
        t = np.array(times)
        gyr = np.array([[self.imu[x][i][0] for i in ids] for x in times])
        acc = np.array([[self.imu[x][i][1] for i in ids] for x in times])
        hand = self.hand_motion(t)
        return FingerSamples(t, gyr, acc, hand), dropped

    def hand_motion(self, t: np.ndarray) -> BaseMotion:
        if not self.pose_t:
            raise ValueError("the recording has no optical pose messages; the metacarpus pose is required")
        valid = np.array(self.pose_valid)
        pos = np.array([p if v else [0.0, 0.0, 0.0] for p, v in zip(self.pose_position, valid)])
        ori = np.array([o if v else [0.0, 0.0, 0.0, 1.0] for o, v in zip(self.pose_orientation, valid)])
        return hand_kinematics_acausal(np.array(self.pose_t), pos, ori, valid, t)

    def truth_angles(self, finger: str, t: np.ndarray) -> np.ndarray | None:
        names = self.calibration.finger(finger).joint_names
        rows = [self.truth.get(float(x), {}).get(finger) for x in t]
        if any(r is None for r in rows):
            return None
        return np.array([[r[n] for n in names] for r in rows])  # type: ignore[index]


def load_recording(path: str | Path) -> Recording:
    """Read a protocol-v1 recording; raises ``ProtocolError``/``ValueError`` naming the problem."""
    hand = None
    rec: Recording | None = None
    for number, msg in read_recording(path):
        if isinstance(msg, Hello):
            hand = msg.hand
            continue
        if rec is None:
            if hand is None:
                raise ValueError(f"{path}:{number}: the recording must start with a hello message")
            rec = Recording(default_calibration(hand))
        if isinstance(msg, Calibration):
            rec.calibration = rec.calibration.with_overrides(msg.overrides())
        elif isinstance(msg, IMU):
            rec.imu.setdefault(msg.t, {})[msg.id] = (msg.gyr, msg.acc)
        elif isinstance(msg, IMU_BATCH):
            for s in msg.samples:
                rec.imu.setdefault(s.t, {})[s.id] = (s.gyr, s.acc)
        elif isinstance(msg, POSE):
            rec.pose_t.append(msg.t)
            rec.pose_valid.append(msg.valid)
            rec.pose_position.append(msg.position or [0.0, 0.0, 0.0])
            rec.pose_orientation.append(msg.orientation or [0.0, 0.0, 0.0, 1.0])
        elif isinstance(msg, ReferencePose):
            rec.references.append(msg)
        elif isinstance(msg, Truth):
            rec.truth[msg.t] = msg.fingers
    if rec is None:
        raise ValueError(f"{path}: no messages after hello")
    return rec


def run_with_references(estimator: FingerEstimator, samples: FingerSamples, finger: str,
                        references: list[ReferencePose], std_rad: float) -> FingerTrack:
    """Batch ``estimator.run`` that applies each ``reference_pose`` naming ``finger`` right after the
    last sample at or before its ``t1`` (as the live pipeline does at the first tick at or after it)."""
    t = np.asarray(samples.t, dtype=float)
    cuts = []
    for ref in sorted(references, key=lambda r: r.t1):
        angles = ref.joint_angles([finger]).get(finger)
        if angles is not None:
            cuts.append((int(np.searchsorted(t, ref.t1 - 1e-9)) + 1, angles, (ref.t0, ref.t1)))
    parts, start = [], 0
    for stop, angles, hold in cuts + [(len(t), None, None)]:
        stop = min(stop, len(t))
        if stop > start:
            parts.append(estimator.run(_slice(samples, start, stop)))
            start = stop
        if angles is not None:
            estimator.known_configuration(joint_to_phalanx_angles(np.asarray(angles, dtype=float)), std_rad, hold_s=hold)
    if not parts:
        return estimator.run(samples)
    return FingerTrack(t, *(np.concatenate([getattr(p, k) for p in parts]) for k in ("theta", "phi", "mode")))


def _slice(samples: FingerSamples, start: int, stop: int) -> FingerSamples:
    h = samples.hand
    return FingerSamples(samples.t[start:stop], samples.gyr[start:stop], samples.acc[start:stop],
                         BaseMotion(*(getattr(h, k)[start:stop] for k in (
                             "rotation", "position", "velocity", "acceleration", "angular_velocity", "angular_acceleration"))))
