"""Service settings (pydantic-settings): environment variables ``FINGERTRACK_*`` and an optional
JSON or ``.env`` file given with ``--config`` (or ``FINGERTRACK_CONFIG``). Every field has a unit and
a default; unknown names are errors. ``ServiceSettings.load`` checks everything before the service
opens its port (tokens, the default estimator, the listen address, the recording folder) and turns any mistake into one
``SettingsError`` line per bad setting, naming it (never a token's value)."""
from __future__ import annotations

import fnmatch
import hmac
import json
import re
import secrets
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

ROLES = ("source", "viewer", "admin")
MIN_TOKEN_CHARS = 8
TOKEN_PATTERN = re.compile(r"^[A-Za-z0-9._~+/=-]+$")
"""Tokens travel in headers and query strings: printable ASCII without spaces or URL delimiters."""


class SettingsError(ValueError):
    """A bad setting; the message is one line per setting, naming it (never a token's value)."""


class TokenGrant(BaseModel):
    """A token's role, optionally limited to session names matching one of ``sessions``
    (shell-style patterns, e.g. ``"booth-*"``; empty: every session)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    role: Literal["source", "viewer", "admin"]
    sessions: tuple[str, ...] = ()

    def allows(self, session: str | None) -> bool:
        return session is None or not self.sessions or any(fnmatch.fnmatchcase(session, p) for p in self.sessions)


def _check_token(token: str, what: str) -> None:
    if len(token) < MIN_TOKEN_CHARS:
        raise ValueError(f"{what} must have at least {MIN_TOKEN_CHARS} characters")
    if not TOKEN_PATTERN.match(token):
        raise ValueError(f"{what} may only use letters, digits and . _ ~ + / = -")


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
    tokens: dict[str, TokenGrant] = Field(
        default_factory=dict, description="token -> role (source, viewer, admin) or {\"role\": ..., \"sessions\": "
                                          "[patterns]} (the token is valid for matching session names only); tokens "
                                          "have at least 8 characters of A-Z a-z 0-9 . _ ~ + / = -")
    admin_token: str | None = Field(None, description="admin token; generated and printed once at start when unset")
    record_dir: str | None = Field(None, description="folder for session recordings (JSON Lines); None: no recording")
    record_all: bool = Field(False, description="record every session (else per-session config)")
    estimator: str = Field("chain", description="default estimator of new sessions")
    output_rate_hz: float = Field(90.0, gt=0, le=1000, description="frame rate, Hz")
    max_message_bytes: int = Field(1 << 20, ge=1024, description="largest WebSocket message, bytes")
    rate_limit_msgs_per_s: float = Field(20000.0, gt=0, description="per-connection message rate limit, messages/s")
    subscriber_queue_frames: int = Field(64, ge=1, le=10000, description="frames buffered per subscriber before the oldest is dropped")
    subscriber_queue_events: int = Field(1024, ge=1, description="gesture events buffered per subscriber (never dropped: a client this far behind is closed)")
    subscriber_send_timeout_s: float = Field(10.0, gt=0, le=600, description="a connection that takes no data for "
                                             "this long (a send stuck on a full socket) is dropped and its buffers freed, s")
    ping_interval_s: float = Field(10.0, gt=0, description="WebSocket keepalive ping interval, s")
    ping_timeout_s: float = Field(20.0, gt=0, description="WebSocket keepalive timeout, s")
    websocket_compression: bool = Field(False, description="accept a client's offer of per-message deflate: "
                                        "JSON frames about 3x smaller on the wire, but every subscriber's copy is "
                                        "compressed on its own, the largest CPU cost of a subscriber in the serving "
                                        "process (off: for a venue's local network, CPU is scarcer than bandwidth)")
    ingest_backlog_messages: int = Field(1024, ge=1, le=100_000, description="source messages received and not yet "
                                         "processed, per connection; beyond it data messages are refused 'overloaded' "
                                         "until half of it is processed (api/backlog.py)")
    ingest_backlog_bytes: int = Field(32 << 20, ge=1024, description="bytes of source messages received and not yet "
                                      "processed, per connection (as ingest_backlog_messages)")
    flush_interval_s: float = Field(1.0, gt=0, le=1.0, description="recordings are flushed at least this often, s")
    max_sessions: int = Field(64, ge=1, description="largest number of live sessions")
    max_sessions_per_token: int = Field(8, ge=1, description="live sessions one (non-admin) token may have created")
    max_connections_per_token: int = Field(32, ge=1, description="open WebSockets per (non-admin) token")
    idle_timeout_s: float = Field(300.0, gt=0, description="a session with no source and no output for this long "
                                  "is removed and its recording closed, whether viewers watch it or not (they wait "
                                  "for its next source), s")
    connection_gc_delay_s: float = Field(1.0, gt=0, le=60, description="a cycle collection (and a heap trim) this "
                                         "long after WebSocket connections ended frees their memory, s (api/churn.py)")
    preload_kernels: bool = Field(True, description="once serving, load in the background the compiled kernels of "
                                  "every estimator found in the disk cache, in the hand workers where a session switched "
                                  "to one will run: the spare (hand_worker_spare), and the shared ones only with "
                                  "hand_worker_isolate off; the switch then does not wait for them (0.32 s of CPU for "
                                  "inertial). Not in the web process without hand workers, nor in a bus worker")
    hand_workers: int = Field(2, ge=0, le=64, description="worker processes that run the sessions' hands (each "
                              "session in one of them); 0: every hand on the web process's event loop")
    hand_worker_nice: int = Field(5, ge=0, le=19, description="a hand worker runs this much nicer than the web "
                                  "process once its kernels are loaded, so that the web process, on every frame's and "
                                  "health check's path, gets a core first; 0 on a machine shared with other work where "
                                  "the workers should not yield to it")
    hand_worker_isolate: bool = Field(True, description="a session switched to an estimator that runs per finger and "
                                      "sample through Python (any but the compiled chain: 8-140 % of a core per hand) moves "
                                      "with its state to a hand worker process of its own, hand_worker_isolated_nice nicer "
                                      "than the web process, and back to a shared worker when switched to the compiled "
                                      "chain: it cannot starve the other sessions, but may fall behind its source on a busy "
                                      "machine, which it says (GET /v1/sessions: behind_s; the log); false: it stays on its "
                                      "shared worker")
    hand_worker_isolated_max: int = Field(2, ge=0, le=64, description="sessions with a hand worker of their own "
                                          "(hand_worker_isolate) at once, the spare (hand_worker_spare) counted, about 200 MB each; past it a session switched "
                                          "to a costly estimator stays on its shared worker (logged)")
    hand_worker_spare: bool = Field(True, description="keep one hand worker process started ahead (once the shared "
                                    "ones are ready, hand_worker_isolated_nice nicer than the web process, replaced once "
                                    "the session that took it runs its new estimator there and has caught up; it counts in hand_worker_isolated_max) for the next session switched to a "
                                    "costly estimator (hand_worker_isolate): it moves at once instead of waiting for a "
                                    "process to start (9-40 s on a busy machine)")
    hand_worker_isolated_nice: int = Field(10, ge=0, le=19, description="a session's own hand worker (hand_worker_isolate) "
                                           "runs this much nicer than the web process from its start")
    hand_worker_stall_s: float = Field(10.0, gt=0, le=600, description="a hand worker that answers nothing for this "
                                       "long while it owes answers is killed and its sessions move to the others, s")
    hand_worker_lag_s: float = Field(1.0, gt=0, le=600, description="sooner: a hand worker that answers nothing for "
                                     "this long while it owes answers, does not work either (stopped or blocked: neither runnable nor "
                                     "using CPU) and the other workers go on answering theirs (the machine is not "
                                     "stalled as a whole) is killed and its sessions move, s")
    event_loop: Literal["asyncio", "uvloop", "auto"] = Field(
        "asyncio", description="the web process's event loop: asyncio (Python's own), uvloop (the optional extra "
                               "'uvloop'; an error where it is not installed; no gain measured over asyncio, README "
                               "'The event loop') or "
                               "auto (uvloop where it is installed, else asyncio)")
    bus: str | None = Field(None, pattern=r"^(nats|tls)://\S+$", description="NATS URL (nats://HOST:PORT): run as a gateway whose sessions run in "
                            "'fingertrack worker' processes; None: everything in this process")

    def with_admin_token(self) -> "ServiceSettings":
        return self if self.admin_token else self.model_copy(update={"admin_token": secrets.token_urlsafe(24)})

    @field_validator("tokens", mode="before")
    @classmethod
    def _roles_as_grants(cls, tokens):
        if isinstance(tokens, dict):
            return {t: {"role": g} if isinstance(g, str) else g for t, g in tokens.items()}
        return tokens

    @field_validator("tokens")
    @classmethod
    def _valid_tokens(cls, tokens: dict) -> dict:
        for n, token in enumerate(tokens, start=1):
            _check_token(token, f"token #{n}")
        return tokens

    @field_validator("admin_token")
    @classmethod
    def _valid_admin_token(cls, token: str | None) -> str | None:
        if token is not None:
            _check_token(token, "admin_token")
        return token

    def grant_of(self, token: str | None) -> TokenGrant | None:
        """The token's role and scope, or ``None``. Compared in constant time as UTF-8 bytes, so any
        input (empty, non-ASCII) is simply not a match."""
        if not token:
            return None
        given = token.encode("utf-8", "replace")
        if self.admin_token and hmac.compare_digest(given, self.admin_token.encode()):
            return TokenGrant(role="admin")
        for known, grant in self.tokens.items():
            if hmac.compare_digest(given, known.encode()):
                return grant
        return None

    def role_of(self, token: str | None) -> str | None:
        grant = self.grant_of(token)
        return None if grant is None else grant.role

    def masked(self) -> dict:
        """The settings without secrets: tokens as counts per role."""
        data = self.model_dump()
        roles = [grant.role for grant in self.tokens.values()]
        data["tokens"] = {role: roles.count(role) for role in ROLES if role in roles}
        data["admin_token"] = "set" if self.admin_token else None
        data["bus"] = redacted_url(self.bus)
        return data

    @staticmethod
    def load(path: str | None = None, **overrides) -> "ServiceSettings":
        """Environment, then the file (JSON object of fields), then explicit overrides; every setting
        checked (``SettingsError``, one line per bad setting)."""
        values: dict = {}
        if path:
            try:
                values = json.loads(Path(path).read_text())
            except json.JSONDecodeError as err:
                raise SettingsError(f"{path}: not a JSON object of settings ({err})") from None
            if not isinstance(values, dict):
                raise SettingsError(f"{path}: expected a JSON object of settings")
        values.update({k: v for k, v in overrides.items() if v is not None})
        try:
            settings = ServiceSettings(**values)
        except ValidationError as err:
            raise SettingsError(describe_validation_error(err, "setting")) from None
        except ValueError as err:           # pydantic-settings: an environment value that does not parse
            field = re.search(r'field "(\w+)"', str(err))
            if field is None:
                raise SettingsError(f"environment: {str(err).splitlines()[0]}") from None
            name = field.group(1)
            raise SettingsError(f"setting '{name}' (FINGERTRACK_{name.upper()}): not a valid JSON value") from None
        if not settings.open_access and settings.host not in ("127.0.0.1", "localhost", "::1"):
            raise SettingsError(f"setting 'host': {settings.host!r} is not loopback; set open_access "
                                "(FINGERTRACK_OPEN_ACCESS=true) to listen there")
        if settings.record_dir is not None and (problem := _unusable_folder(Path(settings.record_dir))):
            raise SettingsError(f"setting 'record_dir': {settings.record_dir!r} {problem}")
        if settings.event_loop == "uvloop" and not uvloop_installed():
            raise SettingsError("setting 'event_loop': 'uvloop' is not installed here; choose auto or asyncio")
        from ..estimators.registry import estimator_class
        try:
            estimator_class(settings.estimator)
        except ValueError as err:
            raise SettingsError(f"setting 'estimator': {err}") from None
        return settings


def uvloop_installed() -> bool:
    """Whether uvloop can be imported here (it has no build for every platform)."""
    try:
        import uvloop  # noqa: F401
    except ImportError:
        return False
    return True


def event_loop_name(settings: ServiceSettings) -> str:
    """The event loop the web process runs on with ``settings``: ``"uvloop"`` or ``"asyncio"``."""
    if settings.event_loop == "auto":
        return "uvloop" if uvloop_installed() else "asyncio"
    return settings.event_loop


def _unusable_folder(path: Path) -> str | None:
    """Why recordings cannot be written into ``path`` (created when first needed), or ``None``."""
    import os
    existing = path
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if not existing.is_dir():
        return "is not a folder" if existing == path else f"cannot be created ({str(existing)!r} is not a folder)"
    if not os.access(existing, os.W_OK | os.X_OK):
        return "is not writable" if existing == path else f"cannot be created ({str(existing)!r} is not writable)"
    return None


def describe_validation_error(err: ValidationError, what: str, prefix: str = "") -> str:
    """A pydantic error as one line per field: ``what 'prefix.a.b': message (got value)``; values
    of token fields are never shown."""
    lines = []
    for e in err.errors(include_url=False):
        loc = prefix + ".".join(str(p) for p in e["loc"])
        secret = "token" in loc
        if secret and e["loc"][0] == "tokens" and len(e["loc"]) > 1:
            loc = "tokens"                   # the key of a token entry is the token itself
        msg = e["msg"].removeprefix("Value error, ")
        value = e.get("input")
        if isinstance(value, str) and "://" in value:
            value = redacted_url(value)      # a URL's user and password are never shown either
        shown = "" if secret or e["type"] == "missing" else f" (got {json.dumps(value, default=str, ensure_ascii=False)[:60]})"
        lines.append(f"{what} '{loc}': {msg}{shown}" if loc else f"{what}: {msg}{shown}")
    return "\n".join(lines)
