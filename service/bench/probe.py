"""A health and metrics probe for ``fingertrack bench load``: ``python -m service.bench.probe URL
SECONDS [INTERVAL_S [METRICS_EVERY_S]]`` (the token in the environment variable ``FINGERTRACK_PROBE_TOKEN``)
polls a running service for ``SECONDS``: ``GET /health`` every ``INTERVAL_S`` (0.05 s), as a load
balancer's health check would, and ``GET /metrics`` (the token's view) every ``METRICS_EVERY_S`` (1 s;
a Prometheus server scrapes every 15 s to 1 min: the whole exposition, some 2 kB per session, rendered by
the service and read here 20 times a second would load the machine as no monitoring system does), each
on one kept-alive HTTP connection of its own, one request after the other; it prints one JSON object:
per endpoint the response times (request sent -> whole body read, ms: count, p50, p99, max) and how many
answers were not 200.

It runs in its own process so that the load generator's busy event loop does not add to the times it
measures (the machine's other work still does: the figures are what a monitoring system on the same
machine would see)."""
from __future__ import annotations

import http.client
import json
import os
import signal
import sys
import time
from urllib.parse import urlsplit

import numpy as np


def _stats(times_s: list[float], failures: int) -> dict:
    ms = np.array(times_s) * 1e3
    return {"count": int(ms.size), "failures": failures,
            "p50_ms": float(np.percentile(ms, 50)) if ms.size else None,
            "p99_ms": float(np.percentile(ms, 99)) if ms.size else None,
            "max_ms": float(ms.max()) if ms.size else None}


def probe(url: str, token: str, seconds: float, interval_s: float = 0.05, metrics_every_s: float = 1.0,
          stopped: list | None = None) -> dict:
    """``/health`` in each round, a round every ``interval_s``; ``/metrics`` in the first round and then in the first
    round at least ``metrics_every_s`` after its last request began (0: in each round). Ends early, with what it
    measured, once ``stopped`` is not empty."""
    parts = urlsplit(url)
    paths = {"health": "/health", "metrics": "/metrics"}
    conns = {k: http.client.HTTPConnection(parts.hostname, parts.port, timeout=30) for k in paths}
    times: dict[str, list[float]] = {k: [] for k in paths}
    failures = dict.fromkeys(paths, 0)
    headers = {"Authorization": f"Bearer {token}"}
    every = {"health": 0.0, "metrics": metrics_every_s}
    due = dict.fromkeys(paths, time.perf_counter())
    end = time.perf_counter() + seconds
    stopped = [] if stopped is None else stopped
    while time.perf_counter() < end and not stopped:
        for key, path in paths.items():
            t0 = time.perf_counter()
            if t0 < due[key]:
                continue
            due[key] = t0 + every[key]
            try:
                conns[key].request("GET", path, headers=headers)
                resp = conns[key].getresponse()
                resp.read()
                ok = resp.status == 200
            except (OSError, http.client.HTTPException):
                conns[key].close()
                conns[key] = http.client.HTTPConnection(parts.hostname, parts.port, timeout=30)
                ok = False
            if ok:
                times[key].append(time.perf_counter() - t0)
            else:
                failures[key] += 1
        time.sleep(interval_s)
    return {k: _stats(times[k], failures[k]) for k in paths}


def main(argv: list[str]) -> int:
    if len(argv) not in (2, 3, 4):
        print("usage: FINGERTRACK_PROBE_TOKEN=T python -m service.bench.probe URL SECONDS [INTERVAL_S [METRICS_EVERY_S]]",
              file=sys.stderr)
        return 2
    token = os.environ.get("FINGERTRACK_PROBE_TOKEN", "")
    stopped: list = []
    signal.signal(signal.SIGTERM, lambda *_: stopped.append(True))      # ends early, with what it measured
    print(json.dumps(probe(argv[0], token, float(argv[1]), *(float(a) for a in argv[2:]), stopped=stopped)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
