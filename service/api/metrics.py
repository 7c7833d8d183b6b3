"""Prometheus metrics of one service instance (its own registry, so several apps can live in one
process, as the tests do). Series labelled by session are shown to admins only (``render``)."""
from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Summary, generate_latest
from prometheus_client.registry import Collector


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.messages_in = Counter("fingertrack_messages_in", "source messages received", ["session"], registry=self.registry)
        self.messages_out = Counter("fingertrack_messages_out", "messages sent to subscribers", ["session"], registry=self.registry)
        self.errors = Counter("fingertrack_errors", "error replies by code", ["code"], registry=self.registry)
        self.dropped_frames = Counter("fingertrack_dropped_frames", "frames dropped for slow subscribers", ["session"], registry=self.registry)
        self.overloaded = Counter("fingertrack_overloaded_messages", "source messages refused because the service "
                                  "could not keep up with their source", ["session"], registry=self.registry)
        self.disconnects = Counter("fingertrack_disconnects", "connections the service dropped, by reason", ["reason"],
                                   registry=self.registry)
        self.worker_restarts = Counter("fingertrack_hand_worker_restarts", "hand worker processes restarted after "
                                       "they ended (a crash, a kill)", registry=self.registry)
        self.connection_gc = Summary("fingertrack_connection_gc_seconds", "cycle collections (and heap trims) run "
                                     "on the event loop after WebSocket connections ended (api/churn.py)",
                                     registry=self.registry)
        self.sessions = Gauge("fingertrack_sessions", "live sessions", registry=self.registry)
        self.behind = Gauge("fingertrack_session_behind_seconds", "how much later the session's last frame came behind "
                            "its source's real time than its frames did at best (hand workers; a session on a costly "
                            "estimator in a worker of its own may fall behind on a busy machine)", ["session"],
                            registry=self.registry)
        self.subscribers = Gauge("fingertrack_subscribers", "connected subscribers", registry=self.registry)
        self.latency = Histogram("fingertrack_ingest_to_send_seconds", "time from receiving a source message to sending "
                                 "the output it caused", ["session"], registry=self.registry,
                                 buckets=(0.0005, 0.001, 0.0015, 0.002, 0.0025, 0.003, 0.0035, 0.004, 0.0045, 0.005,
                                          0.006, 0.0075, 0.01, 0.015, 0.02, 0.05, 0.1, 0.5))

        self._series: dict[str, SessionSeries] = {}

    def of_session(self, name: str) -> SessionSeries:
        """The session's per-message series, looked up once (``labels`` on every message cost more than
        the count itself) until ``forget_session``."""
        series = self._series.get(name)
        if series is None:
            series = self._series[name] = SessionSeries(self, name)
        return series

    def forget_session(self, name: str) -> None:
        """Drop the series of a removed session (a name may come back as a new session)."""
        self._series.pop(name, None)
        for family in (self.messages_in, self.messages_out, self.dropped_frames, self.overloaded, self.latency, self.behind):
            try:
                family.remove(name)
            except KeyError:
                pass

    def render(self, admin: bool = True) -> bytes:
        """The exposition text; without ``admin``, series labelled by session are left out (session
        names are not every role's business)."""
        return generate_latest(self.registry if admin else _WithoutSessions(self.registry))


class SessionSeries:
    """A session's ``messages_in``, ``messages_out`` and ``latency`` series, each made on its first use (as
    ``labels`` makes it: a session that has sent no frame shows no frame series)."""

    __slots__ = ("_metrics", "_name", "_in", "_out", "_latency")

    def __init__(self, metrics: Metrics, name: str):
        self._metrics, self._name = metrics, name
        self._in = self._out = self._latency = None

    @property
    def messages_in(self) -> Counter:
        if self._in is None:
            self._in = self._metrics.messages_in.labels(self._name)
        return self._in

    @property
    def messages_out(self) -> Counter:
        if self._out is None:
            self._out = self._metrics.messages_out.labels(self._name)
        return self._out

    @property
    def latency(self) -> Histogram:
        if self._latency is None:
            self._latency = self._metrics.latency.labels(self._name)
        return self._latency


class _WithoutSessions(Collector):
    def __init__(self, registry: CollectorRegistry):
        self.registry = registry

    def collect(self):
        for family in self.registry.collect():
            family.samples = [s for s in family.samples if "session" not in s.labels]
            yield family
