"""Latency benchmark: ``fingertrack bench latency [--seconds N] [--imu-rate HZ] [--hand-workers N] --out DIR``.

The service runs as its own process (``fingertrack serve`` on a free localhost port, as deployed); a
second process streams one simulated hand in real time (10 IMUs at 200 Hz or ``--imu-rate``, each
tick one ``imu_batch``, optical poses at 90 Hz) and a third subscribes to the frames. For every frame
received, the latency is the time since the glove sent the message that completed the frame's tick
(``completing_sends``: the first after which the reorder window has passed and a pose covers the
tick) to the moment the frame's last bytes are read from the subscriber's socket, on the machine's
monotonic clock: transport both ways plus the service's processing. (Until the subscriber's own decoding
is done, this benchmark's figure before, is reported beside it: the Python client's decoding of a frame,
the subscriber's work, not the service's, took 0.5-0.8 ms with the standard library's ``json`` and a
walk of the value, and is read by ``msgspec`` now, about eight times fewer instructions. The time
since the glove's latest send, this benchmark's earlier figure, is reported beside it: at high IMU
rates a later message has often been sent by the time a frame arrives, which makes that figure too
small.) The service's own ingest-to-send histogram (``/metrics``) is reported too. The pipeline's
deliberate alignment delay (reorder window, optical latency) is on the source clock and not part of
these figures. The subscriber freezes its heap once connected and reports its own garbage collections,
so that a pause of the measuring process is neither counted as the service's latency nor unseen.
"""
from __future__ import annotations

import asyncio
import collections
import json
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np

from ..sim.session import SimConfig
from .process import end_with_parent, service_process, torn_down_on_signal


def _histogram_quantile(metrics_text: str, q: float) -> float | None:
    buckets = []
    for line in metrics_text.splitlines():
        if line.startswith("fingertrack_ingest_to_send_seconds_bucket"):
            le = line.split('le="')[1].split('"')[0]
            buckets.append((float("inf") if le == "+Inf" else float(le), float(line.rsplit(" ", 1)[1])))
    if not buckets or buckets[-1][1] == 0:
        return None
    total = buckets[-1][1]
    for le, count in sorted(buckets):
        if count >= q * total:
            return le
    return None


def _gc_pauses(pauses: list) -> object:
    """A ``gc.callbacks`` entry that appends each collection's ``(generation, duration in ms)``."""
    started = [0.0]

    def callback(phase: str, info: dict) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
        else:
            pauses.append((info["generation"], 1e3 * (time.perf_counter() - started[0])))
    return callback


def _timed_connection():
    """A WebSocket client connection class that notes, on the machine's monotonic clock
    (``time.perf_counter``), when each whole data message has arrived (``arrivals``, in order): the moment
    its last bytes are read from the socket, before the client decodes it."""
    from websockets.asyncio.client import ClientConnection
    from websockets.frames import DATA_OPCODES, Frame

    class TimedConnection(ClientConnection):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.arrivals: collections.deque[float] = collections.deque()

        def process_event(self, event) -> None:
            if isinstance(event, Frame) and event.opcode in DATA_OPCODES and event.fin:
                self.arrivals.append(time.perf_counter())
            super().process_event(event)
    return TimedConnection


def _subscriber(url: str, viewer: str, ready, stop, conn, parent: int) -> None:
    """The subscriber, in its own process (so the glove's sends never delay its reads): every frame's
    ``(arrival time, decoded time, frame t, decoding's duration)`` on the machine's monotonic clock
    (``time.perf_counter``): when the frame's last bytes were read from the socket, when the Python
    client's decoding (``clients.client``, ``protocol.decode``: ``msgspec``, which refuses non-finite
    numbers and deep nesting as it reads) had it ready, and how long that decoding took; sent back
    through ``conn`` once ``stop`` is set, with its own garbage collections' pauses. Its heap is frozen
    once it is connected (a full collection of its modules took 0.3 s on a busy machine, and would be
    counted as the service's latency); the collections left are reported. It ends with the benchmark's
    process (``parent``), however that ends."""
    import gc

    end_with_parent(parent)

    from websockets.asyncio.client import connect

    from clients.client import _decode, _path, _url

    received: list[tuple[float, float, float, float]] = []
    pauses: list[tuple[int, float]] = []

    async def main():
        async with connect(_url(url, _path("stream", "bench"), viewer, False), max_size=None,
                           create_connection=_timed_connection()) as ws:
            await ws.recv()                         # the server's hello
            ws.arrivals.popleft()

            async def collect():
                async for data in ws:
                    arrived = ws.arrivals.popleft()
                    start = time.perf_counter()
                    msg = _decode(data)
                    if msg["type"] == "frame":
                        decoded = time.perf_counter()
                        received.append((arrived, decoded, msg["t"], decoded - start))

            task = asyncio.create_task(collect())
            gc.freeze()
            gc.callbacks.append(_gc_pauses(pauses))
            ready.set()
            while not stop.is_set() and not task.done():
                await asyncio.sleep(0.05)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    asyncio.run(main())
    conn.send((received, pauses))
    conn.close()


def completing_sends(sends: list[tuple[float, str, float]], frame_ts: np.ndarray, reorder_window_s: float) -> np.ndarray:
    """For each frame time, the index in ``sends`` (``(wall time, type, source time)`` in send order;
    an ``imu_batch``'s time is its newest sample's) of the message that completed the frame's tick: the
    first after which both the reorder window has passed (an IMU sample at least ``reorder_window_s``
    newer) and a pose at or after the tick has arrived (``pipeline.hand``'s rule); -1 where no message
    did (the optics' timeout released the tick, or the stream ended first)."""
    imu = np.maximum.accumulate([t if kind == "imu_batch" else -np.inf for _, kind, t in sends])
    pose = np.maximum.accumulate([t if kind == "pose" else -np.inf for _, kind, t in sends])
    i_imu = np.searchsorted(imu, frame_ts + reorder_window_s - 1e-12, side="left")
    i_pose = np.searchsorted(pose, frame_ts, side="left")
    index = np.maximum(i_imu, i_pose)
    return np.where(index < len(sends), index, -1)


async def _stream(url: str, source: str, config: SimConfig) -> list[tuple[float, str, float]]:
    from clients.glove import stream_glove

    sends: list[tuple[float, str, float]] = []

    def on_send(wall, msg):
        kind = msg["type"]
        t = max(s["t"] for s in msg["samples"]) if kind == "imu_batch" else msg.get("t", -np.inf)
        sends.append((wall, kind, t))
    pub = await stream_glove(url, "bench", source, config, on_send=on_send)
    await asyncio.sleep(0.5)
    await pub.close()
    return sends


def _measure(url: str, source: str, viewer: str, config: SimConfig) -> tuple[list, list]:
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_subscriber, args=(url, viewer, ready, stop, child, os.getpid()), daemon=True)
    proc.start()
    try:
        if not ready.wait(120.0):
            raise RuntimeError("the subscriber did not connect")
        sends = asyncio.run(_stream(url, source, config))
        stop.set()
        received, pauses = parent.recv() if parent.poll(60.0) else ([], [])
    finally:
        stop.set()
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
    return sends, received, pauses


def _quantiles(ms: np.ndarray) -> dict:
    if not len(ms):
        return {"p50": None, "p95": None, "p99": None, "max": None}
    return {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)),
            "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


def run(out_dir: str | Path, seconds: float = 20.0, imu_rate_hz: float = 200.0, hand_workers: int | None = None) -> str:
    """``hand_workers``: the service's setting of that name (its default where None; 0 runs the hands
    on the service's event loop)."""
    from clients.client import rest

    from ..pipeline.hand import PipelineSettings

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # no spare hand worker: this stream switches no estimator, and its start (2.4 s of CPU) would fall
    # into the measured window
    extra = {"hand_worker_spare": False, **({} if hand_workers is None else {"hand_workers": hand_workers})}
    load_before = _load_average()
    # SIGTERM stops the service and the subscriber as Ctrl-C does
    with torn_down_on_signal(), service_process(extra_settings=extra) as svc:
        config = SimConfig(motion="random", t_m_s=seconds, noise="both", hand_motion="slow-rotation", seed=0,
                           rate_hz=imu_rate_hz)
        cpu0 = (svc.cpu_seconds(), svc.children_cpu_seconds())
        wall0 = time.perf_counter()
        sends, received, sub_pauses = _measure(svc.url, svc.source, svc.viewer, config)
        wall = time.perf_counter() - wall0
        cpu1 = (svc.cpu_seconds(), svc.children_cpu_seconds())
        _, metrics_text = rest(svc.url, "GET", "/metrics", svc.admin)
    # the service's CPU while it streamed (its web process, and its hand workers), in % of one core
    service_cpu = {name: (None if a is None or b is None else 100 * (b - a) / wall)
                   for name, a, b in (("web_process_pct", cpu0[0], cpu1[0]), ("hand_workers_pct", cpu0[1], cpu1[1]))}
    frame_ts = np.array([r[2] for r in received])
    recv_wall = np.array([r[0] for r in received])
    decoded_wall = np.array([r[1] for r in received])
    done = completing_sends(sends, frame_ts, PipelineSettings().reorder_window_s) if len(received) else np.zeros(0, int)
    matched = done >= 0
    send_wall = np.array([w for w, _, _ in sends])
    exact = (recv_wall[matched] - send_wall[done[matched]]) * 1e3
    # the figure before the arrival time was taken: once the Python client had decoded the frame
    decoded = (decoded_wall[matched] - send_wall[done[matched]]) * 1e3
    # the earlier figure: the time since the glove's latest send before the frame arrived
    latest = np.searchsorted(send_wall, recv_wall, side="right") - 1
    since_latest = (recv_wall[latest >= 0] - send_wall[latest[latest >= 0]]) * 1e3
    imu_messages = sum(1 for _, kind, _ in sends if kind == "imu_batch")
    result = {
        "seconds": seconds, "imu_rate_hz": imu_rate_hz, "imu_batch_messages": imu_messages,
        "messages_sent": len(sends), "frames": int(len(received)), "frames_matched": int(matched.sum()),
        "hand_workers": "service default" if hand_workers is None else hand_workers,
        "client_latency_ms": _quantiles(exact),
        "client_latency_decoded_ms": _quantiles(decoded),
        "since_latest_send_ms": _quantiles(since_latest),
        "subscriber_decode_ms": _quantiles(np.array([r[3] for r in received]) * 1e3),
        "service_ingest_to_send_ms_bucket_upper_bound": {
            q: (None if (v := _histogram_quantile(metrics_text, p)) is None else 1e3 * v)
            for q, p in (("p50", 0.5), ("p99", 0.99))},
        "service_cpu_while_streaming": service_cpu,
        "subscriber_gc": {"collections": len(sub_pauses), "full": sum(1 for g, _ in sub_pauses if g == 2),
                          "max_ms": max((d for _, d in sub_pauses), default=0.0),
                          "total_ms": sum(d for _, d in sub_pauses)},
        "load_average_1min": [load_before, _load_average()],
    }
    (out / "results.json").write_text(json.dumps(result, indent=2))
    c, s, o = result["client_latency_ms"], result["service_ingest_to_send_ms_bucket_upper_bound"], result["since_latest_send_ms"]
    d = result["client_latency_decoded_ms"]

    def row(name, q):
        return f"| {name} | " + " | ".join("-" if q[k] is None else f"{q[k]:.2f}" for k in ("p50", "p95", "p99", "max")) + " |\n"
    load = " -> ".join("?" if v is None else f"{v:.1f}" for v in result["load_average_1min"])
    text = (f"# Latency: one hand, 10 IMUs at {imu_rate_hz:g} Hz ({imu_messages} imu_batch messages), {seconds:.0f} s, "
            f"service in its own process (hand workers: {result['hand_workers']}); load average {load}\n\n"
            f"| measure, ms | p50 | p95 | p99 | max |\n|---|---|---|---|---|\n"
            + row("glove sends the message that completes a frame -> the frame's last bytes read by the subscriber", c)
            + row("the same -> the Python client has decoded the frame (this benchmark's figure before)", d)
            + row("glove's latest send -> subscriber receives a frame", o)
            + row("the Python client's decoding of a frame (`_decode`, in the subscriber)", result["subscriber_decode_ms"])
            + f"\nService histogram (ingest -> send, bucket upper bounds): p50 <= {s['p50']} ms, p99 <= {s['p99']} ms; "
            f"{len(received)} frames, {int(matched.sum())} with their completing message found. Service CPU while "
            f"streaming (incl. start-up of the subscriber): web process "
            + " , hand workers ".join("?" if v is None else f"{v:.0f} %" for v in service_cpu.values()) + " of a core. "
            f"The subscriber's garbage collections while streaming: {result['subscriber_gc']['collections']} "
            f"({result['subscriber_gc']['full']} full), longest {result['subscriber_gc']['max_ms']:.1f} ms.\n")
    (out / "summary.md").write_text(text)
    return text


def _load_average() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None
