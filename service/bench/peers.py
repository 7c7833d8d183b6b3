"""Our orientation cores against the field on real data: ``fingertrack bench peers --data DIR [--quick] --out DIR``.

Data: BROAD (Berlin Robust Orientation estimation Assessment Dataset, CC-BY-4.0; Laidig et al.
2021) trials, ``.mat`` files with ``imu_gyr`` (rad/s), ``imu_acc`` (m/s²), ``opt_quat`` (w,x,y,z,
IMU to an east-north-up frame; NaN where the markers were lost), ``movement`` and ``sampling_rate``.

Metric: the inclination error, the angle between the true and the estimated gravity direction in the
sensor frame, RMS over the movement phases (samples with ground truth). Heading is not scored.

Methods: ours (``fingertrack-inertial``, the inertial-frame core with gyro bias and scale-factor
estimation, ``rigid/inertial.py``; ``fingertrack-madgwick``, ``fingertrack-ekf``) IMU-only and with a second reference
vector from the optical data (``+optical``: the east axis in sensor coordinates from the optical
ground truth, which is what a finger filter gets from the optical metacarpus pose; it carries
information the 6D peers do not have). Peers with their documented defaults: ``vqf``, ``vqf-basic``,
``vqf-offline`` (VQF, Laidig & Seel 2023), ``ahrs-madgwick``, ``ahrs-ekf`` (the ``ahrs`` package),
``imufusion`` (Fusion AHRS, no magnetometer). Our Madgwick and EKF start from the first
accelerometer sample (tilt only); the inertial core and the peers initialise themselves.

Timing, measured in the same run: microseconds per sample. Streaming = one sample per call on one
trial; batch = our filters over all trials at once (leading batch dimension; the shorter trials are
padded to the longest, and the time of the batch call is divided by the sensor-samples it processed),
the peers' batch entry points where they have one, per trial. The summary adds our batch call on one
record alone, the case that compares one-to-one with a peer's batch call.
"""
from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np

from ..estimators.rigid.filters import EkfImu, InertialImu, MadgwickImu
from ..model import quaternion as quat
from ..model.quaternion import tilt_from_accelerometer

UP_ENU = np.array([0.0, 0.0, 1.0])
EAST_ENU = np.array([1.0, 0.0, 0.0])
QUICK_N = 20000
"""--quick: the first 20000 samples (70 s; movement starts after 30-45 s) of the first three trials."""
OUR_BETA = 0.041
"""Madgwick gain for BROAD (Madgwick's recommendation for MARG sensors, as the comparison paper used)."""


def load_trial(path: str | Path) -> dict:
    from scipy.io import loadmat
    path = Path(path)
    d = loadmat(path)
    for key in ("imu_gyr", "imu_acc", "opt_quat", "sampling_rate"):
        if key not in d:
            raise ValueError(f"{path}: not a BROAD trial, it has no {key!r}")
    return {"name": path.stem, "gyr": np.asarray(d["imu_gyr"], float), "acc": np.asarray(d["imu_acc"], float),
            "quat": np.asarray(d["opt_quat"], float), "rate": float(np.squeeze(d["sampling_rate"])),
            "movement": np.asarray(d["movement"], bool).ravel() if "movement" in d else np.ones(len(d["imu_gyr"]), bool)}


def inclination_rmse_deg(q_est_wxyz: np.ndarray, q_true_wxyz: np.ndarray, mask: np.ndarray) -> float:
    """RMS over ``mask`` of the angle between true and estimated gravity direction in the sensor frame."""
    def up_in_sensor(q):
        return np.einsum("nji,j->ni", quat.to_matrix(quat.normalize(q)), UP_ENU)
    ok = mask & np.all(np.isfinite(q_true_wxyz), axis=1) & np.all(np.isfinite(q_est_wxyz), axis=1)
    a, b = up_in_sensor(q_est_wxyz[ok]), up_in_sensor(q_true_wxyz[ok])
    ang = np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))
    return float(np.sqrt(np.mean(ang**2)))


def _east_in_sensor(q_true: np.ndarray) -> np.ndarray:
    """The world east axis in sensor coordinates from the optical quaternions (NaN where they are)."""
    ok = np.all(np.isfinite(q_true), axis=1)
    q = np.where(ok[:, None], q_true, np.array([1.0, 0.0, 0.0, 0.0]))
    return np.einsum("nji,j->ni", quat.to_matrix(quat.normalize(q)), EAST_ENU) * np.where(ok, 1.0, np.nan)[:, None]


def _make(kind: str, dt: float, batch_shape=()):
    """One of our rigid cores with the bench's settings (world frame east-north-up)."""
    if kind == "madgwick":
        return MadgwickImu(beta=OUR_BETA, up=tuple(UP_ENU), batch_shape=batch_shape)
    if kind == "ekf":
        return EkfImu(up=tuple(UP_ENU), use_filterpy=False, batch_shape=batch_shape)
    if kind == "inertial":
        return InertialImu(dt, up=tuple(UP_ENU), batch_shape=batch_shape)
    raise ValueError(f"unknown core {kind!r}")


def _ours(kind: str, optical: bool, gyr, acc, q_true, dt, batch_shape=()):
    """Run our core over (N, *B, 3) arrays; returns ((N, *B, 4) quaternions [w,x,y,z], seconds spent
    in the filter's batch call alone: the inputs are prepared before the clock starts, as for the peers)."""
    f = _make(kind, dt, batch_shape)
    if kind != "inertial":          # the inertial core starts itself (it averages the first tau_acc seconds)
        f.q = tilt_from_accelerometer(acc[0], UP_ENU)
    ref_w = ref_s = None
    if optical:
        ref_s = np.stack([_east_in_sensor(q_true[:, b]) for b in range(q_true.shape[1])], axis=1) if q_true.ndim == 3 \
            else _east_in_sensor(q_true)
        ref_w = np.broadcast_to(EAST_ENU, ref_s.shape)
    t0 = time.perf_counter()
    out = f.run(gyr, acc, dt, ref_w, ref_s)
    seconds = time.perf_counter() - t0
    return quat.from_xyzw(out), seconds


def _peer(name: str, gyr, acc, rate):
    """Returns (quaternions [w,x,y,z] (N,4), batch µs/sample or None, streaming µs/sample)."""
    dt = 1.0 / rate
    n = len(gyr)
    if name.startswith("vqf"):
        from vqf import BasicVQF, VQF, offlineVQF
        g, a = np.ascontiguousarray(gyr), np.ascontiguousarray(acc)
        if name == "vqf-offline":
            t0 = time.perf_counter()
            out = offlineVQF(g, a, None, dt)
            return out["quat6D"], 1e6 * (time.perf_counter() - t0) / n, None
        cls = VQF if name == "vqf" else BasicVQF
        t0 = time.perf_counter()
        out = cls(dt).updateBatch(g, a)
        batch = 1e6 * (time.perf_counter() - t0) / n
        f = cls(dt)
        m = min(n, 20000)
        t0 = time.perf_counter()
        for k in range(m):
            f.update(g[k], a[k])
        stream = 1e6 * (time.perf_counter() - t0) / m
        return out["quat6D"], batch, stream
    if name == "imufusion":
        import imufusion
        ahrs = imufusion.Ahrs()
        if hasattr(ahrs, "set_sample_period"):
            ahrs.set_sample_period(dt)
        q = np.empty((n, 4))
        gd, ag = np.degrees(gyr), acc / 9.81          # Fusion takes deg/s and g
        t0 = time.perf_counter()
        for k in range(n):
            if hasattr(ahrs, "set_sample_period"):
                ahrs.update_no_magnetometer(gd[k], ag[k])
                q[k] = ahrs.get_quaternion()
            else:                                       # imufusion < 1.3
                ahrs.update_no_magnetometer(gd[k], ag[k], dt)
                q[k] = ahrs.quaternion.wxyz
        return q, None, 1e6 * (time.perf_counter() - t0) / n
    import ahrs as ahrs_pkg
    t0 = time.perf_counter()
    if name == "ahrs-madgwick":
        est = ahrs_pkg.filters.Madgwick(gyr=gyr, acc=acc, frequency=rate)
    else:
        est = ahrs_pkg.filters.EKF(gyr=gyr, acc=acc, frequency=rate)   # its default frame (NED) reads BROAD correctly
    return est.Q, None, 1e6 * (time.perf_counter() - t0) / n


def _streaming_us(kind: str, optical: bool, trial: dict, rate: float, sensors: int = 1, m: int = 3000) -> float:
    """µs per ``update`` call (one sample of ``sensors`` IMUs), our filter's streaming mode."""
    b = (sensors,) if sensors > 1 else ()
    f = _make(kind, 1.0 / rate, b)
    g = np.broadcast_to(trial["gyr"][:m, None], (m,) + b + (3,)) if b else trial["gyr"][:m]
    a = np.broadcast_to(trial["acc"][:m, None], (m,) + b + (3,)) if b else trial["acc"][:m]
    rs = _east_in_sensor(trial["quat"][:m])
    rs = np.broadcast_to(rs[:, None], (m,) + b + (3,)) if b else rs
    rw = np.broadcast_to(EAST_ENU, rs.shape)
    f.update(g[0], a[0], 1.0 / rate, rw[0] if optical else None, rs[0] if optical else None)   # compile / warm up
    t0 = time.perf_counter()
    for k in range(m):
        f.update(g[k], a[k], 1.0 / rate, rw[k] if optical else None, rs[k] if optical else None)
    return 1e6 * (time.perf_counter() - t0) / m


PEERS = ("vqf", "vqf-basic", "vqf-offline", "ahrs-madgwick", "ahrs-ekf", "imufusion")
OURS = [(f"fingertrack-{k}" + ("+optical" if o else ""), k, o) for k in ("inertial", "madgwick", "ekf") for o in (False, True)]


def run(data_dir: str | Path, out_dir: str | Path, quick: bool = False, progress: bool = True) -> str:
    from tqdm import tqdm

    import importlib.util

    files = sorted(Path(data_dir).glob("*.mat"))
    if not files:
        raise ValueError(f"{data_dir}: no .mat trials found")
    missing = [m for m in ("vqf", "ahrs", "imufusion") if importlib.util.find_spec(m) is None]
    if missing:
        raise ValueError(f"bench peers needs the peer libraries {missing}: pip install -e '.[peers]'")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    trials = [load_trial(f) for f in files]
    if quick:
        trials = [dict(t, gyr=t["gyr"][:QUICK_N], acc=t["acc"][:QUICK_N], quat=t["quat"][:QUICK_N], movement=t["movement"][:QUICK_N])
                  for t in trials[:3]]
    rates = {t["rate"] for t in trials}
    if len(rates) != 1:
        raise ValueError(f"trials have different sampling rates {sorted(rates)}; run them separately")
    rate = rates.pop()
    rows: list[dict] = []
    # ours: all trials at once (padded; each trial scored on its own samples)
    n_max = max(len(t["gyr"]) for t in trials)

    def pad(key, fill_last=True):
        return np.stack([np.concatenate([t[key], np.repeat(t[key][-1:], n_max - len(t[key]), axis=0)]) for t in trials], axis=1)
    gyr_b, acc_b, q_b = pad("gyr"), pad("acc"), pad("quat")
    jobs = [(label, k, o) for label, k, o in OURS] + [(p, None, None) for p in PEERS]
    # compile the numba kernels once before anything is timed (a one-time start-up cost, ~1 s cold)
    for kind in ("madgwick", "inertial"):
        _ours(kind, True, gyr_b[:2], acc_b[:2], q_b[:2], 1.0 / rate, batch_shape=(len(trials),))
    for label, kind, optical in tqdm(jobs, desc="bench peers", unit="method", disable=not progress):
        if kind is not None:
            q_all, seconds = _ours(kind, optical, gyr_b, acc_b, q_b, 1.0 / rate, batch_shape=(len(trials),))
            batch_us = 1e6 * seconds / gyr_b.shape[0] / len(trials)        # per sensor-sample processed
            stream_us = _streaming_us(kind, optical, trials[0], rate)
            for i, t in enumerate(trials):
                err = inclination_rmse_deg(q_all[: len(t["gyr"]), i], t["quat"], t["movement"])
                rows.append({"trial": t["name"], "method": label, "inclination_rmse_deg": err,
                             "us_per_sample": stream_us, "batch_us_per_sample": batch_us})
        else:
            for t in trials:
                q, batch_us, stream_us = _peer(label, t["gyr"], t["acc"], rate)
                rows.append({"trial": t["name"], "method": label,
                             "inclination_rmse_deg": inclination_rmse_deg(np.asarray(q), t["quat"], t["movement"]),
                             "us_per_sample": stream_us if stream_us is not None else float("nan"),
                             "batch_us_per_sample": batch_us if batch_us is not None else float("nan")})
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["trial", "method", "inclination_rmse_deg", "us_per_sample", "batch_us_per_sample"])
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    methods = [j[0] for j in jobs]
    hand = {k: _streaming_us(k, False, trials[0], rate, sensors=10) for k in ("inertial", "madgwick")}
    first = trials[0]
    alone = {k: 1e6 * _ours(k, False, first["gyr"], first["acc"], first["quat"], 1.0 / rate)[1] / len(first["gyr"])
             for k in ("inertial", "madgwick")}
    vqf_alone = _peer("vqf", first["gyr"], first["acc"], rate)[1]
    text = _summary(rows, methods, quick) + "\nStreaming one hand (10 IMUs) per `update` call: " + ", ".join(
        f"fingertrack-{k} {us:.2f} µs" for k, us in hand.items()) + " per call.\n" + \
        f"\nBatch on one record alone (trial {first['name']}, a single sensor, no stack to interleave): " + ", ".join(
        f"fingertrack-{k} {us:.3f} µs" for k, us in alone.items()) + f", vqf {vqf_alone:.3f} µs per sample.\n"
    (out / "summary.md").write_text(text)
    _plot(rows, methods, out / "peers.png")
    return text


def _summary(rows, methods, quick) -> str:
    trials = sorted({r["trial"] for r in rows})
    scope = f", quick: first {QUICK_N} samples of 3" if quick else ""
    lines = [f"# Orientation cores on BROAD: inclination RMSE over movement phases ({len(trials)} trials{scope})", "",
             "| method | mean inclination RMSE, deg | streaming µs/sample | batch µs/sample |", "|---|---|---|---|"]
    for m in methods:
        sel = [r for r in rows if r["method"] == m]
        mean = np.mean([r["inclination_rmse_deg"] for r in sel])
        stream, batch = (_finite_mean([r[k] for r in sel]) for k in ("us_per_sample", "batch_us_per_sample"))
        lines.append(f"| {m} | {mean:.3f} | {'-' if np.isnan(stream) else f'{stream:.2f}'} | "
                     f"{'-' if np.isnan(batch) else f'{batch:.3f}'} |")
    lines += ["", "Per trial, inclination RMSE in degrees:", "",
              "| trial | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for t in trials:
        cells = [next(r["inclination_rmse_deg"] for r in rows if r["trial"] == t and r["method"] == m) for m in methods]
        lines.append(f"| {t} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    lines += ["", "`+optical` rows use a second reference vector from the optical ground truth (information the 6D "
              "peers do not have)."]
    return "\n".join(lines) + "\n"


def _finite_mean(values) -> float:
    """Mean of the finite values, NaN when there are none (a method without that mode)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def _plot(rows, methods, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    means = [np.mean([r["inclination_rmse_deg"] for r in rows if r["method"] == m]) for m in methods]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    colors = ["tab:orange" if m.startswith("fingertrack") else "tab:blue" for m in methods]
    ax.bar(range(len(methods)), means, color=colors)
    ax.set_xticks(range(len(methods)), methods, rotation=35, ha="right")
    ax.set_ylabel("mean inclination RMSE, deg")
    ax.set_title("BROAD trials: ours (orange) and peers (blue)")
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
