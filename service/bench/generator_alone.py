"""The load generator's clients alone, without the service: ``python -m service.bench.generator_alone
[--hands 8] [--seconds 10] [--clients lean|product]``.

A sink process (a plain websockets server, not the service) answers each glove's ``hello`` and ``sync``
and, for every ``pose`` a glove sends (90 a second), sends each subscriber of that session a frame the
pipeline made (about 7 kB of JSON). This process streams ``hands`` simulated gloves and reads two
subscribers per hand, with ``bench load``'s clients (``lean``: ``loadclients``) or the product's
(``product``: ``clients.glove.stream_glove`` and ``clients.client.Subscription`` decoding every frame, as
``bench load``'s generator did before), and prints its own CPU time per second of one hand's data
(user + system, and system alone) and its wakes per second (voluntary context switches) while the gloves
stream, and (lean clients) how late the gloves sent their messages (p50 and p99 of send time minus due
time), as JSON; the lean subscribers are read at the gloves' wakes (``TickReads``), as in ``bench load``. The sink's CPU is not counted;
it shares the machine.
"""
from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import resource
import sys
import time


def _sink_main(port_file: str) -> None:
    """The sink: serves until killed; writes its port to ``port_file`` once listening."""
    from websockets.asyncio.server import serve

    from service.pipeline.tracked import replay
    from service.protocol import encode, parse_message
    from service.sim.session import SimConfig, simulate

    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=3, duration_s=1.0)
    frames = [encode(o, False) for o in replay(parse_message(m) for m in simulate(config).messages(include_truth=False))
              if o["type"] == "frame"]
    subscribers: dict[str, list] = {}

    async def handler(ws):
        kind, session = ws.request.path.split("?")[0].split("/")[-2:]
        if kind == "stream":
            subscribers.setdefault(session, []).append(ws)
            await ws.send(json.dumps({"type": "hello", "protocol": 1}))
            await ws.wait_closed()
            return
        sent = 0
        async for data in ws:
            msg = json.loads(data)
            if msg["type"] == "hello":
                await ws.send(json.dumps({"type": "hello", "protocol": 1}))
            elif msg["type"] == "sync":
                await ws.send(json.dumps({"type": "sync", "id": msg["id"]}))
            elif msg["type"] == "pose":
                for sub in subscribers.get(session, []):
                    await sub.send(frames[sent % len(frames)])
                sent += 1

    async def main():
        async with serve(handler, "127.0.0.1", 0, max_size=None) as server:
            with open(port_file, "w") as f:
                f.write(str(server.sockets[0].getsockname()[1]))
            await asyncio.Future()

    asyncio.run(main())


async def _generate(url: str, hands: int, seconds: float, clients: str) -> dict:
    """The gloves and subscribers of ``hands`` sessions against the sink at ``url``; their CPU time."""
    from clients.client import Subscription
    from clients.glove import encoded_messages, source_messages, stream_glove
    from service.sim.session import SimConfig

    import numpy as np

    from .loadclients import GloveSchedule, LeanGlove, LeanSubscription, SessionDecodes, TickReads, stream_gloves, ws_frames

    configs = [SimConfig(motion="random", t_m_s=seconds, noise="both", hand_motion="slow-rotation", seed=i,
                         hand="right" if i % 2 == 0 else "left") for i in range(hands)]
    msgs = [source_messages(c) for c in configs]
    encoded = [encoded_messages(m) for m in msgs]
    names = [f"alone-{i}" for i in range(hands)]
    frames = [0]
    if clients == "lean":
        def count(_msg, _arrival):
            frames[0] += 1
        shared = {n: SessionDecodes() for n in names}
        reads = TickReads()
        subs = [LeanSubscription(url, n, "t", count, shared=shared[n], reads=reads) for n in names for _ in range(2)]
        for s in subs:
            s.start()
        gloves = [LeanGlove(url, n, "t") for n in names]
        await asyncio.gather(*(g.open(m[0][1]) for g, m in zip(gloves, msgs)))
        framed = [ws_frames(e) for e in encoded]
        schedule = GloveSchedule(msgs, framed)
        while not all(s.server_hello is not None for s in subs):
            await asyncio.sleep(0.05)
    else:
        subs = [Subscription(url, n, "t") for n in names for _ in range(2)]

        async def read(sub):
            async for msg in sub:
                if msg["type"] == "frame":
                    frames[0] += 1
        readers = [asyncio.create_task(read(s)) for s in subs]
        while not all(s.server_hello is not None for s in subs):
            await asyncio.sleep(0.05)
    gc.collect()                              # as ``bench load``'s generator: the simulated messages kept
    gc.freeze()                               # out of the collector's generations while they stream
    lags: list[float] = []
    sent = [[] for _ in names]
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    cpu0, sys0, wall0 = time.process_time(), os.times().system, time.perf_counter()
    if clients == "lean":
        reads.start(subs)
        await stream_gloves(gloves, msgs, framed, None, wall0, sent=sent, schedule=schedule, reads=reads)
    else:
        pubs = await asyncio.gather(*(stream_glove(url, n, "t", c, messages=m, encoded=e)
                                      for n, c, m, e in zip(names, configs, msgs, encoded)))
    cpu, system, wall = time.process_time() - cpu0, os.times().system - sys0, time.perf_counter() - wall0
    usage1 = resource.getrusage(resource.RUSAGE_SELF)
    if clients == "lean":
        lags = [t - (wall0 + d) for times, due in zip(sent, schedule.due) for t, d in zip(times, due)]
    for closing in (gloves if clients == "lean" else pubs):
        await closing.close()                 # the sink has answered every message: its frames are on the way
    expected = 2 * sum(1 for m in msgs for _, x in m if x["type"] == "pose")
    deadline = time.monotonic() + 30.0
    while frames[0] < expected and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    for s in subs:
        await s.close()
    if clients != "lean":
        for r in readers:
            r.cancel()
        await asyncio.gather(*readers, return_exceptions=True)
    return {"clients": clients, "hands": hands, "seconds": seconds, "stream_wall_s": wall, "frames_received": frames[0],
            "frames_sent": expected,
            "cpu_ms_per_hand_s": 1e3 * cpu / (hands * seconds), "system_ms_per_hand_s": 1e3 * system / (hands * seconds),
            "wakes_per_s": (usage1.ru_nvcsw - usage0.ru_nvcsw) / wall,
            "tick_reads": reads.reads if clients == "lean" else None,
            "send_lag_ms_p50_p99": ([round(float(x), 3) for x in np.percentile(np.array(lags) * 1e3, [50, 99])]
                                    if lags else None),
            "send_lag_ms_p90_p999_max": ([round(float(x), 3) for x in np.percentile(np.array(lags) * 1e3, [90, 99.9, 100])]
                                         if lags else None)}


def main(argv: list[str] | None = None) -> int:
    import subprocess
    import tempfile

    parser = argparse.ArgumentParser(prog="python -m service.bench.generator_alone", description=__doc__.split("\n\n")[0])
    parser.add_argument("--hands", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--clients", choices=("lean", "product"), default="lean")
    args = parser.parse_args(argv)
    if args.hands < 1 or args.seconds <= 0:
        parser.error("--hands must be at least 1 and --seconds positive")
    frozen_before = gc.get_freeze_count() > 0
    with tempfile.TemporaryDirectory() as tmp:
        port_file = os.path.join(tmp, "port")
        sink = subprocess.Popen([sys.executable, "-m", "service.bench.generator_alone", "--sink", port_file])
        try:
            while not os.path.exists(port_file) or not open(port_file).read():
                if sink.poll() is not None:
                    raise SystemExit("the sink did not start")
                time.sleep(0.05)
            url = f"http://127.0.0.1:{open(port_file).read()}"
            print(json.dumps(asyncio.run(_generate(url, args.hands, args.seconds, args.clients))))
        finally:
            if not frozen_before:             # ``_generate`` froze the heap: a caller's process gets it back
                gc.unfreeze()                 # as it was (a test calls this in its own process)
            sink.kill()
            sink.wait()
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--sink":
        _sink_main(sys.argv[2])
        sys.exit(0)
    sys.exit(main())
