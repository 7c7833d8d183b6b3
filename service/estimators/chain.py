"""``chain``: our estimator. A per-phalanx extended Kalman filter that keeps what the paper's
estimators throw away.

What it uses that the others ignore:

1. **Sensor errors as states.** Each sensor's state is ``[θ, b_g, b_ax, b_ay, b_az]``: its phalanx
   angle, the gyro zero offset about the hinge axis (the only gyro axis that matters in the planar
   model) and the full 3-axis accelerometer zero offset (in phalanx coordinates). Switching, Madgwick
   and the EKF baseline treat the accelerometer offset as noise, which leaves a constant tilt error
   of up to ``offset/g`` (about 3.5 deg for 60 mg) in every slow phase.
2. **The known starting configuration.** When the initial configuration is given (as in the paper's
   test, or after a calibration pose), its prior is tight (``initial_angle_std_rad``, 1 deg). With
   the hand pose known, the expected specific force is then known, so the first samples reveal the
   accelerometer offset (all of it along the hinge axis, the in-plane part to within the prior's
   1 deg · g), and the drift of the angle against the accelerometer reveals the gyro offset. Later
   motion through different orientations keeps both observable, so they keep improving. (A
   zero-rate detector was tried and dropped: slow motion is indistinguishable from rest over short
   windows, and its false detections corrupted the gyro offset; measured on the grasp motion.)
3. **Both IMUs of a finger jointly through the chain model.** The accelerometer is predicted with
   the full eq. 2 kinematics (tangential and centripetal terms of every phalanx between the MCP joint
   and the sensor, the unmeasured proximal phalanx from the coupling), using both sensors' angles and
   bias-corrected rates, so fast motion is modelled instead of being a disturbance. What remains
   unmodelled (the rate change is a causal difference) inflates the accelerometer noise in
   proportion to the eq. 6 bound.

4. **The accelerometer's linear errors as states** (realistic gloves: scale ±3 %, cross-axis ±2 %,
   a mounting misalignment of up to 5 deg). The accelerometer reads ``(I + G) R_x(θ)ᵀ u + b_a``
   with ``G`` (3x3, row-major in the state) its scale, cross-axis and mounting error. One direction
   of ``G`` is left out: a turn about the hinge axis (``G_zy = -G_yz``) is the same as a change of
   ``θ`` for every gravity direction (only the finger's own acceleration, weakly, tells them apart),
   so it stays with the angle, where only a known configuration can calibrate it. The other eight
   become observable as the hand turns and the finger flexes. On tuning trials disjoint from the
   scored ones (``bench accuracy --first-seed 500 --trials 3 --seconds 8``, pooled RMS over every
   scored joint sample with the reference pose) they took ``chain`` from 4.09 to 3.82 deg, but on
   more tuning trials of 12 s they did not hold up: seeds 500-503 4.52 -> 4.13 deg, 504-509 4.51 ->
   4.61, 510-519 4.12 -> 4.15 (p95 7.97 -> 7.52, 8.71 -> 9.26, 7.98 -> 8.11), a tie over the 20
   trials; in the paper's conditions they cost a little (1.61 -> 1.64 deg, ``bench paper --quick``
   'both'). So they are **off by default** (``initial_acc_scale_std = initial_acc_axis_std =
   calibration_walk_rts = 0``: the map stays the identity and the filter is the five-state one) and
   kept as settings (the kernel computes them too) to try on other gloves. Why they do not help
   here: what they could fix is small. Removing the accelerometer's scale and cross-axis errors from
   the simulation altogether takes ``chain`` only from 4.10 to 4.06 deg (seeds 500-511, reference
   pose, before items 5 and 6 and the pipeline's flexion-axis fit), 3.15 -> 3.03 after them; the
   accelerometer carries a low weight (below), so its few-percent map errors barely reach the angle,
   while eight more states per sensor, learned within seconds from that weak accelerometer, add
   their own estimation noise. The mounting's turn about the hinge axis, the one accelerometer
   error that does matter (4.10 -> 3.40 deg with it removed), is the direction ``G`` leaves out; it
   is item 5. With items 5 and 6 and the flexion-axis fit the eight states are still a tie (seeds
   500-511 3.15 -> 3.14 deg, 512-519 3.31 -> 3.47).

5. **The mounting turn about the hinge axis, from a known configuration.** A sensor turned on its
   phalanx by ``δ`` about the hinge axis (a hand-placed sensor: up to 5 deg about a random axis,
   Picerno 2017; the hinge component's std is about 1.7 deg) reads the accelerometer of ``θ + δ`` and
   the gyro of ``θ``, so ``δ`` is the direction of ``G`` that item 4 leaves out, unobservable from the
   sensor alone; with the default placement it reaches the MCP as ``2 δ_1 - δ_2``. A known
   configuration (the ``reference_pose``) observes ``θ``, and with it ``δ``: at the first one the
   filter takes ``δ`` up as a state (``G_zy = -G_yz = -δ``) with the prior ``mounting_hinge_std_rad``,
   correlated with the angle as the accelerometer has seen it (``P_θθ += σ²``, ``P_θδ = σ²``), and
   keeps it (across rebuilds too). The reference is one update for all of a finger's sensors with the
   covariance of its joint errors (two sensors share the joints below the lower one), so the
   difference of two phalanx angles is calibrated to within one joint's deviation. Without a reference
   nothing changes. On tuning trials (``bench accuracy`` seeds 500-511, 12 s, chain with the reference
   pose, mean joint RMS): 4.10 -> 3.80 deg (p95 8.44 -> 7.70; no reference: 4.20 either way); with
   the mounting turn removed from the simulation instead 3.40, with an exact flat hold and a tight
   reference 3.37. The flat hold itself is only within ±3 deg per joint, which bounds what it can
   calibrate. The other two mounting angles (the hinge axis tilted in the sensor frame) cost less
   (4.10 -> 3.84 with them removed from the simulation) and are left to the ``G`` states.

6. **The gyro's scale error about the hinge axis** ``s_g`` (MPU-9250 ±3 %, prior std 0.017): the
   rate is ``ω - b_g - s_g g_x`` with ``g_x`` the hinge-axis reading, so a fast flexion through 90 deg
   with a 3 % scale error no longer leaves a 2.7 deg error for the weak accelerometer to pull back;
   the accelerometer's angle after each transition reveals ``s_g``. Measured with the scale error
   removed from the simulation instead: 3.15 -> 2.77 deg; with the state: 3.15 -> 2.83 deg (seeds
   500-511, p95 6.58 -> 5.67), 3.31 -> 2.98 (512-519), 3.80 -> 3.46 without a reference (500-511);
   the dropout recovery unchanged (median next-second ratio after a dropout 0.84 -> 0.85). A finger
   on a fallback closure (a sensor silent) holds the state (its gain row zeroed): an earlier attempt
   that let it learn there (with the gyro's cross-rate leaks as two more states) learned the
   fallback's errors, and the finger took 1.7x its undisturbed error in the second after the sensor
   returned. ``gyro_scale_uncertainty`` (the angle's process noise from scale and cross-axis errors)
   stays 0.03: 0.02 with the state gave the same (2.84 deg); a random walk of the state (1e-3/√s)
   changed nothing.

Process model (per sensor, trapezoid/RK4 step as in ``integration``; the ``G`` states of item 4
are constant but for a small random walk, and enter only the measurement):
``θ ← θ + dt (ω̄ - b_g - s_g g_x)``, ``F = [[1, -dt, 0, -dt g_x], [0, 1, 0, 0], [0, 0, I3, 0], [0, 0, 0, 1]]``
(``[θ, b_g, b_a, s_g]``; ``G`` left out),
``Q = diag(σ_ω² dt, σ_bg² dt, σ_ba² dt I3)``.
Measurement: ``f = (I + G) v + b_a``, ``v = R_x(θ)ᵀ u`` with ``u`` the reference force of the chain
model (``observations.reference_force``); ``∂f/∂θ = (I + G) [0, -sin θ u_y + cos θ u_z, -cos θ u_y - sin θ u_z]``,
``∂f/∂b_a = I``, ``∂f_i/∂G_ij = v_j``; noise ``σ_a² + (κ |μ̂|)²`` with ``|μ̂|`` the eq. 6 bound, plus the
optical acceleration's predicted error ``e eᵀ`` (below).

Honest accelerometer weight. The accelerometer errors the model does not carry as states (scale
±3 %, cross-axis ±2 %, a mounting misalignment of up to 5 deg, ±10 % phalanx lengths in the kinematic
terms, soft tissue) are constant or slowly varying, not white: a per-sample std equal to their size
(about 0.05 of the force) is averaged down over the 200 samples of every second, so the angle's
variance shrinks far below the few degrees these terms leave in the accelerometer's angle, and a
reference pose (±3 deg per joint) or a slower correction by the gyro can no longer move it. The
per-sample std is therefore ``acc_scale_uncertainty`` = 0.3 of the force, the white-noise equivalent of
those errors over a correlation time of a few samples. With the item-4 states (then with the gyro states too) a lower weight did not help on the same
tuning trials (0.15 -> 4.24 deg, 0.25 -> 3.64, 0.3 -> 3.58, 0.4 -> 3.58 pooled): what the accelerometer still gets wrong is not
only its linear map (the optical hand acceleration in fast reaches, the phalanx lengths). The value was first chosen on tuning trials of
``bench accuracy`` disjoint from its scored ones (chain's rows of ``--first-seed 500 --trials 3
--seconds 8``, mean joint RMS with the reference pose: 0.05 -> 4.35 deg, 0.1 -> 4.15, 0.25 -> 3.85, 0.4 -> 3.71,
0.6 -> 3.68; p95 lowest at 0.25-0.4); not on the scored seeds. The hinge-axis part of the mounting
stays unobservable without a reference (the accelerometer sees only ``θ + δ``, the gyro only changes
of ``θ``), and with the default placement it is amplified into the MCP angle: with the coupling
``φ_2 = c φ_1`` (the paper's first approximation, DIP = PIP, section 2) the joints follow from the
two observed phalanx angles as ``φ_1 = (θ_2 - θ_1) / c``, ``φ_0 = θ_1 - φ_1``, so phalanx errors
``e_1, e_2`` become an MCP error ``(1 + 1/c) e_1 - e_2 / c`` (``2 e_1 - e_2`` at ``c = 1``).

What the placement makes observable: sensors on phalanges 1 and 2 (the paper's placement, section 2)
observe ``θ_1 = φ_0 + φ_1`` and ``θ_2 = φ_0 + φ_1 + φ_2``, two numbers for three unknowns
``φ_0, φ_1, c``; the optics give only the metacarpus. So the coupling ``c`` is not observable from
the orientations (only weakly, through the accelerations the unmeasured proximal phalanx adds in fast
motion, eq. 2); a flat reference pose does not reveal it either (every joint near 0). It needs a known configuration with a bent PIP (a reference pose other than flat) or a
sensor on phalanx 0, and is not estimated here.

The optics' acceleration. The hand's linear acceleration ``a`` in the reference force comes from the
pipeline's optical fit (``pipeline/optical.py``): the second-derivative coefficient of a quadratic
least-squares fit to the positions of the last ``W`` = 0.15 s of poses, at the newest one. On a path
with jerk ``j`` that fit returns the acceleration of the window's middle: expanded about the middle
``m = -W/2``, the cubic part ``(τ - m)³`` is odd about it, so its least-squares projection on the
quadratics is a line (no second derivative), and what is left is a quadratic whose second derivative
is ``a(m)``. So ``â(t) ≈ a(t - λ)`` with the lag ``λ = W/2`` (0.061-0.072 s for the 14 poses of a 90
Hz window, by where the newest pose falls), and the fit is off by ``a(t - λ) - a(t) ≈ -λ j``. On
tuning trials (seeds 500-503) this lag is nearly all of its error where it matters: from noise-free
poses 0.11-1.2 m/s² RMS on turning hands and 3.3 m/s² on fast reaches, against the jitter's
0.25-0.94 m/s². The accelerometers read that error as a tilt. The jerk is not measured, but the
fit's own change over its last lag tells how far it is off now: ``ā``, the fit's acceleration
through a first-order filter of time constant ``λ``, lags it by ``λ`` on a ramp, so ``â - ā ≈ λ ĵ``
(one lag late). Each accelerometer reads that error in its own frame, ``e = (I + G) R_x(θ)ᵀ R_Bᵀ
R_Mᵀ (â - ā)``, so its noise becomes ``R = σ² I + e eᵀ``: widened along the direction the optics are
wrong in, not across (``optical_fit_lag_s``, derived, not tuned). The jitter's share (the fit's
acceleration weights the 14 positions with a norm of about 300 s⁻², so ``300 σ_p`` per axis:
0.15-0.6 m/s² for the realistic 0.5-2 mm) is left out: it is small against ``σ``
(``acc_scale_uncertainty`` · g, 2.9 m/s²). On tuning trials 500-519 (12 s, mean joint RMS): with the
reference pose 2.224 -> 2.161 deg (14 of 20 trials better, mean difference -0.063 ± 0.018), without
it 3.043 -> 2.998 (13 of 20, -0.044 ± 0.015). Widening all three axes by ``k |â - ā|`` instead
gained with the reference pose only (k = 1 2.183, k = 2 2.172) and tied without it (k = 2 3.055):
the accelerometer's other two directions still tell the angle while the hand's acceleration is
uncertain along one.

**The optics' acceleration error as a state every sensor of the hand shares** (the default where the
fingers run together, ``ChainHand``: the pipeline's one kernel call per tick). The hand is rigid, so
every finger's accelerometer reads the same error ``δ`` of the optical acceleration (world frame),
turned into its own frame: ``f = h(x_k) + M_k δ``, ``M_k = (I + G) R_x(θ)ᵀ R_Bᵀ R_Mᵀ``. ``δ`` is three
states of a first-order Gauss-Markov process with the fit's lag as time constant and a std of
``hand_acc_error_scale`` |â - ā| (0.22) and ``hand_acc_error_floor_m_s2`` (0.05) in quadrature; it
replaces the widening ``e eᵀ`` there. Sensor after sensor in the tick, each accelerometer updates its
own state and ``δ`` jointly, and every other sensor of the hand moves by its correlation with ``δ``
(``C_l = P_{x_l δ}``, kept per sensor), so what one finger learns of ``δ`` corrects the others at once;
the cross terms between two sensors' own states are dropped, as between separate filters, so another
sensor's covariance is not reduced by it (that would count the same information twice).
``chain_kernel._joint_update``, its numpy reference ``ChainHand.advance_reference``. Why ``δ``'s prior
is far below the fit's predicted error (0.22 of it): ``δ`` is confounded with a common tilt of the
whole hand's sensors (a turn of every sensor about its hinge axis changes what it reads of gravity as a
hand acceleration would), which only the gyros and ``δ``'s prior tell apart. With the prior at the
predicted error itself (scale 1, floor 0.3 m/s²) the fingers locked onto a wrong common tilt on one
tuning trial (502: every MCP about 10 deg off after a dropout, +2.8 deg mean joint RMS), and the
first ten lost (500-509: 2.203 -> 2.717 deg with the reference pose); with a time constant of 0.03 s,
or a widening kept as well, or only the other sensors' angles moved, the same. Tuning trials 500-519
(12 s, mean joint RMS, against the widening alone): with the reference pose 2.161 -> 2.035 deg (16 of
20 better, -0.126 ± 0.040), without it 2.998 -> 2.885 (11 of 20, -0.114 ± 0.078); events back within
1.5x in 1 s 96 -> 95 of 100 in both. A finger advanced alone (a rebuild, a batch, the reference
implementation) keeps the widening. ``δ`` is the optics' error, not a filter's: it is kept across a
rebuild of the fingers' filters (a sensor's fallback and return, a calibration, an estimator switch) and
decays over the whole time since it was last advanced, not over the new filters' first step; it restarts
from its prior when its settings change or the source's clock steps back. Within a tick, a later
sensor of a finger moved through its correlation with ``δ`` has its predicted angle moved by ``F dx``
(its offset's correction enters the angle's prediction, ``-dt dx_bg``). (A separate filter of ``δ`` fed
back to the next tick was tried before: it found ``δ`` but the angles did not gain, since it ignored the
correlation with them.)

**The hold of a reference pose.** A ``reference_pose`` says the hand held the configuration from ``t0``
to ``t1`` (DESIGN.md), not only that it was there at ``t1``: every phalanx was still on the hand, so each
gyro's relative hinge-axis rate (its hinge-axis reading less the hand's rate about the hinge axis, the
``rate_meas`` the filter integrates) averaged over the hold is its offset, ``r̄ = b_g + s_g ḡ_x + n``
(item 6's scale term with ``ḡ_x`` the mean hinge-axis reading). Without it the offsets come only from
the weak accelerometer, and at the reference they move with the angle through the correlation the
filter has built while converging from an unknown start: on a tuning trial whose start was 30-43 deg off
(556), every long-finger offset estimate was 3-4 deg/s off after the reference, all the same way, and the
fingers drifted 6-10 deg. The measurement's std is ``hold_rate_std_rad_s`` and the gyro's scale and
cross-axis errors times the mean reading (``gyro_scale_uncertainty`` |ḡ|: a hand turning during the hold
leaks into the hinge axis). Applied at the reference before its angle update, per sensor, over the part of
the hold this estimator saw (at least ``hold_min_s``). (Zero-rate *detection* was tried and dropped,
item 2; this is a hold the glove app declares.) A sensor that turned on its hand during the hold is not
read: a finger that moved during a claimed hold would otherwise leave its offset wrong for good (the
offset's random walk is slow). What a still finger's relative rate integrates to over the hold is its
offset's line, ``b (t - t0)``, plus the gyro's scale and cross-axis errors times the hand's turn seen
by the sensor, ``s · ∫ g``; what is left beyond both is how far the finger turned on its hand. So the
integral's deviation from its mean line is fitted by that deviation of the reading's integral, ``s``
with the prior ``gyro_scale_uncertainty`` per axis, and a sensor whose residual reaches
``hold_still_max_rad`` moved. Still holds of tuning trials 500-599 (600 sensors on rotating and reaching
hands) leave at most 3.2 deg (p99 2.2; 7.3 without the fit of ``s``). A turn of ``A`` at the fraction
``u`` of the hold strays about ``A max(u, 1 - u)`` from the line (less what the fit of ``s`` takes up), so
the check is weakest in the hold's middle: on a still hand a turn of 7 deg in the last 0.3 s strays 6
deg and is caught, one in the middle only 3 deg and is read (its offset left 3.5 deg/s off); on the
tuning holds with the turn added, 7 deg is caught on 384 of 600 sensors at the end, 18 in the middle,
10 deg on 460 and 401. The fit's data term counts every tick with the same angle noise, so at a higher
sample rate it weighs the data more against the prior of ``s`` (the limit was set at the benchmark's 200 Hz).
(A first check compared the mean rate over the hold's two halves against 15 deg/s: still holds differed
by up to 9 deg/s there, so it caught gross motions only.)

**The hand's rotation seen from the phalanx.** The gyro reads the whole phalanx's angular velocity,
``f = R_x(θ)ᵀ w + θ̇ x`` in the phalanx frame, with ``w`` the hand's rate in the finger base frame (optics).
Only the hinge-axis part ``f_x`` enters the prediction; the other two are ``(w_y, w_z)`` turned by ``-θ``, so
while the hand turns across the hinge axis the gyro alone tells the sensor's angle,
``atan2(w_z, w_y) - atan2(f_z, f_y) = θ - δ_m`` (``δ_m`` the mounting turn about the hinge axis, which the
accelerometer sees alike), and nothing of the hand's acceleration is in it: the optics' acceleration,
which lags on a turning hand and which the accelerometers read as a tilt, is what misleads the angle
most there (failure mode 4 of the README's diagnosis). ``ChainHand`` takes it as one more measurement of
each sensor after the tick's update, where the hand turns across the hinge axis faster than
``gyro_angle_min_rate_rad_s``, the finger turns on its hand slower than ``gyro_angle_max_flexion_rad_s``,
the optics track and no gyro of the finger is clipped; its std is the optical rate's error
(``gyro_angle_rate_std_rad_s``) over the rate across the hinge, counted once per optical fit window
(``gyro_angle_window_s``: the rate's error is correlated over it), and an angle further than 0.5 rad from
the prediction is not taken. It updates the sensor's own states and their covariance with δ; δ and the
other sensors take no gain from it (a valid, not optimal, update). A finger advanced alone (a rebuild, a
batch, the per-finger reference) does not take it. It comes after the tick's angles are read out, so a
correction shows in the next frame. A finger on a fallback closure holds its gyro scale state: the
measurement's gain on it is zeroed (the general covariance form). The gyro's cross axes carry their
offsets (MPU-9250 ±5 deg/s, 2.9 deg/s RMS per axis), which turn the angle they tell by about
``|b| / |w_yz|`` (typically 1-3 deg at 1-3 rad/s, up to 7 deg at the bound and the least rate taken) and do
not average out over windows; the pipeline's flexion-axis fit has the cross axes' residuals regressed on
``[ω_x, 1]`` (``service/pipeline/mounting.py``), whose constant terms estimate them, so with
``gyro_angle_cross_offsets`` they are taken off the cross axes' reading first (``ChainHand.cross_offsets``,
set by the pipeline each tick from the fit, which learns them from fast flexions and from the samples of a
still hand, those once the optics' window is full and where the gyro's own cross axes agree the hand is
still). The estimate has its own error (RMS per axis on tuning trial 522 2.5 deg/s at 3 s, 1.6 at 12 s,
3.3 with none taken off; on 521 0.82 and 0.30, 3.0 with none taken off);
with
``gyro_angle_offset_error`` its variance as the fit's normal equations give it, ``σ_b² = σ² a00 / det``
(the prior's 2.9 deg/s before any sample), is added to the optical rate's,
``(σ_rate² + σ_b²) / |w_yz|²``, and counted once per window like it. Not modelled yet: ``σ_b²`` is not
calibrated (it takes the fit's samples as independent with the fast flexions' residual std; a review
measured the mean of ``(b̂ - b)² / σ_b²`` at 0.13-0.36 on trial 521 and 1.7-3.1 on 522), and the estimate's
error is correlated far longer than a window; a tick longer than the window counts as more than one window; the gyro's scale and cross-axis
errors and the mounting's tilt do not average out over windows as the noise model assumes; the fit's sums
weigh an old sample as much as a new one, so a temperature drift of the offsets (±0.24 deg/s/K) is followed
ever more slowly. On tuning trials it
measured each rotating hand's sensor to 1.8 deg RMS of bias per sensor against the filter's 2.3 deg.

Not used: the coupling as a soft constraint. With the default placement (sensors on phalanges 1 and
2) the coupling is what determines the MCP angle, so there is no redundancy to soften; with sensors
on all three phalanges it would be, and is left for later. The hand kinematics are taken as given
(from the optics); their errors are not states.

Implementation: the filter runs as one compiled numba call per finger and tick (``chain_kernel.run``:
every sensor, batch row and sample over flat float64 arrays; ``run`` makes one call for a whole
batch). ``_step_reference`` is the same filter in numpy, the reference the kernel is tested equal to
(``tests/test_chain_kernel.py``, 1e-9); the setting ``implementation="reference"`` runs it instead.
A change to the filter goes into both.
"""
from __future__ import annotations

import math
from dataclasses import replace
from operator import is_ as _is
from typing import Literal

import numpy as np
from pydantic import Field

from ..model.units import DEG, MPU9250_ACC_OFFSET_STD_M_S2, MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ, MPU9250_GYRO_OFFSET_STD_RAD_S
from . import chain_kernel as K
from ..pipeline.tick_kernel import steady_tick
from .chain_kernel import GA_START, GS, N_STATE
from . import kalman
from .base import MODE_FAST, MODE_FUSED, EstimatorSettings, FingerEstimate, FingerEstimator, FingerSamples, FingerTrack, \
    lost_optics_variance
from .observations import ChainClosure, FingerObservations, initial_sensor_theta


TH, BG = 0, 1
BA = slice(2, 5)
GA = slice(GA_START, GA_START + 9)
_HINGE_ROTATION = np.zeros(9)
_HINGE_ROTATION[7], _HINGE_ROTATION[5] = np.sqrt(0.5), -np.sqrt(0.5)        # G_zy = -G_yz: a turn about x
_HINGE_FREE = np.eye(9) - np.outer(_HINGE_ROTATION, _HINGE_ROTATION)
"""The linear-map states ``G`` leave out the turn about the hinge axis (item 4 of the module docstring):
their prior and random walk are projected onto the other eight directions."""


class ChainSettings(EstimatorSettings):
    gyro_noise_density_rad_s_rthz: float = Field(MPU9250_GYRO_NOISE_DENSITY_RAD_S_RTHZ, gt=0.0, description="gyro white noise, rad/s/√Hz")
    gyro_bias_walk_rad_s_rts: float = Field(1e-5, ge=0.0, description="gyro offset random walk, rad/s/√s")
    acc_bias_walk_m_s2_rts: float = Field(1e-4, ge=0.0, description="accelerometer offset random walk, m/s²/√s")
    initial_gyro_bias_std_rad_s: float = Field(MPU9250_GYRO_OFFSET_STD_RAD_S, gt=0.0, description="prior std of the gyro offset (MPU-9250 ±5 deg/s), rad/s")
    initial_acc_bias_std_m_s2: float = Field(MPU9250_ACC_OFFSET_STD_M_S2, gt=0.0, description="prior std of the accelerometer offset (MPU-9250 ±60-80 mg), m/s²")
    initial_angle_std_rad: float = Field(1.0 * DEG, gt=0.0, description="prior std of a given initial configuration, rad")
    unknown_angle_std_rad: float = Field(10.0 * DEG, gt=0.0, description="prior std when starting from a vector observation, rad")
    acc_noise_m_s2: float = Field(0.03, gt=0.0, description="accelerometer white noise per sample, m/s² (MPU-9250 at 200 Hz)")
    kinematic_uncertainty: float = Field(0.1, ge=0.0, description="added accelerometer std per m/s² of the eq. 6 bound")
    gyro_scale_uncertainty: float = Field(0.03, ge=0.0, le=1.0, description="gyro scale and cross-axis error as a fraction of the rate's magnitude (MPU-9250: ±3 %, ±2 %); widens the angle's process noise")
    acc_scale_uncertainty: float = Field(0.3, ge=0.0, le=1.0, description="accelerometer scale, cross-axis, mounting and hand-geometry error as a fraction of the specific force's magnitude, as per-sample white noise (see 'Honest accelerometer weight' in the module docstring)")
    gyro_range_rad_s: float = Field(2000.0 * DEG, gt=0.0, description="gyro full scale (MPU-9250: ±2000 deg/s); a sample at it is saturated, rad/s")
    acc_range_m_s2: float = Field(16.0 * 9.80665, gt=0.0, description="accelerometer full scale (±16 g); a sample at it is saturated, m/s²")
    clipped_rate_std_rad_s: float = Field(200.0 * DEG, ge=0.0, description="the angle's process noise per clipped gyro sample, rad/s: the pipeline adds what a clipped run missed after it (mounting.py), to within 3.2 deg RMS on runs of about ten samples on tuning trials, about 200 deg/s per sample; without that reconstruction the unknown excess rate is up to the full scale (2000 deg/s)")
    optical_fit_lag_s: float = Field(0.075, ge=0.0, description="lag of the optical hand acceleration, half the pipeline's fit window (PipelineSettings.pose_window_s, 0.15 s): the accelerometer's noise is widened along the fit's change over this lag, its predicted error ('The optics' acceleration' in the module docstring), and it is the time constant of the shared error δ (hand_acc_error_scale); 0 turns both off, s")
    hand_acc_error_scale: float = Field(0.22, ge=0.0, description="the hand's optical acceleration error δ as a state shared by every sensor of the hand (with ChainHand, the pipeline's one call per tick): its std as a fraction of the fit's predicted lag error |â - ā|, time constant optical_fit_lag_s; with this and the floor at 0 the lag error widens each accelerometer's noise instead ('The optics' acceleration' in the module docstring)")
    hand_acc_error_floor_m_s2: float = Field(0.05, ge=0.0, description="the least std of δ, m/s²")
    untracked_acc_noise_m_s2: float = Field(3.0, gt=0.0, description="accelerometer std while the hand's acceleration is unknown (optics lost), m/s²")
    initial_acc_scale_std: float = Field(0.0, ge=0.0, description="prior std of each diagonal term of the accelerometer's linear map error (MPU-9250 scale ±3 %, uniform: 0.017); 0 (the default) keeps the map at identity (item 4 of the module docstring)")
    initial_acc_axis_std: float = Field(0.0, ge=0.0, description="prior std of each off-diagonal term of the accelerometer's linear map error (cross-axis ±2 % and a mounting of up to 5 deg: 0.031); 0 (the default) keeps them at zero")
    calibration_walk_rts: float = Field(0.0, ge=0.0, description="random walk of the linear-map states, 1/√s (1e-4 with the priors above)")
    mounting_hinge_std_rad: float = Field(0.03, ge=0.0, description="prior std of each sensor's mounting turn about the hinge axis (a misalignment of up to 5 deg about a random axis: 0.029), taken up as a state at the first known configuration; 0 leaves it with the angle, rad")
    initial_gyro_scale_std: float = Field(0.017, ge=0.0, description="prior std of the gyro's scale error about the hinge axis (MPU-9250 ±3 %, uniform: 0.017); 0 keeps it at zero (item 6 of the module docstring)")
    gyro_scale_walk_rts: float = Field(0.0, ge=0.0, description="random walk of the gyro scale state, 1/√s")
    lost_optics_drift_rad_s: float = Field(0.1, gt=0.0, description="growth of the angle std while the optics are lost, rad/s: the pipeline carries the hand's orientation on from the finger gyros, so it drifts by their scale (±3 %) and cross-axis (±2 %) errors of a hand turning at up to 2-3 rad/s and their offsets' residual, not by the hand's whole rotation (the shared LOST_RATE_RAD_S of 1 rad/s: tuning trials 500-511 2.55 -> 2.48 deg, 512-519 2.78 -> 2.67)")
    rebuild_angle_std_rad: float = Field(1.0 * DEG, gt=0.0, description="least angle std kept across a rebuild for a sensor that stayed live, rad")
    reference_hold_offsets: bool = Field(True, description="a reference_pose's hold [t0, t1] also measures each gyro's offset: the finger was still on its hand, so its mean relative hinge-axis rate over the hold is the offset ('The hold of a reference pose' in the module docstring)")
    hold_rate_std_rad_s: float = Field(1.0 * DEG, gt=0.0, description="std of a hold's mean relative rate as a measurement of the gyro offset, besides the gyro's scale and cross-axis errors: the optical hand rate's error over the hold (orientation jitter of 0.1-0.5 deg at both ends of a 2 s hold: about 0.35 deg/s) and a held hand's slow drift (1 deg over 2 s: 0.5 deg/s), rad/s")
    hold_still_max_rad: float = Field(4.0 * DEG, gt=0.0, description="a sensor whose relative hinge-axis rate, integrated over the hold, strays this far, rad, from its offset's line and what the gyro's scale and cross-axis errors make of the hand's turn was not held still: no offset is read from that hold ('The hold of a reference pose' in the module docstring; a finger that moved 7-12 deg in the last 0.3 s of a claimed hold made its offset 4-8 deg/s wrong for good; still holds of tuning trials 500-599 reached 3.2 deg; a turn A at the fraction u of the hold strays about A max(u, 1 - u), so turns in the hold's middle below about 8 deg pass)")
    gyro_angle_rate_std_rad_s: float = Field(0.1, ge=0.0, description="the optical hand rate's error for the angle each finger gyro's cross axes tell (with ChainHand, the pipeline's one call per tick; 'The hand's rotation seen from the phalanx' in the module docstring): about twice a quadratic fit's rate error over 0.15 s of 90 Hz poses with 0.1 deg jitter (0.04 rad/s), for its lag on a turning hand; 0 turns the measurement off, rad/s")
    gyro_angle_min_rate_rad_s: float = Field(1.0, gt=0.0, description="the measurement is taken while the hand turns across the hinge axis at least this fast (its rate about the finger base's other two axes), rad/s")
    gyro_angle_max_flexion_rad_s: float = Field(1.0, gt=0.0, description="... and the finger turns on its hand slower than this (its hinge-axis reading less the hand's rate about it), rad/s")
    gyro_angle_window_s: float = Field(0.15, gt=0.0, description="the optical hand rate's error is correlated over the optics' fit window (PipelineSettings.pose_window_s), so the gyro's angle counts once per window: its variance per tick is multiplied by this over the tick's step, s")
    gyro_angle_cross_offsets: bool = Field(True, description="take each gyro's cross-axis offsets, as the pipeline's flexion-axis fit estimates them (service/pipeline/mounting.py), off its cross axes' reading for the gyro's angle (MPU-9250 offsets ±5 deg/s: b/|w| is typically 1-3 deg of angle at a hand rate of 1-3 rad/s across the hinge, up to 7 deg at the bound)")
    gyro_angle_offset_error: bool = Field(True, description="with gyro_angle_cross_offsets, count the offsets' own estimation error in the gyro angle's noise: their variance from the flexion-axis fit's normal equations over the rate across the hinge squared, sigma_b^2 / |w_yz|^2, beside the optical rate's")
    hold_min_s: float = Field(0.5, gt=0.0, description="least part of a reference_pose's hold the estimator must have seen for the offset measurement, s")
    implementation: Literal["compiled", "reference"] = Field(
        "compiled", description="'compiled': the numba kernel (chain_kernel.py); 'reference': the numpy implementation it is "
                                "tested equal to (to 1e-9), about a hundred times slower, finger by finger, so without "
                                "the hand's shared acceleration error and the gyros' angle (their numpy reference is "
                                "ChainHand.advance_reference)")


_GYRO_ANGLE_H = np.zeros(N_STATE)
_GYRO_ANGLE_H[TH] = 1.0
_GYRO_ANGLE_H[GA] = -_HINGE_ROTATION / np.sqrt(2.0)
"""The gyro's angle ``θ - δ_m`` as a row over a sensor's states: ``G = √2 δ_m`` along the hinge rotation."""
_GYRO_ANGLE_GATE_RAD = 0.5
"""A gyro's angle further than this from the predicted one is not taken (a rate too small or too
disturbed for its direction to mean anything), rad."""

_HOLD_ANGLE_NOISE_RAD = 1.0 * DEG
"""The angle's noise per tick in ``HoldLog.mean``'s fit: what a still finger's integrated relative rate
strays from its line by (the optical hand rate's error; 0.8 deg median on tuning trials 500-599)."""


class HoldLog:
    """Running integrals over time of each sensor's relative hinge-axis rate (S,) and gyro reading (S, 3)
    at every tick, for the mean over a ``reference_pose``'s hold. Grows to ``capacity`` ticks, then keeps
    the newer half.

    Its arrays are the times ``t`` (capacity,), the integrals ``r`` (capacity, S) and ``g`` (capacity, S, 3)
    and the count of ticks ``count`` (1,), int64: its own, or (``arrays``) views of a hand's log that
    ``ChainHand`` keeps, which ``chain_kernel.run_hand`` advances as ``add`` does, finger by finger."""

    def __init__(self, n_sensors: int, capacity: int = 4096, arrays: tuple | None = None):
        if arrays is None and (capacity < 2 or capacity % 2):
            raise ValueError(f"capacity: a hold log keeps the newer half when full, so an even number of ticks of "
                             f"at least 2; got {capacity}")
        if arrays is None:
            arrays = np.empty(capacity), np.zeros((capacity, n_sensors)), np.zeros((capacity, n_sensors, 3)), \
                np.zeros(1, dtype=np.int64)
        self._t, self._r, self._g, self._count = arrays

    @property
    def _n(self) -> int:
        return int(self._count[0])

    @property
    def capacity(self) -> int:
        return self._t.shape[0]

    def add(self, t: float, dt: float, rate: np.ndarray, gyr: np.ndarray) -> None:
        """One tick at ``t`` after a step of ``dt``: ``rate`` (S,) and ``gyr`` (S, 3) the sensors' values."""
        n = self._n
        if n == self._t.shape[0]:
            half = n // 2
            self._t[:half], self._r[:half], self._g[:half] = self._t[half:], self._r[half:], self._g[half:]
            n = half
        if n:
            np.add(self._r[n - 1], dt * rate, out=self._r[n])
            np.add(self._g[n - 1], dt * gyr, out=self._g[n])
        self._t[n] = t
        self._count[0] = n + 1

    def add_many(self, t: np.ndarray, dts: np.ndarray, rate: np.ndarray, gyr: np.ndarray) -> None:
        """``add`` of every tick in turn (``t``, ``dts`` (N,), ``rate`` (N, S), ``gyr`` (N, S, 3)), the sums
        accumulated over runs of ticks (``np.add.accumulate`` adds in order: the same numbers); a full
        log keeps its newer half between runs, where ``add`` would."""
        k = 0
        while k < len(t):
            if self._n == self._t.shape[0]:
                self.add(float(t[k]), float(dts[k]), rate[k], gyr[k])      # keeps the newer half first
                k += 1
                continue
            n = self._n
            m = min(len(t) - k, self._t.shape[0] - n)
            self._t[n:n + m] = t[k:k + m]
            for log, values in ((self._r, rate), (self._g, gyr)):
                terms = dts[k:k + m].reshape((m,) + (1,) * (values.ndim - 1)) * values[k:k + m]
                if n:
                    terms[0] += log[n - 1]
                else:
                    terms[0] = log[0]       # a log's first tick keeps what it holds (nothing before it)
                np.add.accumulate(terms, axis=0, out=log[n:n + m])
            self._count[0] = n + m
            k += m

    def mean(self, t0: float, t1: float, min_s: float, map_std: float = 0.03):
        """``(mean rate (S,), mean reading (S, 3), moved (S,))`` over the ticks within ``[t0, t1]``, or
        None when they span less than ``min_s``. ``moved`` is how far, rad, each sensor's integrated rate
        strays from its mean line beyond what a linear map error ``s`` of the gyro (prior std ``map_std``
        per axis) makes of the same deviation of its integrated reading: about 0 for a finger held still
        (an offset is a line, the map's error of the hand's turn is fitted), the angle it turned on its
        hand otherwise ("The hold of a reference pose" in the module docstring)."""
        t = self._t[:self._n]
        i0 = int(np.searchsorted(t, t0 - 1e-9))
        i1 = int(np.searchsorted(t, t1 + 1e-9)) - 1
        if i1 <= i0 or t[i1] - t[i0] < min_s:
            return None
        tt = t[i0:i1 + 1] - t[i0]
        span = tt[-1]
        r = self._r[i0:i1 + 1] - self._r[i0]
        g = self._g[i0:i1 + 1] - self._g[i0]
        r_dev = r - tt[:, None] * (r[-1] / span)                       # (n, S) beyond the offset's line
        g_dev = g - tt[:, None, None] * (g[-1] / span)                 # (n, S, 3)
        # ridge fit of s per sensor: (Xᵀ X / σ² + I / map_std²) s = Xᵀ y / σ², σ the angle's noise per tick
        a = np.einsum("nsi,nsj->sij", g_dev, g_dev) / _HOLD_ANGLE_NOISE_RAD**2 + np.eye(3) / map_std**2
        b = np.einsum("nsi,ns->si", g_dev, r_dev) / _HOLD_ANGLE_NOISE_RAD**2
        fit = np.linalg.solve(a, b[..., None])[..., 0]
        moved = np.abs(r_dev - np.einsum("nsi,si->ns", g_dev, fit)).max(axis=0)
        return r[-1] / span, g[-1] / span, moved


_GEOMETRY: dict[tuple, tuple] = {}
"""``chain_kernel.geometry_vector`` of shared finger constants (``FingerObservations.of``, ``ChainClosure.of``), by
their ids and gravity's bits (each entry keeps its objects alive)."""


def _geometry_vector(obs: FingerObservations, closure: ChainClosure, gravity_world: np.ndarray) -> np.ndarray:
    """``chain_kernel.geometry_vector(obs, closure, gravity_world)``, a new array each call: concatenated once
    per shared (read-only) ``obs`` and ``closure``."""
    if obs.mount.flags.writeable or closure.matrix.flags.writeable:     # (not shared: they may change)
        return K.geometry_vector(obs, closure, gravity_world)
    key = (id(obs), id(closure), gravity_world.shape, gravity_world.tobytes())
    hit = _GEOMETRY.get(key)
    if hit is None or hit[0] is not obs or hit[1] is not closure:
        if len(_GEOMETRY) >= 512:
            _GEOMETRY.clear()
        hit = _GEOMETRY[key] = (obs, closure, K.geometry_vector(obs, closure, gravity_world))
    return hit[2].copy()


class Chain(FingerEstimator):
    name = "chain"
    Settings = ChainSettings
    jit_kernels = True
    kernels = (K.run, K.run_hand, steady_tick)
    """``run_hand`` also inside the hand pipeline's steady tick (``pipeline.tick_kernel``, warmed with it)."""

    @classmethod
    def whole_hand_compiled(cls, settings: ChainSettings) -> bool:
        return settings.implementation == "compiled"

    def __init__(self, *args, extra_couplings: tuple = (), **kwargs):
        super().__init__(*args, extra_couplings=extra_couplings, **kwargs)
        self._compiled = self.settings.implementation == "compiled"
        self._nb = int(np.prod(self.batch_shape, dtype=int))
        self._settings_vector = K.settings_vector(self.settings)
        # a finger on a fallback closure (a sensor silent) holds its gyro scale states (item 6)
        self._settings_vector[K.ST_GS_LEARN] = 0.0 if extra_couplings else 1.0
        self._geometry_vector = _geometry_vector(self.obs, self.closure, self.gravity_world)
        self._hand_untracked = False
        # the running integrals for a reference pose's hold (advanced here or by a ChainHand)
        self._hold = HoldLog(self.n_sensors) if not self.batch_shape else None

    # -- the compiled path ---------------------------------------------------------------------
    def _advance(self, t, gyr, acc, hand):
        dt = 0.0 if self._state is None else t - self._t_last
        out = self._advance_filter(t, gyr, acc, hand)
        if self._hold is not None:
            self._hold.add(t, dt, self._state["rate"], gyr)
        return out

    def _advance_filter(self, t, gyr, acc, hand):
        if self._state is None:
            self._start_t = t
        if not self._compiled:
            return super()._advance(t, gyr, acc, hand)
        if self._state is None:
            state, dt = self._init_state(gyr, acc, hand, self._initial_theta), 0.0
        else:
            state, dt = self._state, t - self._t_last
        nb, ns = self._nb, self.n_sensors
        self._state, theta, phi, phal, mode = self._kernel(
            state, np.array([dt]), np.ascontiguousarray(gyr, dtype=float).reshape(1, nb, ns, 3),
            np.ascontiguousarray(acc, dtype=float).reshape(1, nb, ns, 3), hand.flat.reshape(1, nb, K.HAND_SIZE),
            hand.acceleration)
        self._t_last = t
        if not self.batch_shape:
            return FingerEstimate(t, phal[0, 0], phi[0, 0], mode[0, 0])
        b = self.batch_shape
        return FingerEstimate(t, phal[0].reshape(b + phal.shape[-1:]), phi[0].reshape(b + phi.shape[-1:]),
                              mode[0].reshape(b + (ns,)))

    def run(self, samples: FingerSamples) -> FingerTrack:
        """All samples in one kernel call (the reference: one ``_step`` per sample); the same numbers
        as ``update`` on each."""
        if not self._compiled or len(samples) == 0:
            return super().run(samples)
        self._validate_batch(samples)
        t = np.asarray(samples.t, dtype=float)
        n, nb, ns = len(t), self._nb, self.n_sensors
        if self._state is None:
            self._start_t = float(t[0])
            state = self._init_state(*samples.sample(0)[1:], self._initial_theta)
            dt0 = 0.0
        else:
            state, dt0 = self._state, t[0] - self._t_last
        dts = np.diff(t, prepend=t[0] - dt0)
        hand = samples.hand
        self._state, _, phi, phal, mode = self._kernel(
            state, dts, np.ascontiguousarray(samples.gyr, dtype=float).reshape(n, nb, ns, 3),
            np.ascontiguousarray(samples.acc, dtype=float).reshape(n, nb, ns, 3), hand.flat.reshape(n, nb, K.HAND_SIZE),
            np.asarray(hand.acceleration)[0])
        self._t_last = float(t[-1])
        if self._hold is not None:
            # the relative rate the kernel integrates (``_init_state``'s), sample by sample
            rate = self.obs.relative_rate(np.asarray(samples.gyr, dtype=float), hand)
            self._hold.add_many(t, dts, rate, np.asarray(samples.gyr, dtype=float))
        b = (n,) + self.batch_shape
        return FingerTrack(t, phal.reshape(b + phal.shape[-1:]), phi.reshape(b + phi.shape[-1:]), mode.reshape(b + (ns,)))

    def _kernel(self, state, dts, gyr, acc, hand_flat, first_hand_acc):
        """``chain_kernel.run`` on the state dict: returns ``(state, theta, phi, phalanx angles,
        mode)`` with the kernel's (N, B, ...) shapes. The returned state is the one the kernel updated in
        place: ``state`` itself once it holds C-contiguous float64 arrays (a copy of them first, kept
        with its (B, ...) views until the estimator's state is replaced by another dict)."""
        nb, ns, nph = self._nb, self.n_sensors, self.geom.n_phalanges
        views = getattr(self, "_views", None)
        if views is None or views[0] is not state:
            x = np.ascontiguousarray(state["x"], dtype=float)
            P = np.ascontiguousarray(state["P"], dtype=float)
            rate = np.ascontiguousarray(state["rate"], dtype=float)
            hand_acc = state.get("hand_acc")
            hand_acc = (np.array(first_hand_acc, dtype=float) if hand_acc is None
                        else np.ascontiguousarray(hand_acc, dtype=float))
            state = {"x": x, "P": P, "rate": rate, "hand_acc": hand_acc}
            views = self._views = (state, x.reshape(nb, ns, K.N_STATE), P.reshape(nb, ns, K.N_STATE, K.N_STATE),
                                   rate.reshape(nb, ns), hand_acc.reshape(nb, 3))
        n = dts.shape[0]
        theta = np.empty((n, nb, ns))
        phi = np.empty((n, nb, nph))
        phal = np.empty((n, nb, nph))
        mode = np.empty((n, nb, ns), dtype=np.int8)
        K.run(views[1], views[2], views[3], views[4], dts, gyr, acc, hand_flat, self._settings_vector,
              self._geometry_vector, self._hand_untracked, theta, phi, phal, mode)
        return views[0], theta, phi, phal, mode

    def _step(self, state, dt, gyr, acc, hand):
        if not self._compiled:
            return self._step_reference(state, dt, gyr, acc, hand)
        nb, ns = self._nb, self.n_sensors
        state, theta, _, _, mode = self._kernel(
            {k: v.copy() for k, v in state.items()}, np.array([float(dt)]),
            np.ascontiguousarray(gyr, dtype=float).reshape(1, nb, ns, 3),
            np.ascontiguousarray(acc, dtype=float).reshape(1, nb, ns, 3), hand.flat.reshape(1, nb, K.HAND_SIZE),
            hand.acceleration)
        return state, theta[0].reshape(self.batch_shape + (ns,)), mode[0].reshape(self.batch_shape + (ns,))

    def _init_state(self, gyr, acc, hand, theta0):
        s = self.settings
        theta = initial_sensor_theta(self.obs, acc, hand, theta0, self.gravity_world)
        P = np.zeros(theta.shape + (N_STATE, N_STATE))
        known_std = getattr(self, "_known_std_rad", None) or s.initial_angle_std_rad
        P[..., 0, 0] = (known_std if theta0 is not None else s.unknown_angle_std_rad) ** 2
        P[..., 1, 1] = s.initial_gyro_bias_std_rad_s**2
        P[..., BA, BA] = s.initial_acc_bias_std_m_s2**2 * np.eye(3)
        P[..., GS, GS] = s.initial_gyro_scale_std**2
        P[..., GA, GA] = _HINGE_FREE @ np.diag([s.initial_acc_scale_std**2 if i == j else s.initial_acc_axis_std**2
                                                for i in range(3) for j in range(3)]) @ _HINGE_FREE
        if getattr(self, "_known_std_rad", None):
            self._take_up_hinge_mounting(P)
        x = np.concatenate([theta[..., None], np.zeros(theta.shape + (N_STATE - 1,))], axis=-1)
        self._restore_memory(x, P)
        return {"x": x, "P": P, "rate": self.obs.relative_rate(gyr, hand)}

    # -- what survives a rebuild -------------------------------------------------------------
    def inherit(self, previous: FingerEstimator) -> None:
        """Take over what ``previous`` (the estimator this one replaces: a sensor fell silent or came
        back, a calibration, an estimator switch) learned about each sensor, by sensor id: the
        offsets with their covariance always; the angle, with its covariance (at least
        ``rebuild_angle_std_rad``) and its correlation with the offsets, for sensors that were live in
        ``previous`` up to now. Offsets of sensors not in this geometry are remembered for a later
        rebuild.

        A sensor that was silent keeps its offsets and starts from the given configuration, which
        for its phalanx is the fallback closure's guess (``PIP = c·MCP`` with the coupling), not an
        observation. Its prior is what that guess was last seen to be worth: when the sensor fell
        silent, the estimator it left had both its angle and the live sensors' ones, so the closure's
        error for its phalanx at that moment, ``e`` (the deviation of the finger's joints from the
        closure), is known; the angle's variance is ``e² + P_θθ`` (its own variance then). A finger
        whose joints follow the closure (a grasp closing) gets a tight prior, and its accelerometer,
        weak in fast motion, cannot pull it off; one bent against it (MCP straight, PIP flexed) gets
        a wide one, and its first accelerometer samples place it. (With the ``initial_angle_std_rad``
        of a known configuration instead, a sensor returning 20-30° off took seconds to come back.)
        Without such a record (the sensor was never live in a ``Chain`` of this finger) the prior is
        ``unknown_angle_std_rad``."""
        memory = dict(getattr(previous, "_memory", {}))
        fresh = set()
        state = getattr(previous, "_state", None)
        same = isinstance(previous, Chain) and state is not None and previous.batch_shape == self.batch_shape
        if same:
            for k, sp in enumerate(previous.geom.sensors):
                memory[sp.id] = (state["x"][..., k, :].copy(), state["P"][..., k, :, :].copy(), previous.last_t)
                fresh.add(sp.id)
        self._memory = memory
        self._fresh = fresh
        self._closure_error = {k: v for k, v in getattr(previous, "_closure_error", {}).items() if k not in fresh}
        if same:
            self._closure_error.update(self._fallback_errors(previous, state["x"][..., 0]))
        self._hand_untracked = getattr(previous, "_hand_untracked", False)

    def _fallback_errors(self, previous: "Chain", theta: np.ndarray) -> dict:
        """For each sensor of ``previous`` that this estimator goes on without, while all of this one's
        sensors were live in ``previous``: its phalanx angle ``theta`` (``previous``'s, (..., S)) minus
        what this estimator's closure gives for that phalanx from the other sensors' angles."""
        ids = [sp.id for sp in previous.geom.sensors]
        kept = [sp.id for sp in self.geom.sensors]
        if any(i not in ids for i in kept) or len(kept) == len(ids):
            return {}
        live = np.stack([theta[..., ids.index(i)] for i in kept], axis=-1)
        closure = np.cumsum(self.closure.joint_angles(live), axis=-1)
        return {sp.id: theta[..., k] - closure[..., sp.phalanx]
                for k, sp in enumerate(previous.geom.sensors) if sp.id not in kept}

    def _restore_memory(self, x: np.ndarray, P: np.ndarray) -> None:
        memory = getattr(self, "_memory", {})
        s = self.settings
        for k, sp in enumerate(self.geom.sensors):
            if sp.id not in memory:
                continue
            mx, mP, t_mem = memory[sp.id]
            gap = max(0.0, getattr(self, "_start_t", t_mem) - t_mem)
            walk = np.array([s.gyro_bias_walk_rad_s_rts**2] + [s.acc_bias_walk_m_s2_rts**2] * 3
                            + [s.calibration_walk_rts**2] * 9 + [s.gyro_scale_walk_rts**2]) * gap
            x[..., k, 1:] = mx[..., 1:]
            P[..., k, 1:, 1:] = mP[..., 1:, 1:] + np.diag(walk)
            if sp.id not in self._fresh:
                error = getattr(self, "_closure_error", {}).get(sp.id)
                var = error**2 + mP[..., 0, 0] if error is not None else s.unknown_angle_std_rad**2
                P[..., k, 0, 0] = np.maximum(P[..., k, 0, 0], var)
            else:
                x[..., k, 0] = mx[..., 0]
                P[..., k, 0, :] = mP[..., 0, :]
                P[..., k, :, 0] = mP[..., :, 0]
                P[..., k, 0, 0] = np.maximum(mP[..., 0, 0], s.rebuild_angle_std_rad**2)

    def known_configuration(self, theta: np.ndarray, std_rad: float, hold_s: tuple[float, float] | None = None) -> None:
        """A measurement ``θ_{i_k} = theta[i_k]`` of every sensor's phalanx angle, all of a finger's
        sensors in one update: a phalanx angle sums ``i_k + 1`` joints, each known to ``std_rad``
        independently, so two sensors' errors share the joints below the lower one (covariance
        ``(min(i_k, i_l) + 1) std²``). It corrects the angles and, through the covariance the filter
        has built up, the offsets and the mounting turns about the hinge axes (item 5 of the module
        docstring). The sensors' filters are separate, so the update's cross terms between sensors
        are dropped afterwards. Before the first sample it becomes the initial configuration. With
        ``hold_s`` ``(t0, t1)``, the interval the configuration was held, each gyro's mean relative rate
        over it is first a measurement of its offset ("The hold of a reference pose" in the module
        docstring)."""
        if self._state is None:
            self.reset(initial_theta=theta)
            self._known_std_rad = std_rad
            return
        theta = np.broadcast_to(np.asarray(theta, dtype=float), self.batch_shape + (self.geom.n_phalanges,))
        phalanges = np.array([sp.phalanx for sp in self.geom.sensors])
        measured = theta[..., phalanges]
        x, P = self._state["x"].copy(), self._state["P"].copy()
        if hold_s is not None:
            self._hold_offsets(x, P, hold_s)
        self._take_up_hinge_mounting(P, correlated=True)
        ns = len(phalanges)
        n = ns * N_STATE
        P_all = np.zeros(x.shape[:-2] + (n, n))
        H = np.zeros(x.shape[:-2] + (ns, n))
        for k in range(ns):
            rows = slice(k * N_STATE, (k + 1) * N_STATE)
            P_all[..., rows, rows] = P[..., k, :, :]
            H[..., k, k * N_STATE + TH] = 1.0
        R = (np.minimum.outer(phalanges, phalanges) + 1.0) * std_rad**2 * np.ones(x.shape[:-2] + (1, 1))
        # the innovation on the angle's own 2π branch
        y = np.mod(measured - x[..., TH] + np.pi, 2.0 * np.pi) - np.pi
        # a held gyro scale state (a finger on a fallback closure, item 6) is taken as known here too
        held = None if self._settings_vector[K.ST_GS_LEARN] > 0.5 else np.arange(n) % N_STATE == GS
        dx, P_all = kalman.update(P_all, H, R, y, held)
        P = np.stack([P_all[..., k * N_STATE:(k + 1) * N_STATE, k * N_STATE:(k + 1) * N_STATE] for k in range(ns)], axis=-3)
        self._state = {**self._state, "x": x + dx.reshape(x.shape), "P": P}

    def _hold_offsets(self, x: np.ndarray, P: np.ndarray, hold_s: tuple[float, float]) -> None:
        """The hold's mean relative rate of each sensor as a measurement of its offset (in place on ``x``,
        ``P``): ``r̄ = b_g + s_g ḡ_x`` with std ``hold_rate_std_rad_s`` and ``gyro_scale_uncertainty`` |ḡ|; a
        scale state held (a finger on a fallback closure) is taken as known and left as it is."""
        s = self.settings
        if not s.reference_hold_offsets or self._hold is None:
            return
        means = self._hold.mean(float(hold_s[0]), float(hold_s[1]), s.hold_min_s, max(s.gyro_scale_uncertainty, 1e-6))
        if means is None:
            return
        rate, gyr, moved = means
        gx = self.obs.hinge_rate(gyr)
        learn = self._settings_vector[K.ST_GS_LEARN] > 0.5
        for k in range(self.n_sensors):
            if not moved[k] < s.hold_still_max_rad:
                continue                      # the finger moved during the hold: no offset to read from it
            h = np.zeros(N_STATE)
            h[BG] = 1.0
            h[GS] = gx[k] if learn else 0.0
            r = s.hold_rate_std_rad_s**2 + (s.gyro_scale_uncertainty * float(np.linalg.norm(gyr[k])))**2
            y = rate[k] - h @ x[k] - (0.0 if learn else x[k, GS] * gx[k])
            ph = P[k] @ h
            innovation_var = h @ ph + r
            gain = ph / innovation_var
            if learn:
                P[k] -= np.outer(gain, ph)
            else:
                # a held scale state takes no correction (the kernel zeroes its gain row; item 6): the
                # general covariance update P - K (PHᵀ)ᵀ - PHᵀ Kᵀ + K S Kᵀ for that gain
                gain[GS] = 0.0
                P[k] += innovation_var * np.outer(gain, gain) - np.outer(gain, ph) - np.outer(ph, gain)
            x[k] += gain * y
            P[k] = 0.5 * (P[k] + P[k].T)

    def _take_up_hinge_mounting(self, P: np.ndarray, correlated: bool = False) -> None:
        """Add the mounting turn about the hinge axis (``G_zy = -G_yz = δ``) to ``P`` (in place) with its
        prior ``mounting_hinge_std_rad``, for sensors that do not carry it yet. The accelerometer sees
        only ``θ - δ``: once the filter has run (``correlated``), its angle has estimated ``θ - δ``, so the
        true angle is that plus ``δ`` (``P_θθ += σ²``, ``P_θδ = σ²``)."""
        var = self.settings.mounting_hinge_std_rad**2
        if var == 0.0:
            return
        h = _HINGE_ROTATION
        carried = np.einsum("i,...ij,j->...", h, P[..., GA, GA], h)
        take = (carried < 1e-3 * var)[..., None, None]
        add = np.zeros(P.shape[-2:])
        add[GA, GA] = 2.0 * var * np.outer(h, h)
        if correlated:
            add[TH, TH] = var
            add[TH, GA] = add[GA, TH] = np.sqrt(2.0) * var * h
        P += np.where(take, add, 0.0)

    def hand_tracked(self, tracked: bool) -> None:
        self._hand_untracked = not tracked

    def reference_lost(self, duration_s: float) -> None:
        if self._state is not None:
            self._state["P"][..., 0, 0] += lost_optics_variance(duration_s, self.settings.lost_optics_drift_rad_s)

    def _step_reference(self, state, dt, gyr, acc, hand):
        """One sample in numpy (the reference the kernel is tested equal to)."""
        s = self.settings
        x, P, rate_meas, rate, prev_rate, P_pred = self._predict_reference(state, dt, gyr, hand)
        theta_pred = x[..., TH]
        force, u, mu, sigma, acc_sat = self._measure_reference(dt, gyr, acc, hand, theta_pred, rate, prev_rate)
        c, sn = np.cos(theta_pred), np.sin(theta_pred)
        uy, uz = u[..., 1], u[..., 2]
        v = np.stack([u[..., 0], c * uy + sn * uz, -sn * uy + c * uz], axis=-1)        # R_x(θ)ᵀ u
        dv = np.stack([np.zeros_like(uy), -sn * uy + c * uz, -c * uy - sn * uz], axis=-1)
        gmap = np.eye(3) + x[..., GA].reshape(x.shape[:-1] + (3, 3))
        predicted = np.einsum("...ij,...j->...i", gmap, v) + x[..., BA]
        y = force - predicted
        H = np.zeros(rate.shape + (3, N_STATE))
        H[..., :, TH] = np.einsum("...ij,...j->...i", gmap, dv)
        H[..., :, BA] = np.eye(3)
        for i in range(3):
            H[..., i, GA_START + 3 * i:GA_START + 3 * i + 3] = v
        # the optical fit's predicted lag error (``The optics' acceleration``): its change over one lag,
        # â - ā, read as the accelerometer reads the hand's acceleration, R = σ² I + e eᵀ
        smoothed = np.asarray(state.get("hand_acc", hand.acceleration), dtype=float)
        change = hand.acceleration - smoothed if s.optical_fit_lag_s > 0.0 else np.zeros_like(smoothed)
        change = np.einsum("ji,...j->...i", self.obs.base, np.einsum("...ji,...j->...i", hand.rotation, change))
        change = change[..., None, :]
        e_v = np.stack(np.broadcast_arrays(change[..., 0], c * change[..., 1] + sn * change[..., 2],
                                           -sn * change[..., 1] + c * change[..., 2]), axis=-1)
        e = np.einsum("...ij,...j->...i", gmap, e_v)
        e = np.where(acc_sat[..., None], 0.0, e)
        R = (sigma**2)[..., None, None] * np.eye(3) + e[..., :, None] * e[..., None, :]
        P = P_pred
        if self._settings_vector[K.ST_GS_LEARN] > 0.5:
            dx, P = kalman.update(P, H, R, y)
        else:
            # the scale state held: its gain row zeroed, the Joseph form (valid for any gain)
            pht = P @ np.swapaxes(H, -1, -2)
            gain = pht @ np.linalg.inv(H @ pht + R)
            gain[..., GS, :] = 0.0
            dx = np.einsum("...ij,...j->...i", gain, y)
            i_kh = np.eye(N_STATE) - gain @ H
            P = i_kh @ P @ np.swapaxes(i_kh, -1, -2) + gain @ R @ np.swapaxes(gain, -1, -2)
        x = x + dx
        theta = x[..., TH]
        # "fast" while the accelerometer carries little weight (eq. 6 bound above g/2), else "fused"
        mode = np.where(mu > 0.5 * np.linalg.norm(self.gravity_world), MODE_FAST, MODE_FUSED).astype(np.int8)
        return {"x": x, "P": P, "rate": rate_meas, "hand_acc": self._smoothed_reference(smoothed, dt, hand)}, theta, mode

    def _smoothed_reference(self, smoothed, dt, hand):
        """ā: the optical acceleration smoothed over the fit's lag (a first-order filter)."""
        lag = self.settings.optical_fit_lag_s
        w_bar = dt / (lag + dt) if lag > 0.0 else 1.0
        return smoothed + w_bar * (hand.acceleration - smoothed)

    def _predict_reference(self, state, dt, gyr, hand):
        """The prediction of ``_step_reference``: ``(x with the predicted angle, P, measured relative
        rate, corrected rate, corrected previous rate, predicted P)``."""
        s = self.settings
        x, P = state["x"], state["P"]
        rate_meas = self.obs.relative_rate(gyr, hand)

        # predict (the offset and the scale error s_g of the hinge-axis reading g_x; the previous
        # sample's reading taken as equal)
        gx = self.obs.hinge_rate(gyr)
        corr = x[..., BG] + x[..., GS] * gx
        rate = rate_meas - corr
        prev_rate = state["rate"] - corr
        theta_pred = x[..., TH] + dt * 0.5 * (prev_rate + rate)
        x = np.concatenate([theta_pred[..., None], x[..., 1:]], axis=-1)
        F = np.broadcast_to(np.eye(N_STATE), P.shape).copy()
        F[..., TH, BG] = -dt
        # a held scale state (item 6) is taken as known: it corrects the rate but adds no uncertainty
        F[..., TH, GS] = -dt * gx if self._settings_vector[K.ST_GS_LEARN] > 0.5 else 0.0
        q_diag = np.array([s.gyro_noise_density_rad_s_rthz**2, s.gyro_bias_walk_rad_s_rts**2]
                          + [s.acc_bias_walk_m_s2_rts**2] * 3 + [0.0] * 9 + [s.gyro_scale_walk_rts**2]) * dt
        Q = np.broadcast_to(np.diag(q_diag), P.shape).copy()
        Q[..., GA, GA] = _HINGE_FREE * (s.calibration_walk_rts**2 * dt)
        # scale and cross-axis errors move the angle by a fraction of the rate; a saturated gyro
        # says only that the rate is at least its range (what it missed comes after the clipped run,
        # reconstructed by the pipeline to within about clipped_rate_std_rad_s per sample)
        gyr_norm = np.linalg.norm(gyr, axis=-1)
        gyr_sat = np.any(np.abs(gyr) >= s.gyro_range_rad_s * (1.0 - 1e-3), axis=-1)
        Q[..., TH, TH] += (dt * (s.gyro_scale_uncertainty * gyr_norm + np.where(gyr_sat, s.clipped_rate_std_rad_s, 0.0))) ** 2
        return x, P, rate_meas, rate, prev_rate, kalman.predict(P, F, Q)

    def _measure_reference(self, dt, gyr, acc, hand, theta_pred, rate, prev_rate):
        """The accelerometer's model in ``_step_reference``: ``(force in the phalanx frame, reference
        force u, eq. 6 bound, noise std σ, clipped)``."""
        s = self.settings
        force = self.obs.phalanx_force(acc)
        gyr_sat = np.any(np.abs(gyr) >= s.gyro_range_rad_s * (1.0 - 1e-3), axis=-1)
        # accelerometer through the chain model (both sensors' angles and corrected rates), read through
        # its linear map: f = (I + G) R_x(θ)ᵀ u + b_a
        rate_change = self.obs.rate_change(rate, prev_rate, dt)
        theta_all, rate_all, rc_all = self.obs.chain(self.closure, theta_pred, rate, rate_change)
        u = self.obs.reference_force(hand, theta_all, self.gravity_world, rate_all, rc_all)
        mu = self.obs.acceleration_bound(self.closure, rate, rate_change)
        force_norm = np.linalg.norm(force, axis=-1)
        sigma = np.sqrt(s.acc_noise_m_s2**2 + (s.kinematic_uncertainty * mu) ** 2 + (s.acc_scale_uncertainty * force_norm) ** 2
                        + (s.untracked_acc_noise_m_s2 if getattr(self, "_hand_untracked", False) else 0.0) ** 2)
        # a clipped accelerometer carries no usable direction, nor does any sensor of the finger
        # while one of its gyros is clipped: the chain's kinematic terms take every sensor's rate and
        # rate change, so they are unknown for all of them: no update
        acc_sat = np.any(np.abs(acc) >= s.acc_range_m_s2 * (1.0 - 1e-3), axis=-1) | np.any(gyr_sat, axis=-1, keepdims=True)
        sigma = np.where(acc_sat, 1e6, sigma)
        return force, u, mu, sigma, acc_sat

    def _joint_step_reference(self, dt, gyr, acc, hand, together: "ChainHand", s_off: int) -> tuple:
        """One sample of this finger (no batch) with the hand's shared acceleration error ``δ`` in numpy,
        the reference ``chain_kernel._joint_update`` is tested equal to: the state (views into
        ``together``'s stacked arrays), ``δ``, ``P_δ`` and every sensor's ``C_l = P_{x_l δ}`` updated in
        place. Sensor after sensor, each accelerometer ``f = h(x_k) + M δ`` updates ``[x_k, δ]`` and moves
        every other sensor of the hand by its correlation with ``δ`` (``K_l = C_l Mᵀ S⁻¹``); the cross
        terms between two sensors' states are dropped, as between separate filters, so another
        sensor's own covariance is not reduced (that would count the same information again). The
        general covariance update ``P - K (PHᵀ)ᵀ - PHᵀ Kᵀ + K S Kᵀ`` holds for the held scale state's
        zeroed gain. Returns the sensors' angles and mode codes, as ``_step_reference``."""
        state = self._state
        x, P = state["x"], state["P"]
        dl0 = together._dl.copy()
        hand_d = replace(hand, acceleration=hand.acceleration + dl0)
        x_pred, _, rate_meas, rate, prev_rate, P_pred = self._predict_reference(state, dt, gyr, hand)
        th = x_pred[:, TH].copy()
        force, u, mu, sigma, _ = self._measure_reference(dt, gyr, acc, hand_d, th, rate, prev_rate)
        learn = self._settings_vector[K.ST_GS_LEARN] > 0.5
        fs = dt * self.obs.hinge_rate(gyr) if learn else np.zeros(len(th))
        to_base = self.obs.base.T @ hand.rotation.T                   # R_Bᵀ R_Mᵀ
        cx, x_all, ns = together._cx, together._x, len(th)
        for k in range(ns):
            g = s_off + k
            cx[g, TH] = cx[g, TH] - dt * cx[g, BG] - fs[k] * cx[g, GS]
            c, sn = np.cos(th[k]), np.sin(th[k])
            rx_t = np.array([[1.0, 0.0, 0.0], [0.0, c, sn], [0.0, -sn, c]])
            gmap = np.eye(3) + x[k, GA].reshape(3, 3)
            v, dv = rx_t @ u[k], np.array([0.0, -sn * u[k, 1] + c * u[k, 2], -c * u[k, 1] - sn * u[k, 2]])
            m = gmap @ rx_t @ to_base
            y = force[k] - (gmap @ v + x[k, BA]) - m @ (together._dl - dl0)
            H = np.zeros((3, N_STATE))
            H[:, TH] = gmap @ dv
            H[:, BA] = np.eye(3)
            for i in range(3):
                H[i, GA_START + 3 * i:GA_START + 3 * i + 3] = v
            pk, ck, pd = P_pred[k], cx[g].copy(), together._pd.copy()
            pht = pk @ H.T + ck @ m.T
            phd = ck.T @ H.T + pd @ m.T
            S = H @ pht + m @ phd + sigma[k] ** 2 * np.eye(3)
            s_inv = np.linalg.inv(S)
            gain, gain_d = pht @ s_inv, phd @ s_inv
            if not learn:
                gain[GS] = 0.0
            for lo in range(cx.shape[0]):
                if lo == g:
                    continue
                phl = cx[lo] @ m.T
                gain_l = phl @ s_inv
                gain_l[GS] = 0.0
                cx[lo] = cx[lo] - gain_l @ phd.T - phl @ gain_d.T + gain_l @ S @ gain_d.T
                dx = gain_l @ y
                if s_off <= lo < s_off + ns and lo - s_off > k:
                    # not updated yet this tick: its correction is of the state before the prediction,
                    # so the predicted angle moves by F dx (θ ← θ - dt b_g - dt g_x s_g)
                    th[lo - s_off] += dx[TH] - dt * dx[BG] - fs[lo - s_off] * dx[GS]
                    x_all[lo, 1:] += dx[1:]
                else:
                    x_all[lo] += dx
            P[k] = pk - gain @ pht.T - pht @ gain.T + gain @ S @ gain.T
            cx[g] = ck - gain @ phd.T - pht @ gain_d.T + gain @ S @ gain_d.T
            together._pd[:] = pd - gain_d @ phd.T - phd @ gain_d.T + gain_d @ S @ gain_d.T
            dx = gain @ y
            x[k, 1:] += dx[1:]
            x[k, TH] = th[k] + dx[TH]
            together._dl += gain_d @ y
        state["rate"][:] = rate_meas
        state["hand_acc"][:] = self._smoothed_reference(state["hand_acc"], dt, hand)
        return x[:, TH].copy(), np.where(mu > 0.5 * np.linalg.norm(self.gravity_world), MODE_FAST, MODE_FUSED).astype(np.int8)


class ChainHand:
    """The fingers of one hand that run ``chain``'s compiled kernel, advanced together by one kernel
    call per tick (``chain_kernel.run_hand``) instead of one call per finger: the same arithmetic per
    finger, so the same numbers as ``update`` on each (``tests/test_chain_kernel.py``).

    The fingers' states live in stacked arrays kept here; each estimator's state holds views of its
    rows, so the estimator stays whole (``inherit``, ``reference_lost``, a later ``update`` of its own
    read and write the same numbers). An estimator whose state was replaced since the last tick (a
    ``known_configuration``, a rebuild) is stacked again before the call."""

    def __init__(self):
        self._estimators: list[Chain] = []
        self._states: list[dict] = []
        self._dl: np.ndarray | None = None
        self._t_dl: float | None = None     # the time δ was last advanced to
        self.cross_offsets: np.ndarray | None = None
        """Each stacked sensor's gyro cross-axis offsets ``(b_y, b_z)`` (S, 2), rad/s, in the frame of the reading
        this call gets (the pipeline's corrected reading turned by the mounting), as
        the pipeline's flexion-axis fit estimates them (``HandMountings.cross_offsets``; it sets them where
        ``gyro_angle_cross_offsets``), taken off the cross axes' reading for the gyro's angle; None (or
        another shape): none taken off."""
        self._no_offsets = np.zeros((0, 2))
        self._untracked: tuple[list, np.ndarray] | None = None   # the estimators' untracked flags, as a list and an array
        self._run_ws: tuple | None = None   # ``advance_run``'s arrays for the stack as it is (``_run_arrays``)

    @staticmethod
    def takes(estimator, t: float) -> bool:
        """Whether ``estimator`` can be advanced to ``t`` here: a started compiled ``chain`` of one
        finger (no batch) whose last sample is before ``t``."""
        return (type(estimator) is Chain and estimator._compiled and not estimator.batch_shape
                and estimator._state is not None and t > estimator._t_last)

    def _stack(self, estimators: list[Chain], hand_acc) -> None:
        states = [e._state for e in estimators]
        ns = [e.n_sensors for e in estimators]
        nph = [e.geom.n_phalanges for e in estimators]
        sensor_start = np.concatenate([[0], np.cumsum(ns)]).astype(np.int64)
        phalanx_start = np.concatenate([[0], np.cumsum(nph)]).astype(np.int64)
        geo = [e._geometry_vector for e in estimators]
        self._x = np.ascontiguousarray(np.concatenate([np.reshape(s["x"], (-1, N_STATE)) for s in states]), dtype=float)
        self._p = np.ascontiguousarray(np.concatenate([np.reshape(s["P"], (-1, N_STATE, N_STATE)) for s in states]),
                                       dtype=float)
        self._rate = np.ascontiguousarray(np.concatenate([np.reshape(s["rate"], (-1,)) for s in states]), dtype=float)
        self._hand_acc = np.array([s["hand_acc"] if s.get("hand_acc") is not None else hand_acc for s in states], dtype=float)
        self._st = np.ascontiguousarray([e._settings_vector for e in estimators], dtype=float)
        self._geo = np.ascontiguousarray(np.concatenate(geo), dtype=float)
        self._geo_start = np.concatenate([[0], np.cumsum([len(g) for g in geo])]).astype(np.int64)
        self._sensor_start, self._phalanx_start = sensor_start, phalanx_start
        self._starts = phalanx_start.tolist(), sensor_start.tolist()       # as ``advance`` returns them
        self._theta = np.empty(int(sensor_start[-1]))
        self._phal = np.empty(int(phalanx_start[-1]))
        self._mode = np.empty(int(sensor_start[-1]), dtype=np.int8)
        self._gyr, self._acc = np.empty((int(sensor_start[-1]), 3)), np.empty((int(sensor_start[-1]), 3))
        # the hand's shared acceleration error δ ("The optics' acceleration" in the module docstring):
        # kept across a restack (a property of the optics, not of the filters: ``advance`` decays it
        # over the time since it was last advanced), its cross-covariances with the restacked states
        # start at 0; it restarts from its prior when its settings changed
        s = estimators[0].settings
        on = s.optical_fit_lag_s > 0.0 and (s.hand_acc_error_scale > 0.0 or s.hand_acc_error_floor_m_s2 > 0.0)
        # the time constant, scale and floor, and (set by each ``advance``) the time δ decays over
        jp = np.array([s.optical_fit_lag_s if on else 0.0, s.hand_acc_error_scale, s.hand_acc_error_floor_m_s2, 0.0])
        self._cx = np.zeros((int(sensor_start[-1]), N_STATE, 3))
        self._pd0 = np.eye(3) * s.hand_acc_error_floor_m_s2**2
        if self._dl is None or not np.array_equal(jp[:3], self._jp[:3]):
            self._dl = np.zeros(3)
            self._pd = self._pd0.copy()
        self._jp = jp
        for f, e in enumerate(estimators):
            s0, s1 = sensor_start[f], sensor_start[f + 1]
            e._state = {"x": self._x[s0:s1], "P": self._p[s0:s1], "rate": self._rate[s0:s1], "hand_acc": self._hand_acc[f]}
        self._stack_holds(estimators)
        # each sensor's mounting (sensor -> phalanx) and its finger's base frame, for the gyro's angle
        self._mount = np.concatenate([e.obs.mount for e in estimators])
        self._base_cat = np.concatenate([np.tile(e.obs.base, e.n_sensors) for e in estimators], axis=1)   # (3, 3 S)
        self._estimators = list(estimators)
        self._states = [e._state for e in estimators]

    def _stack_holds(self, estimators: list[Chain]) -> None:
        """The fingers' logs for a reference pose's hold in one hand log the kernel advances (``HoldLog``'s
        arrays, tick by finger and tick by sensor): each finger's history so far copied in, its
        ``HoldLog`` then made of views of its columns. The hand's log has the fingers' largest capacity (every
        finger's is ``HoldLog``'s default: a finger made with a smaller one would halve later here than alone)."""
        starts = self._starts[1]
        cap = max(e._hold.capacity for e in estimators)
        self._log_t = np.empty((cap, len(estimators)))
        self._log_r = np.zeros((cap, starts[-1]))
        self._log_g = np.zeros((cap, starts[-1], 3))
        self._log_n = np.zeros(len(estimators), dtype=np.int64)
        for f, e in enumerate(estimators):
            s0, s1 = starts[f], starts[f + 1]
            old, kept = e._hold, min(e._hold._n, cap)
            n0 = old._n - kept
            self._log_t[:kept, f] = old._t[n0:n0 + kept]
            self._log_r[:kept, s0:s1] = old._r[n0:n0 + kept]
            self._log_g[:kept, s0:s1] = old._g[n0:n0 + kept]
            self._log_n[f] = kept
            e._hold = HoldLog(s1 - s0, arrays=(self._log_t[:, f], self._log_r[:, s0:s1], self._log_g[:, s0:s1],
                                               self._log_n[f:f + 1]))

    def _stacked(self, estimators: list[Chain]) -> bool:
        # the same estimators (a list compares its items by identity first; ``Chain`` has no ``__eq__``),
        # each still holding the state stacked here
        return estimators == self._estimators and all(map(_is, [e._state for e in estimators], self._states))

    def advance(self, t: float, estimators: list[Chain], gyr: np.ndarray, acc: np.ndarray, hand) -> tuple:
        """Every estimator (each ``takes`` it) one sample further to ``t``: ``gyr`` and ``acc`` (S, 3) are
        their sensors' samples, finger after finger in each one's sensor order. Returns the joint
        angles of all of them (one flat array, finger after finger), the mode codes (one list, sensor
        after sensor) and the finger boundaries in both (``phalanx_start``, ``sensor_start``: the same two lists
        while the same fingers are stacked; never to be modified)."""
        self._stack_if_new(estimators, hand)
        dts, untracked, phi = self._begin(t, estimators)
        K.run_hand(self._x, self._p, self._rate, self._hand_acc, dts, np.ascontiguousarray(gyr, dtype=float),
                   np.ascontiguousarray(acc, dtype=float), hand.flat, self._st, self._geo, untracked,
                   self._sensor_start, self._phalanx_start, self._geo_start, self._theta, phi, self._phal, self._mode,
                   self._cx, self._dl, self._pd, self._jp, t, self._log_t, self._log_r, self._log_g, self._log_n,
                   self._cross_offsets())
        return self._end(t, estimators, phi)

    def advance_in(self, kernel, head: tuple, t: float, estimators: list[Chain], hand, rows: int):
        """``advance`` with ``run_hand`` called inside ``kernel`` (``pipeline.tick_kernel.steady_tick``) as
        ``kernel(*head, *run_hand's arguments)``: ``kernel`` writes ``rows`` sensors' samples into the gyro
        and accelerometer arrays it gets (kept here) before it calls ``run_hand`` with them, and may write
        as many rows of ``cross_offsets`` first. Returns what ``advance`` returns, then the kernel's result.
        Raises ``RuntimeError`` unless ``rows`` is the number of sensors stacked and ``cross_offsets`` (if
        set) is the array the kernel gets: a compiled kernel checks no bounds, and ``cross_offsets`` of
        another shape would have it write into the shared zeros (or past them). The refusal comes before
        any state is advanced (δ's clock included), and is a defect of the caller, not of the readings: not a
        ``ValueError``, which the service answers as the client's bad input."""
        self._stack_if_new(estimators, hand)
        offsets = self._cross_offsets()
        if rows != self._gyr.shape[0] or (self.cross_offsets is not None and offsets is not self.cross_offsets):
            shape = None if self.cross_offsets is None else np.shape(self.cross_offsets)
            raise RuntimeError(f"the kernel would write {rows} sensors' rows: {self._gyr.shape[0]} are stacked "
                               f"(cross_offsets {shape})")
        dts, untracked, phi = self._begin(t, estimators)
        out = kernel(*head, self._x, self._p, self._rate, self._hand_acc, dts, self._gyr, self._acc, hand.flat,
                     self._st, self._geo, untracked, self._sensor_start, self._phalanx_start, self._geo_start,
                     self._theta, phi, self._phal, self._mode, self._cx, self._dl, self._pd, self._jp, t,
                     self._log_t, self._log_r, self._log_g, self._log_n, offsets)
        return (*self._end(t, estimators, phi), out)

    def advance_run(self, kernel, head: tuple, ts: list, estimators: list[Chain], rows: int, at_ws: tuple):
        """``advance_in`` over the ticks ``ts`` (in order) in one call of ``kernel``
        (``pipeline.tick_kernel.steady_run_in``) as ``kernel(*head, δ's step to ts[0], run_hand's arguments without
        the hand, the angles and the time, run_hand's work arrays, at_ws)``, which advances the estimators tick after
        tick and returns how many ticks it did (it may leave the rest undone, with no state moved). ``at_ws``: the
        optics' work arrays (``OpticalTrack.run_scratch``); ``run_hand``'s (``chain_kernel.hand_scratch``) are kept
        here per stack (``run_hand_in`` clears them first). The estimators must be
        stacked already (their hand acceleration is not known here). Returns that count and, when it is not
        0, the last tick's mode codes and the finger boundaries (as ``advance``); None, with no state moved,
        when the estimators are not stacked or δ's clock steps back at ``ts[0]`` (the tick by tick path
        restarts δ then). Refuses as ``advance_in`` does."""
        if not self._stacked(estimators):
            return None
        offsets = self._cross_offsets()
        if rows != self._gyr.shape[0] or (self.cross_offsets is not None and offsets is not self.cross_offsets):
            shape = None if self.cross_offsets is None else np.shape(self.cross_offsets)
            raise RuntimeError(f"the kernel would write {rows} sensors' rows: {self._gyr.shape[0]} are stacked "
                               f"(cross_offsets {shape})")
        t = ts[0]
        kept = self._run_ws
        if kept is None or kept[0] is not self._sensor_start:
            kept = self._run_ws = self._run_arrays()
        # the fingers' steps to ``t`` (``_begin``'s) into the stack's array (the kernel only reads them before it
        # writes its own): most often every finger was last advanced at the same time, one step for all
        dts, t_last = kept[1], estimators[0]._t_last
        for e in estimators:
            if e._t_last != t_last:
                dts[:] = [t - e._t_last for e in estimators]
                break
        else:
            dts.fill(t - t_last)
        gap = float(dts.max()) if self._t_dl is None else t - self._t_dl     # ``_delta_step``
        if gap < 0.0:
            return None
        flags = [e._hand_untracked for e in estimators]
        untracked = self._untracked
        if untracked is None or untracked[0] != flags:    # (the kernels only read it: one array while the flags stay, ``_begin``)
            untracked = self._untracked = (flags, np.array(flags))
        done = kernel(*head, gap, *kept[2], untracked[1], *kept[3], offsets, kept[4], at_ws)
        if not done:
            return 0, None, None, None
        last = ts[done - 1]
        self._t_dl = last
        for e in estimators:
            e._t_last = last
        return done, self._mode.tolist(), *self._starts

    def _run_arrays(self) -> tuple:
        """What ``advance_run`` hands its kernel for the stack as it is, kept from one call to the next while
        the same estimators are stacked (``_stack`` makes new arrays): the stack's ``sensor_start`` (the key), the
        fingers' steps' array, ``run_hand``'s arguments before and after the untracked flags (without the hand,
        the angles and the time; the steps' array among them) and its work arrays (``chain_kernel.hand_scratch``)."""
        dts = np.empty(len(self._estimators))
        return (self._sensor_start, dts,
                (self._x, self._p, self._rate, self._hand_acc, dts, self._gyr, self._acc, self._st, self._geo),
                (self._sensor_start, self._phalanx_start, self._geo_start, self._theta, self._phal, self._mode, self._cx,
                 self._dl, self._pd, self._jp, self._log_t, self._log_r, self._log_g, self._log_n),
                K.hand_scratch(self._sensor_start, self._phalanx_start))

    def _stack_if_new(self, estimators: list[Chain], hand) -> None:
        """The estimators' states stacked here, unless they are already (``advance``'s first step)."""
        if not self._stacked(estimators):
            self._stack(estimators, hand.acceleration)

    def _begin(self, t: float, estimators: list[Chain]) -> tuple:
        """``advance``'s steps before the kernel, on the stacked estimators: their steps ``dts``, δ's step,
        which are untracked, and the array of the joint angles the kernel writes."""
        dts = np.array([t - e._t_last for e in estimators])
        self._jp[3] = self._delta_step(t, dts)
        flags = [e._hand_untracked for e in estimators]
        kept = self._untracked
        if kept is None or kept[0] != flags:    # (the kernels only read it: one array while the flags stay)
            kept = self._untracked = (flags, np.array(flags))
        return dts, kept[1], np.empty(self._phal.shape[0])

    def _end(self, t: float, estimators: list[Chain], phi: np.ndarray) -> tuple:
        """``advance``'s steps after the kernel (the mode codes read out before the next call writes them)."""
        for e in estimators:
            e._t_last = t
        return phi, self._mode.tolist(), *self._starts

    def _gyro_angles(self, gyr: np.ndarray, hand, dts: np.ndarray, untracked: np.ndarray) -> None:
        """(``advance_reference``; the kernel's ``_gyro_angles`` in ``advance``.) Each sensor's angle as its gyro's cross axes tell it, a measurement after the tick's update ("The
        hand's rotation seen from the phalanx" in the module docstring): the hand's rate in the finger base
        frame ``w`` (optics) seen from the phalanx at angle ``θ`` is ``(w_y, w_z)`` turned by ``-θ``, which the
        gyro reads as ``(f_y, f_z)`` (phalanx frame), so ``atan2(w_z, w_y) - atan2(f_z, f_y) = θ - δ_m`` (with
        the mounting turn about the hinge axis ``δ_m``, as the accelerometer sees it). Taken while the hand
        turns across the hinge axis (``gyro_angle_min_rate_rad_s``), the finger is nearly still on it
        (``gyro_angle_max_flexion_rad_s``), the optics track and no gyro of the finger is clipped; its std is
        ``gyro_angle_rate_std_rad_s`` / |(w_y, w_z)|, its variance counted once per optical fit window (the
        rate's error is correlated over it: ``gyro_angle_window_s / dt`` ticks). It updates the sensor's own
        states and their covariance with δ (``C_k``); δ and the other sensors take no gain from it."""
        s = self._estimators[0].settings
        if s.gyro_angle_rate_std_rad_s <= 0.0:
            return
        w = (hand.angular_velocity @ hand.rotation @ self._base_cat).reshape(-1, 3)    # R_Bᵀ R_Mᵀ ω per sensor
        w_yz2 = w[:, 1] ** 2 + w[:, 2] ** 2
        turning = w_yz2 > s.gyro_angle_min_rate_rad_s ** 2
        if not turning.any():
            return
        starts = self._sensor_start
        counts = np.diff(starts)
        clipped = (np.abs(gyr) >= s.gyro_range_rad_s * (1.0 - 1e-3)).any(axis=1)
        finger_ok = ~untracked & (dts > 0.0) & ~np.logical_or.reduceat(clipped, starts[:-1])
        i = np.flatnonzero(turning & np.repeat(finger_ok, counts))
        if not i.size:
            return
        f = np.matmul(self._mount[i], gyr[i, :, None])[:, :, 0]                     # phalanx frame
        b = self._cross_offsets()[i]
        f[:, 1:] -= b[:, :2]
        w = w[i]
        z = np.arctan2(w[:, 2], w[:, 1]) - np.arctan2(f[:, 2], f[:, 1])
        y = np.mod(z - self._x[i] @ _GYRO_ANGLE_H + np.pi, 2.0 * np.pi) - np.pi
        take = (np.abs(f[:, 0] - w[:, 0]) < s.gyro_angle_max_flexion_rad_s) & (np.abs(y) < _GYRO_ANGLE_GATE_RAD)
        i, y = i[take], y[take]
        if not i.size:
            return
        # the rate's error and the offsets' own (their variance, a third column of cross_offsets if there)
        var = s.gyro_angle_rate_std_rad_s ** 2 + (b[take, 2] if b.shape[1] > 2 else 0.0)
        r = var / w_yz2[i] * s.gyro_angle_window_s / np.repeat(dts, counts)[i]
        ph = self._p[i] @ _GYRO_ANGLE_H
        s_cov = ph @ _GYRO_ANGLE_H + r
        gain = ph / s_cov[:, None]
        held = np.repeat(self._st[:, K.ST_GS_LEARN] <= 0.5, counts)[i]     # a finger on a fallback holds s_g
        gain[held, GS] = 0.0
        hc = _GYRO_ANGLE_H @ self._cx[i]
        self._x[i] += gain * y[:, None]
        p = self._p[i] - gain[:, :, None] * ph[:, None, :]
        if held.any():
            # the gain's scale row zeroed: the general form P - K phᵀ - ph Kᵀ + S K Kᵀ (valid for any gain)
            g, q = gain[held], ph[held]
            p[held] = self._p[i][held] - g[:, :, None] * q[:, None, :] - q[:, :, None] * g[:, None, :] \
                + s_cov[held, None, None] * g[:, :, None] * g[:, None, :]
        self._p[i] = 0.5 * (p + p.transpose(0, 2, 1))
        self._cx[i] -= gain[:, :, None] * hc[:, None, :]

    def _cross_offsets(self) -> np.ndarray:
        """``cross_offsets`` where it fits the stacked sensors, else zeros."""
        n = self._starts[1][-1]
        b = self.cross_offsets
        if b is not None and b.ndim == 2 and b.shape[0] == n and b.shape[1] in (2, 3):
            return b
        if self._no_offsets.shape[0] != n:
            self._no_offsets = np.zeros((n, 2))
        return self._no_offsets

    def _log_holds(self, t: float, dts: np.ndarray, gyr: np.ndarray) -> None:
        """Each estimator's running integrals for a reference pose's hold (``HoldLog``), as its own
        ``_advance`` keeps them (``advance_reference``; ``advance``'s kernel call does the same)."""
        starts = self._starts[1]
        for f, e in enumerate(self._estimators):
            s0, s1 = starts[f], starts[f + 1]
            e._hold.add(t, float(dts[f]), self._rate[s0:s1], gyr[s0:s1])

    def _delta_step(self, t: float, dts: np.ndarray) -> float:
        """The time δ decays over in this tick: since it was last advanced, not the fingers' own step (a
        finger rebuilt, or every finger of the hand after a calibration or an estimator switch, starts
        its step anew while δ was last advanced before); the fingers' step the first time. A time
        before that (the source's clock stepped back) restarts δ from its prior."""
        gap = float(dts.max()) if self._t_dl is None else t - self._t_dl
        self._t_dl = t
        if gap < 0.0:
            self._dl[:], self._pd[:], self._cx[:], gap = 0.0, self._pd0, 0.0, 0.0
        return gap

    def _keep_shared_error_finite(self) -> None:
        """(``advance_reference``; ``advance``'s kernel call does the same.) A finger whose filter diverged in this tick (a non-finite state; ``HandSession._reset_finger``
        restarts it) may have carried the non-finite value into the shared error δ through its update.
        Kept, δ would then make every finger's estimate non-finite on every later tick (each one reset
        again and again). δ restarts from its prior instead, its cross-covariances at 0: at most the
        fingers updated after the diverged one in this tick lose their estimate with it."""
        if not math.isfinite(sum(self._dl.tolist()) + sum(self._pd.ravel().tolist())):
            self._dl[:], self._pd[:], self._cx[:] = 0.0, self._pd0, 0.0

    def advance_reference(self, t: float, estimators: list[Chain], gyr: np.ndarray, acc: np.ndarray, hand) -> tuple:
        """``advance`` in numpy (the same returns): the reference the kernel's shared hand acceleration
        error is tested equal to (``tests/test_chain_kernel.py``). ``δ`` is a first-order Gauss-Markov
        process of time constant ``optical_fit_lag_s`` whose std is ``hand_acc_error_scale`` |â - ā| +
        the floor (in quadrature); while the optics are lost it restarts at 0."""
        if not self._stacked(estimators):
            self._stack(estimators, hand.acceleration)
        dts = np.array([t - e._t_last for e in estimators])
        tau, scale, floor = self._jp[:3]
        step = self._delta_step(t, dts)
        if tau > 0.0:
            q = scale**2 * float(np.sum((hand.acceleration - self._hand_acc[0]) ** 2)) + floor**2
            if any(e._hand_untracked for e in estimators):
                self._dl[:], self._pd[:], self._cx[:] = 0.0, q * np.eye(3), 0.0
            else:
                decay = np.exp(-step / tau)
                self._dl *= decay
                self._pd[:] = decay**2 * self._pd + (1.0 - decay**2) * q * np.eye(3)
                self._cx *= decay
        phi, modes = [], []
        for f, e in enumerate(estimators):
            rows = slice(self._sensor_start[f], self._sensor_start[f + 1])
            if tau > 0.0 and not e._hand_untracked:
                theta, mode = e._joint_step_reference(dts[f], gyr[rows], acc[rows], hand, self, int(self._sensor_start[f]))
            else:
                new, theta, mode = e._step_reference(e._state, dts[f], gyr[rows], acc[rows], hand)
                for key in ("x", "P", "rate", "hand_acc"):
                    e._state[key][...] = new[key]
            e._t_last = t
            phi.append(e.closure.joint_angles(e._branch(theta)))
            modes += mode.tolist()
        self._log_holds(t, dts, gyr)
        self._keep_shared_error_finite()
        self._gyro_angles(gyr, hand, dts, np.array([e._hand_untracked for e in estimators]))
        return np.concatenate(phi), modes, *self._starts
