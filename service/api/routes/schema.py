"""``GET /v1/schema``: the protocol's JSON Schema and AsyncAPI documents (no token needed: they
describe the protocol, not a session)."""
from __future__ import annotations

from fastapi import APIRouter, HTTPException

from ...protocol import PROTOCOL_VERSION
from ...protocol.schema import documents, message_schemas

router = APIRouter(tags=["protocol"])


@router.get("/v1/schema")
def protocol_schema():
    """JSON Schema (draft 2020-12) of every protocol-v1 message, by file name (as in ``docs/schema/``)."""
    return {"protocol": PROTOCOL_VERSION, "schemas": message_schemas()}


@router.get("/v1/schema/{name}")
def protocol_schema_file(name: str):
    """One of the documents of ``/v1/schema``, or the AsyncAPI document ``asyncapi.json``."""
    docs = documents()
    if name not in docs:
        raise HTTPException(404, f"no schema {name!r}; expected one of {sorted(docs)}")
    return docs[name]
