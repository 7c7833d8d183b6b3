"""The load benchmark's health and metrics probe (``service.bench.probe``) against a real HTTP server."""
from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from service.bench import probe as probe_module


class _Counted(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"           # kept alive, as the service's
    counts: dict[str, int] = {}
    tokens: set[str] = set()

    def do_GET(self):                       # noqa: N802 (the standard library's name)
        type(self).counts[self.path] = type(self).counts.get(self.path, 0) + 1
        type(self).tokens.add(self.headers.get("Authorization", ""))
        body = b"ok" if self.path == "/health" else b"# metrics\n" * 200
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def _probed(seconds: float, interval_s: float, metrics_every_s: float) -> dict:
    """``probe``'s result against a fresh counting server, over ``seconds``."""
    _Counted.counts, _Counted.tokens = {}, set()
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Counted)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}"
        return probe_module.probe(url, "T", seconds, interval_s=interval_s, metrics_every_s=metrics_every_s)
    finally:
        server.shutdown()
        server.server_close()


def test_metrics_are_asked_for_at_most_once_per_their_interval_and_health_in_every_round():
    """Over 1 s, ``/metrics`` at most once per 0.4 s (at most three requests: at the start, then at least 0.4 s after
    the one before), ``/health`` in every round (at least as often); each answer counted once, none failed, with
    the token. Asking for both in every round (the earlier rule) fails the first bound whenever the machine
    manages more than three rounds in the second (20 at an idle machine's pace)."""
    result = _probed(1.0, 0.05, 0.4)
    health, metrics = result["health"], result["metrics"]
    assert 1 <= metrics["count"] <= 3
    assert health["count"] >= metrics["count"]
    assert (health["failures"], metrics["failures"]) == (0, 0)
    assert _Counted.counts == {"/health": health["count"], "/metrics": metrics["count"]}
    assert _Counted.tokens == {"Bearer T"}


def test_both_are_asked_for_in_every_round_when_their_intervals_are_the_round_s():
    """``metrics_every_s`` equal to the round's interval: ``/metrics`` in every round, as ``/health``."""
    result = _probed(0.3, 0.05, 0.05)
    assert result["health"]["count"] == result["metrics"]["count"] >= 1
