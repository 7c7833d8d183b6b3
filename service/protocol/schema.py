"""Machine-readable protocol v1: JSON Schema for every message and an AsyncAPI document for the two
WebSockets, generated from the pydantic models (``messages`` and ``outgoing``), never written by hand.

``fingertrack schema --out DIR`` writes them; the service serves them at ``/v1/schema`` and
``/v1/asyncapi``; the copies committed under ``docs/schema/`` are tested equal to what this module
generates. The schemas follow JSON Schema draft 2020-12. As the protocol says, readers ignore unknown
fields, so objects leave ``additionalProperties`` open (a later optional field stays valid).
Constraints a schema cannot state are checked by the models only: finite numbers, unit quaternions.
"""
from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel, TypeAdapter
from pydantic.json_schema import models_json_schema

from .messages import (PROTOCOL_VERSION, Calibration, Hello, Imu, ImuBatch, Pose, ReferencePose, SourceMessage, Sync,
                       Truth)
from .outgoing import ERROR_CODES, ErrorMessage, Frame, Gesture, ServerHello, ServiceMessage, SyncReply

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

SOURCE_MODELS: dict[str, type[BaseModel]] = {
    "hello": Hello, "calibration": Calibration, "pose": Pose, "imu": Imu, "imu_batch": ImuBatch,
    "reference_pose": ReferencePose, "sync": Sync, "truth": Truth,
}
"""Messages a source sends on ``/v1/ingest`` (``truth`` only in simulated recordings; ignored)."""
SERVICE_MODELS: dict[str, type[BaseModel]] = {
    "server_hello": ServerHello, "sync_reply": SyncReply, "frame": Frame, "gesture": Gesture, "error": ErrorMessage,
}
"""Messages the service sends: ``server_hello``, ``sync_reply`` and ``error`` on ``/v1/ingest``;
``server_hello``, ``frame`` and ``gesture`` on ``/v1/stream``."""


def _document(schema: dict, title: str, description: str) -> dict:
    return {"$schema": JSON_SCHEMA_DIALECT, "title": title, "description": description,
            **{k: v for k, v in schema.items() if k not in ("title", "description")}}


@functools.cache
def message_schemas() -> dict[str, dict]:
    """Every protocol-v1 message's JSON Schema, by file name (``frame.schema.json``, ...), plus the
    two unions ``source-message.schema.json`` and ``service-message.schema.json``."""
    out: dict[str, dict] = {}
    for name, model in {**SOURCE_MODELS, **SERVICE_MODELS}.items():
        doc = (model.__doc__ or "").strip() or f"protocol v1 {name} message"
        out[f"{name.replace('_', '-')}.schema.json"] = _document(model.model_json_schema(), model.__name__, doc)
    out["source-message.schema.json"] = _document(
        TypeAdapter(SourceMessage).json_schema(), "SourceMessage",
        f"Any message a source sends on /v1/ingest/{{session}} (protocol {PROTOCOL_VERSION}).")
    out["service-message.schema.json"] = _document(
        TypeAdapter(ServiceMessage).json_schema(), "ServiceMessage",
        f"Any message the service sends on /v1/ingest/{{session}} or /v1/stream/{{session}} (protocol {PROTOCOL_VERSION}).")
    return out


def _channel_messages(names: list[str]) -> dict:
    return {name: {"$ref": f"#/components/messages/{name}"} for name in names}


def _operation(action: str, channel: str, names: list[str], summary: str) -> dict:
    return {"action": action, "channel": {"$ref": f"#/channels/{channel}"}, "summary": summary,
            "messages": [{"$ref": f"#/channels/{channel}/messages/{name}"} for name in names]}


@functools.cache
def asyncapi_document() -> dict:
    """AsyncAPI 3.0 description of the service's two WebSockets, from the service's point of view
    (it receives source messages on ``ingest`` and sends on both)."""
    models = {**SOURCE_MODELS, **SERVICE_MODELS}
    _, defs = models_json_schema([(m, "validation") for m in models.values()],
                                 ref_template="#/components/schemas/{model}")
    messages = {}
    for name, model in models.items():
        messages[name] = {"name": name, "title": model.__name__,
                          "summary": ((model.__doc__ or "").strip().splitlines() or [name])[0],
                          "contentType": "application/json",
                          "payload": {"$ref": f"#/components/schemas/{model.__name__}"}}
    session = {"description": "session name: 1-64 letters, digits, '-', '_' or '.'; one hand per session"}
    query = {"type": "object", "properties": {
        "token": {"type": "string", "description": "the token, when no Authorization header can be sent (browsers)"},
        "format": {"type": "string", "enum": ["msgpack"],
                   "description": "MessagePack binary messages instead of JSON text (or subprotocol fingertrack.msgpack)"}}}
    source_names = list(SOURCE_MODELS)
    return {
        "asyncapi": "3.0.0",
        "info": {
            "title": "fingertrack protocol",
            "version": f"{PROTOCOL_VERSION}.0.0",
            "description": (
                "Finger tracking for VR hand interaction. A source (glove, optical tracker) streams IMU samples "
                "and metacarpus poses into a session; the service fuses them into joint angles, OpenXR joint "
                "poses and gesture events and streams them to every subscriber of the session. Units are SI "
                "(s, m, rad), quaternions [x, y, z, w], the world frame is OpenXR stage space (+Y up). Each "
                "message is a JSON text, or MessagePack binary when asked for. Unknown fields are ignored; a bad "
                "source message gets an error reply and is dropped. Refusals close the connection: 1008 (token, "
                "role, session name, protocol), 1013 (service full or subscriber too slow; try again later), "
                "1001 (service shutting down). Error codes: " + "; ".join(f"{k}: {v}" for k, v in ERROR_CODES.items())),
        },
        "defaultContentType": "application/json",
        "servers": {
            "local": {"host": "127.0.0.1:8765", "protocol": "ws",
                      "description": "fingertrack serve (default address)",
                      "security": [{"$ref": "#/components/securitySchemes/bearer"},
                                   {"$ref": "#/components/securitySchemes/tokenQuery"}]},
        },
        "channels": {
            "ingest": {
                "address": "/v1/ingest/{session}",
                "title": "source ingest",
                "description": "A source (role source or admin) sends hello first, then calibration, pose, imu, "
                               "imu_batch, reference_pose and sync; the service answers hello with its own hello, "
                               "sync with a sync reply once everything before it is handled, and bad messages "
                               "with error.",
                "parameters": {"session": session},
                "messages": _channel_messages(source_names + ["server_hello", "sync_reply", "error"]),
                "bindings": {"ws": {"query": query}},
            },
            "stream": {
                "address": "/v1/stream/{session}",
                "title": "hand stream",
                "description": "A subscriber (role viewer or admin) receives the service's hello, then every frame "
                               "of the session (frames beyond its queue bound drop the oldest) and every gesture "
                               "event (never dropped), in order.",
                "parameters": {"session": session},
                "messages": _channel_messages(["server_hello", "frame", "gesture"]),
                "bindings": {"ws": {"query": query}},
            },
        },
        "operations": {
            "receiveSourceMessages": _operation("receive", "ingest", source_names,
                                                "glove and tracker samples into a session"),
            "replyToSource": _operation("send", "ingest", ["server_hello", "sync_reply", "error"],
                                        "the hello reply, sync replies, and an error for each refused message"),
            "streamHand": _operation("send", "stream", ["server_hello", "frame", "gesture"],
                                     "frames and gesture events to a subscriber"),
        },
        "components": {
            "schemas": defs["$defs"],
            "messages": messages,
            "securitySchemes": {
                "bearer": {"type": "http", "scheme": "bearer",
                           "description": "Authorization: Bearer TOKEN; roles source, viewer, admin"},
                "tokenQuery": {"type": "httpApiKey", "name": "token", "in": "query",
                               "description": "?token=TOKEN, for clients that cannot set headers"},
            },
        },
    }


def documents() -> dict[str, dict]:
    """Every generated document by file name: the message schemas and ``asyncapi.json`` (shared,
    cached objects: do not modify them)."""
    return {**message_schemas(), "asyncapi.json": asyncapi_document()}


def dump(doc: Any) -> str:
    """The committed text of a document (stable: a regenerated file differs only when the models do)."""
    return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"


def write_documents(out_dir: str | Path) -> list[Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, doc in documents().items():
        path = out / name
        path.write_text(dump(doc), encoding="utf-8")
        written.append(path)
    return written
