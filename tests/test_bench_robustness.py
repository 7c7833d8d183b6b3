"""The robustness campaign (``fingertrack bench robustness``): its hostile messages are what they
claim to be, its attribution of replies holds against a real server, a service that stops answering
is reported as hung, and the quick campaign runs end to end and accounts for every message."""
import asyncio
import csv
import json
import os
import random
import socket
import threading

import msgpack
import pytest

from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.bench import robustness as rb
from service.bench.process import ServiceProcess
from service.cli import main
from service.protocol import ProtocolError, parse_line

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE, VIEWER, ADMIN = "src-token-r", "view-token-r", "admin-token-r"


def _strict_json(text):
    def reject(name):
        raise ValueError(name)
    return json.loads(text, parse_constant=reject)


def _payload(made):
    return made[0] if isinstance(made, tuple) else made


@pytest.mark.parametrize("category", sorted(rb.JSON_CATEGORIES))
def test_json_messages_are_deterministic_and_hostile(category):
    for i in range(40):
        payload = _payload(rb._json_message(category, 0.01 * i, random.Random(i), 1 << 20))
        assert payload == _payload(rb._json_message(category, 0.01 * i, random.Random(i), 1 << 20))
        if category in ("truncated_json", "nan_infinity", "random_text", "wrong_shapes", "missing_fields",
                        "non_unit_quaternion"):
            # by the protocol's own definition none of these is a valid source message
            with pytest.raises(ProtocolError):
                parse_line(payload)
        if category == "nan_infinity":
            with pytest.raises(ValueError):
                _strict_json(payload)
            assert json.loads(payload)                      # a lenient parser takes it: the literal is there
        if category == "oversized":
            assert len(payload.encode() if isinstance(payload, str) else payload) > 1 << 20
        if category == "depth_bomb":
            assert payload.count("[") >= 10 or payload.count("{") >= 10
        if category == "random_bytes":
            assert isinstance(payload, bytes)


@pytest.mark.parametrize("category", sorted(rb.MSGPACK_CATEGORIES))
def test_msgpack_messages_are_deterministic_and_hostile(category):
    for i in range(40):
        payload = _payload(rb._msgpack_message(category, 0.01 * i, random.Random(i), 1 << 20))
        assert isinstance(payload, bytes)
        assert payload == _payload(rb._msgpack_message(category, 0.01 * i, random.Random(i), 1 << 20))
        if category in ("mp_truncated", "mp_extra_data", "mp_huge_container"):
            with pytest.raises((ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError)):
                msgpack.unpackb(payload)
        if category == "mp_non_map":
            assert not isinstance(msgpack.unpackb(payload), dict)


def test_a_message_labelled_valid_is_one_the_protocol_accepts_and_the_others_are_refused():
    """The labels come from the generator (what each message was made to be); checked here against the
    protocol's rules for every kind whose answer does not depend on the session (time does: a clock
    step is answered by the pipeline, ``test_pipeline``)."""
    from service.protocol.wire import parse_input
    valid_kinds, hostile_kinds = set(), set()
    for binary in (False, True):
        for i in range(4000):
            category, kind, payload = rb.hostile_message(5, i, binary)
            if category in ("backwards_time", "huge_time", "unknown_sensors", "hello_variants", "oversized",
                            "mp_oversized") or "calibration" in category:
                continue          # answered by the session (time, placement, protocol) or at the door (size)
            if kind.startswith(rb.VALID):
                valid_kinds.add(kind)
                parse_input(payload, binary)
            else:
                hostile_kinds.add(kind)
                with pytest.raises(ProtocolError):
                    parse_input(payload, binary)
    assert any("unknown field" in k for k in valid_kinds) and any("5e-324" in k for k in valid_kinds)
    assert "1e400 in an unknown field" in hostile_kinds and "100 levels in an unknown field" in hostile_kinds


def test_campaign_messages_cover_every_category():
    seen = {rb.hostile_message(3, i, binary)[0] for binary in (False, True) for i in range(3000)}
    rare = {"oversized", "mp_oversized"}                     # weighted low: each is megabytes
    assert seen >= (set(rb.JSON_CATEGORIES) | set(rb.MSGPACK_CATEGORIES)) - rare


def _imu(t, sid="index.1"):
    return json.dumps({"type": "imu", "t": t, "id": sid, "gyr": [0, 0, 0], "acc": [0, 0, 9.81]})


def _pose(t):
    return json.dumps({"type": "pose", "t": t, "position": [0, 1, 0], "orientation": [0, 0, 0, 1]})


def _error(code, **fields):
    return [{"type": "error", "code": code, "detail": "", **fields}]


def test_time_probes_are_labelled_by_the_session_clock_the_replies_reveal():
    clock = rb.SessionClock()
    assert clock.label(_imu(10.0), False) == rb.VALID + "the session's first sample (starts its clock)"
    clock.update(_imu(10.0), False, "replied", [])
    assert clock.label(_imu(9.0), False).startswith("back more than the clock step")        # owed a clock_step
    clock.update(_imu(9.0), False, "replied", _error("clock_step"))
    # 1 s back from the script's clock again, a moment later: in order for a session the last probe stepped
    assert clock.label(_imu(9.001), False) == rb.VALID + "after the session's newest sample, within the clock step (in order)"
    assert clock.label(_imu(10.002), False).startswith("forward more than the clock step")
    assert clock.label(_imu(8.7), False).startswith(rb.VALID + "at or back less")          # reordered or late
    # refused as a whole, or a single sample of a sensor the calibration does not place: no clock effect
    clock.update(_imu(500.0), False, "replied", _error("invalid_message"))
    clock.update(_imu(500.0, "ring.7"), False, "replied", _error("unknown_sensor"))
    clock.update(_imu(500.0), False, "closed_by_design", [])
    assert (clock.newest, clock.disagreements) == (9.0, 0)
    # a batch's refused samples are left out; its first sample is the probe (MessagePack alike)
    batch = {"type": "imu_batch", "samples": [{"t": 2.0**47, "id": "thumb.0", "gyr": [0, 0, 0], "acc": [0, 0, 9.8]},
                                              {"t": 9.01, "id": "thumb.1", "gyr": [0, 0, 0], "acc": [0, 0, 9.8]}]}
    clock.update(msgpack.packb(batch), True, "replied", _error("invalid_samples", samples=[0]))
    assert (clock.newest, clock.disagreements) == (9.01, 0)
    batch["samples"][0]["t"] = 5e-324
    assert clock.label(msgpack.packb(batch), True).startswith("back more than the clock step")
    # poses: late at or before the newest pose, in order again once a clock step restarted the optics
    clock.update(_pose(9.0), False, "replied", [])
    assert clock.label(_pose(5e-324), False).startswith("a pose at or before")
    clock.update(_pose(5e-324), False, "replied", _error("time_backwards"))
    assert clock.pose == 9.0
    clock.update(_imu(5e-324), False, "replied", _error("clock_step"))
    assert clock.label(_pose(5e-324), False).startswith(rb.VALID + "a pose after")
    # the service's notice is the truth: a step the rule did not predict is counted and followed,
    # a predicted one that did not come is counted
    clock.update(_imu(0.2), False, "replied", _error("clock_step"))
    assert (clock.newest, clock.disagreements) == (0.2, 1)
    clock.update(_imu(5.0), False, "replied", [])
    assert clock.disagreements == 2
    with pytest.raises(ValueError):
        clock.label(json.dumps({"type": "calibration"}), False)


def test_the_session_clock_predicts_the_replies_of_a_real_service():
    """A hand-made sequence of time probes against the service: every probe labelled hostile gets an
    error reply, and every clock_step notice is one the rule predicted."""
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    sequence = [_imu(10.0), _pose(10.0), _imu(10.01), _imu(9.0), _imu(9.001), _imu(-1e9), _imu(-99.9),
                _imu(10.05), _pose(10.0), _pose(5e-324), _imu(5e-324), _pose(5e-324), _imu(0.3), _imu(0.2),
                _imu(0.9), _imu(0.0), _imu(0.0, "ring.7")]
    with ServerThread(settings) as srv:
        svc = ServiceProcess(srv.url, os.getpid(), SOURCE, VIEWER, ADMIN)

        async def go():
            attacker = rb.Attacker(svc, "clock", binary=False, reply_timeout_s=60)
            try:
                return await attacker.probe(sequence)
            finally:
                await attacker.close()

        results = asyncio.run(go())
    clock, hostile = rb.SessionClock(), 0
    for payload, (outcome, replies) in zip(sequence, results, strict=True):
        kind = clock.label(payload, False)
        clock.update(payload, False, outcome, replies)
        if not kind.startswith(rb.VALID):
            hostile += 1
            assert any(m["type"] == "error" for m in replies), (payload, kind, replies)
    assert clock.disagreements == 0
    assert hostile == 8


def test_replies_are_attributed_to_the_message_that_caused_them():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        svc = ServiceProcess(srv.url, os.getpid(), SOURCE, VIEWER, ADMIN)
        imu = {"type": "imu", "t": 0.0, "id": "index.1", "gyr": [0, 0, 0], "acc": [0, 0, 9.81]}

        async def go():
            attacker = rb.Attacker(svc, "attrib", binary=False, reply_timeout_s=60)
            first = await attacker.probe(["{not json", json.dumps(imu), '{"type":"wave"}',
                                          json.dumps({"type": "hello", "protocol": 2, "hand": "right"}),
                                          "never answered: the connection is closed before it"])
            second = await attacker.probe(["{still not json"])          # a new connection
            await attacker.close()
            return first, second

        first, second = asyncio.run(go())
    assert [outcome for outcome, _ in first] == ["replied", "replied", "replied", "closed_by_design"]
    assert [[m["code"] for m in replies] for _, replies in first] == [
        ["invalid_json"], [], ["unknown_type"], ["unsupported_protocol", 1008]]     # then the close, with its code
    assert first[3][1][1]["type"] == "close" and "unsupported protocol" in first[3][1][1]["reason"]
    assert second == [("replied", [{"type": "error", "code": "invalid_json", "detail": second[0][1][0]["detail"]}])]


def test_a_service_that_stops_answering_is_reported_as_hung():
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    held = []
    stop = threading.Event()

    def accept_and_ignore():                                  # accepts, never answers a byte
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(listener.accept()[0])
            except OSError:
                pass

    thread = threading.Thread(target=accept_and_ignore, daemon=True)
    thread.start()
    svc = ServiceProcess(f"http://127.0.0.1:{listener.getsockname()[1]}", os.getpid(), SOURCE, VIEWER, ADMIN)
    try:
        with pytest.raises(rb.ServiceDown) as err:
            asyncio.run(rb.Attacker(svc, "silent", False, reply_timeout_s=1.0).probe(["{}"]))
        assert err.value.kind == "hang"
    finally:
        stop.set()
        thread.join()
        for s in held + [listener]:
            s.close()


def test_tracebacks_are_counted_in_a_service_log(tmp_path):
    log = tmp_path / "service.log"
    try:
        json.loads("[" * 100_000 + "]" * 100_000)
    except RecursionError:
        import traceback
        log.write_text("INFO: started\n" + traceback.format_exc() * 2 + "INFO: stopped\n")
    assert rb._tracebacks(log) == 2
    assert rb._tracebacks(tmp_path / "missing.log") == 0


def test_quick_campaign_runs_end_to_end_and_accounts_for_every_message(tmp_path):
    out = tmp_path / "rob"
    assert main(["bench", "robustness", "--quick", "--messages", "240", "--soak-seconds", "3", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert {r["part"] for r in rows} == {"fuzz", "extremes", "never-readers", "storm", "kill -9", "soak"}
    assert all(r["met"] in ("True", "False") for r in rows)
    categories = list(csv.DictReader((out / "fuzz.csv").open()))
    outcomes = ("error_reply", "other_reply", "silent", "closed_by_design", "closed_abnormally", "stalls", "hangs",
                "crashes")
    for c in categories:                                      # every message has exactly one outcome
        assert int(c["sent"]) == sum(int(c[k]) for k in outcomes), c
        # and every connection closed while answering one has its close code and reason listed
        closes = sum(int(x.rsplit("=", 1)[1]) for x in c["closes"].split("; ") if x)
        assert closes == int(c["closed_by_design"]) + int(c["closed_abnormally"]), c
    results = json.loads((out / "results.json").read_text())
    assert sum(int(c["sent"]) for c in categories) == results["fuzz"]["sent"] == 240
    kinds = list(csv.DictReader((out / "fuzz_kinds.csv").open()))
    for c in kinds:
        assert int(c["sent"]) == sum(int(c[k]) for k in outcomes), c
    assert sum(int(c["sent"]) for c in kinds) == 240 and {c["valid"] for c in kinds} <= {"True", "False"}
    assert rb.TIME_PROBE not in {c["kind"] for c in kinds}            # every time probe labelled by the clock
    unanswered = list(csv.DictReader((out / "fuzz_unanswered.csv").open()))
    assert all(not u["kind"].startswith(rb.VALID) for u in unanswered)
    silent = sum(int(c["silent"]) + int(c["other_reply"]) for c in kinds if c["valid"] == "False")
    assert len(unanswered) == silent
    assert isinstance(results["fuzz"]["clock_disagreements"], int)
    good = results["fuzz"]["good"]
    assert good and good[0]["produced"] > 0 and good[0]["received"] <= good[0]["produced"]
    assert len(results["extremes"]) == len(rb.QUICK["probes"])
    assert results["storm"]["connects"] == rb.QUICK["connects"] == sum(results["storm"]["outcomes"].values())
    kill = results["kill9"][0]
    assert kill["files"] == 1 and kill["lines"] > 0
    assert "| part | check | goal | measured | met |" in (out / "summary.md").read_text()


def _gone(pid):
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def test_a_hung_service_leaves_its_stacks_in_the_log_and_no_process_behind(tmp_path):
    import signal
    import time
    from service.bench.process import descendants, service_process
    log = tmp_path / "service.log"
    # two hand workers (not one_hand_worker's one): one of them stopped, the other still answering
    with service_process(log_path=log, env={"FINGERTRACK_HAND_WORKERS": "2"}) as svc:
        workers = descendants(svc.pid)
        assert len(workers) == 2
        # a worker that cannot run (stopped) neither answers nor sees its web process end: left alone
        # it would stay after the web process is killed
        os.kill(workers[1], signal.SIGSTOP)
        seen = rb.stop_hung(svc, bound_s=3.0)
        procs = [svc.pid] + workers
        deadline = time.monotonic() + 60                 # bounds a failure only
        while not all(_gone(p) for p in procs):
            assert time.monotonic() < deadline, [p for p in procs if not _gone(p)]
            time.sleep(0.05)
    text = log.read_text()
    assert seen["stacks_written"] == 2 and set(seen["rss_mib"]) == {str(p) for p in procs}
    assert all(seen["rss_mib"][str(p)] > 10 for p in procs)
    assert seen["mem_available_mib"] > 0
    for pid in procs:
        assert f"(pid {pid}) for its stacks" in text
    assert text.count("most recent call first") >= 2 and "service/cli.py" in text and "hands/worker.py" in text
    assert "Traceback (most recent call last)" not in text
