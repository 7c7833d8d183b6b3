"""The published protocol schema: generated from the models, committed under docs/schema/, served by
the service, and followed by real messages from a real server (validated with the jsonschema package)."""
import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator
from websockets.asyncio.client import connect

from clients.client import Subscription, rest
from clients.glove import stream_glove
from protocol_validation import SCHEMA_DIR, ServiceMessageCheck, closed, published
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.cli import main
from service.protocol import ERROR_CODES, PROTOCOL_VERSION
from service.protocol.schema import documents, dump
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

SOURCE, VIEWER, ADMIN = "src-schema-1", "view-schema-1", "admin-schema-1"


@pytest.fixture(scope="module")
def server():
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        yield srv


def test_the_protocol_names_the_models_joints_and_fingers():
    from service.model.hand import FINGERS
    from service.model.openxr import JOINT_NAMES
    from service.protocol import outgoing
    assert outgoing.JOINT_NAMES == JOINT_NAMES and outgoing.FINGERS == FINGERS


def test_the_committed_documents_are_the_generated_ones():
    generated = documents()
    committed = {p.name for p in SCHEMA_DIR.iterdir()}
    assert committed == set(generated), "run: fingertrack schema --out docs/schema"
    for name, doc in generated.items():
        assert (SCHEMA_DIR / name).read_text(encoding="utf-8") == dump(doc), f"{name} is stale: run fingertrack schema --out docs/schema"


def test_the_schema_command_writes_the_same_documents(tmp_path, capsys):
    assert main(["schema", "--out", str(tmp_path)]) == 0
    for path in SCHEMA_DIR.iterdir():
        assert (tmp_path / path.name).read_text(encoding="utf-8") == path.read_text(encoding="utf-8")
    assert f"wrote {len(documents())} documents" in capsys.readouterr().out
    assert main(["schema"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["protocol"] == PROTOCOL_VERSION and printed["documents"] == json.loads(json.dumps(documents()))


def test_every_message_schema_is_a_valid_draft_2020_12_schema():
    for name, doc in documents().items():
        if name.endswith(".schema.json"):
            Draft202012Validator.check_schema(doc)
            assert doc["$schema"] == "https://json-schema.org/draft/2020-12/schema"


def _resolve(doc: dict, ref: str):
    assert ref.startswith("#/"), ref
    node = doc
    for part in ref[2:].split("/"):
        assert part in node, f"unresolved $ref {ref}"
        node = node[part]
    return node


def _refs(node):
    if isinstance(node, dict):
        if "$ref" in node:
            yield node["$ref"]
        for value in node.values():
            yield from _refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from _refs(value)


def test_the_asyncapi_document_describes_both_websockets():
    doc = json.loads((SCHEMA_DIR / "asyncapi.json").read_text(encoding="utf-8"))
    assert doc["asyncapi"].startswith("3.0")
    assert doc["info"]["title"] and doc["info"]["version"].startswith(f"{PROTOCOL_VERSION}.")
    for ref in _refs(doc):                      # every reference points inside the document
        _resolve(doc, ref)
    channels = doc["channels"]
    assert {c["address"] for c in channels.values()} == {"/v1/ingest/{session}", "/v1/stream/{session}"}
    for name, channel in channels.items():
        assert set(channel["parameters"]) == {"session"}
    for op in doc["operations"].values():
        assert op["action"] in ("send", "receive")
        channel = _resolve(doc, op["channel"]["$ref"])
        for m in op["messages"]:                # an operation's messages are its channel's (AsyncAPI 3 rule)
            assert m["$ref"].startswith(op["channel"]["$ref"] + "/messages/")
            _resolve(doc, m["$ref"])
        assert channel in channels.values()
    stream_out = {m["$ref"].rsplit("/", 1)[1] for op in doc["operations"].values()
                  if op["action"] == "send" and op["channel"]["$ref"] == "#/channels/stream" for m in op["messages"]}
    assert stream_out == {"server_hello", "frame", "gesture"}
    for scheme in doc["components"]["securitySchemes"].values():
        assert scheme["type"] in ("http", "httpApiKey")
    # each message payload is a schema that accepts what the JSON Schema files accept
    schemas = doc["components"]["schemas"]
    for schema in schemas.values():
        Draft202012Validator.check_schema(schema)
    frame_payload = _resolve(doc, doc["components"]["messages"]["frame"]["payload"]["$ref"])
    assert frame_payload["required"] == published("frame.schema.json")["required"]


def test_the_asyncapi_document_follows_the_asyncapi_3_specification():
    """Validated against the specification's own JSON Schema (tests/data/asyncapi: the AsyncAPI
    Initiative's schema of version 3.0.0), which also refuses AsyncAPI 2 shapes and bad values."""
    from jsonschema import validators

    spec = json.loads((Path(__file__).parent / "data" / "asyncapi" / "asyncapi-3.0.0.schema.json").read_text(encoding="utf-8"))
    validator = validators.validator_for(spec)(spec)
    doc = json.loads((SCHEMA_DIR / "asyncapi.json").read_text(encoding="utf-8"))
    assert doc["asyncapi"] == "3.0.0"
    assert [e.message for e in validator.iter_errors(doc)] == []
    channel, operation = next(iter(doc["channels"])), next(iter(doc["operations"]))

    def v2_verb(d):
        d["operations"][operation]["action"] = "publish"

    def v2_channel(d):
        d["channels"][channel]["publish"] = {}

    def no_version(d):
        del d["info"]["version"]
    for change in (v2_verb, v2_channel, no_version):
        bad = json.loads(json.dumps(doc))
        change(bad)
        assert not validator.is_valid(bad), change.__name__


def test_the_service_serves_the_documents_without_a_token(server):
    schemas = {k: v for k, v in documents().items() if k != "asyncapi.json"}
    assert rest(server.url, "GET", "/v1/schema") == (200, {"protocol": PROTOCOL_VERSION, "schemas": schemas})
    assert rest(server.url, "GET", "/v1/schema/asyncapi.json") == (200, published("asyncapi.json"))
    assert rest(server.url, "GET", "/v1/schema/frame.schema.json") == (200, published("frame.schema.json"))
    status, body = rest(server.url, "GET", "/v1/schema/nosuch.json")
    assert status == 404 and "frame.schema.json" in body["detail"]


def test_the_strict_check_rejects_what_the_protocol_does_not_allow():
    """The check used on every message of the suite can fail: broken messages are caught."""
    check = ServiceMessageCheck()
    assert check.problems(json.dumps({"type": "gesture", "t": 1.0, "gesture": "point", "event": "start",
                                      "confidence": 0.5})) == []
    bad = [
        {"type": "gesture", "t": 1.0, "gesture": "wave", "event": "start", "confidence": 0.5},
        {"type": "gesture", "t": 1.0, "gesture": "point", "event": "start", "confidence": 1.5},
        {"type": "gesture", "t": 1.0, "gesture": "point", "event": "start", "confidence": 0.5, "extra": 1},
        {"type": "error", "code": "no_such_code", "detail": "x"},
        {"type": "error", "code": "duplicate"},
        {"type": "hello", "protocol": "one"},
        {"type": "frame", "t": 0.0},
        {"type": "nosuch"},
    ]
    for message in bad:
        assert check.problems(json.dumps(message)), message


async def _live_session(server):
    """A glove streams a point-grasp-relax sequence; a subscriber and a misbehaving source run beside it."""
    received = []
    sub = Subscription(server.ws_url, "schema-live", VIEWER)
    raw_stream = []

    async def collect():
        async for m in sub:
            received.append(m)

    async def raw_subscriber():                 # sees the stream's hello too
        async with connect(f"{server.ws_url}/v1/stream/schema-live?token={VIEWER}") as ws:
            raw_stream.append(json.loads(await ws.recv()))

    task = asyncio.create_task(collect())
    await raw_subscriber()
    while sub.server_hello is None:             # subscribed (waiting for the session's source)
        await asyncio.sleep(0.05)
    replies = []
    async with connect(f"{server.ws_url}/v1/ingest/schema-bad?token={SOURCE}") as ws:
        await ws.send(json.dumps({"type": "pose", "t": 0.0, "valid": False}))       # before hello
        await ws.send(json.dumps({"type": "hello", "protocol": 1, "hand": "left"}))
        for line in ("{not json", '{"type":"wave"}', '{"type":"imu","t":1.0,"id":"index.1","gyr":[0,0],"acc":[0,0,9.8]}',
                     '{"type":"pose","t":1.0,"position":[0,0,0],"orientation":[0,0,0,3]}'):
            await ws.send(line)
        for _ in range(6):
            replies.append(json.loads(await ws.recv()))
    config = SimConfig(motion="sequence", noise="white", seed=4,
                       finger_motion=sequence_motion(steps=(("point", 0.8), ("grasp", 0.8), ("rest", 0.8))))
    pub = await stream_glove(server.url, "schema-live", SOURCE, config, speed=4.0)
    await pub.close()
    while not any(m["type"] == "gesture" and m["gesture"] == "grasp" and m["event"] == "end" for m in received):
        await asyncio.sleep(0.05)
    await sub.close()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    return raw_stream + [sub.server_hello] + received, replies


def test_real_frames_events_and_errors_follow_the_published_schema(server):
    messages, replies = asyncio.run(asyncio.wait_for(_live_session(server), 120))
    kinds = {m["type"] for m in messages}
    assert kinds == {"hello", "frame", "gesture"}
    codes = [r.get("code") for r in replies if r["type"] == "error"]
    assert set(codes) == {"expected_hello", "invalid_json", "unknown_type", "invalid_message", "non_unit_quaternion"}
    assert set(codes) <= set(ERROR_CODES)
    events = [m for m in messages if m["type"] == "gesture"]
    assert any("ray" in e for e in events) and any(m.get("gesture", {}).get("ray") for m in messages if m["type"] == "frame")
    # the published files, as a client would use them (open: unknown fields allowed) ...
    service = Draft202012Validator(published("service-message.schema.json"))
    per_type = {t: Draft202012Validator(published(f"{t}.schema.json")) for t in ("frame", "gesture", "error")}
    per_type["hello"] = Draft202012Validator(published("server-hello.schema.json"))
    for m in messages + replies:
        service.validate(m)
        per_type[m["type"]].validate(m)
    # ... and strictly: nothing undeclared
    strict = Draft202012Validator(closed(published("service-message.schema.json")))
    for m in messages + replies:
        assert not list(strict.iter_errors(m)), m
    # the suite's compiled check (protocol_validation.compiled) accepts these messages and refuses,
    # as jsonschema does, frames broken deep inside
    check = ServiceMessageCheck()
    assert all(check.fast_accepts(m) for m in messages + replies)
    frame = next(m for m in messages if m["type"] == "frame")
    breaks = [
        lambda f: f["joints"]["index_tip"].update(extra=1),                     # an undeclared field
        lambda f: f["joints"]["palm"].update(tracked=1),                        # a number for a boolean
        lambda f: f["joints"]["wrist"]["position"].append(0.0),                 # four coordinates
        lambda f: f["joints"]["wrist"].update(radius=True),                     # a boolean for a number
        lambda f: f["fingers"]["index"].update(mode="guessing"),                # not one of the modes
        lambda f: f["joints"]["palm"].pop("orientation"),                       # a required field missing
        lambda f: f["status"]["dropped"].update(late=-1),                       # below its minimum
        lambda f: f["fingers"].update(sixth=f["fingers"]["index"]),             # no such finger
        lambda f: f["status"].update(optics="maybe"),                           # not one of the states
        lambda f: f["gesture"].update(grab_strength="0.4"),                     # a string for a number
        lambda f: f.update(seq=1.5),                                            # not an integer
    ]
    for n, damage in enumerate(breaks):
        broken = json.loads(json.dumps(frame))
        damage(broken)
        assert not strict.is_valid(broken), n          # the reference refuses it ...
        assert not check.fast_accepts(broken), n       # ... and so does the compiled check
        assert check.problems(json.dumps(broken)), n
    # the source schema accepts what the glove sent and the service rejected what it refuses
    source = Draft202012Validator(published("source-message.schema.json"))
    assert source.is_valid({"type": "hello", "protocol": 1, "hand": "left"})
    assert not source.is_valid({"type": "imu", "t": 1.0, "id": "index.1", "gyr": [0, 0], "acc": [0, 0, 9.8]})
    assert not source.is_valid({"type": "wave"})


def test_the_openapi_document_declares_the_bearer_scheme_and_typed_bodies(server):
    status, doc = rest(server.url, "GET", "/openapi.json")
    assert status == 200
    schemes = doc["components"]["securitySchemes"]
    bearer = {name for name, s in schemes.items() if s["type"] == "http" and s["scheme"].lower() == "bearer"}
    assert bearer, schemes

    def secured(operation) -> bool:
        return any(set(requirement) & bearer for requirement in operation.get("security", []))
    paths = doc["paths"]
    assert secured(paths["/v1/sessions"]["get"]) and secured(paths["/metrics"]["get"])
    put = paths["/v1/sessions/{session}/config"]["put"]
    assert secured(put) and secured(paths["/v1/sessions/{session}/config"]["get"])
    assert not secured(paths["/health"]["get"]) and not secured(paths["/v1/schema"]["get"])
    body = put["requestBody"]["content"]["application/json"]["schema"]
    body = _resolve(doc, body["$ref"]) if "$ref" in body else body
    assert set(body["properties"]) == {"estimator", "estimator_params", "gestures", "record"}
    assert body.get("additionalProperties") is False            # unknown fields are refused, as the route does
    for method in ("get", "put"):                               # both answer the session's whole configuration
        answer = paths["/v1/sessions/{session}/config"][method]["responses"]["200"]["content"]["application/json"]["schema"]
        answer = _resolve(doc, answer["$ref"]) if "$ref" in answer else answer
        assert set(answer["required"]) == {"estimator", "record"}
        assert set(answer["properties"]) == {"estimator", "estimator_params", "gestures", "record"}
    # the whole document follows the OpenAPI specification of its version (a validator made for it)
    from openapi_spec_validator import validate
    from openapi_spec_validator.validation.exceptions import OpenAPIValidationError
    assert doc["openapi"].startswith("3.")
    validate(doc)
    broken = json.loads(json.dumps(doc))
    broken["components"]["securitySchemes"][sorted(bearer)[0]]["type"] = "token"
    with pytest.raises(OpenAPIValidationError):
        validate(broken)


def test_messages_of_a_service_process_are_recorded_for_the_schema_check():
    """A service in its own process (``fingertrack serve``, as the bus, CLI and load tests start it)
    records what it sends for the suite's check: its hello replies, frames and gesture events, over
    JSON and MessagePack, all following the schema."""
    from protocol_validation import SentRecords
    from service.bench.process import service_process

    records = SentRecords(os.environ["FINGERTRACK_TEST_SENT_DIR"])
    config = SimConfig(motion="sequence", noise="white", seed=6,
                       finger_motion=sequence_motion(steps=(("point", 0.6), ("rest", 0.4))))

    async def session(svc):
        subs = [Subscription(svc.url, "proc", svc.viewer), Subscription(svc.url, "proc", svc.viewer, binary=True)]
        received = [[], []]

        async def collect(sub, into):
            async for m in sub:
                into.append(m)
        tasks = [asyncio.create_task(collect(s, r)) for s, r in zip(subs, received)]
        while any(s.server_hello is None for s in subs):
            await asyncio.sleep(0.05)
        pub = await stream_glove(svc.url, "proc", svc.source, config, speed=4.0)
        await pub.close()
        _, sessions = await asyncio.to_thread(rest, svc.url, "GET", "/v1/sessions", svc.viewer)
        total = next(s["frames_out"] for s in sessions if s["session"] == "proc")
        while any(sum(m["type"] == "frame" for m in r) < total for r in received):
            await asyncio.sleep(0.05)
        for s in subs:
            await s.close()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        return received

    with service_process(start_timeout_s=300.0, extra_settings={"subscriber_queue_frames": 10000}) as svc:
        text, binary = asyncio.run(asyncio.wait_for(session(svc), 300))
        pid = svc.pid
    sent = [data for p, data in records.take() if p == pid]
    assert sum(isinstance(d, bytes) for d in sent) >= sum(m["type"] == "frame" for m in binary) > 50
    kinds = {json.loads(d)["type"] for d in sent if isinstance(d, str)}
    assert {"hello", "frame", "gesture"} <= kinds
    check = ServiceMessageCheck()
    assert [check.problems(d) for d in sent if check.problems(d)] == []


def test_the_record_of_a_service_process_catches_a_message_outside_the_schema(tmp_path):
    """The recording behind that check can fail: a process that sends a frame without its fields
    through Starlette's WebSocket is recorded, and the record is refused by the check."""
    from protocol_validation import SentRecords

    code = ("import asyncio\n"
            "from starlette.websockets import WebSocket\n"
            "class Quiet(WebSocket):\n"
            "    def __init__(self): pass\n"
            "    async def send(self, message): pass\n"
            "asyncio.run(Quiet().send_text('{\"type\":\"frame\",\"t\":1.0}'))\n"
            "asyncio.run(Quiet().send_bytes(b'\\x81\\xa4type\\xa4wave'))\n")
    env = dict(os.environ, FINGERTRACK_TEST_SENT_DIR=str(tmp_path))
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    sent = SentRecords(tmp_path).take()
    assert [d for _, d in sent] == ['{"type":"frame","t":1.0}', b"\x81\xa4type\xa4wave"]
    check = ServiceMessageCheck()
    assert all(check.problems(d) for _, d in sent)
