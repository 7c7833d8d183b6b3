"""The paper's experiment (section 3), rerunnable: ``fingertrack bench paper [--quick] [--seeds N] --out DIR``.

Three series of sensor errors (white noise, zero offset, both) at MPU-9250 figures; grasp test
motions with ``t_m`` log-spaced from 0.1 s to 1000 s (32 of them; ``--quick``: 6 from 0.1 s to 31.6 s, one seed) and
``t_d = 0.2 s``; the index finger with the paper's sensor placement; the metacarpus pose known
exactly and still, and the true initial configuration given to every estimator, as in the paper.
The RMS error is taken over each whole motion ``[0, t_d + t_m]`` and over the three joints.

Runs are batched: all series and seeds of a group of similar durations go through an estimator at
once (the estimators broadcast over leading batch dimensions); a shorter motion in a group is
simulated holding its final pose until the group's longest ends, and only its own duration counts.
"""
from __future__ import annotations

import csv
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..estimators.base import FingerSamples
from ..estimators.registry import EstimatorSpec, make_estimator
from ..model.hand import joint_to_phalanx_angles
from ..model.kinematics import BaseMotion
from ..sim.motions import grasp_motion
from ..sim.session import SimConfig, simulate

SERIES = ("white", "offset", "both")
T_D_S = 0.2
FINGER = "index"
OURS = "chain"


@dataclass(frozen=True)
class Method:
    """A benchmark column: an estimator with settings."""

    label: str
    estimator: str
    params: tuple[tuple[str, object], ...] = ()

    def build(self, geom, theta0, batch_shape):
        return make_estimator(EstimatorSpec.of(self.estimator, dict(self.params)), geom, initial_theta=theta0,
                              batch_shape=batch_shape)


METHODS = (
    Method("vector", "vector"),
    Method("integration", "integration"),
    Method("switching", "switching"),
    Method("madgwick-0.1", "madgwick", (("beta", 0.1),)),
    Method("madgwick-0.03", "madgwick", (("beta", 0.03),)),
    Method("madgwick-0.01", "madgwick", (("beta", 0.01),)),
    Method("ekf", "ekf"),
    Method("cf", "cf"),
    Method(OURS, OURS),
)


def durations(quick: bool) -> np.ndarray:
    """Motion durations ``t_m``: 32 log-spaced from 0.1 s to 1000 s (quick: 6, 0.1 s to 31.6 s)."""
    return np.logspace(-1, 1.5, 6) if quick else np.logspace(-1, 3, 32)


def groups(t_m: np.ndarray) -> list[np.ndarray]:
    """Durations grouped by decade (everything from 100 s on in one group), so padding to a group's
    longest costs little next to the long runs, which dominate."""
    keys = np.minimum(np.floor(np.log10(t_m) + 1e-9), 2.0)
    return [t_m[keys == k] for k in np.unique(keys)]


@dataclass
class GroupData:
    t: np.ndarray
    samples: FingerSamples            # batch (N, R, S, 3) with R = len(runs)
    truth: np.ndarray                 # (N, R, 3) joint angles
    theta0: np.ndarray                # (R, 3)
    runs: list[tuple[str, float, int]]
    n_valid: np.ndarray               # (R,) samples inside each run's own motion


CHUNK_SAMPLES = 30_000_000
"""A duration group whose runs hold more samples than this is split by series (memory bound)."""


def simulate_chunk(t_ms: np.ndarray, series: tuple[str, ...], seeds: int, path: Path, rate_hz: float = 200.0) -> None:
    """Simulate some series of a duration group (every duration and seed, padded to the longest) and
    save the arrays to ``path`` (``.npz``) for the estimator jobs."""
    duration = T_D_S + float(np.max(t_ms))
    gyr, acc, truth, runs, n_valid = [], [], [], [], []
    sess = None
    for noise, t_m, seed in ((s, t, k) for s in series for t in t_ms for k in range(seeds)):
        cfg = SimConfig(motion="grasp", t_m_s=float(t_m), noise=noise, seed=seed, rate_hz=rate_hz,
                        fingers=(FINGER,), duration_s=duration, finger_motion=grasp_motion(t_m=float(t_m), t_d=T_D_S))
        sess = simulate(cfg)
        gyr.append(sess.gyr)
        acc.append(sess.acc)
        truth.append(sess.joint_angles[FINGER])
        runs.append((SERIES.index(noise), float(t_m), seed))
        n_valid.append(int(np.floor((T_D_S + t_m) * rate_hz + 1e-9)) + 1)
    if sess is None:
        raise ValueError("nothing to simulate")
    np.savez(path, t=sess.t, gyr=np.stack(gyr, axis=1), acc=np.stack(acc, axis=1), truth=np.stack(truth, axis=1),
             runs=np.array(runs), n_valid=np.array(n_valid), rotation=sess.base.rotation[0])


def load_chunk(path: Path) -> GroupData:
    z = np.load(path)
    t, truth = z["t"], z["truth"]
    n, r = truth.shape[:2]
    zeros = np.zeros((n, r, 3))
    hand = BaseMotion(np.broadcast_to(z["rotation"], (n, r, 3, 3)), zeros, zeros, zeros, zeros, zeros)
    runs = [(SERIES[int(k)], float(tm), int(seed)) for k, tm, seed in z["runs"]]
    return GroupData(t, FingerSamples(t, z["gyr"], z["acc"], hand), truth, joint_to_phalanx_angles(truth[0]),
                     runs, z["n_valid"])


def rms_errors(track_phi: np.ndarray, data: GroupData) -> np.ndarray:
    """(R, 3) per-joint RMS error in degrees over each run's own motion."""
    err = np.degrees(track_phi - data.truth)                                    # (N, R, 3)
    mask = np.arange(len(data.t))[:, None] < data.n_valid[None, :]            # (N, R)
    return np.sqrt((err**2 * mask[..., None]).sum(axis=0) / data.n_valid[:, None])


def _simulate_job(args) -> None:
    simulate_chunk(*args)


def _method_job(args) -> list[dict]:
    method, path = args
    from ..model.hand import default_calibration
    geom = default_calibration("right").finger(FINGER)
    data = load_chunk(path)
    track = method.build(geom, data.theta0, (len(data.runs),)).run(data.samples)
    rms = rms_errors(track.phi, data)
    return [{"series": s, "t_m": t, "estimator": method.label, "seed": seed,
             "rms_mcp_deg": float(rms[i, 0]), "rms_pip_deg": float(rms[i, 1]), "rms_dip_deg": float(rms[i, 2]),
             "rms_deg": float(np.sqrt(np.mean(rms[i] ** 2)))} for i, (s, t, seed) in enumerate(data.runs)]


def run_accuracy(quick: bool, seeds: int, workers: int = 2, progress: bool = True) -> list[dict]:
    """Every method on every group; returns result rows (``results.csv`` columns). Each group and
    series is simulated once, into a temporary folder, and read by every method's job."""
    import tempfile

    from tqdm import tqdm

    labels = [m.label for m in METHODS]
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="fingertrack-bench-") as tmp, ProcessPoolExecutor(max_workers=workers) as pool:
        chunks = []
        for i, g in enumerate(groups(durations(quick))):
            samples = len(g) * len(SERIES) * seeds * (T_D_S + float(np.max(g))) * 200.0
            parts = [(s,) for s in SERIES] if samples > CHUNK_SAMPLES else [SERIES]
            chunks += [(g, part, seeds, Path(tmp) / f"g{i}_{'_'.join(part)}.npz") for part in parts]
        chunks.sort(key=lambda c: -float(np.max(c[0])))          # longest first: the workers finish together
        list(tqdm(pool.map(_simulate_job, chunks), total=len(chunks), desc="simulate", unit="chunk", disable=not progress))
        jobs = [(m, c[3]) for c in chunks for m in METHODS]
        for part in tqdm(pool.map(_method_job, jobs), total=len(jobs), desc="estimate", unit="job", disable=not progress):
            rows.extend(part)
    rows.sort(key=lambda r: (SERIES.index(r["series"]), r["t_m"], labels.index(r["estimator"]), r["seed"]))
    return rows


def timing(duration_s: float = 2.0, repeats: int = 3) -> list[dict]:
    """Microseconds per sample of one finger (two sensors) for each estimator, streaming (``update``
    per sample) and batch (``run``), on a 'both' grasp motion; the best of ``repeats``."""
    sess = simulate(SimConfig(motion="grasp", t_m_s=duration_s, noise="both", seed=0, fingers=(FINGER,)))
    geom = sess.calibration.finger(FINGER)
    from ..estimators.base import samples_from_session
    smp = samples_from_session(sess, FINGER)
    theta0 = joint_to_phalanx_angles(sess.joint_angles[FINGER][0])
    n = len(smp)
    out = []
    for m in METHODS:
        batch, stream = [], []
        for _ in range(repeats):
            est = m.build(geom, theta0, ())
            t0 = time.perf_counter()
            est.run(smp)
            batch.append(time.perf_counter() - t0)
            est = m.build(geom, theta0, ())
            t0 = time.perf_counter()
            for k in range(n):
                est.update(*smp.sample(k))
            stream.append(time.perf_counter() - t0)
        out.append({"estimator": m.label, "stream_us_per_sample": 1e6 * min(stream) / n,
                    "batch_us_per_sample": 1e6 * min(batch) / n})
    return out


def summarize(rows: list[dict]) -> dict[str, dict[str, tuple[float, float]]]:
    """Per series and method: mean over durations and seeds of ``rms_deg``, and the std over seeds of
    the per-seed means (the spread)."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for series in SERIES:
        out[series] = {}
        for m in METHODS:
            sel = [r for r in rows if r["series"] == series and r["estimator"] == m.label]
            seeds = sorted({r["seed"] for r in sel})
            per_seed = [np.mean([r["rms_deg"] for r in sel if r["seed"] == s]) for s in seeds]
            out[series][m.label] = (float(np.mean(per_seed)), float(np.std(per_seed)))
    return out


def write_results(rows: list[dict], out_dir: Path) -> None:
    with open(out_dir / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["series", "t_m", "estimator", "seed", "rms_mcp_deg", "rms_pip_deg", "rms_dip_deg", "rms_deg"])
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def write_summary(rows: list[dict], times: list[dict], out_dir: Path, quick: bool, seeds: int, wall_s: float) -> str:
    summ = summarize(rows)
    t_ms = sorted({r["t_m"] for r in rows})
    lines = [
        "# Paper experiment (section 3): grasp test motions, index finger",
        "",
        f"{len(t_ms)} durations t_m from {t_ms[0]:g} s to {t_ms[-1]:g} s, t_d = {T_D_S} s, {seeds} seed(s), "
        f"IMU 200 Hz, MPU-9250 errors; {'--quick' if quick else 'full run'}; wall time {wall_s:.0f} s.",
        "",
        "## Mean RMS error over all durations, degrees (mean ± std over seeds)",
        "",
        "| estimator | " + " | ".join(SERIES) + " |",
        "|---|" + "---|" * len(SERIES),
    ]
    for m in METHODS:
        cells = [f"{summ[s][m.label][0]:.3f} ± {summ[s][m.label][1]:.3f}" for s in SERIES]
        lines.append(f"| {m.label} | " + " | ".join(cells) + " |")
    both = summ["both"]
    ref = min(both["switching"][0], both["madgwick-0.03"][0])
    lines += ["", f"On 'both', {OURS} is {100 * (1 - both[OURS][0] / ref):.0f}% below the better of switching and "
              f"madgwick-0.03 ({ref:.3f} deg) and {100 * (1 - both[OURS][0] / both['ekf'][0]):.0f}% below the EKF.", ""]
    lines += ["## RMS error by duration, 'both' series, degrees (mean over seeds)", "",
              "| t_m s | " + " | ".join(m.label for m in METHODS) + " |", "|---|" + "---|" * len(METHODS)]
    for t_m in t_ms:
        cells = [np.mean([r["rms_deg"] for r in rows if r["series"] == "both" and r["t_m"] == t_m and r["estimator"] == m.label])
                 for m in METHODS]
        lines.append(f"| {t_m:.3g} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    lines += ["", "## Speed: microseconds per sample, one finger (two IMUs), this machine", "",
              "| estimator | streaming | batch |", "|---|---|---|"]
    for t in times:
        lines.append(f"| {t['estimator']} | {t['stream_us_per_sample']:.1f} | {t['batch_us_per_sample']:.1f} |")
    tt = {t["estimator"]: t for t in times}
    ratio = tt["switching"]["stream_us_per_sample"] / tt["madgwick-0.03"]["stream_us_per_sample"]
    lines += ["", f"Switching / Madgwick streaming time ratio: {ratio:.2f} (the paper reports switching about 10% faster, 0.9).", ""]
    text = "\n".join(lines)
    (out_dir / "summary.md").write_text(text)
    return text


def plot_fig10(rows: list[dict], out_dir: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 5), sharey=True)
    for ax, series in zip(axes, SERIES):
        for m in METHODS:
            sel = [r for r in rows if r["series"] == series and r["estimator"] == m.label]
            t_ms = sorted({r["t_m"] for r in sel})
            vals = np.array([[r["rms_deg"] for r in sel if r["t_m"] == t] for t in t_ms])
            mean = vals.mean(axis=1)
            line, = ax.plot(t_ms, mean, marker="o", ms=3, label=m.label, lw=2.5 if m.label == OURS else 1.2)
            if vals.shape[1] > 1:
                ax.fill_between(t_ms, vals.min(axis=1), vals.max(axis=1), color=line.get_color(), alpha=0.15)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"sensor errors: {series}")
        ax.set_xlabel("motion duration t_m, s")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("RMS error over the motion, deg")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(METHODS), fontsize=9)
    fig.suptitle("RMS error against motion duration (cf. the paper's Figure 10); bands: min-max over seeds")
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(out_dir / "fig10.png", dpi=110)
    plt.close(fig)


def plot_fig9(out_dir: Path, t_m: float = 1.0, series: str = "both", seed: int = 0) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from ..estimators.base import samples_from_session

    sess = simulate(SimConfig(motion="grasp", t_m_s=t_m, noise=series, seed=seed, fingers=(FINGER,),
                              finger_motion=grasp_motion(t_m=t_m, t_d=T_D_S)))
    geom = sess.calibration.finger(FINGER)
    smp = samples_from_session(sess, FINGER)
    truth = sess.joint_angles[FINGER]
    theta0 = joint_to_phalanx_angles(truth[0])
    t = sess.t
    fig, axes = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
    for j, name in enumerate(geom.joint_names):
        axes[0].plot(t, np.degrees(truth[:, j]), label=name)
    axes[0].set_ylabel("true angle, deg")
    axes[0].legend()
    axes[0].set_title(f"grasp motion t_m = {t_m} s, '{series}' errors, seed {seed}: estimation error by joint")
    for m in METHODS:
        tr = m.build(geom, theta0, ()).run(smp)
        err = np.degrees(tr.phi - truth)
        for j in range(3):
            axes[j + 1].plot(t, err[:, j], label=m.label, lw=2.0 if m.label == OURS else 1.0)
    for j, name in enumerate(geom.joint_names):
        axes[j + 1].set_ylabel(f"{name} error, deg")
        axes[j + 1].set_ylim(-15, 15)
        axes[j + 1].grid(True, alpha=0.3)
    axes[1].legend(fontsize=8, ncol=3)
    axes[-1].set_xlabel("t, s")
    fig.tight_layout()
    fig.savefig(out_dir / "fig9.png", dpi=100)
    plt.close(fig)


def run(out_dir: str | Path, quick: bool = False, seeds: int = 5, workers: int = 2, progress: bool = True) -> str:
    """The whole benchmark; returns the summary text."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if seeds < 1:
        raise ValueError(f"--seeds must be at least 1, got {seeds}")
    start = time.perf_counter()
    rows = run_accuracy(quick, 1 if quick else seeds, workers, progress)
    times = timing()
    write_results(rows, out)
    plot_fig10(rows, out)
    plot_fig9(out)
    return write_summary(rows, times, out, quick, 1 if quick else seeds, time.perf_counter() - start)
