"""The service's routes, one module per resource: ``rest`` (health, sessions, config, metrics),
``ingest`` (the source WebSocket) and ``stream`` (the subscriber WebSocket)."""
