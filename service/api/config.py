"""Service settings (pydantic-settings): environment variables ``FINGERTRACK_*`` and an optional
JSON or ``.env`` file given with ``--config`` (or ``FINGERTRACK_CONFIG``). Every field has a unit and
a default; unknown names are errors."""
from __future__ import annotations

import json
import re
import secrets
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

ROLES = ("source", "viewer", "admin")


def redacted_url(url: str | None) -> str | None:
    """The URL without its credentials (``nats://user:password@host`` → ``nats://…@host``), for logs."""
    if url is None:
        return None
    return re.sub(r"^([A-Za-z][A-Za-z0-9+.-]*://)[^/@]*@", r"\1…@", url)


class ServiceSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="FINGERTRACK_", extra="forbid", frozen=True)

    host: str = Field("127.0.0.1", description="listen address; anything but loopback needs open_access")
    port: int = Field(8765, ge=0, le=65535, description="TCP port (0: any free port)")
    open_access: bool = Field(False, description="allow listening on non-loopback addresses")
    tokens: dict[str, str] = Field(default_factory=dict, description="token -> role (source, viewer, admin)")
    admin_token: str | None = Field(None, description="admin token; generated and printed once at start when unset")
    record_dir: str | None = Field(None, description="folder for session recordings (JSON Lines); None: no recording")
    record_all: bool = Field(False, description="record every session (else per-session config)")
    estimator: str = Field("chain", description="default estimator of new sessions")
    output_rate_hz: float = Field(90.0, gt=0, le=1000, description="frame rate, Hz")
    max_message_bytes: int = Field(1 << 20, ge=1024, description="largest WebSocket message, bytes")
    rate_limit_msgs_per_s: float = Field(20000.0, gt=0, description="per-connection message rate limit, messages/s")
    subscriber_queue_frames: int = Field(64, ge=1, le=10000, description="frames buffered per subscriber before the oldest is dropped")
    subscriber_queue_events: int = Field(1024, ge=1, description="gesture events buffered per subscriber (never dropped: a client this far behind is closed)")
    ping_interval_s: float = Field(10.0, gt=0, description="WebSocket keepalive ping interval, s")
    ping_timeout_s: float = Field(20.0, gt=0, description="WebSocket keepalive timeout, s")
    flush_interval_s: float = Field(1.0, gt=0, le=1.0, description="recordings are flushed at least this often, s")
    max_sessions: int = Field(64, ge=1, description="largest number of live sessions")
    bus: str | None = Field(None, pattern=r"^(nats|tls)://\S+$", description="NATS URL (nats://HOST:PORT): run as a gateway whose sessions run in "
                            "'fingertrack worker' processes; None: everything in this process")

    def with_admin_token(self) -> "ServiceSettings":
        return self if self.admin_token else self.model_copy(update={"admin_token": secrets.token_urlsafe(24)})

    def role_of(self, token: str | None) -> str | None:
        if token is None:
            return None
        if self.admin_token and secrets.compare_digest(token, self.admin_token):
            return "admin"
        for known, role in self.tokens.items():
            if secrets.compare_digest(token, known):
                return role
        return None

    def masked(self) -> dict:
        data = self.model_dump()
        data["tokens"] = {f"{t[:3]}…": r for t, r in self.tokens.items()}
        data["admin_token"] = "…" if self.admin_token else None
        data["bus"] = redacted_url(self.bus)
        return data

    @staticmethod
    def load(path: str | None = None, **overrides) -> "ServiceSettings":
        """Environment, then the file (JSON object of fields), then explicit overrides."""
        values: dict = {}
        if path:
            text = Path(path).read_text()
            values = json.loads(text)
            if not isinstance(values, dict):
                raise ValueError(f"{path}: expected a JSON object of settings")
        values.update({k: v for k, v in overrides.items() if v is not None})
        settings = ServiceSettings(**values)
        for token, role in settings.tokens.items():
            if role not in ROLES:
                raise ValueError(f"tokens: role {role!r} of token {token[:3]}… is not one of {ROLES}")
        if not settings.open_access and settings.host not in ("127.0.0.1", "localhost", "::1"):
            raise ValueError(f"host {settings.host!r} is not loopback; set open_access to listen there")
        return settings
