"""Checks every message the service sends against the published JSON Schema (``docs/schema/``).

The published schemas leave objects open (readers ignore unknown fields); these checks are strict:
every object with declared properties gets ``additionalProperties: false``, and an error's code must
be one of ``ERROR_CODES``. So a field the service sends but the schema does not declare fails here.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import fastjsonschema
import msgpack
from jsonschema import Draft202012Validator

from service.protocol import ERROR_CODES

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "docs" / "schema"


def published(name: str) -> dict:
    return json.loads((SCHEMA_DIR / name).read_text(encoding="utf-8"))


def closed(schema: dict) -> dict:
    """A copy of ``schema`` in which every object with ``properties`` admits no other property, with
    the local ``#/$defs/...`` references written out in place (the protocol's schemas have no
    recursion; resolving references is most of a validator's time otherwise)."""
    defs = schema.get("$defs", {})

    def walk(node):
        if isinstance(node, dict):
            ref = node.get("$ref", "")
            if ref.startswith("#/$defs/"):
                rest = {k: v for k, v in node.items() if k != "$ref"}
                return {**walk(defs[ref[len("#/$defs/"):]]), **walk(rest)}
            out = {k: walk(v) for k, v in node.items() if k != "$defs"}
            if "properties" in out and "additionalProperties" not in out:
                out["additionalProperties"] = False
            return out
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node
    return walk(copy.deepcopy(schema))


def compiled(schema: dict):
    """``schema`` (a closed one, its references written out) as a fastjsonschema validator: generated
    Python code, about a hundred times faster than jsonschema on a frame. The closed schemas use only
    keywords draft 7 shares with draft 2020-12; defaults are never written into the message."""
    schema = {k: v for k, v in schema.items() if k != "$schema"}
    return fastjsonschema.compile(schema, use_default=False, use_formats=False)


class ServiceMessageCheck:
    """Validates messages as the service sent them (JSON text or MessagePack bytes): against the
    union schema, through the branch its ``type`` selects (the union's discriminator mapping; a
    message of no known type is checked against the whole union).

    Every message goes through the compiled validator (``fast``); one it refuses is checked again by
    jsonschema, the reference, whose error list is the answer (so a refusal the two disagree on
    never fails a test, and the messages it accepts are the ones both accept: ``tests/test_schema.py``
    checks that the compiled validator refuses what jsonschema refuses)."""

    def __init__(self):
        union = published("service-message.schema.json")
        self.union = Draft202012Validator(closed(union))
        self.fast_union = compiled(closed(union))
        self.by_type, self.fast = {}, {}
        for kind, ref in union["discriminator"]["mapping"].items():
            branch = closed({"$defs": union["$defs"], **union["$defs"][ref.split("/")[-1]]})
            self.by_type[kind] = Draft202012Validator(branch)
            self.fast[kind] = compiled(branch)

    def fast_accepts(self, message) -> bool:
        kind = message.get("type") if isinstance(message, dict) else None
        try:
            self.fast.get(kind, self.fast_union)(message)
        except fastjsonschema.JsonSchemaException:
            return False
        return True

    def problems(self, data) -> list[str]:
        message = msgpack.unpackb(data) if isinstance(data, (bytes, bytearray)) else json.loads(data)
        kind = message.get("type") if isinstance(message, dict) else None
        found = []
        if not self.fast_accepts(message):
            validator = self.by_type.get(kind, self.union)
            found = [f"{'/'.join(map(str, e.absolute_path)) or 'message'}: {e.message}"
                     for e in validator.iter_errors(message)]
        if kind == "error" and message.get("code") not in ERROR_CODES:
            found.append(f"code: {message.get('code')!r} is not one of the documented error codes")
        return found


class SentRecords:
    """What service processes started by the tests sent (``tests/sent_capture/sitecustomize.py``
    writes ``<pid>.sent`` files into ``folder``): ``take()`` returns the (pid, message) records
    completed since the last call; a record still being written is left for the next call."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.offsets: dict[Path, int] = {}

    def take(self) -> list[tuple[int, str | bytes]]:
        out = []
        for path in sorted(self.folder.glob("*.sent")):
            at = self.offsets.get(path, 0)
            with open(path, "rb") as f:
                f.seek(at)
                data = f.read()
            used = 0
            while len(data) - used >= 5:
                size = int.from_bytes(data[used + 1:used + 5], "big")
                if len(data) - used - 5 < size:
                    break
                payload = data[used + 5:used + 5 + size]
                kind = data[used:used + 1]
                if kind not in (b"T", b"B"):
                    raise ValueError(f"{path.name}: unknown record kind {kind!r} at byte {at + used}")
                out.append((int(path.stem), payload.decode("utf-8") if kind == b"T" else payload))
                used += 5 + size
            self.offsets[path] = at + used
        return out
