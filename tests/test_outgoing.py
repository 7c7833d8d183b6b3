"""Each output message is serialised once for all its subscribers (per wire format)."""
import asyncio
import json

import msgpack

from clients.glove import source_messages
from service.api import outgoing
from service.api.config import ServiceSettings
from service.api.metrics import Metrics
from service.api.sessions import LiveSession, Subscriber
from service.protocol import parse_message
from service.sim.session import SimConfig


def test_one_encoding_per_message_and_format_for_many_subscribers(monkeypatch):
    calls = {"json": 0, "msgpack": 0}
    real_encode, real_dumps = outgoing.encode, json.dumps

    def counting_encode(message, binary):
        calls["msgpack" if binary else "json"] += 1
        return real_encode(message, binary)

    monkeypatch.setattr(outgoing, "encode", counting_encode)

    async def run():
        live = LiveSession("enc", ServiceSettings.load(port=0), Metrics())
        subs = [Subscriber(10_000, 10_000, binary=b) for b in (False, False, False, True, True)]
        live.subscribers.update(subs)
        for _, m in source_messages(SimConfig(motion="point", duration_s=0.4, noise="none", seed=1)):
            await live.ingest(m, parse_message(m))
        return live, subs

    live, subs = asyncio.run(run())
    assert live.frames_out > 10
    queues = [[item for _, item, _ in s.queue] for s in subs]
    assert all(len(q) == len(queues[0]) for q in queues)
    for items in zip(*queues):                    # every subscriber holds the very same message object
        assert all(item is items[0] for item in items)
    for s in subs:                                # what the stream handler sends, per subscriber
        for _, item, _ in s.queue:
            data = item.packed() if s.binary else item.text()
            decoded = msgpack.unpackb(data) if s.binary else json.loads(data)
            assert decoded == json.loads(real_dumps(item.message))
    n = len(queues[0])
    assert calls == {"json": n, "msgpack": n}     # not n x subscribers
