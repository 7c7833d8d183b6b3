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
With ``--hands 1,4,12`` each repeat also runs, per N given, N sessions in one hand worker (``_pass_hands``): the
glove streams of N recordings (seeds 0 to N - 1) interleaved in order of arrival and written to the worker as
the web process writes them (grouped every ``GROUP_S`` once the worker has ``GROUP_SESSIONS`` sessions), each
session's first second not timed: CPU per hand and second of data, the cost of a hand among others in its worker.
With ``--starts SESSIONS`` sessions are started one after another, each alone in a hand worker
(``_pass_starts``): the CPU of its hand's construction (as on "open"), of its first second of data and of a
steady second, and the first second's excess over the steady one.

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


def _realistic(seconds: float, seed: int) -> SimConfig:
    """The realistic one-hand recording's configuration (``fingertrack simulate --motion random --hand-motion
    random --noise realistic``)."""
    return SimConfig(motion="random", hand_motion="random", noise="realistic", seed=seed, duration_s=seconds)


def recording_lines(seconds: float, seed: int = 0, batched: bool = False) -> list[str]:
    """The JSON Lines of a realistic one-hand recording (``fingertrack simulate --motion random
    --hand-motion random --noise realistic``), without its ``truth`` messages: one ``imu`` message per
    sensor and sample as in a recording, or (``batched``) each tick's samples in one ``imu_batch`` in
    order of arrival, as the simulated glove streams them (``timed_recording``)."""
    if batched:
        return [line for _, line in timed_recording(seconds, seed)]
    return [json.dumps(m, separators=(",", ":")) for m in simulate(_realistic(seconds, seed)).messages(include_truth=False)]


def timed_recording(seconds: float, seed: int = 0) -> list[tuple[float, str]]:
    """``recording_lines``' batched recording with each message's arrival time on the glove's clock, s
    (``clients.glove.source_messages``: each tick's samples in one ``imu_batch``), in order of arrival."""
    from clients.glove import source_messages

    return [(t, json.dumps(m, separators=(",", ":")))
            for t, m in sorted(source_messages(_realistic(seconds, seed)), key=lambda pair: pair[0])]


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


def worker_messages(lines: list[str], sid: int = 1) -> list[list]:
    """The recording's messages as the web process hands them to a session's hand worker (``api.hands.worker``,
    session number ``sid``): a sample or pose as its JSON text, validated there (``chk``); anything else
    validated by the web process and packed once (``src``)."""
    import msgpack
    import orjson

    out = []
    for n, line in enumerate(lines):
        raw = orjson.loads(line)
        if raw["type"] in ("imu", "imu_batch", "pose"):
            out.append(["chk", sid, n, line, False])
        else:
            out.append(["src", sid, n, msgpack.packb(raw)])
    return out


def _hand_worker(settings: PipelineSettings, sock=None):
    """A hand worker (``api.hands.worker.Worker``, no process of its own) writing to ``sock`` (default: a
    ``_Discarded``), and the service settings its sessions are opened with."""
    from ..api.config import ServiceSettings
    from ..api.hands import worker as hands_worker

    service = ServiceSettings(estimator=settings.estimator, output_rate_hz=settings.output_rate_hz,
                              record_all=False, record_dir=None)
    return hands_worker.Worker(_Discarded() if sock is None else sock, service), service


def _open(worker, service, sid: int, settings: PipelineSettings):
    """Session ``sid``'s hand built in ``worker`` as on ``["open", sid, name, None]`` (there by a thread,
    ``Worker.build``; here on this one), with ``settings``' estimator parameters."""
    from ..api.hands import worker as hands_worker

    owned = worker.hands[sid] = hands_worker.OwnedHand(f"bench{sid}", service, worker.metrics, None)
    if settings.estimator_params:
        owned.live.update_config({"estimator": settings.estimator, "estimator_params": settings.estimator_params})
    return owned


def _pass_worker(messages: list[list], settings: PipelineSettings) -> tuple[float, int]:
    """A hand worker's handling of the recording (``--worker``): each message through ``Worker.dispatch`` as one
    read of the web process's socket (its frames sent as soon as they are made, its reply and the rest at
    the end of the message: a hand alone in its worker), every output encoded there and each write framed
    for the socket (which drops it), under the serving process's garbage-collector policy; its CPU time.
    Not counted: the socket's system calls and the worker's read loop (``Worker.run``)."""
    from ..api.server import serving_gc

    worker, service = _hand_worker(settings)
    owned = _open(worker, service, 1, settings)
    clock = time.process_time
    with serving_gc():
        t0 = clock()
        for message in messages:
            worker.dispatch(message, at_once=True)
            worker.send()
        total = clock() - t0
    return total, owned.sink.last_seq


FIRST_S = 1.0
"""a session's first second of data: its start (its calibration, the fingers' first ticks), left out of the
N-hand passes' time (``_pass_hands``) and measured on its own by ``--starts`` (``_pass_starts``), s"""
STEADY_S = (2.0, 3.0)
"""the second of a session's data that ``--starts`` takes for a steady one (the start's own work done), s"""


def interleaved(recordings: list[list[tuple[float, str]]], first_sid: int = 1) -> list[tuple[float, list]]:
    """Several sessions' recordings (``timed_recording``; the i-th is session ``first_sid`` + i) as one hand worker gets them
    from the web process: each message as ``worker_messages`` makes it, with its arrival time, all merged in
    order of arrival. The gloves start together but do not tick in step: the i-th glove's clock is shifted by
    i / N of a sample period (IMU at 200 Hz)."""
    stream = []
    for i, recording in enumerate(recordings):
        shift = i / len(recordings) / 200.0
        messages = worker_messages([line for _, line in recording], sid=first_sid + i)
        stream += [(t + shift, i, n, m) for n, ((t, _), m) in enumerate(zip(recording, messages))]
    stream.sort(key=lambda item: item[:3])
    return [(t, m) for t, _, _, m in stream]


def worker_batches(stream: list[tuple[float, list]], sessions: int) -> list[tuple[float, list]]:
    """``interleaved``'s messages in the web process's writes to their worker (``api.hands.pool``), each with
    the time it is written: with fewer than ``GROUP_SESSIONS`` sessions a message as it arrives (with any that
    arrive at the same time); with more, a message arriving within ``GROUP_S`` of the last write waits until
    that time is up, with every message that arrives meanwhile."""
    from ..api.hands.pool import GROUP_S
    from ..api.hands.worker import GROUP_SESSIONS

    wait = GROUP_S if sessions >= GROUP_SESSIONS else 0.0
    batches, last, i = [], float("-inf"), 0
    while i < len(stream):
        due = max(stream[i][0], last + wait)
        j = i
        while j < len(stream) and stream[j][0] <= due:
            j += 1
        batches.append((due, [m for _, m in stream[i:j]]))
        last, i = due, j
    return batches


def _pass_hands(recordings: list[list[tuple[float, str]]], settings: PipelineSettings,
                sock=None) -> tuple[float, list[int]]:
    """N sessions in one hand worker (``--hands``): their recordings ``interleaved`` and in the web process's
    writes (``worker_batches``), each write through ``Worker.handle_batch`` as the worker reads it (a batch's
    frames sent as they are made, or once at its end with ``GROUP_SESSIONS`` sessions or more), its outputs
    then written (the worker holds a write of replies alone for up to ``HOLD_S``: not here), each write framed
    for ``sock`` (default: dropped), under the serving process's garbage-collector policy. The hands are built
    as on "open" and the writes of the sessions' first ``FIRST_S`` of data handled before the clock starts:
    returns the CPU time of the rest, and each session's frames."""
    from ..api.server import serving_gc

    worker, service = _hand_worker(settings, sock)
    owned = [_open(worker, service, sid, settings) for sid in range(1, len(recordings) + 1)]
    batches = worker_batches(interleaved(recordings), len(recordings))
    start = next((k for k, (due, _) in enumerate(batches) if due >= FIRST_S), len(batches))
    clock = time.process_time
    with serving_gc():
        for _, batch in batches[:start]:
            worker.handle_batch(batch)
            worker.send()
        t0 = clock()
        for _, batch in batches[start:]:
            worker.handle_batch(batch)
            worker.send()
        total = clock() - t0
    for hand in owned:
        hand.live.close()
    return total, [hand.sink.last_seq for hand in owned]


def _pass_starts(recordings: list[list[tuple[float, str]]], settings: PipelineSettings) -> list[dict]:
    """Sessions started one after another (``--starts``), each alone in a hand worker: its hand built as on
    "open" (``construct_s``), its recording's first ``FIRST_S`` through ``Worker.handle_batch`` as a hand alone
    gets it (``first_s``), the data up to ``STEADY_S`` untimed, its steady second (``steady_s``), the rest
    untimed, then closed; CPU times, and the frames of each of the four parts of its data (``frames``)."""
    from ..api.server import serving_gc

    clock = time.process_time
    out = []
    with serving_gc():
        for sid, recording in enumerate(recordings, 1):
            batches = worker_batches(interleaved([recording], first_sid=sid), 1)
            cuts = [0, *(sum(due < edge for due, _ in batches) for edge in (FIRST_S, *STEADY_S)), len(batches)]
            worker, service = _hand_worker(settings)
            t0 = clock()
            owned = _open(worker, service, sid, settings)
            parts, frames = [clock() - t0], []
            for a, b in zip(cuts, cuts[1:]):
                seen = owned.sink.last_seq
                t0 = clock()
                for _, batch in batches[a:b]:
                    worker.handle_batch(batch)
                    worker.send()
                parts.append(clock() - t0)
                frames.append(owned.sink.last_seq - seen)
            worker.dispatch(["close", sid])
            out.append({"construct_s": parts[0], "first_s": parts[1], "steady_s": parts[3], "frames": frames})
    return out


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
        params: dict | None = None, profile: bool = False, batched: bool = False, worker: bool = False,
        hands: tuple[int, ...] = (), starts: int = 0) -> str:
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
    if hands and seconds <= FIRST_S:
        raise ValueError(f"--hands needs more than {FIRST_S:g} s of data (each session's first second is not timed)")
    recordings = [timed_recording(seconds, seed) for seed in range(max(hands))] if hands else []
    hand_cpu = {n: [] for n in hands}
    hand_frames = {}
    if hands:                                       # the worker's batch paths run once before any timing
        _pass_hands([timed_recording(FIRST_S + 0.5, seed=99)] * min(4, max(hands)), settings)
    clock_us = [clock_read_cpu_us()]
    for repeat in range(repeats):                   # the kinds of pass interleaved: the same conditions
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
        for n in hands if repeat % 2 == 0 else hands[::-1]:       # (no level always first or last)
            total, per_session = _pass_hands(recordings[:n], settings)
            hand_cpu[n].append(total)
            for seed, count in enumerate(per_session):
                if hand_frames.setdefault(seed, count) != count:
                    raise RuntimeError(f"the passes disagree: session {seed + 1} made {hand_frames[seed]} and {count} "
                                       f"frames (hand worker, {n} hands)")
            if batched and per_session[0] != frames:
                raise RuntimeError(f"the passes disagree: {frames} and {per_session[0]} frames (hand worker, {n} hands)")
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
    if hands:
        timed_s = seconds - FIRST_S
        result["hands"] = []
        for n in hands:
            level = {"hands": n, "cpu_s": hand_cpu[n], "frames": sum(hand_frames[seed] for seed in range(n)),
                     "hand_seconds_timed": n * timed_s,
                     "cpu_ms_per_hand_s": {"best": 1e3 * min(hand_cpu[n]) / (n * timed_s),
                                           "median": 1e3 * statistics.median(hand_cpu[n]) / (n * timed_s)}}
            result["hands"].append(level)
        one = next((level for level in result["hands"] if level["hands"] == 1), None)
        for level in result["hands"]:               # (the pairs' ratios: each pass against one hand's of its repeat)
            level["to_one_hand"] = None if one is None else {
                "best": level["cpu_ms_per_hand_s"]["best"] / one["cpu_ms_per_hand_s"]["best"],
                "median_of_repeats": statistics.median(a / level["hand_seconds_timed"] / (b / one["hand_seconds_timed"])
                                                       for a, b in zip(level["cpu_s"], one["cpu_s"]))}
    if starts:
        result["starts"] = _starts_result(_pass_starts([timed_recording(STEADY_S[1], seed) for seed in range(starts)],
                                                       settings))
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


def _starts_result(sessions: list[dict]) -> dict:
    """``_pass_starts``' sessions summed up: per part the mean and median over the sessions, CPU ms; the first
    second's excess over the steady one per session (``excess_ms``: its mean is the means' difference)."""
    per = {"construct_ms": [1e3 * s["construct_s"] for s in sessions],
           "first_second_ms": [1e3 * s["first_s"] for s in sessions],
           "steady_second_ms": [1e3 * s["steady_s"] for s in sessions],
           "excess_ms": [1e3 * (s["first_s"] - s["steady_s"]) for s in sessions]}
    return {"sessions": len(sessions), "first_s": FIRST_S, "steady_s": list(STEADY_S),
            "frames": [s["frames"] for s in sessions], "per_session": per,
            "mean": {k: statistics.fmean(v) for k, v in per.items()},
            "median": {k: statistics.median(v) for k, v in per.items()}}


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
    if "hands" in r:
        lines += ["", f"N sessions in one hand worker (`Worker.handle_batch` as the web process writes to it; recordings of "
                  f"seeds 0 to N - 1, each session's first {FIRST_S:g} s not timed), CPU per hand and second of data, "
                  f"best and median of {r['repeats']} passes:", "",
                  "| hands | frames | CPU ms per hand-second (best) | median | to one hand: best / median of the repeats' ratios |",
                  "|---|---|---|---|---|"]
        for level in r["hands"]:
            c, ratio = level["cpu_ms_per_hand_s"], level["to_one_hand"]
            to_one = "" if ratio is None else f"{ratio['best']:.2f}x / {ratio['median_of_repeats']:.2f}x"
            lines.append(f"| {level['hands']} | {level['frames']} | **{c['best']:.2f}** | {c['median']:.2f} | {to_one} |")
    if "starts" in r:
        s = r["starts"]
        lines += ["", f"A session's start: {s['sessions']} sessions one after another, each alone in a hand worker "
                  f"(seeds 0 to {s['sessions'] - 1}), CPU ms per session, mean and median over the sessions:", "",
                  "| part | mean | median |", "|---|---|---|"]
        for key, what in (("construct_ms", 'the hand built (as on "open")'),
                          ("first_second_ms", f"its first {s['first_s']:g} s of data"),
                          ("steady_second_ms", f"a steady second (data {s['steady_s'][0]:g}-{s['steady_s'][1]:g} s)"),
                          ("excess_ms", "**the first second's excess over the steady one**")):
            lines.append(f"| {what} | {s['mean'][key]:.2f} | {s['median'][key]:.2f} |")
    return "\n".join(lines)
