"""Latency benchmark: ``fingertrack bench latency [--seconds N] --out DIR``.

The service runs as its own process (``fingertrack serve`` on a free localhost port, as deployed); a
second process streams one simulated hand in real time (10 IMUs at 200 Hz, each tick one
``imu_batch``, optical poses at 90 Hz) and subscribes to the frames. For every frame received, the
latency is the time since the glove sent its latest message (the one that completed the frame's
tick): transport both ways plus the service's processing, on one clock. The service's own
ingest-to-send histogram (``/metrics``) is reported beside it. The pipeline's deliberate alignment
delay (reorder window, optical latency) is on the source clock and not part of this figure.
"""
from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np

from ..sim.session import SimConfig
from .process import service_process


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


async def _measure(url: str, source: str, viewer: str, config: SimConfig) -> list[float]:
    from clients.client import Subscription
    from clients.glove import stream_glove

    last_send = [0.0]
    latencies: list[float] = []
    sub = Subscription(url, "bench", viewer)

    async def collect():
        async for msg in sub:
            if msg["type"] == "frame" and last_send[0] > 0:
                latencies.append(time.perf_counter() - last_send[0])

    task = asyncio.create_task(collect())
    await asyncio.sleep(0.3)

    def on_send(wall, _msg):
        last_send[0] = wall
    pub = await stream_glove(url, "bench", source, config, on_send=on_send)
    await asyncio.sleep(0.3)
    await pub.close()
    await sub.close()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    return latencies


def run(out_dir: str | Path, seconds: float = 20.0) -> str:
    from clients.client import rest

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with service_process() as svc:
        config = SimConfig(motion="random", t_m_s=seconds, noise="both", hand_motion="slow-rotation", seed=0)
        lat = np.array(asyncio.run(_measure(svc.url, svc.source, svc.viewer, config)))
        _, metrics_text = rest(svc.url, "GET", "/metrics", svc.admin)
    ms = lat * 1e3
    result = {
        "seconds": seconds, "frames": int(len(ms)),
        "client_latency_ms": {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)),
                              "p99": float(np.percentile(ms, 99)), "max": float(ms.max())},
        "service_ingest_to_send_ms_bucket_upper_bound": {
            q: (None if (v := _histogram_quantile(metrics_text, p)) is None else 1e3 * v)
            for q, p in (("p50", 0.5), ("p99", 0.99))},
    }
    (out / "results.json").write_text(json.dumps(result, indent=2))
    c, s = result["client_latency_ms"], result["service_ingest_to_send_ms_bucket_upper_bound"]
    text = (f"# Latency: one hand, 10 IMUs at 200 Hz, {seconds:.0f} s, service in its own process\n\n"
            f"| measure | p50 | p95 | p99 | max |\n|---|---|---|---|---|\n"
            f"| glove send -> subscriber receive, ms | {c['p50']:.2f} | {c['p95']:.2f} | {c['p99']:.2f} | {c['max']:.2f} |\n\n"
            f"Service histogram (ingest -> send, bucket upper bounds): p50 <= {s['p50']} ms, p99 <= {s['p99']} ms; "
            f"{len(ms)} frames.\n")
    (out / "summary.md").write_text(text)
    return text
