"""The inertial-frame core: our orientation filter for one rigid IMU (gyro + accelerometer, optional
second reference vector), with online gyro bias *and scale-factor* estimation.

Structure (the 6D part of VQF, Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation
with bias estimation and magnetic disturbance rejection", Information Fusion 91; step numbers
below are this docstring's, cited in the code):

1. Strapdown integration of the corrected rate into ``q_g`` (sensor -> an almost-inertial frame I),
   (step 1).
2. The accelerometer rotated into I and low-passed there (second-order Butterworth, time constant
   ``tau_acc``): external accelerations average out in an inertial frame, gravity does
   not.
3. The filtered vector rotated into the world frame by the correction ``q_c``; ``q_c`` is updated by
   the smallest rotation that aligns it with "up" in full. Output ``q = q_c ⊗ q_g``.
4. The gyro errors estimated by a Kalman filter whose measurement is the inclination correction
   rate, low-passed with the same filter (4a), and, during detected rests, the low-passed gyro
   itself (4b).

What is ours: VQF estimates a gyro *bias*; we estimate the bias and a per-axis *scale-factor* error
``s`` with one 6-state Kalman filter. The gyro is modelled as ``g = (1 + s) ∘ ω + b``, so the
world-frame rate error is ``R (b + diag(ω) s)`` and the measurement matrix of step 4a grows from
``LP(R)`` to ``H = [LP(R), LP(R diag(g))]`` (both low-passed like the measurement, so they stay
consistent). Scale errors of a few tenths of a percent are what MEMS gyros have after factory
calibration (the MPU-9250 data sheet allows ±3 %), and at the 1000 °/s of a fast hand rotation 0.3 %
is 3 °/s of drift, more than the bias clip: on the fast-rotation BROAD trials this is most of the
remaining error (``fingertrack bench peers``). The prior ``scale_sigma_init`` is the data sheet's 3 %,
not a fitted value. During rests ``s`` is unobservable (``ω ≈ 0``) and only the bias is measured.

Second reference (``ref_world`` known in the world frame, ``ref_sensor`` its sensor-frame
counterpart; on a finger, the flexion-plane normal from the optical pose): a heading correction
about the vertical with time constant ``tau_ref``, used only where both horizontal projections are
longer than ``ref_min_horizontal`` (a near-vertical reference carries no heading).

The compiled kernel is ``inertial_kernel``; :func:`reference_step` below is the same method written
with numpy matrices, kept for the tests (the two agree to 1e-9).
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ...model.quaternion import multiply, normalize, tilt_from_accelerometer, to_matrix
from ...model.units import DEG
from . import inertial_kernel as K


class InertialSettings(BaseModel):
    """Parameters of the inertial-frame core. Defaults: VQF's published defaults for the shared
    parts; the scale-factor prior from the MPU-9250 data sheet."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    tau_acc_s: float = Field(3.0, gt=0.0, description="accelerometer low-pass time constant in frame I")
    bias_sigma_init_deg_s: float = Field(0.5, gt=0.0, description="prior std of the gyro bias")
    bias_forgetting_s: float = Field(100.0, gt=0.0, description="time for the bias std to grow by 0.1 °/s")
    bias_clip_deg_s: float = Field(2.0, gt=0.0, description="bias estimate and disagreement clip")
    bias_sigma_motion_deg_s: float = Field(0.1, gt=0.0, description="bias measurement std in motion")
    vertical_forgetting_factor: float = Field(1e-4, gt=0.0, description="weight of the vertical bias axis in motion")
    bias_sigma_rest_deg_s: float = Field(0.03, gt=0.0, description="bias measurement std at rest")
    scale_sigma_init: float = Field(0.03, ge=0.0, description="prior std of the scale-factor error (0 disables it)")
    scale_sigma_steady: float = Field(0.001, ge=0.0, description="scale std regained per scale_forgetting_s")
    scale_forgetting_s: float = Field(100.0, gt=0.0, description="time for the scale std to grow by scale_sigma_steady")
    scale_clip: float = Field(0.1, gt=0.0, description="scale-factor estimate clip")
    rest_min_s: float = Field(1.5, gt=0.0, description="stillness needed before a rest is detected")
    rest_filter_tau_s: float = Field(0.5, gt=0.0, description="rest detection low-pass time constant")
    rest_threshold_gyr_deg_s: float = Field(2.0, gt=0.0, description="gyro deviation allowed at rest")
    rest_threshold_acc_m_s2: float = Field(0.5, gt=0.0, description="accelerometer deviation allowed at rest")
    tau_ref_s: float = Field(1.0, gt=0.0, description="heading correction time constant of the second reference")
    ref_min_horizontal: float = Field(0.2, ge=0.0, lt=1.0, description="least horizontal fraction of a usable reference")


def butterworth(tau: float, dt: float) -> tuple[float, float, float, float, float]:
    """(b0, b1, b2, a1, a2) of the second-order Butterworth low-pass with cutoff ``√2 / (2π τ)``
    (VQF's parametrisation), from ``scipy.signal.butter`` (bilinear transform, prewarped)."""
    from scipy.signal import butter
    fc = math.sqrt(2.0) / (2.0 * math.pi * tau)
    if fc >= 0.45 / dt:
        return 1.0, 0.0, 0.0, 0.0, 0.0       # cutoff beyond 90 % of Nyquist: pass through
    b, a = butter(2, fc, fs=1.0 / dt)
    return float(b[0]), float(b[1]), float(b[2]), float(a[1]), float(a[2])


def coefficients(settings: InertialSettings, dt: float) -> np.ndarray:
    """The kernel's coefficient vector for one sampling interval ``dt`` (s)."""
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"sampling interval must be a positive number of seconds, got {dt!r}")
    s = settings
    c = np.zeros(K.C_SIZE)
    c[K.C_DT] = dt
    c[K.C_AB0:K.C_AA2 + 1] = butterworth(s.tau_acc_s, dt)
    c[K.C_TAU_ACC] = s.tau_acc_s
    c[K.C_RB0:K.C_RA2 + 1] = butterworth(s.rest_filter_tau_s, dt)
    c[K.C_TAU_REST] = s.rest_filter_tau_s
    # step 4 covariance bookkeeping: the variance regains (0.1 °/s)² in bias_forgetting_s, and the
    # measurement variances are chosen so that the steady-state std is the given sigma (VQF's choice)
    c[K.C_P0_BIAS] = (s.bias_sigma_init_deg_s * DEG) ** 2
    v = (0.1 * DEG) ** 2 * dt / s.bias_forgetting_s
    c[K.C_V_BIAS] = v
    c[K.C_P0_SCALE] = s.scale_sigma_init ** 2
    c[K.C_V_SCALE] = s.scale_sigma_steady ** 2 * dt / s.scale_forgetting_s if s.scale_sigma_init > 0 else 0.0
    pm = (s.bias_sigma_motion_deg_s * DEG) ** 2
    c[K.C_W_MOTION] = pm * pm / v + pm
    c[K.C_W_VERTICAL] = c[K.C_W_MOTION] / s.vertical_forgetting_factor
    pr = (s.bias_sigma_rest_deg_s * DEG) ** 2
    c[K.C_W_REST] = pr * pr / v + pr
    c[K.C_CLIP_BIAS] = s.bias_clip_deg_s * DEG
    c[K.C_CLIP_SCALE] = s.scale_clip
    c[K.C_REST_MIN_T] = s.rest_min_s
    c[K.C_REST_TH_GYR] = s.rest_threshold_gyr_deg_s * DEG
    c[K.C_REST_TH_ACC] = s.rest_threshold_acc_m_s2
    c[K.C_K_REF] = 1.0 - math.exp(-dt / s.tau_ref_s)
    c[K.C_REF_MIN] = s.ref_min_horizontal
    return c


def world_rotation(up) -> np.ndarray:
    """``[w,x,y,z]`` rotation taking the core's world frame (z up) into a caller's frame whose "up"
    (specific force at rest) is ``up``."""
    return tilt_from_accelerometer(np.array([0.0, 0.0, 1.0]), np.asarray(up, dtype=float))


def initial_state(settings: InertialSettings, batch: int, attitude: np.ndarray | None = None,
                  to_world: np.ndarray | None = None) -> np.ndarray:
    """(batch, STATE_SIZE): zero gyro errors with their prior covariance, low-passes in their
    start-up (averaging) phase; the strapdown quaternion is ``attitude`` ((batch, 4) ``[w,x,y,z]``
    sensor -> the caller's world, ``to_world`` from :func:`world_rotation`) or the identity."""
    st = np.zeros((batch, K.STATE_SIZE))
    st[:, K.QG] = 1.0
    st[:, K.QC] = 1.0
    if attitude is not None:
        from_world = np.asarray(to_world, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])
        st[:, K.QG:K.QG + 4] = normalize(multiply(from_world, np.asarray(attitude, dtype=float).reshape(batch, 4)))
    p0 = [(settings.bias_sigma_init_deg_s * DEG) ** 2] * 3 + [settings.scale_sigma_init ** 2] * 3
    for i in range(K.N_X):
        st[:, K.P + K.N_X * i + i] = p0[i]
    return st


def output(state: np.ndarray) -> np.ndarray:
    """(..., 4) ``[w,x,y,z]`` sensor -> world (z up) of (..., STATE_SIZE) states."""
    return multiply(state[..., K.QC:K.QC + 4], state[..., K.QG:K.QG + 4])


# ---------------------------------------------------------------------------------------------
# numpy reference: one sensor, matrix form


def _rot(q):
    return to_matrix(np.asarray(q, dtype=float))


def _lowpass_ref(s: np.ndarray, off: int, x: np.ndarray, b: np.ndarray, a: np.ndarray, tau: float, dt: float) -> np.ndarray:
    n = len(x)
    z = s[off + 1: off + 1 + 2 * n].reshape(2, n)        # a view: writes go to the state
    if not np.isnan(s[off]):
        s[off] += 1.0
        z[0] += x
        out = z[0] / s[off]
        if s[off] * dt >= tau:
            z[0], z[1] = out * (1.0 - b[0]), out * (b[2] - a[1])
            s[off] = np.nan
        return out.copy()
    y = b[0] * x + z[0]
    z[0], z[1] = b[1] * x - a[0] * y + z[1], b[2] * x - a[1] * y
    return y


def reference_step(s: np.ndarray, gyr: np.ndarray, acc: np.ndarray, c: np.ndarray,
                   ref_w: np.ndarray | None = None, ref_s: np.ndarray | None = None) -> None:
    """One sample of one sensor, state row ``s`` updated in place (numpy reference of the kernel's ``_run`` loop body)."""
    dt, clip = c[K.C_DT], c[K.C_CLIP_BIAS]
    ba, aa = c[K.C_AB0:K.C_AB2 + 1], c[K.C_AA1:K.C_AA2 + 1]
    br, ar = c[K.C_RB0:K.C_RB2 + 1], c[K.C_RA1:K.C_RA2 + 1]
    x = s[K.X:K.X + K.N_X]
    gyr, acc = np.asarray(gyr, dtype=float), np.asarray(acc, dtype=float)
    if np.all(np.isfinite(gyr)):
        glp = _lowpass_ref(s, K.LP_REST_G, gyr, br, ar, c[K.C_TAU_REST], dt)
        s[K.REST_GYR:K.REST_GYR + 3] = glp
        if np.sum((gyr - glp) ** 2) >= c[K.C_REST_TH_GYR] ** 2 or np.max(np.abs(glp)) > clip:
            s[K.REST_T] = s[K.REST] = 0.0
        w = gyr - x[:3] - gyr * x[3:]                                     # step 1 with the scale states
        wn = np.linalg.norm(w)
        if wn > 1e-15:
            dq = np.concatenate([[math.cos(0.5 * wn * dt)], math.sin(0.5 * wn * dt) * w / wn])
            q = multiply(s[K.QG:K.QG + 4], dq)
            s[K.QG:K.QG + 4] = q / np.linalg.norm(q)
    if not (np.all(np.isfinite(acc)) and np.any(acc != 0.0)):
        return
    alp = _lowpass_ref(s, K.LP_REST_A, acc, br, ar, c[K.C_TAU_REST], dt)
    if np.sum((acc - alp) ** 2) >= c[K.C_REST_TH_ACC] ** 2:
        s[K.REST_T] = s[K.REST] = 0.0
    else:
        s[K.REST_T] += dt
        if s[K.REST_T] >= c[K.C_REST_MIN_T]:
            s[K.REST] = 1.0
    acc_i = _lowpass_ref(s, K.LP_ACC, _rot(s[K.QG:K.QG + 4]) @ acc, ba, aa, c[K.C_TAU_ACC], dt)   # step 2
    s[K.ACC_I:K.ACC_I + 3] = acc_i
    e_w = _rot(s[K.QC:K.QC + 4]) @ acc_i
    e_w = e_w / np.linalg.norm(e_w)
    qw = math.sqrt(max(0.5 * (e_w[2] + 1.0), 0.0))                      # step 3
    corr = np.array([qw, 0.5 * e_w[1] / qw, -0.5 * e_w[0] / qw, 0.0]) if qw > 1e-6 else np.array([0.0, 1, 0, 0])
    qc = multiply(corr, s[K.QC:K.QC + 4])
    s[K.QC:K.QC + 4] = qc / np.linalg.norm(qc)
    if ref_w is not None and np.all(np.isfinite(ref_w)) and np.all(np.isfinite(ref_s)):
        h = _rot(output(s)) @ ref_s
        if np.hypot(h[0], h[1]) > c[K.C_REF_MIN] * np.linalg.norm(ref_s) and \
                np.hypot(ref_w[0], ref_w[1]) > c[K.C_REF_MIN] * np.linalg.norm(ref_w):
            ang = math.atan2(h[0] * ref_w[1] - h[1] * ref_w[0], h[0] * ref_w[0] + h[1] * ref_w[1])
            half = 0.5 * c[K.C_K_REF] * ang
            qc = multiply(np.array([math.cos(half), 0.0, 0.0, math.sin(half)]), s[K.QC:K.QC + 4])
            s[K.QC:K.QC + 4] = qc / np.linalg.norm(qc)
    R = _rot(output(s))
    g_h = gyr if np.all(np.isfinite(gyr)) else np.zeros(3)                # a missing gyro: no rotation
    H = np.hstack([R, R * g_h[None, :]])                                 # ours: [R, R diag(g)]
    hx = (H @ x)[:2]
    H = _lowpass_ref(s, K.LP_H, H.ravel(), ba, aa, c[K.C_TAU_ACC], dt).reshape(3, K.N_X)
    hx = _lowpass_ref(s, K.LP_HX, hx, ba, aa, c[K.C_TAU_ACC], dt)
    if s[K.REST] > 0.5:                                                  # step 4b
        H = np.hstack([np.eye(3), np.zeros((3, 3))])
        e = s[K.REST_GYR:K.REST_GYR + 3] - x[:3]
        W = np.full(3, c[K.C_W_REST])
    else:                                                                # step 4a
        e = np.array([-e_w[1] / dt + hx[0], e_w[0] / dt + hx[1], 0.0]) - H @ x
        W = np.array([c[K.C_W_MOTION], c[K.C_W_MOTION], c[K.C_W_VERTICAL]])
    Pm = s[K.P:K.P + K.N_X * K.N_X].reshape(K.N_X, K.N_X)               # a view
    p0 = np.array([c[K.C_P0_BIAS]] * 3 + [c[K.C_P0_SCALE]] * 3)
    v = np.array([c[K.C_V_BIAS]] * 3 + [c[K.C_V_SCALE]] * 3)
    d = np.arange(K.N_X)
    Pm[d, d] += np.where(Pm[d, d] < p0, v, 0.0)
    e = np.clip(e, -clip, clip)
    Kg = Pm @ H.T @ np.linalg.inv(H @ Pm @ H.T + np.diag(W))            # Kalman gain and update
    x += Kg @ e
    Pm -= Kg @ H @ Pm
    x[:3] = np.clip(x[:3], -clip, clip)
    x[3:] = np.clip(x[3:], -c[K.C_CLIP_SCALE], c[K.C_CLIP_SCALE])
