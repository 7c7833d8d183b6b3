"""Prometheus metrics of one service instance (its own registry, so several apps can live in one
process, as the tests do). Series labelled by session are shown to admins only (``render``).

``render`` writes the text ``prometheus_client.generate_latest`` writes, byte for byte, with each series'
name and labels formatted once (``_Exposition``): the library builds a sample object, a label dict and a
formatted label string for every line at every scrape, 7.5 ms of the event loop for 50 sessions (1,400
lines), each time a monitoring system asks."""
from __future__ import annotations

import logging
from bisect import bisect_left

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Summary, generate_latest
from prometheus_client import metrics as _client_metrics
from prometheus_client.openmetrics import exposition as _om
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString
from prometheus_client.values import MutexValue


log = logging.getLogger(__name__)

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
        self._exposition: _Exposition | None = _Exposition(self.registry)
        """the fast writer (``render``); ``None`` once it failed: ``generate_latest`` from then on"""

    def of_session(self, name: str) -> SessionSeries:
        """The session's per-message series, looked up once (``labels`` on every message cost more than
        the count itself) until ``forget_session``."""
        series = self._series.get(name)
        if series is None:
            series = self._series[name] = SessionSeries(self, name)
        return series

    def publish(self) -> None:
        """What the sessions' series counted locally (``SessionSeries.received``, ``sent``, ``behind``) into their
        prometheus series: run before every scrape (``render``), so the text shows every message before it."""
        for series in self._series.values():
            series.publish()

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
        self.publish()
        text = None
        if self._exposition is not None:
            try:
                text = self._exposition.render(admin)
            except Exception:                       # prometheus_client's internals differ (another version)
                log.warning("metrics: the service's exposition writer failed; prometheus_client's own writes "
                            "/metrics from now on", exc_info=True)
                self._exposition = None
        return text if text is not None else generate_latest(self.registry if admin else _WithoutSessions(self.registry))


class SessionSeries:
    """A session's ``messages_in``, ``messages_out`` and ``latency`` series, each made on its first use (as
    ``labels`` makes it: a session that has sent no frame shows no frame series).

    The messages received from a hand worker's session (``received``) and sent to subscribers (``sent``: a count,
    the latencies' histogram buckets and sum) are counted here in plain Python numbers, and the session's
    ``behind`` kept, and added to the prometheus series at the next scrape (``Metrics.publish``): an ``inc``, an
    ``observe`` or a ``set`` per message (a lock each, and a walk over the histogram's bounds in Python) cost more
    of the web process's time than a subscriber write's own Python. The counts at a scrape are the same; the
    latencies' sum is added up per scrape (floats added in another order: the same to about 1e-15 of it)."""

    __slots__ = ("_metrics", "_name", "_in", "_out", "_latency", "_bounds", "_n_sent", "_sent_sum", "_sent_in",
                 "_n_received", "behind")

    def __init__(self, metrics: Metrics, name: str):
        self._metrics, self._name = metrics, name
        self._in = self._out = self._latency = None
        self._n_received = 0
        self.behind: float | None = None
        """the session's ``behind_s`` for the gauge ``behind`` at the next ``publish`` (``None``: unchanged)"""
        self._bounds = metrics.latency._upper_bounds
        """the latency histogram's upper bounds (the last one +inf): a latency counts in the first bound >= it"""
        self._n_sent = 0
        self._sent_sum = 0.0
        self._sent_in = [0] * len(self._bounds)
        """per bucket: the latencies counted in it since the last ``publish``"""

    def received(self, n: int = 1) -> None:
        """``n`` source messages received (``messages_in``, at the next ``publish``)."""
        self._n_received += n

    def sent(self, since: list[float], now: float) -> None:
        """Messages written to a subscriber at ``now`` (``time.perf_counter``), one per time in ``since`` (each
        its source message's arrival): counted in ``messages_out`` and their latencies (``now - t0``) in
        ``latency``, at the next ``publish``."""
        self._n_sent += len(since)
        bounds, buckets, total = self._bounds, self._sent_in, self._sent_sum
        for t0 in since:
            amount = now - t0
            total += amount
            buckets[bisect_left(bounds, amount)] += 1       # (``Histogram.observe``'s: the first bound >= it)
        self._sent_sum = total

    def sent_one(self, amount: float) -> None:
        """``sent`` of one message whose latency is ``amount``."""
        self._n_sent += 1
        self._sent_sum += amount
        self._sent_in[bisect_left(self._bounds, amount)] += 1

    def publish(self) -> None:
        """What was counted by ``received`` and ``sent`` (and the last ``behind``) since the last call into the
        prometheus series."""
        if self._n_received:
            n, self._n_received = self._n_received, 0
            self.messages_in.inc(n)
        if self.behind is not None:
            behind, self.behind = self.behind, None
            self._metrics.behind.labels(self._name).set(behind)
        n, total, buckets = self._n_sent, self._sent_sum, self._sent_in
        if not n:
            return
        self._n_sent, self._sent_sum, self._sent_in = 0, 0.0, [0] * len(buckets)
        self.messages_out.inc(n)
        latency = self.latency
        latency._sum.inc(total)
        for bucket, k in zip(latency._buckets, buckets):
            if k:
                bucket.inc(k)

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


_KINDS = (Counter, Gauge, Histogram, Summary)


def _series_prefix(name: str, labels: dict) -> str:
    """A sample line up to its value, as ``generate_latest`` (default escaping) writes it: the name,
    the labels sorted by name, a space."""
    if not labels:
        return f"{_om.escape_metric_name(name, _om.UNDERSCORES)} "
    text = ",".join('{}="{}"'.format(_om.escape_label_name(k, _om.UNDERSCORES), _om._escape(v, _om.ALLOWUTF8, False))
                    for k, v in sorted(labels.items()))
    return f"{_om.escape_metric_name(name, _om.UNDERSCORES)}{{{text}}} "


def _help(name: str, documentation: str, kind: str) -> str:
    shown = _om.escape_metric_name(name, _om.UNDERSCORES)
    text = documentation.replace("\\", r"\\").replace("\n", r"\n")
    return f"# HELP {shown} {text}\n# TYPE {shown} {kind}\n"


class _Exposition:
    """``generate_latest``'s text of a registry of plain counters, gauges, histograms and summaries
    (``Metrics``'), each series' line heads formatted once and kept while the series lives. ``render``
    gives ``None`` for anything else in the registry (a collector of another kind, a gauge set to a
    function, a sample with a timestamp): the caller then asks ``generate_latest``."""

    def __init__(self, registry: CollectorRegistry):
        self.registry = registry
        self._heads: dict[tuple[str, tuple], tuple[object, list[str], str]] = {}
        """(family, label values) -> (the series, its lines' heads, its ``_created`` line)"""

    def render(self, with_sessions: bool) -> bytes | None:
        families = list(self.registry._collector_to_names)
        if not all(type(f) in _KINDS and not f._unit for f in families):
            return None
        created_too = _client_metrics._use_created
        out: list[str] = []
        seen = set()
        for family in families:
            name, kind, labelnames = family._name, family._type, family._labelnames
            shown = name + "_total" if kind == "counter" else name
            out.append(_help(shown, family._documentation, kind))
            if labelnames:
                if not with_sessions and "session" in labelnames:
                    continue
                with family._lock:
                    children = list(family._metrics.items())
            else:
                children = [((), family)]
            created = []
            for values, child in children:
                key = (name, values)
                seen.add(key)
                if "_child_samples" in child.__dict__:          # a gauge set to a function
                    return None
                kept = self._heads.get(key)
                if kept is None or kept[0] is not child:
                    kept = self._heads[key] = self._series(child, dict(zip(labelnames, values)))
                _, heads, created_line = kept
                if kind == "counter" or kind == "gauge":
                    value = child._value
                    value = value._value if type(value) is MutexValue else value.get()
                    out.append(f"{heads[0]}{repr(value) if type(value) is float and -1e6 < value < 1e6 else floatToGoString(value)}\n")
                elif kind == "histogram":
                    acc = 0.0
                    for head, bucket in zip(heads, child._buckets):
                        acc += bucket._value if type(bucket) is MutexValue else bucket.get()
                        out.append(f"{head}{repr(acc) if -1e6 < acc < 1e6 else floatToGoString(acc)}\n")
                    out.append(f"{heads[-2]}{repr(acc) if -1e6 < acc < 1e6 else floatToGoString(acc)}\n")
                    if child._upper_bounds[0] >= 0:
                        out.append(heads[-1] + floatToGoString(child._sum.get()) + "\n")
                else:                                   # summary
                    out.append(heads[0] + floatToGoString(child._count.get()) + "\n")
                    out.append(heads[1] + floatToGoString(child._sum.get()) + "\n")
                if created_too and created_line:
                    created.append(created_line)
            if created:
                out.append(_help(name + "_created", family._documentation, "gauge"))
                out.extend(created)
        if with_sessions and len(seen) != len(self._heads):  # series removed since (``forget_session``); a render
            # without the session series saw only some: it keeps the others
            self._heads = {k: v for k, v in self._heads.items() if k in seen}
        return "".join(out).encode("utf-8")

    @staticmethod
    def _series(child, labels: dict) -> tuple[object, list[str], str]:
        name, kind = child._name, child._type
        if kind == "counter":
            heads = [_series_prefix(name + "_total", labels)]
        elif kind == "gauge":
            heads = [_series_prefix(name, labels)]
        elif kind == "histogram":
            heads = [_series_prefix(name + "_bucket", {**labels, "le": floatToGoString(b)}) for b in child._upper_bounds]
            heads += [_series_prefix(name + "_count", labels), _series_prefix(name + "_sum", labels)]
        else:
            heads = [_series_prefix(name + "_count", labels), _series_prefix(name + "_sum", labels)]
        created = "" if kind == "gauge" else _series_prefix(name + "_created", labels) + floatToGoString(child._created) + "\n"
        return child, heads, created
