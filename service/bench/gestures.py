"""Gesture benchmark: ``fingertrack bench gestures [--quick] --out DIR``.

Long simulated sessions run through the whole live path (``service.pipeline.tracked.TrackedHand``: protocol
messages, hand pipeline with its default estimator, recogniser): random gesture scripts (point,
grasp, pinch, open and a relaxed hand, 0.25-0.6 s transitions, 0.6-2 s holds), a slowly rotating and
swaying hand, 'both' IMU errors at MPU-9250 figures and the default optical tracker (90 Hz, 20 ms
latency, jitter).

Labels come from the simulator: the same recogniser run on the *true* hand (true joint angles and
metacarpus pose at every output frame) with the same thresholds but no dwell times gives the true
gesture intervals. A detected interval matches a true one of the same gesture when they overlap
(each matched once). Per gesture: precision, recall, F1, onset latency (detected start - true start)
and release latency (detected end - true end), median and 95th percentile; chatter: detected
intervals shorter than 100 ms; pointing-ray error: the angle between the estimated and the true ray
on frames where both say "point".
"""
from __future__ import annotations

import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from ..model.hand import default_calibration
from ..model.openxr import joint_poses
from ..pipeline.hand import HandFrame
from ..protocol import parse_message
from ..sim.motions import random_sequence, sequence_motion
from ..sim.session import SimConfig, simulate

GESTURE_NAMES = ("point", "grasp", "pinch", "open")
CHATTER_S = 0.1


def _intervals(events: list[tuple[str, str, float]], end_t: float) -> dict[str, list[list[float]]]:
    out: dict[str, list[list[float]]] = {g: [] for g in GESTURE_NAMES}
    open_: dict[str, float] = {}
    for g, kind, t in events:
        if kind == "start":
            open_[g] = t
        elif g in open_:
            out[g].append([open_.pop(g), t])
    for g, t0 in open_.items():
        out[g].append([t0, end_t])
    return out


def run_session(seed: int, duration_s: float, hand_motion: str = "slow-rotation") -> dict:
    """One session: detected and true intervals, ray errors."""
    from gestures.recognizer import GestureRecognizer, GestureSettings
    from ..pipeline.tracked import TrackedHand

    steps = random_sequence(duration_s, seed)
    motion = sequence_motion(steps=steps)
    sess = simulate(SimConfig(motion="sequence", noise="both", hand_motion=hand_motion, seed=seed,
                              finger_motion=motion))
    tracked = TrackedHand()
    frames, events = [], []
    for m in sess.messages(include_truth=False):
        for out in tracked.handle(parse_message(m)):
            if out["type"] == "frame":
                frames.append(out)
            else:
                events.append((out["gesture"], out["event"], out["t"]))
    # the true hand at every output frame, through a dwell-free recogniser with the same thresholds
    calib = default_calibration("right")
    truth_rec = GestureRecognizer(GestureSettings(start_dwell_s=0.0, end_dwell_s=0.0))
    true_events, ray_err = [], []
    rate = sess.config.rate_hz
    for f in frames:
        n = int(round((f["t"] - sess.t[0]) * rate))
        phi = {name: a[n] for name, a in sess.joint_angles.items()}
        rot, pos = sess.base.rotation[n], sess.base.position[n]
        hf = HandFrame(f["t"], f["seq"], "right", phi, {}, rot, pos, joint_poses(calib, phi, rot, pos), {})
        ann, evs = truth_rec.update(hf)
        true_events += [(e["gesture"], e["event"], e["t"]) for e in evs]
        if ann["active"] == "point" and f["gesture"]["active"] == "point":
            d_true = np.array(ann["ray"]["direction"])
            d_est = np.array(f["gesture"]["ray"]["direction"])
            ray_err.append(float(np.degrees(np.arccos(np.clip(d_true @ d_est, -1.0, 1.0)))))
    end_t = frames[-1]["t"]
    return {"detected": _intervals(events, end_t), "truth": _intervals(true_events, end_t), "ray_error_deg": ray_err,
            "duration_s": end_t - frames[0]["t"], "frames": len(frames)}


def score(sessions: list[dict]) -> dict:
    result: dict = {"gestures": {}, "chatter": 0}
    for g in GESTURE_NAMES:
        tp_det = tp_true = n_det = n_true = 0
        onset, release = [], []
        for s in sessions:
            det, tru = s["detected"][g], s["truth"][g]
            n_det += len(det)
            n_true += len(tru)
            used = set()
            for d in det:
                match = next((i for i, tr in enumerate(tru) if i not in used and d[0] < tr[1] and tr[0] < d[1]), None)
                if match is not None:
                    used.add(match)
                    tp_det += 1
                    onset.append(d[0] - tru[match][0])
                    release.append(d[1] - tru[match][1])
            tp_true += len(used)
            result["chatter"] += sum(1 for d in det if d[1] - d[0] < CHATTER_S)
        precision = tp_det / n_det if n_det else 1.0
        recall = tp_true / n_true if n_true else 1.0
        f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0

        def pct(v, q):
            return float(np.percentile(v, q)) if v else float("nan")
        result["gestures"][g] = {
            "precision": precision, "recall": recall, "f1": f1, "true_count": n_true, "detected_count": n_det,
            "onset_median_s": pct(onset, 50), "onset_p95_s": pct(onset, 95),
            "release_median_s": pct(release, 50), "release_p95_s": pct(release, 95),
        }
    rays = [e for s in sessions for e in s["ray_error_deg"]]
    result["ray_error_deg"] = {"median": float(np.median(rays)) if rays else float("nan"),
                               "p95": float(np.percentile(rays, 95)) if rays else float("nan")}
    return result


def table(result: dict, sessions: int, duration_s: float, wall_s: float) -> str:
    lines = [f"# Gesture benchmark: {sessions} session(s) of {duration_s:.0f} s, 'both' IMU errors, rotating hand; "
             f"wall time {wall_s:.0f} s", "",
             "| gesture | true | detected | precision | recall | F1 | onset median / p95 ms | release median / p95 ms |",
             "|---|---|---|---|---|---|---|---|"]
    for g, r in result["gestures"].items():
        lines.append(f"| {g} | {r['true_count']} | {r['detected_count']} | {r['precision']:.3f} | {r['recall']:.3f} | "
                     f"{r['f1']:.3f} | {1e3 * r['onset_median_s']:.0f} / {1e3 * r['onset_p95_s']:.0f} | "
                     f"{1e3 * r['release_median_s']:.0f} / {1e3 * r['release_p95_s']:.0f} |")
    lines += ["", f"Chatter (start/end pairs shorter than {1e3 * CHATTER_S:.0f} ms): {result['chatter']}",
              f"Pointing-ray error: median {result['ray_error_deg']['median']:.2f} deg, p95 {result['ray_error_deg']['p95']:.2f} deg", ""]
    return "\n".join(lines)


def _job(args):
    return run_session(*args)


QUICK_SESSIONS = ((1,), 40.0)
"""--quick: (seeds, session length in s)."""
FULL_SESSIONS = ((1, 2, 3, 4, 5, 6), 120.0)
"""The full run: (seeds, session length in s)."""


def run(out_dir: str | Path, quick: bool = False, workers: int = 2, progress: bool = True) -> str:
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seeds, duration = QUICK_SESSIONS if quick else FULL_SESSIONS
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=workers) as pool:
        sessions = list(tqdm(pool.map(_job, [(s, duration) for s in seeds]), total=len(seeds),
                             desc="bench gestures", unit="session", disable=not progress))
    result = score(sessions)
    (out / "results.json").write_text(json.dumps(result, indent=2))
    text = table(result, len(seeds), duration, time.perf_counter() - start)
    (out / "summary.md").write_text(text)
    return text
