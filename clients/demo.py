"""The main job: the service on localhost, a simulated glove performing the scripted sequence (point,
grasp, release, pinch, open) and a subscriber printing what a VR client receives; then a summary."""
from __future__ import annotations

import asyncio
import secrets
import time

import numpy as np

from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.session import SimConfig

from .client import Subscription, rest
from .glove import stream_glove


def angles_line(frame: dict) -> str:
    cells = []
    for f in ("thumb", "index", "middle", "ring", "little"):
        a = frame["fingers"][f]
        cells.append(f"{f[:2]} " + "/".join(f"{np.degrees(v):4.0f}" for k, v in a.items() if k != "mode"))
    g = frame.get("gesture", {})
    return (f"t={frame['t']:6.2f}s  " + "  ".join(cells) + f"  grab {g.get('grab_strength', 0):.2f}"
            f" pinch {g.get('pinch_strength', 0):.2f}  [{g.get('active') or '-'}]")


async def _run(server: ServerThread, source_token: str, viewer_token: str, config: SimConfig, print_every_s: float) -> dict:
    sent_wall: list[float] = []
    events: list[dict] = []
    latencies: list[float] = []
    frames = 0
    last_print = 0.0
    sub = Subscription(server.ws_url, "demo", viewer_token)

    async def subscriber():
        nonlocal frames, last_print
        async for msg in sub:
            now = time.perf_counter()
            if msg["type"] == "gesture":
                events.append(msg)
                ray = ""
                if "ray" in msg:
                    d = msg["ray"]["direction"]
                    ray = f"  ray direction ({d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f})"
                print(f"  gesture {msg['gesture']:<6} {msg['event']:<5} t={msg['t']:6.2f}s confidence {msg['confidence']:.2f}{ray}")
            elif msg["type"] == "frame":
                frames += 1
                if sent_wall:
                    latencies.append(now - sent_wall[-1])
                if msg["t"] - last_print >= print_every_s:
                    last_print = msg["t"]
                    print("  " + angles_line(msg))

    task = asyncio.create_task(subscriber())
    await asyncio.sleep(0.2)
    pub = await stream_glove(server.url, "demo", source_token, config, on_send=lambda w, m: sent_wall.append(w))
    await asyncio.sleep(0.3)
    await pub.close()
    await sub.close()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    return {"events": events, "frames": frames, "latencies": latencies, "errors": list(pub.errors)}


def run_demo(print_every_s: float = 0.5, seed: int = 0) -> int:
    source, viewer = secrets.token_urlsafe(12), secrets.token_urlsafe(12)
    settings = ServiceSettings.load(port=0, tokens={source: "source", viewer: "viewer"})
    config = SimConfig(motion="sequence", noise="both", hand_motion="slow-rotation", seed=seed)
    with ServerThread(settings) as server:
        print(f"fingertrack demo: service on {server.url} (docs at {server.url}/docs); a simulated glove performs "
              f"point, grasp, release, pinch, open in real time (~8 s)")
        result = asyncio.run(_run(server, source, viewer, config, print_every_s))
        status, sessions = rest(server.url, "GET", "/v1/sessions", server.settings.admin_token)
        _, metrics_text = rest(server.url, "GET", "/metrics", server.settings.admin_token)
    lat = np.array(result["latencies"]) * 1e3
    kinds = [(e["gesture"], e["event"]) for e in result["events"]]
    print("\nsummary")
    print(f"  frames received: {result['frames']}, gesture events: {len(kinds)}: "
          + ", ".join(f"{g} {e}" for g, e in kinds))
    if len(lat):
        print(f"  glove send -> frame received (transport + processing): p50 {np.percentile(lat, 50):.2f} ms, "
              f"p99 {np.percentile(lat, 99):.2f} ms")
    print(f"  errors from the service: {len(result['errors'])}; session status: "
          f"{sessions[0]['status'].get('optics') if status == 200 and sessions else 'n/a'}")
    expected = [("point", "start"), ("point", "end"), ("grasp", "start"), ("grasp", "end"),
                ("pinch", "start"), ("pinch", "end"), ("open", "start")]
    ok = kinds == expected
    print("  the scripted sequence was recognised" if ok else f"  expected {expected}")
    return 0 if ok else 1
