"""Simulated glove + optical tracker sessions with known truth, and their protocol-v1 recordings.

``simulate(config)`` returns arrays (for benchmarks and tests) and ``session.messages()`` the same
data as protocol-v1 messages in arrival order (``hello``, ``calibration``, then ``pose``, ``imu``
and ``truth`` interleaved by arrival time), which ``write_recording`` stores as JSON Lines. A
seeded run is reproducible bit for bit: one ``numpy.random.Generator`` is consumed in a fixed order
(zero offsets, IMU white noise, optical jitter) and floats are written with ``repr`` precision.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from ..model.frames import DEFAULT_GRAVITY_WORLD, matrix_to_quat
from ..model.hand import METACARPUS_SENSOR_ID, HandCalibration, MetacarpusImu, calibration_message, default_calibration, \
    joint_to_phalanx_angles
from ..model.kinematics import BaseMotion, ideal_imu, metacarpus_imu
from ..protocol.messages import PROTOCOL_VERSION
from .errors import ImuErrorModel, OpticalModel
from .realistic import RealisticProfile, SubjectDraw, draw_sensor, draw_subject, measure, misaligned, soft_tissue
from .reference import with_reference_hold
from .motions import FingerMotion, HandTrajectory, make_finger_motion, make_hand_motion



@dataclass(frozen=True)
class SimConfig:
    """What to simulate.

    Attributes:
        motion: finger motion name (``motions.FINGER_MOTIONS``).
        t_m_s: movement duration, s (None: the motion's default).
        hand: ``right`` or ``left``.
        hand_motion: metacarpus trajectory name (``motions.HAND_MOTIONS``).
        noise: IMU errors, ``none``/``white``/``offset``/``both`` (the paper's series) or ``realistic``
            (``realistic.py``: per-run draws of every datasheet and body error; the optical latency and
            jitter are drawn too, the optical rate and occlusions come from ``optical``).
        profile: bounds of the realistic draws (None: ``RealisticProfile()``).
        reference_hold_s: > 0: the hand is held flat this long first and the recording announces it
            with a ``reference_pose`` message (``reference.py``), s.
        seed: seed of every random draw.
        rate_hz: IMU sample rate, Hz.
        optical: optical tracker model; None: perfect when ``noise == 'none'``, else the default model.
        calibration: hand geometry; None: ``default_calibration(hand)``.
        gravity_world: gravity vector in the world frame, m/s².
        t0_s: source clock at the first sample, s.
        fingers: simulate only these fingers' sensors (None: all).
        duration_s: length of the run, s (None: the motion's duration; longer runs hold the last pose).
        metacarpus_imu: the glove also has an IMU on the back of the hand (sensor id ``metacarpus``,
            ``MetacarpusImu()`` placement, the same error profile; its errors are drawn from a
            generator of their own, so every other draw is the same with or without it).
    """

    motion: str = "grasp"
    t_m_s: float | None = None
    hand: str = "right"
    hand_motion: str = "still"
    noise: str = "both"
    seed: int = 0
    rate_hz: float = 200.0
    optical: OpticalModel | None = None
    calibration: HandCalibration | None = None
    gravity_world: tuple[float, float, float] = tuple(DEFAULT_GRAVITY_WORLD)  # type: ignore[assignment]
    t0_s: float = 0.0
    fingers: tuple[str, ...] | None = None
    duration_s: float | None = None
    profile: RealisticProfile | None = None
    reference_hold_s: float = 0.0
    finger_motion: FingerMotion | None = field(default=None, compare=False)
    hand_trajectory: HandTrajectory | None = field(default=None, compare=False)
    metacarpus_imu: bool = False


@dataclass
class SimulatedSession:
    """Everything a run produced. Arrays are indexed by IMU sample ``n`` and sensor ``s``.

    ``t`` (N,) s; ``sensor_ids`` (S,); ``gyr``/``acc`` (N,S,3) measured readings (rad/s, m/s²);
    ``gyr_ideal``/``acc_ideal`` the same without errors; ``gyr_offset``/``acc_offset`` (S,3) the
    drawn zero offsets; ``joint_angles``/``joint_rates`` per finger (N, n_joints) rad, rad/s;
    ``base`` the true metacarpus kinematics at IMU times; ``pose_t`` (M,), ``pose_position`` (M,3),
    ``pose_orientation`` (M,4) ``[x,y,z,w]`` and ``pose_valid`` (M,) the optical stream as measured.
    """

    config: SimConfig
    calibration: HandCalibration
    t: np.ndarray
    sensor_ids: list[str]
    gyr: np.ndarray
    acc: np.ndarray
    gyr_ideal: np.ndarray
    acc_ideal: np.ndarray
    gyr_offset: np.ndarray
    acc_offset: np.ndarray
    joint_angles: dict[str, np.ndarray]
    joint_rates: dict[str, np.ndarray]
    base: BaseMotion
    pose_t: np.ndarray
    pose_position: np.ndarray
    pose_orientation: np.ndarray
    pose_valid: np.ndarray
    optical: OpticalModel
    subject: SubjectDraw | None = None
    """The realistic profile's draws (true geometry, coupling, sensor errors); None for the paper's series."""
    metacarpus_gyr: np.ndarray | None = None
    """(N,3) readings of the IMU on the back of the hand (``SimConfig.metacarpus_imu``), rad/s; else None."""
    metacarpus_acc: np.ndarray | None = None
    """(N,3) its accelerometer readings, m/s²."""

    @property
    def true_calibration(self) -> HandCalibration:
        """The geometry the readings were made with (``calibration`` is what the glove sends)."""
        return self.calibration if self.subject is None else self.subject.true_calibration

    def phalanx_angles(self, finger: str) -> np.ndarray:
        """True phalanx angles ``θ`` of ``finger`` relative to the metacarpus, (N, n) rad."""
        return joint_to_phalanx_angles(self.joint_angles[finger])

    def sensor_index(self, sensor_id: str) -> int:
        return self.sensor_ids.index(sensor_id)

    def messages(self, include_truth: bool = True) -> Iterator[dict]:
        """Protocol-v1 messages in arrival order (poses arrive ``latency_s`` after their ``t``)."""
        yield {"type": "hello", "protocol": PROTOCOL_VERSION, "hand": self.calibration.hand,
               "source": f"fingertrack-sim motion={self.config.motion} noise={self.config.noise} seed={self.config.seed}"}
        calibration = calibration_message(self.calibration)
        if self.metacarpus_gyr is not None:
            placement = MetacarpusImu()
            calibration["metacarpus"] = {"position": list(placement.position_m), "mounting": list(placement.mounting)}
        yield calibration
        t_pose_arrival = self.pose_t + self.optical.latency_s
        truth_q = matrix_to_quat(self.base.rotation) if include_truth else None
        i_pose, n_pose = 0, len(self.pose_t)
        hold_end = float(self.t[0] + self.config.reference_hold_s) if self.config.reference_hold_s > 0 else None
        for n, t in enumerate(self.t):
            while i_pose < n_pose and t_pose_arrival[i_pose] <= t:
                yield self._pose_message(i_pose)
                i_pose += 1
            tf = float(t)
            for s, sid in enumerate(self.sensor_ids):
                yield {"type": "imu", "t": tf, "id": sid, "gyr": self.gyr[n, s].tolist(), "acc": self.acc[n, s].tolist()}
            if self.metacarpus_gyr is not None:
                yield {"type": "imu", "t": tf, "id": METACARPUS_SENSOR_ID, "gyr": self.metacarpus_gyr[n].tolist(),
                       "acc": self.metacarpus_acc[n].tolist()}
            if hold_end is not None and tf >= hold_end:
                yield {"type": "reference_pose", "t0": float(self.t[0]), "t1": hold_end, "pose": "flat"}
                hold_end = None
            if include_truth:
                yield {
                    "type": "truth", "t": tf,
                    "fingers": {f: dict(zip(self.calibration.finger(f).joint_names, a[n].tolist()))
                                for f, a in self.joint_angles.items()},
                    "position": self.base.position[n].tolist(),
                    "orientation": truth_q[n].tolist(),  # type: ignore[index]
                }
        while i_pose < n_pose:
            yield self._pose_message(i_pose)
            i_pose += 1

    def _pose_message(self, i: int) -> dict:
        if not self.pose_valid[i]:
            return {"type": "pose", "t": float(self.pose_t[i]), "valid": False}
        return {"type": "pose", "t": float(self.pose_t[i]), "position": self.pose_position[i].tolist(),
                "orientation": self.pose_orientation[i].tolist(), "valid": True}


def simulate(config: SimConfig) -> SimulatedSession:
    """Run the finger model and sensor error models (module docstring)."""
    if not np.isfinite(config.rate_hz) or config.rate_hz <= 0:
        raise ValueError(f"IMU rate must be a positive number of Hz, got {config.rate_hz}")
    calib = config.calibration or default_calibration(config.hand)  # type: ignore[arg-type]
    realistic = config.noise == "realistic"
    optical = config.optical or (OpticalModel.perfect() if config.noise == "none" else OpticalModel())
    rng = np.random.default_rng(config.seed)
    subject = None
    if realistic:
        profile = config.profile or RealisticProfile()
        subject = draw_subject(rng, profile, calib, optical)
        optical = subject.optical
        coupling = subject.coupling
    else:
        errors = ImuErrorModel.named(config.noise)
        coupling = calib.finger("index").coupling
    motion = config.finger_motion or make_finger_motion(config.motion, config.t_m_s, seed=config.seed, coupling=coupling)
    if config.reference_hold_s > 0:
        motion = with_reference_hold(motion, config.reference_hold_s, np.random.default_rng([config.seed, 2]), coupling)
    hand_traj = config.hand_trajectory or make_hand_motion(config.hand_motion, seed=config.seed)
    gravity = np.asarray(config.gravity_world, dtype=float)

    duration = motion.duration_s if config.duration_s is None else config.duration_s
    n = int(np.floor(duration * config.rate_hz + 1e-9)) + 1
    t_rel = np.arange(n) / config.rate_hz
    base = hand_traj.base_motion(t_rel)

    true_calib = calib if subject is None else subject.true_calibration
    sensor_ids, gyr_i, acc_i = [], [], []
    angles, rates = {}, {}
    for fname, geom in true_calib.fingers.items():
        if config.fingers is not None and fname not in config.fingers:
            continue
        phi, dphi, ddphi = motion.joint_angles(fname, t_rel)
        angles[fname], rates[fname] = phi, dphi
        theta, dtheta, ddtheta = (joint_to_phalanx_angles(x) for x in (phi, dphi, ddphi))
        for sensor in geom.sensors:
            th, dth, ddth = theta, dtheta, ddtheta
            if subject is not None:             # the sensor wobbles on the skin about the hinge axis
                d = subject.sensors[sensor.id]
                wobble = soft_tissue(t_rel, ddtheta[:, sensor.phalanx], d.tissue_hz, d.tissue_damping)
                th, dth, ddth = (x.copy() for x in (theta, dtheta, ddtheta))
                for x, w in zip((th, dth, ddth), wobble):
                    x[:, sensor.phalanx] += w
            r = ideal_imu(geom, sensor, base, th, dth, ddth, gravity)
            sensor_ids.append(sensor.id)
            gyr_i.append(r.gyr)
            acc_i.append(r.acc)
    gyr_ideal = np.stack(gyr_i, axis=1)
    acc_ideal = np.stack(acc_i, axis=1)
    if subject is None:
        offsets = errors.draw_offsets(rng, len(sensor_ids))
        gyr, acc = errors.corrupt(rng, gyr_ideal, acc_ideal, config.rate_hz, offsets)
    else:
        measured = [measure(rng, profile, subject.sensors[sid], t_rel, gyr_ideal[:, k], acc_ideal[:, k])
                    for k, sid in enumerate(sensor_ids)]
        gyr = np.stack([g for g, _ in measured], axis=1)
        acc = np.stack([a for _, a in measured], axis=1)
        offsets = (np.array([subject.sensors[s].gyr_offset for s in sensor_ids]).reshape(-1, 3),
                   np.array([subject.sensors[s].acc_offset for s in sensor_ids]).reshape(-1, 3))

    hand_gyr, hand_acc = (_metacarpus_readings(config, base, gravity, t_rel, errors if subject is None else None)
                          if config.metacarpus_imu else (None, None))

    m = int(np.floor(duration * optical.rate_hz + 1e-9)) + 1
    pose_t_rel = np.arange(m) / optical.rate_hz
    pose_base = hand_traj.base_motion(pose_t_rel)
    pos = pose_base.position + rng.normal(0.0, 1.0, (m, 3)) * optical.position_jitter_m
    rot = Rotation.from_rotvec(rng.normal(0.0, 1.0, (m, 3)) * optical.orientation_jitter_rad) * Rotation.from_matrix(pose_base.rotation)
    quat = rot.as_quat(canonical=True)

    return SimulatedSession(
        config=config, calibration=calib, t=config.t0_s + t_rel, sensor_ids=sensor_ids, gyr=gyr, acc=acc,
        gyr_ideal=gyr_ideal, acc_ideal=acc_ideal, gyr_offset=offsets[0], acc_offset=offsets[1],
        joint_angles=angles, joint_rates=rates, base=base,
        pose_t=config.t0_s + pose_t_rel, pose_position=pos, pose_orientation=quat,
        pose_valid=optical.valid_mask(pose_t_rel), optical=optical, subject=subject,
        metacarpus_gyr=hand_gyr, metacarpus_acc=hand_acc,
    )


def _metacarpus_readings(config: SimConfig, base: BaseMotion, gravity: np.ndarray, t_rel: np.ndarray,
                         errors: ImuErrorModel | None) -> tuple[np.ndarray, np.ndarray]:
    """The back-of-hand IMU's readings (N,3) each, from a generator of its own: ``errors`` for the
    paper's series, else (None) the realistic profile with its own mounting misalignment."""
    rng = np.random.default_rng([config.seed, 7])
    nominal = MetacarpusImu()
    if errors is not None:
        ideal = metacarpus_imu(nominal, base, gravity)
        offsets = errors.draw_offsets(rng, 1)
        gyr, acc = errors.corrupt(rng, ideal.gyr[:, None], ideal.acc[:, None], config.rate_hz, offsets)
        return gyr[:, 0], acc[:, 0]
    profile = config.profile or RealisticProfile()
    mount = misaligned(rng, profile.mounting_bound_rad) @ nominal.mounting_matrix()
    true = MetacarpusImu(nominal.position_m, tuple(float(v) for v in matrix_to_quat(mount)))
    ideal = metacarpus_imu(true, base, gravity)
    return measure(rng, profile, draw_sensor(rng, profile), t_rel, ideal.gyr, ideal.acc)


def write_recording(session: SimulatedSession, path: str | Path, include_truth: bool = True) -> int:
    """Write the session as a JSON Lines recording; returns the number of messages written."""
    count = 0
    with open(path, "w", encoding="utf-8") as fh:
        for msg in session.messages(include_truth=include_truth):
            fh.write(json.dumps(msg, separators=(",", ":"), allow_nan=False))
            fh.write("\n")
            count += 1
    return count
