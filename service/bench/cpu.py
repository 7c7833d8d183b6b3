"""CPU cost of one hand (``fingertrack bench cpu``): a realistic simulated recording run through what a
session does with it, stage by stage, in this one process, measured in CPU time (``time.process_time``),
not wall time, so that a busy machine slows it down less.

Stages, summed over the whole recording (the JSON Lines text of ``fingertrack simulate``: one ``imu``
message per sensor and sample, poses at 90 Hz; with ``--batch`` each tick's samples in one
``imu_batch``, as the simulated glove streams them to the service):

* ``parse``: decode and validate every line (``protocol.parse_line``);
* ``pipeline``: the parsed messages through ``TrackedHand`` (alignment, the five finger estimators,
  the optical fit, the OpenXR joints, the gesture recogniser, the outgoing messages);
* ``encode``: every output message encoded once as JSON text (``protocol.encode``).

With ``--worker`` each repeat also runs the recording through a hand worker's handling of its session's
messages (``_pass_worker``: ``api.hands.worker.Worker.dispatch`` as the web process sends them, validation,
pipeline, each output encoded and each write framed; the socket's system calls not counted), its total apart.

Each message goes through all three stages before the next is read, as in a session, under the
serving process's garbage-collector policy (``api.server.serving_gc``).

The total is measured apart from the stages: reading the CPU-time clock is itself a system call
(``clock_read_cpu_us``, measured in each run: several microseconds on a virtual machine, about
as much as a small stage), and the stages need three reads per message, which a session never
makes. So each repeat is two passes: one with the clock read only at its start and end (the
**total**), one with the three reads per message (the **stages**, each with its share of the reads'
own cost; their sum, ``stages_total``, is more than the total by about that cost). (Parsing the whole recording
first and keeping it, as this benchmark once did, made the collector scan thousands of held messages
again and again: three quarters of the ``parse`` figure then was collection that a session never pays.)

The kernels are loaded (or compiled) by a first pass over the first second before any timing; the
time that took is reported apart. ``--param implementation=reference`` runs ``chain``'s numpy
reference, a baseline the compiled core must beat. ``--profile`` adds cProfile's top functions of
one more pipeline pass (its overhead inflates the figures; read the shares, not the seconds).
"""
from __future__ import annotations

import cProfile
import io
import json
import os
import pstats
import statistics
import time
from pathlib import Path

from ..pipeline.hand import PipelineSettings
from ..pipeline.tracked import TrackedHand
from ..protocol import encode, parse_line
from ..sim.session import SimConfig, simulate

STAGES = ("parse", "pipeline", "encode")


def recording_lines(seconds: float, seed: int = 0, batched: bool = False) -> list[str]:
    """The JSON Lines of a realistic one-hand recording (``fingertrack simulate --motion random
    --hand-motion random --noise realistic``), without its ``truth`` messages: one ``imu`` message per
    sensor and sample as in a recording, or (``batched``) each tick's samples in one ``imu_batch`` in
    order of arrival, as the simulated glove streams them (``clients.glove.source_messages``)."""
    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=seed, duration_s=seconds)
    if batched:
        from clients.glove import source_messages
        messages = [m for _, m in sorted(source_messages(config), key=lambda pair: pair[0])]
    else:
        messages = list(simulate(config).messages(include_truth=False))
    return [json.dumps(m, separators=(",", ":")) for m in messages]


def _pass_total(lines: list[str], settings: PipelineSettings) -> tuple[float, int]:
    """``_pass`` with the clock read only before and after the whole recording: its CPU time."""
    from ..api.server import serving_gc

    frames = 0
    hand = TrackedHand("right", settings)
    clock = time.process_time
    with serving_gc():
        t0 = clock()
        for line in lines:
            for m in hand.handle(parse_line(line)):
                encode(m, False)
                frames += m["type"] == "frame"
        total = clock() - t0
    return total, frames


class _Discarded:
    """The web process's end of a hand worker's socket, for ``_pass_worker``: every write dropped (counted)."""

    def __init__(self):
        self.writes = 0

    def sendall(self, data: bytes) -> None:
        self.writes += 1


def worker_messages(lines: list[str]) -> list[list]:
    """The recording's messages as the web process hands them to a session's hand worker (``api.hands.worker``,
    session number 1): a sample or pose as its JSON text, validated there (``chk``); anything else
    validated by the web process and packed once (``src``)."""
    import msgpack
    import orjson

    out = []
    for n, line in enumerate(lines):
        raw = orjson.loads(line)
        if raw["type"] in ("imu", "imu_batch", "pose"):
            out.append(["chk", 1, n, line, False])
        else:
            out.append(["src", 1, n, msgpack.packb(raw)])
    return out


def _pass_worker(messages: list[list], settings: PipelineSettings) -> tuple[float, int]:
    """A hand worker's handling of the recording (``--worker``): each message through ``Worker.dispatch`` as one
    read of the web process's socket (its frames sent as soon as they are made, its reply and the rest at
    the end of the message: a hand alone in its worker), every output encoded there and each write framed
    for the socket (which drops it), under the serving process's garbage-collector policy; its CPU time.
    Not counted: the socket's system calls and the worker's read loop (``Worker.run``)."""
    from ..api.config import ServiceSettings
    from ..api.hands import worker as hands_worker
    from ..api.server import serving_gc

    service = ServiceSettings(estimator=settings.estimator, output_rate_hz=settings.output_rate_hz,
                              record_all=False, record_dir=None)
    worker = hands_worker.Worker(_Discarded(), service)
    owned = worker.hands[1] = hands_worker.OwnedHand("bench", service, worker.metrics, None)
    if settings.estimator_params:
        owned.live.update_config({"estimator": settings.estimator, "estimator_params": settings.estimator_params})
    clock = time.process_time
    with serving_gc():
        t0 = clock()
        for message in messages:
            worker.dispatch(message, at_once=True)
            worker.send()
        total = clock() - t0
    return total, owned.sink.last_seq


def clock_read_cpu_us(reads: int = 20000) -> float:
    """CPU time one read of the CPU-time clock (``time.process_time``) costs, microseconds."""
    clock = time.process_time
    t0 = clock()
    for _ in range(reads):
        clock()
    return (clock() - t0) / reads * 1e6


def _pass(lines: list[str], settings: PipelineSettings) -> tuple[dict, int]:
    """One pass as a session runs: each message parsed, handled and its outputs encoded before the
    next is read (nothing of the recording is held), under the serving process's garbage-collector
    policy (``api.server.serving_gc``); each stage's CPU time summed over the messages."""
    from ..api.server import serving_gc

    parse_s = pipeline_s = encode_s = 0.0
    frames = 0
    hand = TrackedHand("right", settings)
    clock = time.process_time
    with serving_gc():
        t0 = clock()
        for line in lines:
            msg = parse_line(line)
            t1 = clock()
            out = hand.handle(msg)
            t2 = clock()
            for m in out:
                encode(m, False)
                frames += m["type"] == "frame"
            t3 = clock()
            parse_s += t1 - t0
            pipeline_s += t2 - t1
            encode_s += t3 - t2
            t0 = t3
    return {"parse": parse_s, "pipeline": pipeline_s, "encode": encode_s}, frames


def run(out_dir: str | Path, seconds: float = 20.0, repeats: int = 3, estimator: str = "chain",
        params: dict | None = None, profile: bool = False, batched: bool = False, worker: bool = False) -> str:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = PipelineSettings(estimator=estimator, estimator_params=params or {})
    load_before = _load_average()
    lines = recording_lines(seconds, batched=batched)
    data_s = seconds
    t0 = time.process_time()
    _pass(lines[: max(1, int(len(lines) / seconds))], settings)      # about a second: kernels loaded (or compiled)
    warm_cpu = time.process_time() - t0
    runs, totals, workers = [], [], []
    messages = worker_messages(lines) if worker else []
    if worker:
        _pass_worker(messages[: max(1, int(len(messages) / seconds))], settings)
    clock_us = [clock_read_cpu_us()]
    for _ in range(repeats):                        # the kinds of pass interleaved: the same conditions
        total, frames = _pass_total(lines, settings)
        totals.append(total)
        cpu, staged_frames = _pass(lines, settings)
        runs.append(cpu)
        if staged_frames != frames:
            raise RuntimeError(f"the passes disagree: {frames} and {staged_frames} frames")
        if worker:
            total, worker_frames = _pass_worker(messages, settings)
            workers.append(total)
            if worker_frames != frames:
                raise RuntimeError(f"the passes disagree: {frames} and {worker_frames} frames (hand worker)")
    clock_us.append(clock_read_cpu_us())
    staged = [sum(r.values()) for r in runs]
    best = min(range(repeats), key=lambda i: staged[i])
    result = {
        "seconds_of_data": data_s, "lines": len(lines), "batched": batched, "frames": frames, "estimator": estimator,
        "params": params or {}, "repeats": repeats, "warm_up_cpu_s": warm_cpu,
        "runs": runs, "totals": totals,
        "cpu_s_per_s": {"best": min(totals) / data_s, "median": statistics.median(totals) / data_s},
        "stages_best_cpu_s_per_s": {k: runs[best][k] / data_s for k in STAGES},
        "stages_total_cpu_s_per_s": {"best": staged[best] / data_s, "median": statistics.median(staged) / data_s},
        "clock_read_cpu_us": clock_us,
        "clock_reads_per_s_of_data": 3 * len(lines) / data_s,
        "load_average_1min": [load_before, _load_average()],
    }
    if worker:
        result["worker_totals"] = workers
        result["worker_cpu_s_per_s"] = {"best": min(workers) / data_s, "median": statistics.median(workers) / data_s}
    top = ""
    if profile:
        prof = cProfile.Profile()
        messages = [parse_line(line) for line in lines]
        hand = TrackedHand("right", settings)
        from ..api.server import serving_gc
        with serving_gc():
            prof.enable()
            for msg in messages:
                hand.handle(msg)
            prof.disable()
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(25)
        top = buf.getvalue()
        (out / "profile.txt").write_text(top)
    (out / "results.json").write_text(json.dumps(result, indent=2))
    summary = _summary(result)
    (out / "summary.md").write_text(summary + ("\n\n```\n" + top + "```\n" if top else ""))
    return summary


def _load_average() -> float | None:
    """The machine's 1-minute load average (other work inflates CPU time too); None where unknown."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def _summary(r: dict) -> str:
    s = r["stages_best_cpu_s_per_s"]
    lines = [
        f"One hand, {r['seconds_of_data']:g} s of realistic data ({r['lines']} messages"
        f"{', each tick in one imu_batch' if r['batched'] else ', one imu message per sample'}, {r['frames']} frames), "
        f"estimator {r['estimator']}{' ' + json.dumps(r['params']) if r['params'] else ''}; CPU time of this process, "
        f"best and median of {r['repeats']} passes; kernel load/compile pass {r['warm_up_cpu_s']:.2f} CPU s (not counted); "
        f"the stages from passes that read the clock {r['clock_reads_per_s_of_data']:.0f} times per s of data, at "
        f"{' -> '.join(f'{v:.2f}' for v in r['clock_read_cpu_us'])} us each; "
        f"load average {' -> '.join('?' if v is None else f'{v:.1f}' for v in r['load_average_1min'])} "
        f"on {os.cpu_count()} cores.",
        "",
        "| stage | CPU s per s of data (best) | % of a core |",
        "|---|---|---|",
    ]
    for k in STAGES:
        lines.append(f"| {k} | {s[k]:.4f} | {100 * s[k]:.2f} |")
    b, m = r["stages_total_cpu_s_per_s"]["best"], r["stages_total_cpu_s_per_s"]["median"]
    lines.append(f"| stages' sum (with the clock reads) | {b:.4f} (median {m:.4f}) | {100 * b:.2f} (median {100 * m:.2f}) |")
    b, m = r["cpu_s_per_s"]["best"], r["cpu_s_per_s"]["median"]
    lines.append(f"| **total** (clock read per pass) | **{b:.4f}** (median {m:.4f}) | **{100 * b:.2f}** (median {100 * m:.2f}) |")
    if "worker_cpu_s_per_s" in r:
        b, m = r["worker_cpu_s_per_s"]["best"], r["worker_cpu_s_per_s"]["median"]
        lines.append(f"| **in a hand worker** (`Worker.dispatch`: validation, pipeline, encoding, framing) | **{b:.4f}** "
                     f"(median {m:.4f}) | **{100 * b:.2f}** (median {100 * m:.2f}) |")
    return "\n".join(lines)
