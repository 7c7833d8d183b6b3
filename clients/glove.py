"""A simulated glove plus optical tracker streaming in real time (paced by the clock): the
simulator's recording, with each tick's IMU samples sent as one ``imu_batch``."""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from service.protocol import encode
from service.sim.session import SimConfig, simulate

from .client import Publisher


def source_messages(config: SimConfig) -> list[tuple[float, dict]]:
    """``(arrival time on the source clock, message)`` with each tick's IMU samples batched."""
    sess = simulate(config)
    latency = sess.optical.latency_s
    out: list[tuple[float, dict]] = []
    batch: list[dict] = []
    batch_t = None
    for m in sess.messages(include_truth=False):
        if m["type"] == "imu":
            if batch and m["t"] != batch_t:
                out.append((batch_t, {"type": "imu_batch", "samples": batch}))
                batch = []
            batch_t = m["t"]
            batch.append({k: m[k] for k in ("t", "id", "gyr", "acc")})
            continue
        if batch:
            out.append((batch_t, {"type": "imu_batch", "samples": batch}))
            batch = []
        arrival = m["t"] + latency if m["type"] == "pose" else m.get("t", m.get("t1", sess.t[0]))
        out.append((arrival, m))
    if batch:
        out.append((batch_t, {"type": "imu_batch", "samples": batch}))
    return out


def encoded_messages(messages: list[tuple[float, dict]], binary: bool = False) -> list[str | bytes]:
    """Each of ``source_messages``' messages as ``Publisher.send`` would encode it (``binary``:
    MessagePack), so that a stream sends bytes ready made."""
    return [encode(m, binary) for _, m in messages]


async def stream_glove(url: str, session: str, token: str, config: SimConfig, speed: float = 1.0,
                       on_send: Callable[[float, dict], None] | None = None,
                       messages: list[tuple[float, dict]] | None = None, binary: bool = False,
                       stop=None, encoded: list[str | bytes] | None = None) -> Publisher:
    """Stream a simulated session in real time; ``on_send(wall_time, message)`` after each send.
    ``messages``: ``source_messages(config)`` computed beforehand (several gloves that must start
    together), ``encoded``: those messages' ``encoded_messages`` (else they are encoded before the
    stream's clock starts, not while it streams); ``binary``: MessagePack instead of JSON; ``stop``: an
    event (``threading.Event``) that ends the stream early once set."""
    msgs = messages if messages is not None else await asyncio.to_thread(source_messages, config)   # off the loop
    data = encoded if encoded is not None else await asyncio.to_thread(encoded_messages, msgs, binary)   # off the loop too
    if len(data) != len(msgs):
        raise ValueError(f"{len(data)} encoded messages for {len(msgs)} messages")
    pub = Publisher(url, session, token, hand=config.hand, source=f"fingertrack-glove {config.motion}", binary=binary)
    t0_src = msgs[0][0]
    t0_wall = time.perf_counter()
    for (arrival, m), text in zip(msgs, data):
        if stop is not None and stop.is_set():
            break
        due = t0_wall + (arrival - t0_src) / speed
        # always yield to the loop, even when behind schedule, so other tasks keep running
        await asyncio.sleep(max(0.0, due - time.perf_counter()))
        await pub.send(m, text)
        if on_send is not None:
            on_send(time.perf_counter(), m)
    await asyncio.sleep(0.1)
    return pub
