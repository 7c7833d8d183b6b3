"""The hand worker pool (``service.api.hands.pool``) with real worker processes: its stall watchdog (an
idle worker is not silent when it is first sent a message, a stopped worker is replaced as soon as the
other worker goes on answering, and a worker busy with a long message is not), and a session switched
to a costly estimator in a worker of its own. Waits are for events and counts; timeouts only bound a
failure."""
import asyncio
import os
import signal
import time

import msgpack
import pytest

from clients.glove import source_messages
from service.api.config import ServiceSettings
from service.api.hands.pool import CAUGHT_UP, LAG_EVIDENCE, HandPool, WorkerLink
from service.api.metrics import Metrics
from service.api.sessions import Subscriber
from service.protocol import parse_message
from service.protocol.messages import MAX_BATCH_SAMPLES
from service.sim.session import SimConfig

HELLO = {"type": "hello", "protocol": 1, "hand": "right", "source": "pool-test"}


async def _pool(workers: int, **extra) -> HandPool:
    pool = HandPool(ServiceSettings.load(port=0, hand_workers=workers, **extra), Metrics())
    await pool.start()
    await pool.wait_ready()
    return pool


async def _ingest(live, raw: dict) -> None:
    await live.ingest(raw, parse_message(raw))


async def _until(condition, what: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        await asyncio.sleep(0.01)


SOURCE_TOKEN = "source-token"


def _one_worker_source_service() -> ServiceSettings:
    """A service with one hand worker (its sessions stay on it) and a source token."""
    return ServiceSettings.load(port=0, tokens={SOURCE_TOKEN: "source"}, hand_workers=1, hand_worker_isolate=False)


async def _said_hello(ws) -> list:
    """``[type of the server's reply]`` once a source connection has sent its hello."""
    import json
    await ws.send(json.dumps(HELLO))
    return [json.loads(await ws.recv())["type"]]

def _glove(seconds: float, seed: int) -> list[dict]:
    return [m for _, m in source_messages(SimConfig(motion="sequence", hand="right", noise="white", seed=seed,
                                                    duration_s=seconds))]


def test_a_worker_idle_for_longer_than_the_limits_is_not_taken_for_stuck_when_it_is_sent_its_first_message():
    """Silence counts while a worker owes answers: one that owed nothing for longer than the limits
    (the service waiting for its first glove) has just begun to owe when its first message is sent."""
    async def run():
        pool = await _pool(1)
        try:
            # limits of half the idle time: a pause of this process of up to 1.5 s between the send and
            # the check (a busy machine) still leaves the check's answer to the rule, not to the pause
            link, idle_s = pool.links[0], 3.0
            await asyncio.sleep(idle_s)             # ready, no session: it has nothing to say
            live = pool.session("a", pool.settings, pool.metrics)
            await _ingest(live, HELLO)
            owes = bool(live._pending)              # not answered yet: no turn of the loop since
            stalled = link.stalled(time.monotonic(), idle_s / 2, idle_s / 2)
            await live.settled()
            return owes, stalled, link.restarts
        finally:
            await pool.close()
    owes, stalled, restarts = asyncio.run(run())
    assert owes and not stalled and restarts == 0


async def _two_sessions(pool: HandPool):
    a = pool.session("a", pool.settings, pool.metrics)
    b = pool.session("b", pool.settings, pool.metrics)
    assert a.link is not b.link                    # one session per worker
    for live in (a, b):
        await _ingest(live, HELLO)
        await live.settled()
    return a, b


async def _stream_until(live, msgs: list[dict], done) -> int:
    """``live``'s glove sends its messages (again from the start at their end) until ``done()``; the
    number of messages answered."""
    k = 0
    while not done():
        await _ingest(live, msgs[k % len(msgs)])
        k += 1
        if k % 8 == 0:
            await live.settled()
    await live.settled()
    return k


def test_a_stopped_worker_is_replaced_once_the_other_worker_answers_while_the_stall_limit_is_far():
    """SIGSTOP: the worker owes an answer, is neither runnable nor using CPU; after ``hand_worker_lag_s``
    with the other worker answering it is killed and its session answered by the other one (the stall
    limit, 600 s, plays no part)."""
    msgs = _glove(2.0, 1)

    async def run():
        pool = await _pool(2, hand_worker_lag_s=0.2, hand_worker_stall_s=600.0)
        try:
            a, b = await _two_sessions(pool)
            stopped = a.link.pid
            os.kill(stopped, signal.SIGSTOP)
            try:
                await _ingest(a, msgs[0])
                answered = await _stream_until(b, msgs, lambda: a.restarts > 0)
                await a.settled()                   # on the other worker
            finally:
                with_pid = a.link.pid
            return answered, a.restarts, with_pid, stopped, b.link.pid
        finally:
            await pool.close()
    answered, restarts, now_on, stopped, other = asyncio.run(run())
    assert restarts == 1 and now_on == other != stopped
    assert answered >= LAG_EVIDENCE


def test_a_worker_busy_with_a_long_message_is_not_killed_while_the_other_worker_answers_many():
    """Session a's worker handles imu_batch messages of the largest size (hundreds of ms each here),
    answering nothing meanwhile, while session b's worker answers message after message; with
    ``hand_worker_lag_s`` far below one such message the busy worker is not killed: it is running (or
    waiting for a core) all along."""
    msgs = _glove(4.0, 2)
    samples = [x for m in msgs if m["type"] == "imu_batch" for x in m["samples"]][:MAX_BATCH_SAMPLES]
    poses = [m for m in msgs if m["type"] == "pose"]

    async def run():
        pool = await _pool(2, hand_worker_lag_s=0.02, hand_worker_stall_s=600.0)
        try:
            a, b = await _two_sessions(pool)
            worker = a.link.pid
            for m in poses:
                await _ingest(a, m)
            await a.settled()
            for _ in range(3):                      # three long messages in a row
                await _ingest(a, {"type": "imu_batch", "samples": samples})
            a_done = asyncio.create_task(a.settled())
            answered = await _stream_until(b, msgs, a_done.done)
            return answered, a.restarts, b.restarts, a.link.pid, worker, a.frames_out
        finally:
            await pool.close()
    answered, a_restarts, b_restarts, now_on, worker, frames = asyncio.run(run())
    assert a_restarts == 0 and b_restarts == 0 and now_on == worker
    assert answered >= LAG_EVIDENCE and frames > 0


def _owed_matches(pool: HandPool) -> bool:
    """Each worker's count of unanswered source messages is the sum over the sessions it holds."""
    return all(link.owed == sum(len(live._pending) for live in link.sessions.values()) for link in pool.links)


def test_a_worker_s_count_of_unanswered_messages_follows_its_sessions_through_a_kill_and_a_close():
    """The count the watchdog and ``owe`` read (no walk over the sessions per message) stays the sum of
    the sessions' unanswered messages while messages are in flight, when a killed worker's session
    moves with its unanswered messages to the other worker, and when a session closes owing answers.
    Both workers, the one started again after the kill too, run ``hand_worker_nice`` (5) nicer than the web process."""
    msgs = _glove(1.0, 3)

    async def run():
        pool = await _pool(2)
        checks = []
        try:
            a, b = await _two_sessions(pool)
            for m in msgs[:60]:
                await _ingest(a, m)
            checks.append(("in flight", a.link.owed > 0 and _owed_matches(pool)))
            killed, killed_pid = a.link, a.link.pid
            a.link.proc.kill()
            while a.restarts == 0:
                checks.append(("moving", _owed_matches(pool)))
                await asyncio.sleep(0.001)
            checks.append(("moved", a.link is b.link and _owed_matches(pool)))
            await a.settled()
            checks.append(("answered", a.link.owed == 0 and _owed_matches(pool)))
            for m in msgs[:60]:
                await _ingest(b, m)
            owed_before_close = b.link.owed
            b.close()
            checks.append(("closed", owed_before_close > 0 and _owed_matches(pool)))
            await a.settled()
            checks.append(("after close", _owed_matches(pool)))
            # the workers, the restarted one too, run nicer than this (web) process
            own = os.getpriority(os.PRIO_PROCESS, 0)
            want = min(19, own + pool.settings.hand_worker_nice)
            checks.append(("a nicer worker by default", want > own or own == 19))
            await _until(lambda: killed.pid != killed_pid and killed.ready.is_set(), "the killed worker's successor",
                         timeout_s=600.0)           # niced once ready
            checks += [(f"nice of worker {link.slot}", os.getpriority(os.PRIO_PROCESS, link.pid) == want)
                       for link in pool.links]
            return checks
        finally:
            await pool.close()
    checks = asyncio.run(run())
    assert [name for name, ok in checks if not ok] == []


def test_a_data_message_is_known_by_its_head_only_when_nothing_else_could_make_it_another_type():
    """``data_type``: the web process passes a JSON data message to its worker unread only when its
    first key is a ``"type"`` of a data message and no repeated or escaped ``"type"`` key could make the
    decoded message another type (the last of repeated keys wins in JSON decoders)."""
    import json

    from service.api.hands.pool import data_type

    batch = {"type": "imu_batch", "samples": [{"t": 0.0, "id": "index.1", "gyr": [0, 0, 0], "acc": [0, 9.81, 0]}]}
    assert data_type(json.dumps(batch, separators=(",", ":"))) == "imu_batch"
    assert data_type(json.dumps(batch)) == "imu_batch"                     # with spaces
    assert data_type('{"type":"pose","t":0.5,"valid":false}') == "pose"
    assert data_type('{"type":"imu","t":1.0,"id":"a","gyr":[0,0,0],"acc":[0,0,0]}') == "imu"
    repeated = '{"type":"imu","t":1.0,"type":"sync","id":"x"}'
    assert json.loads(repeated)["type"] == "sync" and data_type(repeated) is None
    escaped = '{"type":"imu","t":1.0,"\\u0074ype":"sync","id":"x"}'
    assert json.loads(escaped)["type"] == "sync" and data_type(escaped) is None
    assert data_type('{"t":1.0,"type":"imu"}') is None                     # not its first key
    assert data_type('{"type":"hello","protocol":1}') is None
    assert data_type('{"type":"imu_batchX","samples":[]}') is None
    assert data_type(' {"type":"imu"}') is None and data_type('["type","imu"]') is None
    many_p = '{"type":"pose","t":0.5,' + '"pp":"ppp",' * 10 + '"type":"sync","id":"x"}'
    assert data_type(many_p) is None                                       # found past the quick search's 8 p
    assert data_type(many_p.replace('"type":"sync"', '"typo":"sync"')) == "pose"
    assert data_type('{"type":"imu_batch","samples":[],"type":"sync"}') is None         # a p before it
    assert data_type('{"type":"imu","t":1.0,"id":"a","type"') is None                   # at the very end


def test_the_quick_search_for_a_second_type_key_finds_what_the_whole_word_search_finds():
    """``pool._has_type_key``: ``'"type"' in text[start:]`` found by the word's ``p`` (at most 8 of them, then
    the whole-word search), the same answer on random texts of the word, its pieces, its letters and quotes."""
    import random

    from service.api.hands.pool import _has_type_key

    rng, pieces, found = random.Random(16), ['"type"', '"ty', 'pe"', "p", '"', "t", "y", "e", "x", ":", "1"], 0
    for _ in range(50_000):
        text = "".join(rng.choice(pieces) for _ in range(rng.randrange(40)))
        start = rng.randrange(6)
        assert _has_type_key(text, start) is (text.find('"type"', start) >= 0), (text, start)
        found += _has_type_key(text, start)
    assert 100 < found < 49_900                                            # both answers were asked for


def test_a_session_switched_to_a_costly_estimator_runs_in_a_nicer_worker_of_its_own_and_comes_back_with_its_state():
    """Sessions a and b on one worker; b is switched to ``vector`` (per finger and sample in Python): it
    moves with its state to a worker process of its own, ``hand_worker_isolated_nice`` nicer than this
    one (1 here: at the default 10 its start-up waits for every other process on a busy machine, 29 s
    of this test under --busy 2), and back to the shared worker when switched to ``chain`` (its own worker then ends). Every
    source message of both is answered without an error, b's frames go on with increasing ``seq`` on
    each estimator in turn. a, switched to ``madgwick`` while b has the one worker of their own allowed
    (``hand_worker_isolated_max``), stays on the shared worker."""
    msgs = _glove(0.6, 4)
    parts = [msgs[:len(msgs) // 2], msgs[len(msgs) // 2:3 * len(msgs) // 4], msgs[3 * len(msgs) // 4:]]

    async def run():
        pool = await _pool(1, hand_worker_isolated_max=1, hand_worker_isolated_nice=1)
        try:
            a, b = pool.session("a", pool.settings, pool.metrics), pool.session("b", pool.settings, pool.metrics)
            errors, stages = [], []

            async def answer(code, detail, *samples):
                errors.append((code, detail))
            sub = Subscriber(frames_max=100_000, events_max=100_000)
            b.subscribers.add(sub)
            shared = a.link
            for live in (a, b):
                live.attach_source(answer)
                await _ingest(live, HELLO)
            for part, estimator in zip(parts, ("chain", "vector", "chain")):
                if estimator != b.config.estimator:
                    await asyncio.to_thread(b.update_config, {"estimator": estimator})
                if estimator == "vector":
                    await asyncio.to_thread(a.update_config, {"estimator": "madgwick"})
                link = b.link
                stage = {"link": link, "pid": link.pid, "nice": os.getpriority(os.PRIO_PROCESS, link.pid)}
                for m in part:
                    await _ingest(a, m)
                    await _ingest(b, m)
                await a.settled()
                await b.settled()
                stage["frames"] = [(f.message["seq"], f.message["status"]["estimator"]) for kind, f, _ in sub.queue
                                   if kind == "frame"]
                sub.queue.clear()
                stages.append(stage)
            own = stages[1]["link"]
            await _until(lambda: own.proc.returncode is not None, "b's own worker to end")
            return a, b, shared, stages, errors, pool.settings.hand_worker_isolated_nice
        finally:
            await pool.close()

    a, b, shared, stages, errors, nicer = asyncio.run(run())
    assert errors == []
    first, costly, back = stages
    want_nice = min(19, os.getpriority(os.PRIO_PROCESS, 0) + nicer)
    assert first["link"] is shared and costly["link"].isolated and costly["pid"] != shared.pid
    assert costly["nice"] == want_nice, (costly["nice"], want_nice)
    assert back["link"] is shared and back["pid"] == shared.pid
    for stage, estimator in zip(stages, ("chain", "vector", "chain")):
        assert stage["frames"] and {e for _, e in stage["frames"]} == {estimator}
    seqs = [seq for stage in stages for seq, _ in stage["frames"]]
    assert all(x < y for x, y in zip(seqs, seqs[1:])), seqs
    assert a.link is shared and a.restarts == a.moves == 0 and a.config.estimator == "madgwick"
    assert b.moves == 2 and b.restarts == 0


def test_the_spare_worker_at_the_default_limit_is_kept_through_a_given_up_move_taken_and_replaced_late():
    """With ``hand_worker_spare`` and the default ``hand_worker_isolated_max`` (2), one shared worker:
    the spare's process starts only once the shared worker is ready, ``hand_worker_isolated_nice`` nicer
    than this process. A move to it given up while it starts (``call``'s timeout) leaves it the spare
    (no orphan holding a slot). b, switched to ``vector`` with messages in flight, moves into it and its
    frames go on there on ``vector``; a new spare starts (replaced at the default limit) only once b runs
    ``vector`` there and has caught up (not beside b's worker while it catches up). b, switched back to
    ``chain``, returns to the shared worker and its worker ends; the pool's close ends every worker (the
    new spare's start too: this test does not wait for it)."""
    msgs = _glove(0.4, 8)
    parts = [msgs[:len(msgs) // 2], msgs[len(msgs) // 2:]]

    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1, hand_worker_spare=True,
                                             hand_worker_isolated_nice=1), Metrics())
        await pool.start()
        seen = {"isolated_max": pool.settings.hand_worker_isolated_max}
        try:
            shared, first = pool.links[0], pool.spare
            started, replaced = [], []

            async def start_first():                # when the spare's process is started
                started.append(shared.ready.is_set())
                await type(first).start(first)
            first.start = start_first
            b = pool.session("b", pool.settings, pool.metrics)
            a = pool.session("a", pool.settings, pool.metrics)
            given_up = asyncio.create_task(pool.move(a, isolated=True, config={"estimator": "vector"}))
            await asyncio.sleep(0)                  # the move waits for the spare, which waits for the shared worker
            seen["waiting"] = pool.spare is None and not shared.ready.is_set()
            given_up.cancel()
            await asyncio.gather(given_up, return_exceptions=True)
            await _until(lambda: first.ready.is_set(), "the spare worker")
            assert pool.spare is first and pool.isolated == [first] and a.link is shared, \
                "a move given up while the spare started left it without a session, and no spare"
            seen.update(started=started, spare_nice=os.getpriority(os.PRIO_PROCESS, first.pid))

            def replace_spare(original=pool._replace_spare):    # what b's state is when a new spare is started
                if pool.spare is None and len(pool.isolated) < pool.settings.hand_worker_isolated_max:
                    replaced.append((b.link is first, b.config.estimator, len(b._pending)))
                original()
            pool._replace_spare = replace_spare
            sub = Subscriber(frames_max=100_000, events_max=100_000)
            b.subscribers.add(sub)

            async def answer(*reply):
                seen.setdefault("errors", []).append(reply)
            for live in (a, b):
                live.attach_source(answer)
                await _ingest(live, HELLO)
            for m in parts[0][:40]:
                await _ingest(b, m)                 # in flight when it moves
            seen["in_flight"] = len(b._pending)
            await asyncio.to_thread(b.update_config, {"estimator": "vector"})
            seen["moved_to"] = b.link
            sub.queue.clear()                       # the frames of the messages in flight came before the change
            for m in parts[0][40:]:
                await _ingest(b, m)
            await b.settled()
            seen["estimators"] = {f.message["status"]["estimator"] for kind, f, _ in sub.queue if kind == "frame"}
            await asyncio.gather(*pool._replacing)
            second = pool.spare
            assert second is not None, "no new spare after b took the spare and caught up"
            seen["replaced"] = list(replaced)
            await asyncio.to_thread(b.update_config, {"estimator": "chain"})
            for m in parts[1]:
                await _ingest(b, m)
            await b.settled()
            seen["back_to"], seen["spare_then"], seen["isolated_then"] = b.link, pool.spare, list(pool.isolated)
            await _until(lambda: first.proc.returncode is not None, "b's former worker to end")
            return seen, shared, first, second, a, b
        finally:
            await pool.close()

    seen, shared, first, second, a, b = asyncio.run(run())
    assert seen["isolated_max"] == 2 and "errors" not in seen, seen.get("errors")
    assert seen["started"] == [True]                # not before the shared worker was ready
    assert seen["waiting"]
    assert seen["spare_nice"] == min(19, os.getpriority(os.PRIO_PROCESS, 0) + 1)
    assert seen["in_flight"] > CAUGHT_UP
    assert seen["moved_to"] is first and seen["estimators"] == {"vector"}
    assert second is not first and second.isolated
    assert seen["replaced"] == [(True, "vector", seen["replaced"][0][2])] and seen["replaced"][0][2] <= CAUGHT_UP
    assert seen["back_to"] is shared and b.moves == 2 and b.restarts == 0 and a.link is shared and a.moves == 0
    assert seen["spare_then"] is second and seen["isolated_then"] == [second]
    for link in (first, second):                    # ended with the pool (or, the new spare, never started)
        assert link.proc is None or link.proc.returncode is not None


def test_no_spare_worker_starts_past_the_limit_nor_once_the_pool_closes():
    """With two sessions in workers of their own (the default ``hand_worker_isolated_max``) no spare
    starts; one of those workers ending while the pool closes (its session left it) starts none in its
    place either: ``close`` has already stopped every worker it knows of, a spare started then would
    outlive it. (Workers not started: no process is needed for the rule.)"""
    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1, hand_worker_spare=True), Metrics())
        pool.loop = asyncio.get_running_loop()
        own = [WorkerLink(pool, slot, estimator="vector") for slot in (1, 2)]
        pool.isolated.extend(own)
        pool._replace_spare()
        at_limit = pool.spare
        pool.closing = True
        await pool.retire(own[0])                   # never started: its stop waits for nothing
        return pool.settings.hand_worker_isolated_max, at_limit, pool.spare, pool.isolated, own
    limit, at_limit, closing, isolated, own = asyncio.run(run())
    assert limit == 2 and at_limit is None and closing is None and isolated == own[1:]


def test_the_spare_is_replaced_once_its_session_runs_its_new_estimator_and_has_caught_up_or_has_left_it():
    """The rule for starting a new spare after one was taken (``HandPool.settled_in``): not while the
    session there still runs its old estimator, nor while it has more than ``CAUGHT_UP`` source messages
    unanswered; yes once both hold, or once it has left that worker or closed."""
    from types import SimpleNamespace

    pool = HandPool(ServiceSettings.load(port=0, hand_workers=1), Metrics())
    taken, other = WorkerLink(pool, 1, estimator="chain"), WorkerLink(pool, 2, estimator="chain")
    live = SimpleNamespace(link=taken, sid=7, config=SimpleNamespace(estimator="chain"),
                           _pending=dict.fromkeys(range(40)))
    taken.sessions[7] = live

    def rule(estimator="chain", pending=40, link=taken, there=True):
        live.config.estimator, live._pending, live.link = estimator, dict.fromkeys(range(pending)), link
        if not there:
            taken.sessions.pop(7, None)
        return HandPool.settled_in(live, taken, "vector")
    assert not rule("chain", 0)                     # the change has not applied yet
    assert not rule("vector", CAUGHT_UP + 1)        # it has, but the session has not caught up
    assert rule("vector", CAUGHT_UP) and rule("vector", 0)
    assert rule("chain", 40, link=other)            # it left that worker
    assert rule("chain", 40, there=False)           # it closed


def test_a_spare_after_the_service_started_does_not_wait_for_a_restarting_shared_worker(monkeypatch):
    """The first spare starts once the shared workers are ready (it never slows the service's start); a
    later one (a replacement) starts while a shared worker restarts: a switch may be waiting for it.
    (No process: the workers' start is recorded instead.)"""
    from service.api.hands import pool as pool_module

    started = []

    async def start(link):
        started.append((link.slot, [x.ready.is_set() for x in link.pool.links]))
    monkeypatch.setattr(pool_module.WorkerLink, "start", start)

    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1, hand_worker_spare=True), Metrics())
        pool.loop = asyncio.get_running_loop()
        shared = pool.links[0]
        pool._replace_spare()
        first = pool.spare
        for _ in range(5):
            await asyncio.sleep(0)
        before_ready = list(started)
        shared.ready.set()
        await asyncio.wait_for(first.starting, 60.0)
        shared.ready.clear()                        # the shared worker restarts (a crash)
        pool.spare = None                           # the spare was taken by a move,
        await pool.retire(first)                    # and its session left it: a new spare starts
        await asyncio.wait_for(pool.spare.starting, 60.0)
        return before_ready, started, first.slot, pool.spare.slot
    before_ready, started, first, second = asyncio.run(run())
    assert before_ready == []
    assert started == [(first, [True]), (second, [False])]


def test_a_session_moving_back_to_a_restarting_worker_drops_the_close_of_it_held_there():
    """A worker restarting when a session left it holds that session's ``close`` until its new process
    runs; if the session moves back meanwhile, its reopen must not be followed by that close (the worker
    would drop the hand and the session's messages go unanswered). Held closes of other sessions stay."""
    class Moving:                                  # what ``take`` needs of a session
        def __init__(self, sid, link):
            self.sid, self.link, self._pending, self.reopened = sid, link, {1: None, 2: None}, []
            link.sessions[sid] = self

        def reopen(self, config, restart):
            self.reopened.append((config, restart))
    pool = HandPool(ServiceSettings.load(port=0, hand_workers=2), Metrics())
    restarting, other = pool.links
    restarting._held = [["close", 5], ["close", 6]]
    live = Moving(5, other)
    other.owed = 2
    restarting.take(live, {"estimator": "chain"}, restart=False)
    assert restarting._held == [["close", 6]] and live.link is restarting and live.sid in restarting.sessions
    assert live.reopened == [({"estimator": "chain"}, False)] and restarting.owed == 2 and other.owed == 0


def test_what_a_worker_could_not_restore_goes_to_the_session_s_source_with_its_next_reply():
    """The web process passes a worker's ``lost`` errors (``hands.worker``) to the session's source with
    the next reply (as on the bus: to the source connected then, also when the session moved while its
    source was away), before that reply's own errors."""
    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1), Metrics())
        pool.loop = asyncio.get_running_loop()
        live = pool.session("s", pool.settings, pool.metrics)
        got = []

        async def answer(code, detail, *samples):
            got.append((code, detail))
        pool.links[0]._dispatch(["lost", live.sid, [["invalid_message", "its calibration: sensors; send it again"]]])
        live.attach_source(answer)                  # a source connecting after the move
        await asyncio.sleep(0)
        told_before_a_reply = list(got)
        live._pending[1] = ("imu", ["src", b""], time.perf_counter(), None)
        live.link.owed += 1
        pool.links[0]._dispatch(["rep", live.sid, 1, [["duplicate", "the same sensor and time"]]])
        await _until(lambda: len(got) == 2, "the source's error replies")
        return told_before_a_reply, got
    before, got = asyncio.run(run())
    assert before == []
    assert got == [("invalid_message", "its calibration: sensors; send it again"), ("duplicate", "the same sensor and time")]


def test_the_link_reader_passes_on_every_message_in_order_a_few_frames_per_turn_and_finishes_after_the_last():
    """``_LinkReader`` (the web process's end of a worker's socket): batches split anywhere across reads
    are dispatched in order; at most ``outs_per_turn`` frames and events go before the loop's next turn
    (so that the subscribers' senders go first), and a batch after frames waits for that turn too; what
    arrives meanwhile waits in its buffer, and reading pauses only once more than ``READ_AHEAD`` bytes
    wait there (resumed at that turn; not once the connection is lost); every read counts as a sign of
    life; once the connection is lost, what arrived before is dispatched, then ``finished`` is done."""
    from types import SimpleNamespace

    from service.api.hands.pool import _LinkReader
    from service.api.hands.worker import frame

    batches = [[["rep", 1, 1, []], *[["out", 1, 2, ["frame", k, 0.0, "right"], "{}", None] for k in range(5)],
                ["rep", 1, 2, []]],
               [["rep", 1, 3, []]], [["out", 1, 4, ["gesture", None, None, None], "{}", None]], [["rep", 1, 4, []]]]
    data = b"".join(frame(batch) for batch in batches)

    async def run(read_ahead, lose):
        got, heard, turns = [], [], []
        link = SimpleNamespace(pool=SimpleNamespace(outs_per_turn=2), _dispatch=got.append,
                               _hear=lambda: heard.append(1), slot=0)
        calls = []
        transport = SimpleNamespace(pause_reading=lambda: calls.append("pause"),
                                    resume_reading=lambda: calls.append("resume"), close=lambda: None)
        reader = _LinkReader(link)
        if read_ahead is not None:
            reader.READ_AHEAD = read_ahead
        reader.connection_made(transport)
        for i in range(0, len(data), 7):           # reads of 7 bytes, all in one turn of the loop
            reader.data_received(data[i:i + 7])
        outs_in_first_turn = sum(1 for m in got if m[0] == "out")
        in_first_turn = list(calls)
        assert reader.unread()
        assert len(heard) == -(-len(data) // 7)
        if lose:
            reader.connection_lost(None)            # lost while messages still wait
        while not (reader.finished.done() if lose else not reader.unread()):
            turns.append(sum(1 for m in got if m[0] == "out"))
            await asyncio.sleep(0)
        return got, outs_in_first_turn, turns, reader.unread(), in_first_turn, calls
    for read_ahead, lose, first_calls, all_calls in ((None, True, [], []), (40, True, ["pause"], ["pause"]),
                                                     (40, False, ["pause"], ["pause", "resume"])):
        got, first, turns, unread, in_first_turn, calls = asyncio.run(run(read_ahead, lose))
        assert got == [m for batch in batches for m in batch]
        assert first == 2                           # outs_per_turn, then the senders' turn
        assert all(b - a <= 2 for a, b in zip([first, *turns], turns)), turns
        assert not unread and in_first_turn == first_calls and calls == all_calls, (read_ahead, lose, calls)


def _reader_pair(batches, outs_per_turn=2, dispatch=None):
    """A ``_LinkReader`` on a fake link and transport: what it dispatches, its pause/resume calls."""
    from types import SimpleNamespace

    from service.api.hands.pool import _LinkReader

    got, calls = [], []
    link = SimpleNamespace(pool=SimpleNamespace(outs_per_turn=outs_per_turn), _dispatch=dispatch or got.append,
                           _hear=lambda: None, slot=0)
    transport = SimpleNamespace(pause_reading=lambda: calls.append("pause"),
                                resume_reading=lambda: calls.append("resume"), close=lambda: calls.append("close"))
    reader = _LinkReader(link)
    reader.connection_made(transport)
    return reader, got, calls


def _out(k: int) -> list:
    return ["out", 1, k, ["frame", k, 0.0, "right"], "{}", None]


def test_the_link_reader_keeps_its_per_turn_bound_across_batches_and_finishes_only_after_the_last_message():
    """A batch that ends on its ``outs_per_turn``-th frame and a batch of frames after it, in one read: at
    most ``outs_per_turn`` frames per turn of the loop across the two. A message whose passing on raises
    (a defect) is skipped and logged, the connection closed, and ``finished`` is done only once the
    messages after it have been passed on too (its sessions move only then)."""
    from service.api.hands.worker import frame

    async def bound():
        reader, got, _ = _reader_pair([])
        reader.data_received(frame([_out(0), _out(1)]) + frame([_out(k) for k in range(2, 7)]))
        per_turn = [len(got)]
        while reader.unread():
            await asyncio.sleep(0)
            per_turn.append(len(got) - sum(per_turn))
        return per_turn, len(got)
    per_turn, total = asyncio.run(bound())
    assert total == 7 and max(per_turn) <= 2, per_turn

    async def defect():
        got = []

        def dispatch(message):
            if message[0] == "bad":
                raise KeyError("a defect")
            got.append(message)
        reader, _, calls = _reader_pair([], dispatch=dispatch)
        reader.data_received(frame([_out(0), ["bad"], *[_out(k) for k in range(1, 6)]]))
        reader.connection_lost(None)                # (the transport's close, then its end)
        done_early = reader.finished.done() and reader.unread()
        await asyncio.wait_for(reader.finished, 30)
        return done_early, len(got), reader.unread(), calls
    done_early, passed, unread, calls = asyncio.run(defect())
    assert not done_early and passed == 6 and not unread and "close" in calls


def test_a_link_over_its_high_water_mark_holds_its_batches_and_writes_them_in_order_once_it_has_drained():
    """``WorkerLink.writable``: while the transport's buffer is over its high-water mark (``pause_writing``) each
    turn's batch is packed and kept, not appended to that buffer; once it has drained (``resume_writing``) they
    go in one write, in order, and only then does a worker that owes its first answer count as silent; a stop
    writes what is kept before the close."""
    from types import SimpleNamespace

    from service.api.hands.worker import frame

    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1), Metrics())
        pool.loop = asyncio.get_running_loop()
        link, writes = pool.links[0], []
        link._writer = SimpleNamespace(write=writes.append, is_closing=lambda: False,
                                       close=lambda: writes.append("close"))
        link.send(["a", 1])
        await asyncio.sleep(0)
        at_once = writes[:]
        link._reader = None
        link.writable(False)
        link.owe()                                  # its first answer owed from the next write on
        heard = link.heard
        for k in range(3):
            link.send(["b", k])
            await asyncio.sleep(0)
        held = (writes[:], link._owing_from_flush, link.heard == heard)
        link.writable(True)
        drained = (writes[1:], link._owing_from_flush)
        link.writable(False)
        link.send(["c", 0])
        await asyncio.sleep(0)
        await link.stop()
        return at_once, held, drained, writes[2:]

    at_once, held, drained, stopped = asyncio.run(run())
    assert at_once == [frame([["a", 1]])]
    assert held == (at_once, True, True)
    assert drained == ([b"".join(frame([["b", k]]) for k in range(3))], False)
    assert stopped == [frame([["c", 0]]), "close"]


def test_a_link_writes_what_it_held_in_bounded_writes_and_what_comes_meanwhile_after_it(monkeypatch):
    """``WorkerLink._write_packed``: the batches kept while the transport's buffer was full go in writes of about
    ``PACKED_WRITE_BYTES``, in order, until it is full again (the rest then waits for the next drain); a batch
    of a later turn goes after everything kept before it, even while the buffer has room."""
    from types import SimpleNamespace

    from service.api.hands import pool as pool_module
    from service.api.hands.worker import frame

    monkeypatch.setattr(pool_module, "PACKED_WRITE_BYTES", 2 * len(frame([["b", 0]])))

    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1), Metrics())
        pool.loop = asyncio.get_running_loop()
        link, writes = pool.links[0], []

        def write(data):
            writes.append(data)
            if len(writes) == 2:                    # the second write fills the buffer again
                link.writable(False)
        link._writer = SimpleNamespace(write=write, is_closing=lambda: False)
        link.writable(False)
        for k in range(6):
            link.send(["b", k])
            await asyncio.sleep(0)
        link.writable(True)                         # two writes of two batches, then full again
        first = writes[:]
        link.writable(True)                         # the rest, then a later turn's batch after it
        link.send(["c", 0])
        await asyncio.sleep(0)
        return first, writes[2:]

    first, rest = asyncio.run(run())
    assert first == [frame([["b", 0]]) + frame([["b", 1]]), frame([["b", 2]]) + frame([["b", 3]])]
    assert rest == [frame([["b", 4]]) + frame([["b", 5]]), frame([["c", 0]])]


def _route(live, settings, metrics):
    """The ingest route's reader and processor (``routes.ingest._Door.read``/``_process``) on a fake connection."""
    import json
    from types import SimpleNamespace

    from service.api.backlog import IngestBacklog
    from service.api.routes import ingest as route
    from service.api.routes.socket import send_error

    class Ws:
        def __init__(self):
            self.inbox, self.sent = asyncio.Queue(), []
            self.state = SimpleNamespace(binary=False, token="t")
            self.app = SimpleNamespace(state=SimpleNamespace(sessions=SimpleNamespace(sending={})))

        async def receive(self):
            return await self.inbox.get()

        async def send_text(self, text):
            self.sent.append(json.loads(text))

        async def close(self, code=1000, reason=""):
            pass

        def feed(self, message):
            text = message if isinstance(message, str) else json.dumps(message, separators=(",", ":"))
            self.inbox.put_nowait({"type": "websocket.receive", "text": text})

    ws = Ws()
    live.source = ws
    live.attach_source(lambda code, detail, samples=None: send_error(ws, metrics, code, detail, samples=samples))
    backlog = IngestBacklog(settings.ingest_backlog_messages, settings.ingest_backlog_bytes)
    processor = asyncio.create_task(route._process(ws, "s", live, backlog, metrics))
    reader = asyncio.create_task(route._Door(ws, "s", live, backlog, processor, settings, metrics).read())
    return ws, backlog, processor, reader


def _offline_session(**extra):
    """A ``ProcessSession`` whose worker link only keeps what it is sent (no process)."""
    from service.api.hands.pool import ProcessSession

    pool = HandPool(ServiceSettings.load(port=0, hand_workers=1, **extra), Metrics())
    pool.loop = asyncio.get_running_loop()
    sent = []
    pool.links[0].send = sent.append
    return pool.settings, pool.metrics, ProcessSession("s", pool.settings, pool.metrics, pool.links[0], 1), sent


def _offline_session_with_source() -> tuple:
    """``_offline_session`` with a source attached to its session, and the list its error replies' codes go
    into (where a test also notes the session's answers, in order)."""
    settings, metrics, live, sent = _offline_session()
    got = []

    async def error(code, detail, *samples):
        got.append(code)
    live.attach_source(error)
    return settings, metrics, live, sent, got


def _source_types(sent: list) -> list[str]:
    """The types of the source messages a worker link was sent, in order."""
    import json

    return [json.loads(m[3])["type"] if m[0] == "chk" else msgpack.unpackb(m[3])["type"]
            for m in sent if m[0] in ("chk", "src")]


async def _answer_all(live, turns: int = 30) -> None:
    for _ in range(turns):
        await asyncio.sleep(0)
        for n in sorted(live._pending):
            live.on_reply(n, [], True)


def _in_order_over_seeds(order) -> int:
    """``order(seed)`` (the worker's types, the types fed, how many went the quick way) over six seeds: the
    worker got every message in order each time; how many went the quick way in all."""
    quick = 0
    for seed in range(6):
        got, expected, n = asyncio.run(order(seed))
        assert got == expected, seed
        quick += n
    return quick


async def _random_stream(rnd, msgs: list[dict], ws, live, sent, reader, backlog, processor) -> list[str]:
    """A hello and ``msgs`` fed to the ingest route in random interleavings (data whose head the reader knows
    and data only the processor decodes, syncs, the worker answering at random turns) until the worker got
    them all and every sync was answered, then the connection's end; the types fed, in order."""
    expected, syncs = ["hello"], 0
    ws.feed(HELLO)
    for m in msgs:
        if m["type"] in ("imu_batch", "pose") and rnd.random() < 0.3:     # type last: the processor's path
            m = {**{k: v for k, v in m.items() if k != "type"}, "type": m["type"]}
        ws.feed(m)
        expected.append(m["type"])
        if rnd.random() < 0.1:
            syncs += 1
            ws.feed({"type": "sync", "id": syncs})
        for _ in range(rnd.randrange(3)):
            await asyncio.sleep(0)
        if live._pending and rnd.random() < 0.5:
            live.on_reply(min(live._pending), [], True)
    while len(_source_types(sent)) < len(expected) or sum(s["type"] == "sync" for s in ws.sent) < syncs:
        await _answer_all(live, 1)
    ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
    await reader
    backlog.close()
    await processor
    return expected


def test_the_ingest_reader_hands_data_on_itself_only_in_order_and_only_after_its_own_connection_s_hello():
    """The ingest route's reader hands a data message on itself only while the processor waits with nothing
    queued: over random interleavings (data whose head the reader knows and data only the processor decodes,
    calibrations, syncs, the worker answering at random turns) the worker gets every source message in the
    order received, and the reader did hand some on. After a takeover, the new connection's data before its
    own hello gets ``expected_hello`` and does not reach the worker, although the older connection's hello
    (handled after the takeover) greeted the session. A defect while the reader hands a message on is
    answered as the processor answers one (``internal_error``), and the connection goes on (its ``sync``
    is answered)."""
    import json
    import random

    msgs = [m for m in _glove(0.3, 1) if m["type"] != "hello"]
    data = next(m for m in msgs if m["type"] == "imu_batch")

    async def order(seed):
        settings, metrics, live, sent = _offline_session(rate_limit_msgs_per_s=1e6)
        ws, backlog, processor, reader = _route(live, settings, metrics)
        by_reader = []
        forwardable = live.forwardable
        live.forwardable = lambda data: by_reader.append(forwardable(data)) or by_reader[-1]
        expected = await _random_stream(random.Random(seed), msgs, ws, live, sent, reader, backlog, processor)
        return _source_types(sent), expected, sum(x is not None for x in by_reader)

    async def takeover():
        settings, metrics, live, sent = _offline_session()
        live._pending[99] = ("imu", ["chk", "{}", False], 0.0, None)      # an earlier message not yet answered
        live.link.owed += 1
        a, backlog_a, processor_a, reader_a = _route(live, settings, metrics)
        a.feed(HELLO)
        for _ in range(10):
            await asyncio.sleep(0)                  # A's processor waits for message 99 before A's hello
        b, backlog_b, processor_b, reader_b = _route(live, settings, metrics)             # B takes over
        live.on_reply(99, [], True)                 # A's hello goes on now and greets the session
        await _answer_all(live, 10)
        b.feed(data)                                # B's data before B's hello
        await _answer_all(live)
        for ws, backlog, processor, reader in ((a, backlog_a, processor_a, reader_a), (b, backlog_b, processor_b, reader_b)):
            ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
            await reader
            backlog.close()
            await processor
        return [s["code"] for s in b.sent if s["type"] == "error"], _source_types(sent)

    async def defect():
        settings, metrics, live, sent = _offline_session()

        def send(message):
            if message[0] == "chk":
                raise KeyError("a defect")
            sent.append(message)
        live.link.send = send
        ws, backlog, processor, reader = _route(live, settings, metrics)
        ws.feed(HELLO)
        await _answer_all(live, 10)
        ws.feed(data)
        ws.feed({"type": "sync", "id": 1})
        while not any(s["type"] == "sync" for s in ws.sent):
            assert not reader.done(), reader
            await _answer_all(live, 1)
        ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
        await reader
        backlog.close()
        await processor
        return [(s["type"], s.get("code")) for s in ws.sent if s["type"] != "hello"]

    assert _in_order_over_seeds(order) > 0
    errors, to_worker = asyncio.run(takeover())
    assert errors == ["expected_hello"] and to_worker == ["hello"]
    assert asyncio.run(defect()) == [("error", "internal_error"), ("sync", None)]


def test_a_sync_holds_back_no_later_message_and_is_answered_in_its_place_among_the_error_replies():
    """A ``sync`` of a source whose worker has not answered the messages before it: the messages after it go
    on to the worker at once (they used to wait here until the worker had answered everything before the
    sync), and the source gets the replies in the order of its messages: the earlier message's error, the
    sync's answer, the later message's error."""
    msgs = [m for m in _glove(0.1, 2) if m["type"] == "imu_batch"][:4]

    async def run():
        settings, metrics, live, sent = _offline_session()
        ws, backlog, processor, reader = _route(live, settings, metrics)
        ws.feed(HELLO)
        await _answer_all(live, 10)
        ws.feed(msgs[0])
        ws.feed({"type": "sync", "id": 7})
        ws.feed(msgs[1])
        ws.feed(msgs[2])
        for _ in range(50):                         # the worker answers nothing meanwhile
            await asyncio.sleep(0)
        before_answers = _source_types(sent)
        first = min(live._pending)
        live.on_reply(first, [["late", "first"]], True)
        for _ in range(200):                        # (the code before sent the later ones only now)
            for n in sorted(live._pending):
                live.on_reply(n, [["late", f"later {n}"]], True)
            await asyncio.sleep(0)
        ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
        await reader
        backlog.close()
        await processor
        return before_answers, [(s["type"], s.get("detail", s.get("id"))) for s in ws.sent if s["type"] != "hello"]

    before_answers, replies = asyncio.run(run())
    assert before_answers == ["hello", "imu_batch", "imu_batch", "imu_batch"]
    assert replies[:2] == [("error", "first"), ("sync", 7)] and [r[0] for r in replies[2:]] == ["error", "error"]


def test_an_answer_that_fails_is_logged_and_the_replies_after_it_still_go_out(monkeypatch):
    """A defect in an answer (``answer_in_order``) is logged in one line and answered ``internal_error`` in
    its place (as a defect in a message's processing), and the replies queued after it still go out."""
    import gc

    import service.api.hands.pool as pool_module

    logged = []
    monkeypatch.setattr(pool_module.log, "warning", lambda *args: logged.append(args[0]))

    async def run():
        settings, metrics, live, sent = _offline_session()
        got = []

        async def send_error(code, detail, samples=None):
            got.append(detail)

        async def broken():
            raise KeyError("a defect")
        live.attach_source(send_error)
        live._send_source("imu", ["chk", "{}", False], None)
        live.answer_in_order(broken)
        live._send_source("imu", ["chk", "{}", False], None)
        first, second = sorted(live._pending)
        live.on_reply(first, [["late", "first"]], True)      # the first error, the answer, the second error queued
        live.on_reply(second, [["late", "second"]], True)
        for _ in range(50):
            await asyncio.sleep(0)
        return got

    got = asyncio.run(run())
    gc.collect()          # (a task that ended with the defect, before: finalised here, not while pytest reports)
    assert got == ["first", "KeyError while answering the source; answer dropped", "second"], got
    assert logged == ["session %s: %s while answering its source: %s"], logged


@pytest.mark.parametrize("behind", ["worker", "source"])
def test_a_flood_of_syncs_is_bounded_by_the_backlog_while_the_worker_or_the_source_is_behind(behind):
    """Syncs answered in their place among the replies (``answer_in_order``) wait in the web process while
    the worker is behind, or while the source reads nothing (their sending blocks): at most
    ``ingest_backlog_messages`` of them; the ones after wait in the connection's backlog, whose bounds refuse
    the rest. Every sync gets one reply, the answers in order."""
    msg = [m for m in _glove(0.1, 2) if m["type"] == "imu_batch"][0]
    flood = 60

    async def run():
        settings, metrics, live, sent = _offline_session(ingest_backlog_messages=8)
        ws, backlog, processor, reader = _route(live, settings, metrics)
        ws.feed(HELLO)
        await _answer_all(live, 10)
        reading = asyncio.Event()
        send_text = ws.send_text
        if behind == "source":

            async def blocked(text):                # the source reads nothing: its socket's buffer is full
                await reading.wait()
                await send_text(text)
            ws.send_text = blocked
        ws.feed(msg)                                # the worker does not answer it for now (or at once)
        for i in range(flood):
            ws.feed({"type": "sync", "id": i})
        most = 0
        for _ in range(300):
            await asyncio.sleep(0)
            if behind == "source":
                for n in sorted(live._pending):
                    live.on_reply(n, [], True)
            most = max(most, len(live._answers) + sum(map(callable, live._errors)))
        held = len(backlog)
        reading.set()
        await _answer_all(live, 300)
        ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
        await reader
        backlog.close()
        await processor
        return most, held, [s for s in ws.sent if s["type"] != "hello"]

    most, held, replies = asyncio.run(run())
    answered = [r["id"] for r in replies if r["type"] == "sync"]
    refused = [r for r in replies if r["type"] == "error"]
    assert 0 < most <= 8 and 0 < held <= 16, (most, held)
    assert refused and all(r["code"] == "overloaded" for r in refused), refused[:3]
    assert answered == sorted(answered) and len(answered) + len(refused) == flood, (answered, len(refused))


def _door(live, settings, metrics):
    """The ingest route's reader and processor on a fake connection that offers each message to the route's
    way in (``_Door.intake``) while nothing waits in its queue, as ``server.DrainingWebSocket`` does; the
    texts taken that way are listed."""
    import json

    from service.api.backlog import IngestBacklog
    from service.api.routes import ingest as route
    from service.api.routes.socket import send_error

    ws, _, processor, reader = _route(live, settings, metrics)     # (its reader is replaced below)
    reader.cancel()
    processor.cancel()
    backlog = IngestBacklog(settings.ingest_backlog_messages, settings.ingest_backlog_bytes)
    say = route._Say(ws)                        # one for both, as the route has it
    processor = asyncio.create_task(route._process(ws, "s", live, backlog, metrics, say))
    door = route._Door(ws, "s", live, backlog, processor, settings, metrics, say)
    taken = []

    def feed(message):                          # as ``server.DrainingWebSocket`` offers a message
        text = message if isinstance(message, str) else json.dumps(message, separators=(",", ":"))
        if ws.inbox.empty() and door.intake(text):
            taken.append(text)
        else:
            ws.inbox.put_nowait({"type": "websocket.receive", "text": text})
    ws.feed = feed
    live.attach_source(lambda code, detail, samples=None: send_error(ws, metrics, code, detail, samples=samples))
    return ws, backlog, processor, asyncio.create_task(door.read()), taken


async def _greeted_door(**extra):
    """``_door`` on an offline session (``_offline_session(**extra)``) whose hello the worker has answered:
    settings, live, the link's list, the connection, the backlog, the processor, the reader, the texts taken."""
    settings, metrics, live, sent = _offline_session(**extra)
    ws, backlog, processor, reader, taken = _door(live, settings, metrics)
    ws.feed(HELLO)
    await _answer_all(live, 10)
    return settings, live, sent, ws, backlog, processor, reader, taken


async def _route_ended(ws, reader, backlog, processor) -> None:
    """The connection's end, the reader and the processor done."""
    ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
    await reader
    backlog.close()
    await processor


def test_the_server_s_way_in_hands_data_on_as_it_arrives_only_in_order_and_within_the_rate_limit():
    """``routes.ingest._Door.intake`` (the server offers a text message as it arrives while nothing waits in
    its queue before it): over random interleavings (data whose head is known and data only the processor
    decodes, calibrations, syncs, the worker answering at random turns) the worker gets every source message in
    the order received, and the way in did take some; past the rate limit it takes none and the reader
    refuses them (``rate_limited``) in their places, between the answers to the syncs around them."""
    import random

    msgs = [m for m in _glove(0.3, 3) if m["type"] != "hello"]

    async def order(seed):
        settings, metrics, live, sent = _offline_session(rate_limit_msgs_per_s=1e6)
        ws, backlog, processor, reader, taken = _door(live, settings, metrics)
        expected = await _random_stream(random.Random(seed), msgs, ws, live, sent, reader, backlog, processor)
        return _source_types(sent), expected, len(taken)

    async def limited():
        settings, metrics, live, sent = _offline_session(rate_limit_msgs_per_s=5)
        ws, backlog, processor, reader, taken = _door(live, settings, metrics)
        ws.feed(HELLO)
        await _answer_all(live, 10)
        data = [m for m in msgs if m["type"] == "imu_batch"][:12]
        ws.feed({"type": "sync", "id": 1})
        for m in data:
            ws.feed(m)
            await _answer_all(live, 3)
        ws.feed({"type": "sync", "id": 2})
        deadline = time.monotonic() + 60            # (bounds a failure only)
        while len(ws.sent) < 1 + 1 + (12 - _source_types(sent).count("imu_batch")) + 1:
            assert time.monotonic() < deadline, ws.sent
            await _answer_all(live, 1)
        ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
        await reader
        backlog.close()
        await processor
        return [(s["type"], s.get("code", s.get("id"))) for s in ws.sent if s["type"] != "hello"], \
            _source_types(sent), len(taken)

    assert _in_order_over_seeds(order) > 0
    replies, to_worker, taken = asyncio.run(limited())
    # a bucket of 5: the hello and the first sync took 2; 3 data messages pass (one more if the bucket refilled
    # meanwhile), the others are refused in their places; the last sync is answered or refused
    passed = to_worker.count("imu_batch")
    assert 3 <= passed <= 4 and 1 <= taken <= passed + 2       # (the way in answers syncs too)
    assert replies[:-1] == [("sync", 1)] + [("error", "rate_limited")] * (12 - passed)
    assert replies[-1] in (("sync", 2), ("error", "rate_limited"))


def test_a_sync_taken_on_the_way_in_is_answered_in_its_place_and_a_bad_one_is_left_to_the_processor():
    """``_Door.answer_sync``: a ``sync`` offered as it arrives, with nothing queued before it, is taken there (no
    wake of the reader and the processor) and answered only once the worker has answered every message before
    it, after their error replies; an invalid one (no ``id``) is not taken: the processor answers it with its
    error, in its place; the ones after go the quick way again."""
    batch = next(m for m in _glove(0.2, 5) if m["type"] == "imu_batch")

    async def run():
        _, live, _, ws, backlog, processor, reader, taken = await _greeted_door(rate_limit_msgs_per_s=1e6)
        ws.feed(batch)                              # the worker does not answer it for now
        ws.feed({"type": "sync", "id": 1})
        for _ in range(10):
            await asyncio.sleep(0)
        early = [s["type"] for s in ws.sent if s["type"] != "hello"]
        n = next(iter(live._pending))
        live.on_reply(n, [["invalid_samples", "sample 0 refused", [0]]], True)
        ws.feed({"type": "sync"})                   # no id
        deadline = time.monotonic() + 60            # (bounds a failure only)
        while len(ws.sent) < 1 + 3:
            assert time.monotonic() < deadline, ws.sent
            await _answer_all(live, 1)
        ws.feed({"type": "sync", "id": 2})          # nothing queued before it: the quick way again
        while len(ws.sent) < 1 + 4:
            assert time.monotonic() < deadline, ws.sent
            await _answer_all(live, 1)
        await _route_ended(ws, reader, backlog, processor)
        return early, [(s["type"], s.get("code", s.get("id"))) for s in ws.sent if s["type"] != "hello"], taken

    early, replies, taken = asyncio.run(run())
    assert early == []
    assert replies == [("error", "invalid_samples"), ("sync", 1), ("error", "invalid_message"), ("sync", 2)], replies
    syncs = [t for t in taken if '"sync"' in t]
    assert syncs == ['{"type":"sync","id":1}', '{"type":"sync","id":2}'], taken


def test_a_sync_on_the_way_in_does_not_pass_a_message_queued_before_it():
    """``_Door.answer_sync`` takes a sync only with nothing queued before it (``_may_hand_on``): a sync right
    after a message the processor still holds (one only it decodes) is answered after that message's error."""
    async def run():
        _, live, _, ws, backlog, processor, reader, taken = await _greeted_door(rate_limit_msgs_per_s=1e6)
        ws.feed({"type": "wave"})                   # not for the way in: queued for the processor
        await asyncio.sleep(0)                      # the reader has put it in the backlog
        ws.feed({"type": "sync", "id": 7})
        deadline = time.monotonic() + 60            # (bounds a failure only)
        while len(ws.sent) < 1 + 2:
            assert time.monotonic() < deadline, ws.sent
            await _answer_all(live, 1)
        await _route_ended(ws, reader, backlog, processor)
        return [(s["type"], s.get("code", s.get("id"))) for s in ws.sent if s["type"] != "hello"]

    assert asyncio.run(run()) == [("error", "unknown_type"), ("sync", 7)]


def test_syncs_on_the_way_in_count_against_the_rate_limit_and_one_left_to_the_processor_is_charged_once(monkeypatch):
    """A sync answered from the way in takes a token of the rate limit (past it, syncs are refused
    ``rate_limited`` in their places); one the way in leaves to the processor (its answer cannot wait in its
    place) gets its token back, so the processor answers it with the bucket's last token (the clock stands
    still: the bucket never refills)."""
    from types import SimpleNamespace

    from service.api.routes import ingest as route

    monkeypatch.setattr(route, "time", SimpleNamespace(monotonic=lambda: 1000.0))     # the buckets' clock only

    async def until(ws, live, n):
        deadline = time.perf_counter() + 60         # (bounds a failure only)
        while len(ws.sent) < n:
            assert time.perf_counter() < deadline, ws.sent
            await _answer_all(live, 1)

    async def limited():
        _, live, _, ws, backlog, processor, reader, taken = await _greeted_door(rate_limit_msgs_per_s=3)
        for i in range(4):                          # the hello took one of three tokens
            ws.feed({"type": "sync", "id": i})
            await until(ws, live, 2 + i)
        await _route_ended(ws, reader, backlog, processor)
        return [(s["type"], s.get("code", s.get("id"))) for s in ws.sent if s["type"] != "hello"], len(taken)

    async def given_back():
        _, live, _, ws, backlog, processor, reader, taken = await _greeted_door(rate_limit_msgs_per_s=2)
        live.answer_in_order = lambda answer: False     # its answer cannot wait in its place
        ws.feed({"type": "sync", "id": 9})          # the hello took one of two tokens
        await until(ws, live, 2)
        await _route_ended(ws, reader, backlog, processor)
        return [(s["type"], s.get("code", s.get("id"))) for s in ws.sent if s["type"] != "hello"], len(taken)

    assert asyncio.run(limited()) == ([("sync", 0), ("sync", 1), ("error", "rate_limited"), ("error", "rate_limited")], 2)
    assert asyncio.run(given_back()) == ([("sync", 9)], 0)


def test_the_way_in_takes_no_more_than_the_worker_s_window_nor_a_message_over_the_size_limit():
    """``_Door.intake`` and the reader hand a session at most ``WINDOW`` unanswered messages (``forward`` does
    not wait: ``forwardable``'s bound is the only one): the rest wait in the backlog, in order, and go on as the
    worker answers. A data message over ``max_message_bytes`` is not taken: the reader answers
    ``message_too_large`` in its place and the next one goes on to the worker."""
    import json

    from service.api.hands.pool import WINDOW

    batch = next(m for m in _glove(0.2, 5) if m["type"] == "imu_batch")

    async def run():
        settings, live, sent, ws, backlog, processor, reader, taken = await _greeted_door(rate_limit_msgs_per_s=1e6)
        for _ in range(WINDOW + 40):             # the worker answers nothing meanwhile
            ws.feed(batch)
            await asyncio.sleep(0)
        for _ in range(20):
            await asyncio.sleep(0)
        held = (len(live._pending), len(backlog), len(taken))
        deadline = time.monotonic() + 60     # (bounds a failure only)
        while _source_types(sent).count("imu_batch") < WINDOW + 40:
            assert time.monotonic() < deadline
            await _answer_all(live, 1)
        big = {**batch, "padding": "x" * settings.max_message_bytes}
        ws.feed(big)
        ws.feed(batch)
        ws.feed({"type": "sync", "id": 1})
        while not any(s["type"] == "sync" for s in ws.sent):
            assert time.monotonic() < deadline
            await _answer_all(live, 1)
        await _route_ended(ws, reader, backlog, processor)
        big_text = json.dumps(big, separators=(",", ":"))
        return held, [(s["type"], s.get("code")) for s in ws.sent if s["type"] != "hello"], big_text in taken, \
            _source_types(sent).count("imu_batch"), len(taken)

    (pending, waiting, taken_then), replies, big_taken, to_worker, taken = asyncio.run(run())
    assert pending == WINDOW and 39 <= waiting <= 40 and taken_then == WINDOW     # (one may wait in the processor)
    assert replies == [("error", "message_too_large"), ("sync", None)] and not big_taken
    assert to_worker == WINDOW + 41 and taken >= WINDOW


def test_the_way_in_takes_nothing_more_once_it_started_closing_an_overloaded_connection():
    """A message ``_Door.intake`` took whose hand-on failed with no room left for its reply starts the
    overload close (1013); from then on the way in takes nothing more (the next message is not handed to the
    session from the server's callback: it goes to the reader)."""
    seen = {}

    async def run():
        settings, metrics, live, sent = _offline_session(rate_limit_msgs_per_s=1e6)
        ws, backlog, processor, reader, taken = _door(live, settings, metrics)
        closes = []
        ws.close = lambda code=1000, reason="": closes.append(code) or asyncio.sleep(0)
        ws.feed(HELLO)
        await _answer_all(live, 10)
        forwarded = []

        def broken(msg):                     # a defect in the hand-on, and no room for its reply
            forwarded.append(msg)
            raise RuntimeError("a defect")
        live.forward = broken
        backlog.put_reply = lambda reply: False
        batch = next(m for m in _glove(0.2, 5) if m["type"] == "imu_batch")
        ws.feed(batch)
        ws.feed(batch)
        for _ in range(10):
            await asyncio.sleep(0)
        seen["taken"], seen["forwarded"], seen["closes"] = len(taken), len(forwarded), closes[:]
        ws.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
        await asyncio.wait_for(reader, 60)   # (bounds a failure)
        backlog.close()
        await asyncio.wait_for(processor, 60)

    asyncio.run(run())
    # the second message went to the reader, which handed it on too and, finding the replies full as well,
    # closed too (a second 1013)
    assert seen["taken"] == 1 and seen["forwarded"] == 2 and seen["closes"][:1] == [1013]


@pytest.mark.parametrize("workers", [1, 0])
def test_data_messages_taken_as_they_arrive_keep_their_replies_in_order_with_a_real_server(monkeypatch, workers):
    """A real server and worker: data messages the route takes as they arrive (``_Door.intake``: some are, a
    count of the real method's takes) go to the worker in order, each invalid one answered by the worker
    in its place, and every sync after the error replies of the messages before it. With the hands on the
    service's own loop (``hand_workers=0``: the session validates each message itself) the way in is not
    offered (it would size and check every message twice) and the replies are the same."""
    import json

    import websockets

    from service.api.routes import ingest as route
    from service.api.server import ServerThread

    taken = []
    intake = route._Door.intake

    def counted(self, text):
        took = intake(self, text)
        taken.append(took)
        return took
    monkeypatch.setattr(route._Door, "intake", counted)
    settings = ServiceSettings.load(port=0, tokens={SOURCE_TOKEN: "source"}, hand_workers=workers,
                                    hand_worker_isolate=False)
    batches = [m for m in _glove(1.0, 4) if m["type"] == "imu_batch"][:40]

    async def run(url):
        async with websockets.connect(f"{url}/v1/ingest/s?token={SOURCE_TOKEN}") as ws:
            got = await _said_hello(ws)
            expected = []
            for k, m in enumerate(batches):
                if k % 5 == 2:                      # its head is a data message's; its body is not valid
                    m = {"type": "imu_batch", "samples": [{"t": m["samples"][0]["t"], "id": "index.1",
                                                           "gyr": [0.0, 0.0], "acc": [0.0, 9.81, 0.0]}]}
                    expected.append(("error", k))
                await ws.send(json.dumps(m, separators=(",", ":")))
                if k % 8 == 7:
                    await ws.send(json.dumps({"type": "sync", "id": k}))
                    expected.append(("sync", k))
            while len(got) < 1 + len(expected):
                reply = json.loads(await asyncio.wait_for(ws.recv(), 60))
                got.append(("sync", reply["id"]) if reply["type"] == "sync" else ("error", reply["code"]))
        return got, expected

    with ServerThread(settings) as server:
        got, expected = asyncio.run(run(server.ws_url))
    assert got[0] == "hello"
    # each invalid message's error before the sync after it, none after; their codes the worker's
    shown = [("error", "invalid_message") if kind == "error" else (kind, k) for kind, k in expected]
    assert got[1:] == shown
    assert any(taken) if workers else taken == []


def test_an_intake_that_fails_leaves_the_connection_and_its_messages_to_the_app_s_receive(monkeypatch, caplog):
    """A defect in ``_Door.intake`` (it raises at its third message): one log line, and that message and every
    later one of the connection go through the app's receive, each answered in order, the connection
    open (before, the exception escaped the server's callback: the connection was aborted, no close frame,
    the rest of the read lost)."""
    import json

    import websockets

    from service.api.routes import ingest as route
    from service.api.server import ServerThread

    calls = []
    intake = route._Door.intake

    def failing(self, text):
        calls.append(text)
        if len(calls) == 3:
            raise RuntimeError("a defect in the intake")
        return intake(self, text)
    monkeypatch.setattr(route._Door, "intake", failing)
    settings = _one_worker_source_service()
    batches = [m for m in _glove(1.0, 4) if m["type"] == "imu_batch"][:30]

    async def run(url):
        async with websockets.connect(f"{url}/v1/ingest/s?token={SOURCE_TOKEN}") as ws:
            got = await _said_hello(ws)
            for k, m in enumerate(batches):
                await ws.send(json.dumps(m, separators=(",", ":")))
                if k % 10 == 9:
                    await ws.send(json.dumps({"type": "sync", "id": k}))
            while len(got) < 4:
                got.append(json.loads(await asyncio.wait_for(ws.recv(), 60)))
        return got

    with caplog.at_level("ERROR", logger="service.api.server"):
        with ServerThread(settings) as server:
            got = asyncio.run(run(server.ws_url))
    assert got == ["hello", {"type": "sync", "id": 9}, {"type": "sync", "id": 19}, {"type": "sync", "id": 29}], got
    assert len(calls) == 3                          # no intake after it failed
    assert sum("intake failed" in r.getMessage() for r in caplog.records) == 1


class _Writes:
    """A worker link's transport that keeps each write."""

    def __init__(self):
        self.writes: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.writes.append(data)

    def is_closing(self) -> bool:
        return False

    def close(self) -> None:
        pass

    def batches(self) -> list[list]:
        from service.api.hands.worker import whole_batches
        return [batch for data in self.writes for batch in whole_batches(bytearray(data))]


def test_a_link_with_many_sessions_writes_what_comes_within_its_group_time_at_once_and_one_with_few_each_turn(monkeypatch):
    """``WorkerLink.send``: with ``GROUP_SESSIONS`` sessions or more, messages queued over several turns of the
    loop within ``GROUP_S`` of the link's last write wait and go in one write, in order (here a group time no
    test outlasts, then the stop's write: what waits is written before the close; then a short one, waited for
    by its write); the first message after a quiet time goes at the end of its turn; with fewer sessions (one
    hand at 1 kHz) every turn's messages go at the end of that turn."""
    from service.api.hands import pool as pool_module

    from service.api.hands import worker as worker_module

    monkeypatch.setattr(worker_module, "ACTIVE_S", 3600.0)   # the sessions noted stay active however slow the test

    async def run(sessions: int, group_s: float):
        monkeypatch.setattr(pool_module, "GROUP_S", group_s)
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1), Metrics())
        pool.loop = asyncio.get_running_loop()
        link, transport = pool.links[0], _Writes()
        link._writer = transport
        link.sessions = {sid: None for sid in range(sessions)}
        for sid in range(sessions):                 # each sent a source message just now
            link.active.note(sid, time.monotonic())
        link.send(["a", 0])                         # after a quiet time: at the end of the turn
        await asyncio.sleep(0)
        first = len(transport.writes)
        for k in range(5):
            link.send(["b", k])
            link.send(["c", k])
            if group_s > 60:                        # (a short group time: all in one turn, which no timer splits)
                await asyncio.sleep(0)
        for _ in range(5):
            await asyncio.sleep(0)
        within = len(transport.writes)
        if group_s > 60:
            await link.stop()
        else:
            await _until(lambda: len(transport.writes) > first, "the group's write")
        return first, within, transport.batches()

    many = pool_module.GROUP_SESSIONS
    everything = [["a", 0], *[m for k in range(5) for m in (["b", k], ["c", k])]]
    assert asyncio.run(run(many, 3600.0)) == (1, 1, [[["a", 0]], everything[1:]])
    first, within, batches = asyncio.run(run(many + 3, 0.01))
    assert first == 1 and batches == [[["a", 0]], everything[1:]]
    first, within, batches = asyncio.run(run(many - 1, 3600.0))
    assert (first, within) == (1, 6) and batches == [[["a", 0]], *[[["b", k], ["c", k]] for k in range(5)]]
    first, within, batches = asyncio.run(run(1, 3600.0))
    assert (first, within) == (1, 6) and [m for b in batches for m in b] == everything


def test_an_answer_that_can_be_written_at_once_is_written_in_its_place_without_a_task():
    """``ProcessSession._send_errors_soon``: answers first in line that say they are written at once
    (``routes.ingest.SyncAnswer.now``) are answered there, in order, with no task; one behind an error reply,
    one whose ``now`` cannot write (False) or fails, goes the awaited way, after what is before it."""
    async def run():
        settings, metrics, live, sent, got = _offline_session_with_source()

        class Answer:
            def __init__(self, name, can):
                self.name, self.can = name, can

            def now(self):
                if self.can is None:
                    raise RuntimeError("a defect")
                if self.can:
                    got.append(self.name + " at once")
                return self.can

            async def __call__(self):
                got.append(self.name + " awaited")
        live._send_source("imu", ["chk", "{}", False], None)
        live.answer_in_order(Answer("a", True))     # due after message 1
        assert got == [] and live._error_task is None
        live.on_reply(1, [])
        assert got == ["a at once"] and live._error_task is None    # answered in the reply's callback
        live.answer_in_order(Answer("b", True))     # nothing before it: at once
        assert got == ["a at once", "b at once"] and live._error_task is None
        live._send_source("imu", ["chk", "{}", False], None)
        live.answer_in_order(Answer("c", True))
        live.on_reply(2, [["invalid_message", "x"]])   # an error reply before it: the awaited way, in order
        assert got == ["a at once", "b at once"] and live._error_task is not None
        await live.settled()
        assert got[2:] == ["invalid_message", "c awaited"]
        live.answer_in_order(Answer("d", False))
        live.answer_in_order(Answer("e", None))
        await live.settled()
        return got[4:]

    assert asyncio.run(run()) == ["d awaited", "e awaited"]


def test_a_plain_sync_is_read_without_its_model_and_anything_else_the_whole_way():
    """``routes.ingest._plain_sync_id``: the id of exactly ``{"type": "sync", "id": <0..2**53>}`` (what ``Sync``
    takes as it is); ``None`` for everything ``Sync`` refuses or reads otherwise, which the model then answers."""
    from service.api.routes.ingest import _plain_sync_id
    from service.protocol import ProtocolError, Sync, parse_input

    texts = ['{"type":"sync","id":7}', '{ "id": 0, "type": "sync" }', '{"type":"sync","id":9007199254740992}',
             '{"type":"sync","id":9007199254740993}', '{"type":"sync","id":-1}', '{"type":"sync","id":true}',
             '{"type":"sync","id":7.0}', '{"type":"sync","id":"7"}', '{"type":"sync","id":7,"x":1}',
             '{"type":"sync"}', '{"type":"sync","id":NaN}', '{"type":"sync","id":7', '["sync",7]',
             '{"type":"Sync","id":7}', '{"type":"sync","type":"sync","id":3}']
    plain = []
    for text in texts:
        sync_id = _plain_sync_id(text)
        if sync_id is not None:
            plain.append(text)
            msg = parse_input(text)[1]
            assert isinstance(msg, Sync) and msg.id == sync_id and type(sync_id) is int
        else:                                           # (left to the model: refused, or read its own way)
            try:
                parse_input(text)
            except ProtocolError:
                pass
    assert plain == texts[:3] + texts[-1:]


def test_a_worker_s_reply_to_a_run_of_messages_releases_them_as_their_replies_one_by_one_would():
    """``["reps", sid, first, last]`` (``hands.worker``): the session's messages ``first`` to ``last`` are
    answered (the source's window, the worker's count of what it owes, the messages received, the pool's count
    of answers), and an answer due after the run's last message is released, not one due after a later one; a
    session's ``lost`` errors go to its source with it."""
    async def run():
        settings, metrics, live, sent, got = _offline_session_with_source()
        for _ in range(5):
            live._send_source("imu", ["chk", "{}", False], None)
        answers = []

        def answer_after(k):
            async def answer():
                answers.append(k)
            return answer
        live.answer_in_order(answer_after(5))       # due once 1..5 are answered
        link, pool = live.link, live.link.pool
        owed = link.owed
        live.lost = [["invalid_message", "its calibration"]]
        link._dispatch(["reps", live.sid, 1, 3])
        for _ in range(5):
            await asyncio.sleep(0)
        metrics.publish()                           # (what a scrape shows: counted since the last one)
        middle = (sorted(live._pending), owed - link.owed, pool.answered, list(answers), list(got),
                  metrics.messages_in.labels("s")._value.get())
        link._dispatch(["reps", live.sid, 4, 5])
        await _until(lambda: answers, "the answer due after the run")
        metrics.publish()
        return middle, (sorted(live._pending), link.owed, pool.answered, answers, got,
                        metrics.messages_in.labels("s")._value.get())

    middle, end = asyncio.run(run())
    assert middle == ([4, 5], 3, 3, [], ["invalid_message"], 3)
    assert end == ([], 0, 5, [5], ["invalid_message"], 5)


def test_open_but_silent_sessions_make_no_link_group_its_writes():
    """Grouping counts the sessions that sent source messages lately (``ActiveSessions``): a link with many
    sessions of which fewer than ``GROUP_SESSIONS`` sent one (one hand at 1 kHz beside idle sessions) writes
    every turn's messages at the end of that turn."""
    from service.api.hands import pool as pool_module

    async def run():
        pool = HandPool(ServiceSettings.load(port=0, hand_workers=1), Metrics())
        pool.loop = asyncio.get_running_loop()
        link, transport = pool.links[0], _Writes()
        link._writer = transport
        link.sessions = {sid: None for sid in range(pool_module.GROUP_SESSIONS + 3)}
        for sid in range(pool_module.GROUP_SESSIONS - 1):
            link.active.note(sid, time.monotonic())
        for k in range(5):
            link.send(["b", k])
            await asyncio.sleep(0)
        return len(transport.writes)

    assert asyncio.run(run()) == 5


def test_active_sessions_count_from_their_first_message_and_let_the_silent_go_after_active_s():
    """``ActiveSessions``: a session counts at once; one silent for more than ``ACTIVE_S`` is let go at the
    next sweep (at most every ``ACTIVE_S / 2``), one that sent meanwhile is kept."""
    from service.api.hands.worker import ACTIVE_S, GROUP_SESSIONS, ActiveSessions

    active = ActiveSessions()
    assert not active.many(0.0)
    for sid in range(GROUP_SESSIONS):
        active.note(sid, 0.0)
    assert active.many(0.1)                         # at once, before any sweep is due
    active.note(0, 0.9 * ACTIVE_S)
    assert active.many(ACTIVE_S)                    # swept now: none older than ACTIVE_S yet
    assert active.many(1.4 * ACTIVE_S)              # no sweep due before 1.5 ACTIVE_S: the silent still count
    assert not active.many(1.5 * ACTIVE_S)          # swept: only session 0 sent within ACTIVE_S
    assert set(active.seen) == {0}
    for sid in range(1, GROUP_SESSIONS):
        active.note(sid, 1.6 * ACTIVE_S)
    assert active.many(1.6 * ACTIVE_S)
