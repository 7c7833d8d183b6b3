"""Scripted load test: ``fingertrack bench load [--hands 1,2,4] [--subscribers 2] [--seconds 15]
[--binary] --out DIR``.

For each load level (a number of hands) a fresh service process (``fingertrack serve``, as deployed)
receives that many simulated hands at once, each in its own session (10 IMUs at 200 Hz in per-tick
``imu_batch`` messages, optical poses at 90 Hz, alternately right and left, distinct seeds), streamed
in real time from load-generator processes (below), and every session has ``subscribers`` VR-client subscribers. Per
level it reports:

- frames the service produced (``/v1/sessions``), frames delivered to the subscribers against
  ``produced x subscribers``, and frames the service dropped for slow subscribers;
- glove send -> subscriber receive latency (as ``bench latency``: the time since the glove sent its
  latest message of that session) over all frames of all subscribers;
- integrity: every subscriber's frame ``seq`` strictly increasing and every frame's ``hand`` that of
  its own session (no cross-talk between sessions), a message that does not decode or a frame without
  its ``seq``, ``hand`` or ``t`` counted as a violation too, and ``error`` messages the gloves received;
- backlog: how long after the last message the service still needed to process what it had been
  sent and deliver its last frames (the run waits for every frame to be received or counted as dropped);
- CPU: the service process's CPU time during the streaming window as a share of one core (Linux
  ``/proc``), and the load generator's own share, so that a saturated generator is visible: on a
  2-core machine the gloves, the subscribers and the service compete for the same cores.

The gloves and subscribers run in load-generator processes (``GENERATOR_HANDS`` hands each, or
``--generators N``), started together once each has simulated its gloves, framed their messages,
connected them and opened its subscriptions; a process's gloves are sent from one timer, each message
at its due time (their lag behind it is reported), and its subscribers read each frame for the checked
fields only, a session's second subscriber comparing its bytes with the first's decoded message; while
the gloves stream the subscribers are read at the gloves' timer's wakes, a frame's arrival the moment
its bytes reached the socket (the kernel's receive time), not the moment the generator read them
(``loadclients``). Each reports
its frames, and the frames' delay behind the source's schedule beyond the pipeline's alignment wait
(``_timing``), back as JSON.
"""
from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from ..protocol import PROTOCOL_VERSION
from ..sim.session import SimConfig
from .process import bound_to_this_process, service_process, torn_down_on_signal



FIRST_S = 1.0
"""the first seconds of each session's data left out of the second behind-schedule figure: all of a level's
gloves start in the same moment, and a session's first frames carry its start (its calibration, its fingers'
first ticks tick by tick: about 10 ms of a worker's CPU, so a worker's share of sessions queue behind each
other then), which a venue, where visitors put their gloves on one after another, does not see at once"""

GENERATOR_HANDS = 50
"""hands per load-generator process (gloves and subscribers); more hands: more processes. Each process
wakes at every due time of its gloves' schedule (about 280 a second; its subscribers read then too)
whatever its number of hands, and a wake costs about 50-70 us of CPU here: 50 hands share them where 25
did (at 50 hands one process used about a quarter of a core, 5.0-5.3 ms per hand-second, where two of 25
used 5.4-6.4 together: far from being the bottleneck)"""

PROBE_HEALTH_EVERY_S = 0.05
"""the probe's time between two ``/health`` requests (a load balancer's health check, often)"""
PROBE_METRICS_EVERY_S = 1.0
"""the probe's time between two ``/metrics`` requests by default (``--metrics-every``). The exposition holds some
2 kB per session (52.7 kB at 25 sessions): asked for every 50 ms, as ``/health``, its rendering and reading took
about 8 % of the web process's busy time at 25 hands and the probe process 7 % of a core, a load no monitoring
system puts on a service (a Prometheus server scrapes every 15 s to 1 min)"""


def generator_processes(hands: int) -> int:
    """How many load-generator processes stream ``hands`` hands (``GENERATOR_HANDS`` each)."""
    return max(1, -(-hands // GENERATOR_HANDS))


def _schedule(msgs: list[tuple[float, dict]]) -> list[tuple[float, str, float]]:
    """``(arrival, type, time)`` of each message as ``bench.latency.completing_sends`` reads a send log."""
    out = []
    for arrival, m in msgs:
        kind = m["type"]
        t = max(x["t"] for x in m["samples"]) if kind == "imu_batch" else m.get("t", -np.inf)
        out.append((arrival, kind, t))
    return out


def _timing(rows: list, first_send: float, msgs: list[tuple[float, dict]]) -> tuple[list, list]:
    """For a subscriber's frames: how far behind the source's schedule each arrived beyond the
    pipeline's alignment wait (arrival minus the moment the message that completed its tick was due to
    be sent), and that alignment wait (the completing message's due time minus the tick's own). A
    frame no message completed (the optics' timeout released it) counts from its tick's due time."""
    from ..pipeline.hand import PipelineSettings
    from .latency import completing_sends

    if not rows:
        return [], []
    schedule = _schedule(msgs)
    t0 = msgs[0][0]
    frame_ts = np.array([r[4] for r in rows])
    index = completing_sends(schedule, frame_ts, PipelineSettings().reorder_window_s)
    arrivals = np.array([a for a, _, _ in schedule])
    completed = np.where(index >= 0, arrivals[np.maximum(index, 0)], frame_ts)
    align = np.maximum(completed - frame_ts, 0.0)
    beyond = np.array([r[0] for r in rows]) - (first_send + (completed - t0))
    return beyond.tolist(), align.tolist()


async def _generate(spec: dict, ready, start_at, stop=None) -> dict:
    """One load-generator process's part of a level: the gloves and subscribers of sessions
    ``spec["indices"]``. ``ready()`` once everything is simulated and subscribed; ``start_at()`` gives
    the common start (``time.time()``) of every generator process; ``stop`` (a ``threading.Event``),
    once set, ends the gloves' streams early."""
    from clients.glove import encoded_messages, source_messages

    from .loadclients import GloveSchedule, LeanGlove, LeanSubscription, SessionDecodes, TickReads, stream_gloves, ws_frames

    urls, viewer, subscribers, seconds, binary = spec["urls"], spec["viewer"], spec["subscribers"], spec["seconds"], spec["binary"]
    indices = spec["indices"]
    configs = [SimConfig(motion="random", t_m_s=seconds, noise="both", hand_motion="slow-rotation", seed=i,
                         hand="right" if i % 2 == 0 else "left") for i in indices]
    # simulate every glove, and encode and frame its messages, before the clock starts, so that they all
    # stream together and the gloves only write bytes ready made while they stream
    # the simulated messages are millions of objects that live to the end: the collector's passes over them
    # while they are made took 45 % of that work (13 gloves of 14 s: 2.2 s of CPU, 1.2 s without), and a
    # full collection scanning them took 0.65 s for two hands of 150 s and paused the gloves and
    # subscribers mid-stream (taken for the service's delay): no collection while they are made, then
    # kept out of the collector's generations from here on
    gc.disable()
    try:
        msgs = [source_messages(c) for c in configs]
        frames = [ws_frames(encoded_messages(m, binary)) for m in msgs]
        schedule = GloveSchedule(msgs, frames)
    finally:
        gc.enable()
    gc.collect()
    gc.freeze()
    names = [f"load-{i}" for i in indices]
    frames_got = {(n, k): [] for n in names for k in range(subscribers)}    # (arrival, Received)

    def on_frame_for(got):
        append = got.append
        return lambda msg, arrival: append((arrival, msg))

    # decoded only for the fields checked (``loadclients``); a session's subscribers get the same bytes: one
    # decodes a message, the others compare theirs with it whole (``SessionDecodes``); read at the gloves'
    # wakes while they stream, each read's arrival the kernel's receive time of its bytes (``TickReads``)
    shared = {n: SessionDecodes(binary, subscribers) for n in names}
    reads = TickReads()
    subs = {(n, k): LeanSubscription(urls[(i + k) % len(urls)], n, viewer, on_frame_for(frames_got[(n, k)]),
                                     binary=binary, shared=shared[n], reads=reads)
            for i, n in zip(indices, names) for k in range(subscribers)}
    for s in subs.values():
        s.start()
    # the gloves connected (hello sent) before the clock starts too
    gloves = [LeanGlove(urls[i % len(urls)], n, spec["source"], binary=binary) for i, n in zip(indices, names)]
    await asyncio.gather(*(g.open(m[0][1] if m[0][1]["type"] == "hello" else
                                  {"type": "hello", "protocol": PROTOCOL_VERSION, "hand": c.hand,
                                   "source": f"fingertrack-glove {c.motion}"})
                           for g, m, c in zip(gloves, msgs, configs)))
    deadline = time.monotonic() + 120.0
    while not all(s.server_hello is not None for s in subs.values()) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)                            # the subscriptions are open before any data
    await ready()
    await asyncio.sleep(max(0.0, await start_at() - time.time()))

    switches0 = _waits()
    cpu0, sys0, wall0 = time.process_time(), os.times().system, time.perf_counter()
    first_send = {n: wall0 for n in names}   # every glove's schedule starts then (its first message is due)
    sent = [[] for _ in names]               # each glove's send times, message after message
    reads.start(subs.values())
    await stream_gloves(gloves, msgs, frames, None, wall0, stop, None, sent, schedule, reads)   # one timer for all
    await asyncio.sleep(0.1)
    wall, generator_cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    generator_sys = os.times().system - sys0
    wakes = _waits() - switches0
    # each message's send time minus its due time
    lags = np.concatenate([np.array(t) - (wall0 + np.array(due[:len(t)])) for t, due in zip(sent, schedule.due)])
    # each glove closes once the service has handled everything it sent (sync)
    for r in await asyncio.gather(*(g.close() for g in gloves), return_exceptions=True):
        if isinstance(r, BaseException):
            raise RuntimeError(f"a glove failed: {r!r}") from r
    accounts = await _until_delivered(urls, names, frames_got, subscribers, spec["admin"], indices)
    errors = sum(len(g.errors) for g in gloves)               # after closing: replies to the last messages included
    # a subscriber that reconnects loses what its old connection had queued: neither delivered nor dropped
    reconnects = sum(s.reconnects for s in subs.values())
    glove_reconnects = sum(g.reconnects for g in gloves)
    for r in await asyncio.gather(*(s.close() for s in subs.values()), return_exceptions=True):
        if isinstance(r, BaseException):
            raise RuntimeError(f"a subscriber failed: {r!r}") from r
    reads.close()
    # each frame as (arrival, latency, seq, hand, t): its latency the time since its glove's latest send
    # before it arrived, from the send times kept per glove (a frame is read after the sends of the wake
    # it is read at, and may have arrived before some of them)
    received = {(n, k): _rows(frames_got[(n, k)], sent[gi]) for gi, n in enumerate(names) for k in range(subscribers)}
    # a frame's delay behind the source's schedule: its arrival minus the wall time at which the data
    # of its tick were due to be sent (the first message was sent at first_send, source time m[0][0])
    delays, beyond, align, beyond_by, later = [], [], [], [], []
    for n, m in zip(names, msgs):
        for k in range(subscribers):
            rows = received[(n, k)]
            delays += [r[0] - (first_send[n] + (r[4] - m[0][0])) for r in rows]
            b, a = _timing(rows, first_send[n], m)
            beyond += b
            align += a
            beyond_by.append([n, k, b])
            # the same without the session's first second of data (``FIRST_S``), whose frames carry its start
            later += [x for x, r in zip(b, rows) if r[4] >= m[0][0] + FIRST_S]
    return {"received": [[n, k, rows] for (n, k), rows in received.items()], "beyond_by_subscriber": beyond_by,
            "hands_of": {n: c.hand for n, c in zip(names, configs)}, "accounts": accounts,
            "delays": delays, "beyond_alignment": beyond, "alignment": align, "beyond_alignment_later": later,
            "subscriber_reconnects": reconnects, "glove_reconnects": glove_reconnects, "errors": errors,
            "malformed": sum(s.malformed_count for s in subs.values()),
            "malformed_examples": [repr(m) for s in subs.values() for m in s.malformed][:10],
            "gestures": sum(s.gestures for s in subs.values()), "other_messages": sum(s.others for s in subs.values()),
            "wall_s": wall, "generator_cpu_s": generator_cpu, "generator_system_cpu_s": generator_sys,
            "generator_wakes": wakes,
            "send_lags_us": np.round(lags * 1e6).astype(int).tolist(),
            "messages_decoded": sum(d.decoded for d in shared.values()),
            "messages_compared": sum(d.hits for d in shared.values()),
            "tick_reads": reads.reads, "tick_reads_unstamped": reads.unstamped}


def _waits() -> int:
    """How often this process has waited so far (voluntary context switches: each is a wake after it);
    0 where that cannot be read."""
    try:
        import resource
    except ImportError:
        return 0
    return resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw


def _rows(got: list, sent: list[float]) -> list[tuple]:
    """A subscriber's frames ``(arrival, Received)`` as rows ``(arrival, latency, seq, hand, t)``: latency the
    time since its glove's latest send at or before the frame's arrival (``sent``: the glove's send times,
    in order; NaN for a frame before its glove's first send)."""
    if not got:
        return []
    arrivals, times = np.array([a for a, _ in got]), np.array(sent, dtype=float)
    latest = np.searchsorted(times, arrivals, side="right") - 1
    latency = np.full(len(got), np.nan)
    latency[latest >= 0] = arrivals[latest >= 0] - times[latest[latest >= 0]]
    return [(a, float(lat), m.seq, m.hand, m.t) for (a, m), lat in zip(got, latency)]


def _generator_main() -> int:
    """A load-generator process: its spec (JSON) on the first line of stdin; prints ``ready``, reads the
    common start time (a line), streams (until its data end, or a line ``stop`` comes), and prints its
    results (JSON) on one line."""
    import threading

    spec = json.loads(sys.stdin.readline())
    stop = threading.Event()

    async def ready():
        print("ready", flush=True)

    def until_stop():
        while (line := sys.stdin.readline()) and line.strip() != "stop":
            pass
        if line:
            stop.set()

    async def start_at():
        start = float(await asyncio.to_thread(sys.stdin.readline))
        threading.Thread(target=until_stop, daemon=True).start()
        return start

    result = asyncio.run(_generate(spec, ready, start_at, stop))
    print(json.dumps(result), flush=True)
    return 0


async def _level(urls: list[str], source: str, viewer: str, admin: str, hands: int, subscribers: int, seconds: float,
                 binary: bool, service_cpu, kill=None, processes: int | None = None, end_with_kill: bool = False,
                 metrics_every_s: float = PROBE_METRICS_EVERY_S) -> dict:
    """``urls``: the service's, or its gateways' (session i's glove streams to gateway i, its subscriber
    k listens at gateway i + k, modulo their number, so that frames must reach every gateway).
    ``service_cpu()``: the service processes' CPU seconds so far (None where it cannot be read).
    ``kill``: ``(seconds, coroutine function)`` run that long into the stream (a worker killed);
    ``end_with_kill``: the stream ends when that function returns (at the latest after ``seconds``).
    The gloves and subscribers run in ``processes`` load-generator processes (``generator_processes``); the probe
    (``bench.probe``) asks for ``/metrics`` every ``metrics_every_s``."""
    count = processes or generator_processes(hands)
    parts = [list(range(hands))[j::count] for j in range(count)]
    parts = [p for p in parts if p]
    procs: list = []
    try:
        return await _stream_level(procs, parts, urls, source, viewer, admin, subscribers, seconds, binary,
                                   service_cpu, kill, hands, end_with_kill, metrics_every_s)
    finally:                                        # interrupted (Ctrl-C, SIGTERM): no generator or probe left behind
        for proc in procs:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()


async def _stream_level(procs: list, parts: list, urls: list[str], source: str, viewer: str, admin: str,
                        subscribers: int, seconds: float, binary: bool, service_cpu, kill, hands: int,
                        end_with_kill: bool = False, metrics_every_s: float = PROBE_METRICS_EVERY_S) -> dict:
    """``_level``'s run; every process it starts goes into ``procs`` at once."""
    url = urls[0]
    for part in parts:
        proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "service.bench.load",
                                                    stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
                                                    limit=1 << 30, preexec_fn=bound_to_this_process())
        procs.append(proc)
        spec = {"urls": urls, "source": source, "viewer": viewer, "admin": admin, "indices": part,
                "subscribers": subscribers, "seconds": seconds, "binary": binary}
        proc.stdin.write((json.dumps(spec) + "\n").encode())
        await proc.stdin.drain()
    generators = list(procs)
    for proc in generators:
        line = await proc.stdout.readline()
        if line.strip() != b"ready":
            raise RuntimeError("a load-generator process did not start")
    start = time.time() + 0.5
    for proc in generators:
        proc.stdin.write(f"{start!r}\n".encode())
        await proc.stdin.drain()
    await asyncio.sleep(max(0.0, start - time.time()))
    # CPU shares over the streaming window only (the service may work on past it when it falls behind)
    service0, wall0 = service_cpu(), time.perf_counter()
    killed: dict = {}

    async def kill_later():
        await asyncio.sleep(kill[0])
        killed.update(await kill[1]())
        killed["t"] = time.perf_counter()

    killer = asyncio.create_task(kill_later()) if kill is not None else None
    probe = await _start_probe(url, admin, seconds, metrics_every_s)
    procs.append(probe)
    if end_with_kill and killer is not None:
        await asyncio.wait([killer], timeout=max(0.0, seconds - (time.perf_counter() - wall0)))
        for proc in generators + [probe]:
            with contextlib.suppress(ConnectionError):
                if proc is probe:
                    proc.terminate()                # it reports what it measured so far
                else:
                    proc.stdin.write(b"stop\n")
                    await proc.stdin.drain()
    else:
        await asyncio.sleep(max(0.0, seconds - (time.perf_counter() - wall0)))
    service1, wall = service_cpu(), time.perf_counter() - wall0
    probed = await _probe_result(probe)
    if killer is not None:
        await killer
    results = []
    for proc in generators:
        out, _ = await proc.communicate()
        if await proc.wait() != 0 or not out.strip():
            raise RuntimeError("a load-generator process failed")
        results.append(json.loads(out.strip().splitlines()[-1]))
    service2, busy_wall = service_cpu(), time.perf_counter() - wall0      # every frame delivered or dropped
    drain = busy_wall - wall
    received = {(n, k): [tuple(r) for r in rows] for res in results for n, k, rows in res["received"]}
    shares = [r["generator_cpu_s"] / r["wall_s"] for r in results]
    return {"names": [f"load-{i}" for i in range(hands)],
            "hands_of": {n: h for r in results for n, h in r["hands_of"].items()}, "received": received,
            "delays": [d for r in results for d in r["delays"]],
            "beyond_alignment": [d for r in results for d in r["beyond_alignment"]],
            "beyond_alignment_later": [d for r in results for d in r["beyond_alignment_later"]],
            "beyond_by_subscriber": {(n, k): b for r in results for n, k, b in r["beyond_by_subscriber"]},
            "alignment": [d for r in results for d in r["alignment"]],
            "killed": killed, "probe": probed,
            "subscriber_reconnects": sum(r["subscriber_reconnects"] for r in results),
            "accounts": {n: a for r in results for n, a in r["accounts"].items()},
            "glove_reconnects": sum(r["glove_reconnects"] for r in results),
            "wall_s": wall, "drain_s": drain, "generator_cpu_s": sum(r["generator_cpu_s"] for r in results),
            "generator_processes": len(results), "generator_cpu_share": sum(shares),
            "generator_system_cpu_s": sum(r["generator_system_cpu_s"] for r in results),
            "generator_cpu_share_max": max(shares),
            "send_lag_ms": _quantiles(np.array([x for r in results for x in r["send_lags_us"]]) * 1e-3),
            "messages_decoded": sum(r["messages_decoded"] for r in results),
            "messages_compared": sum(r["messages_compared"] for r in results),
            "generator_wakes_per_s": sum(r["generator_wakes"] / r["wall_s"] for r in results),
            "tick_reads": sum(r["tick_reads"] for r in results),
            "tick_reads_unstamped": sum(r["tick_reads_unstamped"] for r in results),
            "service_cpu_until_drained_s": None if service0 is None or service2 is None else service2 - service0,
            "until_drained_wall_s": busy_wall,
            "errors": sum(r["errors"] for r in results),
            "malformed": sum(r["malformed"] for r in results),
            "malformed_examples": [m for r in results for m in r["malformed_examples"]][:10],
            "gestures": sum(r["gestures"] for r in results), "other_messages": sum(r["other_messages"] for r in results),
            "service_cpu_s": None if service0 is None or service1 is None else service1 - service0}


def _accounts(urls: list[str], names: list[str], summaries: list[dict], received: dict, subscribers: int,
              indices: list[int]) -> dict:
    """Per session, over every gateway (or the one service): frames the service sent out to this
    level's subscribers (each gateway's ``frames_out`` times its subscribers of the session), dropped
    for slow subscribers, and delivered; subscriber k of session i listens at gateway (i + k) mod G."""
    out = {}
    for i, n in zip(indices, names):
        expected = dropped = produced = 0
        for g, by_name in enumerate(summaries):
            here = [k for k in range(subscribers) if (i + k) % len(urls) == g]
            if n in by_name and here:
                expected += by_name[n]["frames_out"] * len(here)
                dropped += by_name[n]["dropped_subscriber_frames"]
            if n in by_name:
                produced = max(produced, by_name[n]["frames_out"])
        out[n] = {"expected": expected, "dropped": dropped, "produced": produced,
                  "delivered": sum(len(received[(n, k)]) for k in range(subscribers))}
    return out


async def _until_delivered(urls: list[str], names: list[str], received: dict, subscribers: int, admin: str,
                           indices: list[int], timeout_s: float = 120.0) -> dict:
    """Wait until every frame the service produced was received or counted as dropped, for every
    subscriber (the service has handled all it was sent once the gloves are closed); returns the
    accounts (``_accounts``). Bounded: after ``timeout_s`` the accounts show what is missing."""
    from clients.client import rest

    deadline = time.monotonic() + timeout_s
    while True:
        summaries = []
        for url in urls:
            _, sessions = await asyncio.to_thread(rest, url, "GET", "/v1/sessions", admin)
            summaries.append({s["session"]: s for s in sessions})
        accounts = _accounts(urls, names, summaries, received, subscribers, indices)
        if all(a["delivered"] + a["dropped"] >= a["expected"] for a in accounts.values()) \
                or time.monotonic() > deadline:
            return accounts
        await asyncio.sleep(0.05)


async def _start_probe(url: str, token: str, seconds: float, metrics_every_s: float = PROBE_METRICS_EVERY_S):
    """The health and metrics probe (``bench.probe``) in its own process, for the streaming window: ``/health``
    every ``PROBE_HEALTH_EVERY_S``, ``/metrics`` every ``metrics_every_s``."""
    env = {**os.environ, "FINGERTRACK_PROBE_TOKEN": token}
    return await asyncio.create_subprocess_exec(sys.executable, "-m", "service.bench.probe", url, f"{seconds:g}",
                                                repr(PROBE_HEALTH_EVERY_S), repr(metrics_every_s),
                                                stdout=asyncio.subprocess.PIPE, env=env, preexec_fn=bound_to_this_process())


async def _probe_result(proc) -> dict | None:
    out, _ = await proc.communicate()
    try:
        return json.loads(out)
    except ValueError:
        return None


def _integrity(received: dict, hands_of: dict) -> int:
    """Frames out of order (seq not strictly increasing) or of another session's hand, over all subscribers."""
    bad = 0
    for (name, _), rows in received.items():
        seq = np.array([r[2] for r in rows])
        bad += int(np.sum(np.diff(seq) <= 0)) if len(seq) > 1 else 0
        bad += sum(1 for r in rows if r[3] != hands_of[name])
    return bad


def _recovery(received: dict, killed: dict, subscribers: int) -> dict | None:
    """After a worker was killed: for each session it owned, the time from the kill to the first frame
    a subscriber got from the new owner, and the frames never produced (the jump in ``seq``)."""
    if not killed:
        return None
    t_kill, moved = killed["t"], killed["sessions"]
    times, lost = [], 0
    for name in moved:
        rows = received[(name, 0)]
        after = [r for r in rows if r[0] > t_kill]
        before = [r for r in rows if r[0] <= t_kill]
        if not after:
            times.append(float("inf"))
            continue
        base = before[-1][2] if before else after[0][2] - 1
        jump = next((i for i, r in enumerate(after) if r[2] - (after[i - 1][2] if i else base) > 1), None)
        times.append(after[jump][0] - t_kill if jump is not None else after[0][0] - t_kill)
        seqs = [base] + [r[2] for r in after]
        lost += sum(b - a - 1 for a, b in zip(seqs, seqs[1:]) if b - a > 1)
    return {"worker": killed["worker"], "sessions_moved": len(moved),
            "recovery_s_max": max(times) if times else None, "recovery_s": times,
            "frames_never_produced": lost, "messages_lost": killed.get("messages_lost"),
            "messages_resent": killed.get("messages_resent")}


def run_level(hands: int, subscribers: int = 2, seconds: float = 15.0, binary: bool = False,
              bus_workers: int | None = None, kill_at_s: float | None = None, hand_workers: int | None = None,
              gateways: int = 1, generators: int | None = None, metrics_every_s: float = PROBE_METRICS_EVERY_S) -> dict:
    """One load level in a fresh service process (with ``hand_workers`` hand worker processes; None: the
    service's default), or with ``bus_workers`` a fresh NATS cluster (``gateways`` gateways and that
    many workers). ``kill_at_s``: the worker owning most sessions is killed (SIGKILL) that long into the
    stream. ``generators``: load-generator processes (None: ``generator_processes``). ``metrics_every_s``: the
    probe's time between two ``/metrics`` requests. Returns the level's measured figures."""
    from clients.client import rest

    # one source token streams every glove and one viewer token serves every subscriber
    limits = {"max_sessions": max(64, hands), "max_sessions_per_token": max(8, hands),
              "max_connections_per_token": max(32, hands * (subscribers + 1))}
    with contextlib.ExitStack() as stack:
        readings: list = []                        # the workers' CPU seconds at the streaming window's ends
        if bus_workers is None:
            # no spare hand worker: no estimator is switched, and its start would fall into the measured window
            extra = {**limits, "hand_worker_spare": False, **({} if hand_workers is None else {"hand_workers": hand_workers})}
            svc = stack.enter_context(service_process(extra_settings=extra))
            urls = [svc.url]

            def service_cpu():
                own, workers = svc.cpu_seconds(), svc.children_cpu_seconds()
                readings.append(workers)
                return None if own is None or workers is None else own + workers

            async def kill_busiest():
                _, sessions = await asyncio.to_thread(rest, svc.url, "GET", "/v1/sessions", svc.admin)
                pids = {x["session"]: x["worker"]["pid"] for x in sessions if x.get("worker")}
                if not pids:
                    return {"worker": None, "sessions": []}
                victim = max(set(pids.values()), key=list(pids.values()).count)
                os.kill(victim, signal.SIGKILL)
                return {"worker": f"pid {victim}", "sessions": [n for n, p in pids.items() if p == victim]}
        else:
            from .cluster import cluster
            cl = stack.enter_context(cluster(bus_workers, gateways=gateways, extra_settings=limits))
            svc = cl.gateway
            urls = [g.url for g in cl.gateways]

            def service_cpu():
                g, w = [x.cpu_seconds() for x in cl.gateways], cl.worker_cpu_seconds()
                readings.append(w)
                return None if None in g or w is None else sum(g) + w

            async def kill_busiest():
                owners = await cl.owners()
                counts = {w: sum(1 for o in owners.values() if o == w) for w in cl.workers}
                victim = max(counts, key=counts.get)
                cl.kill(victim)
                return {"worker": victim, "sessions": [s for s, o in owners.items() if o == victim]}
        kill = (kill_at_s, kill_busiest) if kill_at_s is not None else None
        lvl = asyncio.run(_level(urls, svc.source, svc.viewer, svc.admin, hands, subscribers, seconds, binary,
                                 service_cpu, kill, generators, metrics_every_s=metrics_every_s))
        w0, w1 = (readings[0], readings[1]) if len(readings) >= 2 else (None, None)
        summaries = [rest(url, "GET", "/v1/sessions", svc.admin)[1] for url in urls]
    every = [x for sessions in summaries for x in sessions if x["session"] in lvl["names"]]   # all gateways
    by_name = {x["session"]: x for x in every}
    if lvl["killed"]:
        lvl["killed"]["messages_lost"] = sum(x.get("lost_to_failover", 0) for x in every)
        lvl["killed"]["messages_resent"] = sum(x.get("resent_after_failover", 0)
                                               + x.get("worker", {}).get("resent_after_restart", 0) for x in every)
    accounts = lvl["accounts"]
    produced = sum(a["produced"] for a in accounts.values())
    dropped = sum(a["dropped"] for a in accounts.values())
    rows = [r for v in lvl["received"].values() for r in v]
    lat = np.array([r[1] for r in rows if np.isfinite(r[1])]) * 1e3
    delay = np.array(lvl["delays"]) * 1e3
    beyond = np.array(lvl["beyond_alignment"]) * 1e3
    align = np.array(lvl["alignment"]) * 1e3
    delivered = len(rows)
    service_share = None if lvl["service_cpu_s"] is None else lvl["service_cpu_s"] / lvl["wall_s"]
    worker_share = None if w0 is None or w1 is None else (w1 - w0) / lvl["wall_s"]
    return {
        "hands": hands, "subscribers_per_hand": subscribers, "seconds": seconds, "binary": binary,
        "sessions_seen": sum(1 for n in lvl["names"] if n in by_name),
        "frames_produced": int(produced), "frames_expected": int(sum(a["expected"] for a in accounts.values())),
        "frames_delivered": int(delivered), "frames_dropped": int(dropped),
        "per_subscriber_min": int(min((len(v) for v in lvl["received"].values()), default=0)),
        "latency_ms": ({"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                        "max": float(lat.max())} if lat.size else None),
        "schedule_delay_ms": ({"p50": float(np.percentile(delay, 50)), "p99": float(np.percentile(delay, 99)),
                               "max": float(delay.max())} if delay.size else None),
        "behind_schedule_beyond_alignment_ms": _quantiles(beyond), "alignment_wait_ms": _quantiles(align),
        "behind_schedule_beyond_alignment_after_first_s_ms": _quantiles(np.array(lvl["beyond_alignment_later"]) * 1e3),
        "frames_unaccounted": int(sum(max(0, a["expected"] - a["delivered"] - a["dropped"]) for a in accounts.values())),
        # a frame that did not decode, or lacked its seq, hand or time, is a violation too
        "integrity_violations": _integrity(lvl["received"], lvl["hands_of"]) + lvl["malformed"],
        "malformed_examples": lvl["malformed_examples"],
        "subscriber_gestures": lvl["gestures"], "subscriber_other_messages": lvl["other_messages"],
        "hand_worker_restarts": sum(x.get("worker", {}).get("restarts", 0) for x in every),
        "source_errors": int(lvl["errors"]),
        "subscriber_reconnects": lvl["subscriber_reconnects"], "glove_reconnects": lvl["glove_reconnects"],
        "service_cpu_share": service_share,
        "bus_workers": bus_workers, "gateways": gateways if bus_workers is not None else None,
        "hand_workers": hand_workers,
        "worker_cpu_share": worker_share,
        "web_cpu_share": None if service_share is None or worker_share is None else service_share - worker_share,
        "probe": lvl["probe"], "probe_metrics_every_s": metrics_every_s,
        "failover": _recovery(lvl["received"], lvl["killed"], subscribers),
        "generator_cpu_share": lvl["generator_cpu_share"],
        "service_cpu_share_until_drained": (None if lvl["service_cpu_until_drained_s"] is None
                                            else lvl["service_cpu_until_drained_s"] / lvl["until_drained_wall_s"]),
        "worker_cpu_share_until_drained": (None if len(readings) < 3 or None in readings[:3]
                                           else (readings[2] - readings[0]) / lvl["until_drained_wall_s"]),
        "front_cpu_s_per_hand_s": (None if lvl["service_cpu_until_drained_s"] is None or len(readings) < 3
                                   or None in readings[:3]
                                   else (lvl["service_cpu_until_drained_s"] - (readings[2] - readings[0]))
                                   / (hands * seconds)),
        "generator_processes": lvl["generator_processes"],
        "generator_cpu_share_max": lvl["generator_cpu_share_max"],
        # the generator processes' wakes (voluntary context switches) per second while they stream, summed
        "generator_wakes_per_s": lvl["generator_wakes_per_s"],
        # how late the gloves sent their messages (send time minus due time, every message): the
        # generator's own lag, which the frames' delay behind schedule includes, and the time a glove held a
        # message while 256 of its messages were unconfirmed (the glove's flow control, when the service is behind)
        "glove_send_lag_ms": lvl["send_lag_ms"],
        # the subscribers' messages decoded, and those compared whole with a decoded one of the session
        "subscriber_messages_decoded": lvl["messages_decoded"],
        "subscriber_messages_compared": lvl["messages_compared"],
        # the subscribers' reads at the gloves' wakes while they streamed (``TickReads``), and those of them
        # without the kernel's receive time (their frames' arrival then taken at the read)
        "subscriber_tick_reads": lvl["tick_reads"], "subscriber_tick_reads_unstamped": lvl["tick_reads_unstamped"],
        # the generator's CPU seconds (user + system; system alone) per second of one hand's data
        "generator_cpu_s_per_hand_s": lvl["generator_cpu_s"] / (hands * seconds),
        "generator_system_cpu_s_per_hand_s": lvl["generator_system_cpu_s"] / (hands * seconds),
        "stream_wall_s": lvl["wall_s"],
        "drain_after_stream_s": lvl["drain_s"],
    }


def run(out_dir: str | Path, hands: tuple[int, ...] = (1, 2, 4), subscribers: int = 2, seconds: float = 15.0,
        binary: bool = False, progress: bool = True, bus_workers: int | None = None,
        kill_at_s: float | None = None, hand_workers: int | None = None, gateways: int = 1,
        generators: int | None = None, metrics_every_s: float = PROBE_METRICS_EVERY_S) -> str:
    from tqdm import tqdm

    if not hands or any(h < 1 for h in hands):
        raise ValueError(f"hands must be positive counts, got {list(hands)}")
    if subscribers < 1:
        raise ValueError(f"subscribers must be at least 1, got {subscribers}")
    if bus_workers is not None and bus_workers < 1:
        raise ValueError(f"--bus nats needs at least one worker, got --workers {bus_workers}")
    if gateways < 1 or (gateways > 1 and bus_workers is None):
        raise ValueError(f"--gateways {gateways}: more than one gateway needs --bus nats")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if kill_at_s is not None and bus_workers is not None and bus_workers < 2:
        raise ValueError("--kill-worker-at with --bus nats needs at least 2 workers (one takes the other's sessions over)")
    if kill_at_s is not None and bus_workers is None and hand_workers == 0:
        raise ValueError("--kill-worker-at needs hand worker processes (--workers 0 runs the hands in the service)")
    if kill_at_s is not None and not 0 < kill_at_s < seconds:
        raise ValueError(f"--kill-worker-at must lie inside the stream (0 < S < {seconds:g} s), got {kill_at_s:g}")
    with torn_down_on_signal():                     # SIGTERM stops the service and generators as Ctrl-C does
        levels = [run_level(h, subscribers, seconds, binary, bus_workers, kill_at_s, hand_workers, gateways, generators,
                            metrics_every_s)
                  for h in tqdm(hands, desc="bench load", unit="level", disable=not progress)]
    (out / "results.json").write_text(json.dumps(levels, indent=2))
    return summary(levels, out)


def _quantiles(ms: np.ndarray) -> dict | None:
    if not ms.size:
        return None
    return {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


def _ms(stats: dict | None) -> str:
    return "-" if not stats or stats.get("p50_ms") is None else f"{stats['p50_ms']:.1f} / {stats['p99_ms']:.1f}"


def summary(levels: list[dict], out: Path | None = None) -> str:
    """The levels as Markdown tables (written to ``out/summary.md`` when given)."""
    first = levels[0]
    subscribers, seconds, bus_workers = first["subscribers_per_hand"], first["seconds"], first["bus_workers"]
    metrics_every = first.get("probe_metrics_every_s", PROBE_HEALTH_EVERY_S)     # (earlier results: with /health)
    enc = "MessagePack" if first["binary"] else "JSON"
    if bus_workers is None:
        workers = first.get("hand_workers")
        where = ("one service process, its hands on the event loop" if workers == 0 else
                 f"one service process with {'its default number of' if workers is None else workers} hand worker processes")
    else:
        g = first.get("gateways") or 1
        where = f"NATS: {g} gateway{'s' if g > 1 else ''} and {bus_workers} workers, own processes"
    lines = [f"# Load: hands at once, {subscribers} subscribers per hand, {seconds:.0f} s per level, {enc}, {where}", "",
             "| hands | frames produced | delivered / expected | dropped | unaccounted | send -> receive p50 / p99, ms | "
             "behind schedule beyond the alignment wait p50 / p99 / max, ms | alignment wait p50 / p99, ms | "
             "service still busy after the stream, s | service CPU, % of a core | "
             "generator CPU, % of a core (processes; busiest, %) | gloves' send lag p50 / p99, ms | "
             "integrity violations | source errors | "
             "/health p50 / p99, ms | /metrics p50 / p99, ms | reconnects: subscribers / gloves |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for lv in levels:
        lat = lv["latency_ms"]
        lat_s = "-" if lat is None else f"{lat['p50']:.1f} / {lat['p99']:.1f}"
        d = lv["behind_schedule_beyond_alignment_ms"]
        delay_s = "-" if d is None else f"{d['p50']:.1f} / {d['p99']:.1f} / {d['max']:.0f}"
        a = lv["alignment_wait_ms"]
        align_s = "-" if a is None else f"{a['p50']:.0f} / {a['p99']:.0f}"
        cpu = "-" if lv["service_cpu_share"] is None else f"{100 * lv['service_cpu_share']:.0f}"
        gen = (f"{100 * lv['generator_cpu_share']:.0f} ({lv['generator_processes']}; "
               f"{100 * lv['generator_cpu_share_max']:.0f})")
        lag = lv.get("glove_send_lag_ms")
        lag_s = "-" if not lag else f"{lag['p50']:.2f} / {lag['p99']:.2f}"
        probe = lv.get("probe") or {}
        lines.append(f"| {lv['hands']} | {lv['frames_produced']} | {lv['frames_delivered']} / {lv['frames_expected']} | "
                     f"{lv['frames_dropped']} | {lv['frames_unaccounted']} | {lat_s} | {delay_s} | {align_s} | "
                     f"{lv['drain_after_stream_s']:.1f} | {cpu} | {gen} | {lag_s} | "
                     f"{lv['integrity_violations']} | {lv['source_errors']} | {_ms(probe.get('health'))} | {_ms(probe.get('metrics'))} | "
                     f"{lv.get('subscriber_reconnects', '-')} / {lv.get('glove_reconnects', '-')} |")
    front = "web process" if bus_workers is None else "gateways"
    lines += ["", f"| hands | workers' CPU, % of a core | {front}' CPU, % | service CPU until every frame was delivered, % "
              f"(workers') | {front}' CPU per second of data per hand, ms | hand worker restarts | worker killed | "
              "sessions on it | kill -> first frame after it, max s | frames never produced | source messages resent / lost | "
              f"behind schedule beyond the alignment wait after each session's first {FIRST_S:g} s p50 / p99 / max, ms |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for lv in levels:
        wc = "-" if lv["worker_cpu_share"] is None else f"{100 * lv['worker_cpu_share']:.0f}"
        svc, work = lv["service_cpu_share"], lv["worker_cpu_share"]
        fc = "-" if svc is None or work is None else f"{100 * (svc - work):.0f}"
        fo = lv["failover"]
        sd, wd = lv.get("service_cpu_share_until_drained"), lv.get("worker_cpu_share_until_drained")
        drained = ("-" if sd is None else f"{100 * sd:.0f}") + ("" if wd is None else f" ({100 * wd:.0f})")
        restarts = lv.get("hand_worker_restarts", "-")
        per_hand = "-" if lv.get("front_cpu_s_per_hand_s") is None else f"{1e3 * lv['front_cpu_s_per_hand_s']:.1f}"
        d = lv.get("behind_schedule_beyond_alignment_after_first_s_ms")
        later = "-" if d is None else f"{d['p50']:.1f} / {d['p99']:.1f} / {d['max']:.0f}"
        if fo is None:
            lines.append(f"| {lv['hands']} | {wc} | {fc} | {drained} | {per_hand} | {restarts} | - | - | - | - | - | {later} |")
        else:
            rec = "-" if fo["recovery_s_max"] is None else f"{fo['recovery_s_max']:.2f}"
            lines.append(f"| {lv['hands']} | {wc} | {fc} | {drained} | {per_hand} | {restarts} | {fo['worker']} | {fo['sessions_moved']} | {rec} | "
                         f"{fo['frames_never_produced']} | {fo['messages_resent']} / {fo['messages_lost']} | {later} |")
    lines += ["", "Send -> receive: the time since the glove sent its latest message of that session (it cannot show "
              "a backlog: with one message every 5 ms it stays small even when frames are late). Behind schedule beyond "
              "the alignment wait: a frame's arrival after the moment the message that completed its tick (the reorder "
              "window passed and a pose at or after the tick arrived, `bench latency`'s rule) was due to be sent by the "
              "source's schedule; it grows without bound when the service or the generator falls behind. A frame's "
              "arrival: while the gloves stream, the moment its bytes reached the generator's socket (the kernel's "
              "receive time of the last TCP segment read with it; the subscribers are read at the gloves' timer's "
              "wakes), after that the moment it was read. The same after each session's first second: without the "
              "frames of each session's first second of data, which carry its start (every glove of a level starts "
              "at once). Alignment "
              "wait: the pipeline's deliberate wait, that message's due time minus the tick's (the optics' 20 ms latency "
              "and the 20 ms reorder window). Unaccounted: frames the service sent out that were neither delivered nor "
              "counted as dropped. /health and /metrics: response times measured during the stream by a probe "
              f"in its own process (admin token): /health every {PROBE_HEALTH_EVERY_S * 1e3:g} ms, as a load balancer's health "
              f"check, /metrics every {metrics_every:g} s (`--metrics-every`; a Prometheus server scrapes every 15 s "
              "to 1 min). CPU per second of data per hand: the "
              "web process's (or gateways') user + system CPU time from the stream's start until every frame was "
              "delivered, over hands x seconds streamed (it holds on a loaded machine, where shares of a core "
              "do not). Reconnects: a subscriber whose connection "
              "dropped (e.g. a keepalive timeout on a starved machine) loses the frames its old connection had queued, "
              "which are then neither delivered nor counted as dropped. Each level runs in a fresh service; "
              f"the generator (gloves and subscribers, {GENERATOR_HANDS} hands per process) shares the machine with it: "
              "its CPU is the sum over its processes while they stream, the busiest process's share beside it (near "
              "100 % it would be the bottleneck). Gloves' send lag: each message's send time minus its due time by "
              "the source's schedule, over every message (the gloves' timer wakes at the due times to the kernel "
              "timer's precision; a lag there, e.g. a generator short of CPU, is in the delay behind schedule too); it also "
              "counts the time a glove held a message while the service had many of its messages unconfirmed (flow "
              "control: seconds when the service is behind)."]
    text = "\n".join(lines) + "\n"
    if out is not None:
        (out / "summary.md").write_text(text)
    return text


if __name__ == "__main__":
    sys.exit(_generator_main())
