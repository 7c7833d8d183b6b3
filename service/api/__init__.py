"""The tracking service: FastAPI app, WebSocket ingest and stream, REST, tokens, metrics, recording."""
