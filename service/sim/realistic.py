"""The realistic error profile (``--noise realistic``): what a real glove and tracker do that the
paper's profile (``--noise both``: white noise and constant offsets only) leaves out.

Every term is drawn once per run (a trial, a subject, a glove) from the seeded generator, and each
comes from a datasheet or a published figure:

IMU, MPU-9250 Product Specification rev. 1.1 (InvenSense, 2014), sections 3.1 (gyroscope) and 3.2
(accelerometer):

* sensitivity scale factor tolerance ±3 % per axis (gyro and accelerometer, "Sensitivity Scale Factor
  Tolerance"), drawn uniformly;
* cross-axis sensitivity ±2 % (both, "Cross-Axis Sensitivity"), each off-diagonal term uniform;
* total RMS noise 0.1 deg/s-rms (gyro, DLPF 92 Hz) and 8 mg-rms (accelerometer, DLPF 94 Hz) as the
  per-sample white noise ("Total RMS Noise"; 2.7x the accelerometer's PSD-derived figure);
* initial offsets ±5 deg/s and ±60/60/80 mg (as in the paper's profile);
* offset drift with temperature: ZRO variation ±30 deg/s over -40..85 °C (±0.24 deg/s/K) and zero-g
  change ±1.5 mg/K; a glove warming on the hand at up to ``warming_k_s`` (an assumed 2 K/min, the
  first minutes after putting it on) makes a linear drift of up to ±0.008 deg/s per second and
  ±0.05 mg per second;
* full-scale ranges ±2000 deg/s and ±16 g (the largest settings, "Full-Scale Range"): readings clip;
* 16-bit ADC: 16.4 LSB/(deg/s) and 2048 LSB/g at those ranges ("Sensitivity Scale Factor"):
  readings are rounded to whole LSBs.

Placement and body:

* mounting misalignment: each sensor sits on its phalanx rotated by up to ``mounting_bound_rad``
  (5 deg) about a random axis, unknown to the estimator. Hand-placed IMUs on segments show errors of
  this size before a functional calibration (Picerno, 2017, Gait & Posture 51: 239-246, review of
  sensor-to-segment alignment);
* soft-tissue motion: the sensor wobbles on the skin about the hinge axis as a damped second-order
  system driven by the bone's angular acceleration, ``δ̈ + 2ζω_n δ̇ + ω_n² δ = -θ̈``, natural frequency
  15-30 Hz and damping ratio 0.2-0.5 (skin-mounted inertial sensors resonate at tens of Hz, more
  damped when strapped tighter: Forner-Cordero et al., 2008, Physiol. Meas. 29: N21-N31). A 200 rad/s²
  flexion (a fast grasp) deflects the sensor by about ``200/ω_n²`` rad, 0.3-1.3 deg;
* hand geometry: every phalanx length differs from the calibrated one by up to ±10 % (the 5th to
  95th percentile of adult male hand length spans about ±8 % around the mean: ANSUR, Gordon et al., 1989,
  Natick TR-89/044); the calibration the glove sends still carries the nominal lengths;
* DIP/PIP coupling: ``φ_DIP = c φ_PIP`` with ``c`` uniform in ``coupling_range`` (Rijpkema and
  Girard, 1991, Comput. Graph. 25(4): 339-348, use ``c ≈ 2/3`` from measured grasps; the range
  0.5-1.0 is wider, for person-to-person variation); the calibration still says the estimators' value. The default placement cannot
  observe the coupling, so benchmarks report its effect separately (``coupling_range=None`` keeps the
  calibrated value).

Optical tracker: latency uniform in ``latency_range_s`` (10-40 ms: one to three frames of a 90 Hz
camera tracker plus transport), white jitter of 0.5-2 mm and 0.1-0.5 deg per pose (the
frame-to-frame precision of marker-based and headset tracking is millimetres, far below the
centimetre-level bias of headset hand tracking: Abdlkarim et al., 2024, Behav. Res. Methods 56:
1052-1063). Occlusions are scheduled by the caller (``OpticalModel.occlusions_s``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..model.frames import GRAVITY_M_S2, matrix_to_quat
from ..model.hand import FingerGeometry, HandCalibration
from ..model.units import DEG, MG
from .errors import OpticalModel


@dataclass(frozen=True)
class RealisticProfile:
    """Bounds of the realistic error terms (module docstring); every draw is uniform inside them.

    Attributes (SI units):
        scale_bound: per-axis sensitivity error bound, fraction (MPU-9250: 0.03).
        cross_axis_bound: cross-axis sensitivity bound, fraction (MPU-9250: 0.02).
        gyro_noise_rms_rad_s: per-sample gyro white noise, rad/s (0.1 deg/s-rms).
        acc_noise_rms_m_s2: per-sample accelerometer white noise, m/s² (8 mg-rms).
        gyro_offset_bound_rad_s: initial gyro offset bound, rad/s (±5 deg/s).
        acc_offset_bound_m_s2: initial accelerometer offset bound per axis, m/s² (60, 60, 80 mg).
        gyro_drift_bound_rad_s2: gyro offset drift-rate bound, rad/s per s (0.24 deg/s/K x warming).
        acc_drift_bound_m_s3: accelerometer offset drift-rate bound, m/s² per s (1.5 mg/K x warming).
        gyro_range_rad_s: gyro full scale, rad/s (±2000 deg/s).
        acc_range_m_s2: accelerometer full scale, m/s² (±16 g).
        gyro_lsb_rad_s: gyro quantisation step, rad/s (1/16.4 deg/s).
        acc_lsb_m_s2: accelerometer quantisation step, m/s² (1/2048 g).
        mounting_bound_rad: largest mounting misalignment angle, rad (5 deg).
        tissue_hz: range of the soft-tissue natural frequency, Hz (15-30).
        tissue_damping: range of the soft-tissue damping ratio (0.2-0.5).
        length_bound: phalanx length error bound, fraction (0.10).
        coupling_range: range of the true DIP/PIP coupling; None keeps the calibrated value.
        latency_range_s: optical latency range, s.
        position_jitter_range_m: optical position jitter range (std per axis), m.
        orientation_jitter_range_rad: optical orientation jitter range (std per axis), rad.
    """

    scale_bound: float = 0.03
    cross_axis_bound: float = 0.02
    gyro_noise_rms_rad_s: float = 0.1 * DEG
    acc_noise_rms_m_s2: float = 8.0 * MG
    gyro_offset_bound_rad_s: float = 5.0 * DEG
    acc_offset_bound_m_s2: tuple[float, float, float] = (60 * MG, 60 * MG, 80 * MG)
    warming_k_s: float = 2.0 / 60.0
    gyro_drift_per_kelvin_rad_s: float = 30.0 * DEG / 125.0
    acc_drift_per_kelvin_m_s2: float = 1.5 * MG
    gyro_range_rad_s: float = 2000.0 * DEG
    acc_range_m_s2: float = 16.0 * GRAVITY_M_S2
    gyro_lsb_rad_s: float = DEG / 16.4
    acc_lsb_m_s2: float = GRAVITY_M_S2 / 2048.0
    mounting_bound_rad: float = 5.0 * DEG
    tissue_hz: tuple[float, float] = (15.0, 30.0)
    tissue_damping: tuple[float, float] = (0.2, 0.5)
    length_bound: float = 0.10
    coupling_range: tuple[float, float] | None = (0.5, 1.0)
    latency_range_s: tuple[float, float] = (0.01, 0.04)
    position_jitter_range_m: tuple[float, float] = (0.0005, 0.002)
    orientation_jitter_range_rad: tuple[float, float] = (0.1 * DEG, 0.5 * DEG)

    @property
    def gyro_drift_bound_rad_s2(self) -> float:
        return self.gyro_drift_per_kelvin_rad_s * self.warming_k_s

    @property
    def acc_drift_bound_m_s3(self) -> float:
        return self.acc_drift_per_kelvin_m_s2 * self.warming_k_s


@dataclass(frozen=True)
class SensorDraw:
    """One sensor's drawn errors: ``gyr_matrix``/``acc_matrix`` (3,3) scale and cross-axis
    (``reading = M · true``); offsets (3,) and drift rates (3,) in SI units; soft-tissue natural
    frequency (Hz) and damping ratio."""

    gyr_matrix: np.ndarray
    acc_matrix: np.ndarray
    gyr_offset: np.ndarray
    acc_offset: np.ndarray
    gyr_drift: np.ndarray
    acc_drift: np.ndarray
    tissue_hz: float
    tissue_damping: float


@dataclass(frozen=True)
class SubjectDraw:
    """The per-run draws: the true hand geometry (lengths, mountings, coupling) and each sensor's errors."""

    true_calibration: HandCalibration
    coupling: float
    sensors: dict[str, SensorDraw]
    optical: OpticalModel


def _sensitivity_matrix(rng: np.random.Generator, scale: float, cross: float) -> np.ndarray:
    m = rng.uniform(-cross, cross, (3, 3))
    np.fill_diagonal(m, 1.0 + rng.uniform(-scale, scale, 3))
    return m


def _misaligned(rng: np.random.Generator, bound_rad: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * rng.uniform(0.0, bound_rad)).as_matrix()


def draw_sensor(rng: np.random.Generator, p: RealisticProfile) -> SensorDraw:
    """One IMU's errors (the order of draws is fixed)."""
    return SensorDraw(
        gyr_matrix=_sensitivity_matrix(rng, p.scale_bound, p.cross_axis_bound),
        acc_matrix=_sensitivity_matrix(rng, p.scale_bound, p.cross_axis_bound),
        gyr_offset=rng.uniform(-1.0, 1.0, 3) * p.gyro_offset_bound_rad_s,
        acc_offset=rng.uniform(-1.0, 1.0, 3) * np.asarray(p.acc_offset_bound_m_s2),
        gyr_drift=rng.uniform(-1.0, 1.0, 3) * p.gyro_drift_bound_rad_s2,
        acc_drift=rng.uniform(-1.0, 1.0, 3) * p.acc_drift_bound_m_s3,
        tissue_hz=float(rng.uniform(*p.tissue_hz)),
        tissue_damping=float(rng.uniform(*p.tissue_damping)),
    )


def misaligned(rng: np.random.Generator, bound_rad: float) -> np.ndarray:
    """A rotation by up to ``bound_rad`` about a random axis (a sensor's mounting misalignment)."""
    return _misaligned(rng, bound_rad)


def draw_subject(rng: np.random.Generator, profile: RealisticProfile, nominal: HandCalibration,
                 optical: OpticalModel) -> SubjectDraw:
    """Draw every realistic term for one run (the order of draws is fixed: reproducible per seed).
    ``optical`` gives the rate and occlusions; latency and jitter are drawn."""
    p = profile
    coupling = nominal.finger("index").coupling if p.coupling_range is None else float(rng.uniform(*p.coupling_range))
    fingers: dict[str, FingerGeometry] = {}
    sensors: dict[str, SensorDraw] = {}
    for name, geom in nominal.fingers.items():
        scale = 1.0 + rng.uniform(-p.length_bound, p.length_bound, geom.n_phalanges)
        lengths = tuple(float(v) for v in np.asarray(geom.lengths_m) * scale)
        placed = []
        for s in geom.sensors:
            mount = _misaligned(rng, p.mounting_bound_rad) @ s.mounting_matrix()
            offset = min(s.offset_m * scale[s.phalanx], lengths[s.phalanx])
            placed.append(replace(s, offset_m=float(offset), mounting=tuple(float(v) for v in matrix_to_quat(mount))))
            sensors[s.id] = draw_sensor(rng, p)
        fingers[name] = replace(geom, lengths_m=lengths, coupling=coupling if geom.n_phalanges == 3 else geom.coupling,
                                sensors=tuple(placed))
    optical = replace(optical,
                      latency_s=float(rng.uniform(*p.latency_range_s)),
                      position_jitter_m=float(rng.uniform(*p.position_jitter_range_m)),
                      orientation_jitter_rad=float(rng.uniform(*p.orientation_jitter_range_rad)))
    return SubjectDraw(replace(nominal, fingers=fingers), coupling, sensors, optical)


def soft_tissue(t: np.ndarray, ddtheta: np.ndarray, natural_hz: float, damping: float) -> tuple[np.ndarray, ...]:
    """Deflection ``δ`` of a skin-mounted sensor about the hinge axis and its two derivatives, (N,) each:
    ``δ̈ + 2ζω_n δ̇ + ω_n² δ = -θ̈`` from rest (module docstring), integrated exactly for an input that is
    linear between samples (``scipy.signal.lsim``)."""
    from scipy import signal          # here: importing it takes 1-2 s, at every start of whatever imports the simulator

    wn = 2.0 * np.pi * natural_hz
    a = np.array([[0.0, 1.0], [-wn * wn, -2.0 * damping * wn]])
    b = np.array([[0.0], [-1.0]])
    sys = signal.StateSpace(a, b, np.eye(2), np.zeros((2, 1)))
    _, _, x = signal.lsim(sys, ddtheta, t - t[0], interp=True)
    delta, ddelta = x[:, 0], x[:, 1]
    dddelta = -ddtheta - 2.0 * damping * wn * ddelta - wn * wn * delta
    return delta, ddelta, dddelta


def measure(rng: np.random.Generator, profile: RealisticProfile, draw: SensorDraw, t_rel: np.ndarray,
            gyr_true: np.ndarray, acc_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One sensor's readings (N,3) from its true rate and specific force (N,3): sensitivity and
    cross-axis, drifting offsets, white noise, clipping at full scale, rounding to the LSB."""
    p = profile
    gyr = gyr_true @ draw.gyr_matrix.T + draw.gyr_offset + t_rel[:, None] * draw.gyr_drift
    acc = acc_true @ draw.acc_matrix.T + draw.acc_offset + t_rel[:, None] * draw.acc_drift
    gyr = gyr + rng.normal(0.0, p.gyro_noise_rms_rad_s, gyr.shape)
    acc = acc + rng.normal(0.0, p.acc_noise_rms_m_s2, acc.shape)
    gyr = np.round(np.clip(gyr, -p.gyro_range_rad_s, p.gyro_range_rad_s) / p.gyro_lsb_rad_s) * p.gyro_lsb_rad_s
    acc = np.round(np.clip(acc, -p.acc_range_m_s2, p.acc_range_m_s2) / p.acc_lsb_m_s2) * p.acc_lsb_m_s2
    return gyr, acc


def saturated(gyr: np.ndarray, acc: np.ndarray, profile: RealisticProfile = RealisticProfile()) -> np.ndarray:
    """True where a reading sits at full scale on any axis (a clipped sample), shape ``gyr.shape[:-1]``."""
    g = np.any(np.abs(gyr) >= profile.gyro_range_rad_s - 0.5 * profile.gyro_lsb_rad_s, axis=-1)
    a = np.any(np.abs(acc) >= profile.acc_range_m_s2 - 0.5 * profile.acc_lsb_m_s2, axis=-1)
    return g | a


