"""The wire encodings of protocol v1, shared by the service and the Python client: JSON text by
default, MessagePack binary (the same objects) when a client asks with the WebSocket subprotocol
``MSGPACK_SUBPROTOCOL`` or ``?format=msgpack``; and recordings, JSON Lines of source messages.

``decode`` is the one place raw bytes become a Python value: bad input raises ``ProtocolError``
(``invalid_json`` or ``invalid_msgpack``), and the non-standard ``NaN``/``Infinity`` JSON literals
are refused (DESIGN.md: non-finite numbers are an error).
"""
from __future__ import annotations

import functools
import json
import math
import re
from pathlib import Path
from typing import Any, Callable, Iterator, Literal, Mapping, Union

import msgpack
import msgspec
import orjson

from . import fast as _fast
from .messages import MAX_NESTING, Imu, ImuBatch, ImuSample, Pose, ProtocolError, parse_message

MSGPACK_SUBPROTOCOL = "fingertrack.msgpack"
"""WebSocket subprotocol name of the MessagePack encoding."""


def _reject_constant(name: str):
    raise ValueError(f"non-finite number {name} is not allowed")


def finite_copy(message: Mapping[str, Any]) -> Mapping[str, Any]:
    """``message`` unchanged if every number in it is finite; else a copy with each non-finite number
    replaced by ``None`` and their paths listed in ``invalid`` (strict JSON parsers, a browser's
    ``JSON.parse`` among them, reject NaN and infinity)."""
    bad: list[str] = []

    def clean(value, path: str):
        if isinstance(value, float) and not math.isfinite(value):
            bad.append(path)
            return None
        if isinstance(value, dict):
            return {k: clean(v, f"{path}.{k}" if path else str(k)) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v, f"{path}[{i}]") for i, v in enumerate(value)]
        return value

    cleaned = clean(message, "")
    if not bad:
        return message
    cleaned["invalid"] = bad
    return cleaned


_ORJSON_STRICT = orjson.OPT_PASSTHROUGH_DATACLASS | orjson.OPT_PASSTHROUGH_DATETIME | orjson.OPT_PASSTHROUGH_SUBCLASS
"""``orjson`` writes only what the standard library writes the same way; dataclasses, datetimes and
subclasses of the JSON types are left to the standard library (its text, or its ``TypeError``)."""


_NON_FINITE_DOUBLE = re.compile(rb"\xcb[\x7f\xff][\xf0-\xff]")
"""A MessagePack float64 (``0xcb`` and 8 bytes, big-endian) whose 11 exponent bits are all set: NaN or
an infinity."""


_NULLS_NEVER_NUMBERS = (b'{"active":', b',"active":', b'{"ray":', b',"ray":')
"""What precedes the ``null`` values protocol v1 writes under keys whose value is never a number
(``outgoing.py``: a frame's ``gesture.active``, a gesture name or none; a ray, an object or none): most
frames have one. Such a key cannot be part of a JSON string (its quotes would be escaped, and a key
ending in an escaped quote is preceded by a backslash, not by ``{`` or ``,``), so text whose every
``null`` follows one of these holds no NaN or infinity that ``orjson`` wrote as ``null``."""


def _nulls_all_known(text: bytes) -> bool:
    """True if every ``null`` in ``text`` (none at all included) is the value of a key of
    ``_NULLS_NEVER_NUMBERS``: one C search per ``null`` and one for the end, no walk of the message."""
    i = text.find(b"null")
    while i >= 0:
        if not text.endswith(_NULLS_NEVER_NUMBERS, 0, i):
            return False
        i = text.find(b"null", i + 4)
    return True


def _maybe_non_finite(message: Mapping[str, Any]) -> bool:
    """False only if no number in ``message`` is NaN or infinite. MessagePack writes every float as a
    float64, so a non-finite one shows as ``_NON_FINITE_DOUBLE`` in its bytes (one C pass each, cheaper
    than a walk in Python); bytes that merely look like it (inside a string or another number) give
    True, which only sends the message the standard library's way."""
    try:
        return _NON_FINITE_DOUBLE.search(msgpack.packb(message)) is not None
    except (TypeError, ValueError, OverflowError):
        return True


def encode(message: Mapping[str, Any], binary: bool) -> str | bytes:
    """One message as compact JSON text, or MessagePack bytes when ``binary``; never with NaN or
    infinity (``finite_copy``).

    JSON text is written by ``orjson`` (several times faster than the standard library) where that
    is safe. ``orjson`` writes NaN and infinity as ``null`` instead of refusing them, so a message with
    a non-finite number (``_maybe_non_finite``, asked only when the text has a ``null`` other than
    ``_NULLS_NEVER_NUMBERS``), a text with any byte beyond ASCII (the standard
    library escapes those), and a message ``orjson`` refuses are written by the standard library as
    before. The values are the same either way; only the spelling of some exponents differs
    (``1e-05`` is written ``0.00001``, ``1.5e-07`` ``1.5e-7``)."""
    if binary:
        return msgpack.packb(finite_copy(message))
    try:
        fast = orjson.dumps(message, option=_ORJSON_STRICT)
    except (orjson.JSONEncodeError, TypeError):
        fast = None
    # orjson writes NaN and infinity as ``null``: text without ``null`` has none (no walk needed)
    if fast is not None and fast.isascii() and (_nulls_all_known(fast) or not _maybe_non_finite(message)):
        return fast.decode()
    try:
        return json.dumps(message, separators=(",", ":"), allow_nan=False)
    except ValueError:
        return json.dumps(finite_copy(message), separators=(",", ":"), allow_nan=False)


_NON_FINITE_FLOAT32 = re.compile(rb"\xca[\x7f\xff][\x80-\xff]")
"""A MessagePack float32 (``0xca`` and 4 bytes) whose 8 exponent bits are all set: NaN or an infinity."""

_BIG_EXPONENT = (re.compile(r"[eE]\+?0*[1-9][0-9]{2}"), re.compile(rb"[eE]\+?0*[1-9][0-9]{2}"))
_DIGITS_AS_ZERO = bytes(0x30 if 0x30 <= i <= 0x39 else 0x78 for i in range(256))
_LONG_DIGIT_RUN = b"0" * 309


def _may_overflow(data: str | bytes) -> bool:
    """Whether JSON text holds what a number that overflows a float64 to infinity needs: a positive
    exponent of three digits or 309 digits in a row (text without either holds no such number: no walk
    needed). The run of digits is found in the text with every digit made ``0`` (a byte table), several
    times faster than a regular expression for it (68 against 13 ms for a 700 kB batch)."""
    if _BIG_EXPONENT[isinstance(data, bytes)].search(data) is not None:
        return True
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    return len(raw) >= len(_LONG_DIGIT_RUN) and _LONG_DIGIT_RUN in raw.translate(_DIGITS_AS_ZERO)


def _children(value):
    """``(key, item)`` pairs of an object or array (``None`` for any other value)."""
    if isinstance(value, dict):
        return value.items()
    if isinstance(value, list):
        return enumerate(value)
    return None


def _non_finite_path(value, path: str = "") -> str | None:
    """The path of the first NaN or infinity in a decoded value (``None``: every number is finite)."""
    if isinstance(value, float):
        return None if math.isfinite(value) else (path or "message")
    items = _children(value)
    if items is None:
        return None
    for key, item in items:
        found = _non_finite_path(item, f"{path}.{key}" if path else str(key))
        if found is not None:
            return found
    return None


def _too_deep_path(value, limit: int = MAX_NESTING, path: str = "") -> str | None:
    """The path of the first object or array nested deeper than ``limit`` levels (``None``: none is)."""
    items = _children(value)
    if items is None:
        return None
    if limit <= 0:
        return path or "message"
    for key, item in items:
        if isinstance(item, (dict, list)):
            found = _too_deep_path(item, limit - 1, f"{path}.{key}" if path else str(key))
            if found is not None:
                return found
    return None


def _refuse_too_deep(value, code: str) -> None:
    """Nesting deeper than ``MAX_NESTING`` is an error anywhere in a message: protocol v1 needs six
    levels. Only a message with fields beyond the per-sample ones (``fast_fields_only``) can hold
    such a value that validation would not refuse anyway, so only such a message is walked."""
    if type(value) is dict and not fast_fields_only(value):
        path = _too_deep_path(value)
        if path is not None:
            raise ProtocolError(code, f"nested deeper than {MAX_NESTING} levels at {path}")


def _refuse_non_finite(value, code: str) -> None:
    """Non-finite numbers are an error anywhere in a message (DESIGN.md), in unknown fields too: the
    same rule for a MessagePack NaN and a JSON ``1e400`` as for the JSON ``NaN`` literal."""
    path = _non_finite_path(value)
    if path is not None:
        raise ProtocolError(code, f"non-finite number at {path} (NaN and infinity are not allowed anywhere in a message)")


FAST_LEVELS = 7
"""The deepest nesting ``decode`` reads with ``msgspec`` (protocol v1's deepest value, a calibration's
sensor mounting, is at level 6); a message nested deeper (to ``MAX_NESTING``, or beyond it and then
refused) is read the standard way."""


def _nested_at_most(levels: int):
    """The type of a value whose objects and arrays nest at most ``levels`` levels (the value itself
    is level 1), which ``msgspec`` checks while it decodes. Its decoders are built in about 4 ms for
    7 levels, but in 7 s for ``MAX_NESTING``'s 16 (each level about triples the time)."""
    value = Union[None, bool, int, float, str]
    for _ in range(levels):
        value = Union[None, bool, int, float, str, list[value], dict[str, value]]
    return value


@functools.cache
def _fast_decoders() -> tuple:
    """``decode``'s ``msgspec`` decoders, JSON and MessagePack (built at their first use)."""
    return tuple(decoder(_nested_at_most(FAST_LEVELS)) for decoder in (msgspec.json.Decoder, msgspec.msgpack.Decoder))


_FAST_REFUSED = (msgspec.DecodeError, RecursionError, UnicodeError, TypeError, ValueError)
_UNREAD = object()


def _fast_decode(data: str | bytes, binary: bool) -> object:
    """One message's value by ``msgspec`` (several times faster than the standard library's ``json``
    and a walk of the value for its depth, 0.46 ms for a 7 kB frame), or ``_UNREAD`` where
    ``decode``'s standard path must read it and give its value or its error. ``msgspec`` reads JSON
    as ``json.loads`` does (integers of any length up to ``sys.get_int_max_str_digits()`` digits stay
    integers, floats are correctly rounded, a duplicate key keeps its first place and its last value)
    and refuses everything ``json.loads`` refuses and more: ``NaN``/``Infinity``, a number that
    overflows a float64, a lone surrogate, a byte order mark, UTF-16/32 and invalid UTF-8, any value
    nested deeper than ``FAST_LEVELS``. A JSON value it returns is therefore finite and not too deep;
    a MessagePack one is not too deep and holds the standard path's value (``msgpack``'s bin, ext and
    non-text map keys refused as the standard path refuses them), its NaN and infinities left to
    ``decode``. Only ``str`` and ``bytes`` are read so (``json.loads`` refuses a ``memoryview``, and
    reads a ``bytearray`` the standard way)."""
    if type(data) is not bytes and (binary or type(data) is not str):
        return _UNREAD
    try:
        return _fast_decoders()[binary].decode(data)
    except _FAST_REFUSED:
        return _UNREAD


def decode(data: str | bytes, binary: bool = False) -> object:
    """One message's Python value from JSON text (``str`` or UTF-8 ``bytes``), or from MessagePack
    bytes when ``binary``; raises ``ProtocolError`` naming the encoding and the problem (a NaN or an
    infinity anywhere in it included). Read by ``msgspec`` first (``_fast_decode``), the standard
    library's way (``json``, ``msgpack``, a walk of the value) wherever ``msgspec`` refuses it."""
    value = _fast_decode(data, binary)
    if value is not _UNREAD:
        if binary and (_NON_FINITE_DOUBLE.search(data) is not None or _NON_FINITE_FLOAT32.search(data) is not None):
            _refuse_non_finite(value, "invalid_msgpack")
        return value
    if binary:
        try:
            # protocol v1 has no bin or ext values (they could not be recorded as JSON)
            value = msgpack.unpackb(data, max_bin_len=0, max_ext_len=0)
        except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as err:
            raise ProtocolError("invalid_msgpack", f"not valid MessagePack: {err or type(err).__name__}") from None
        if _NON_FINITE_DOUBLE.search(data) is not None or _NON_FINITE_FLOAT32.search(data) is not None:
            _refuse_non_finite(value, "invalid_msgpack")
        _refuse_too_deep(value, "invalid_msgpack")
        return value
    try:
        value = json.loads(data, parse_constant=_reject_constant)
    except RecursionError:
        raise ProtocolError("invalid_json", "not valid JSON: nested too deeply") from None
    except (ValueError, UnicodeDecodeError) as err:
        raise ProtocolError("invalid_json", f"not valid JSON: {err}") from None
    if _may_overflow(data):
        _refuse_non_finite(value, "invalid_json")
    _refuse_too_deep(value, "invalid_json")
    return value


_SAMPLE_KEYS = frozenset(ImuSample.model_fields) | {"type"}
FAST_KEYS = {"imu": frozenset(Imu.model_fields), "pose": frozenset(Pose.model_fields),
             "imu_batch": frozenset(ImuBatch.model_fields)}
"""The per-sample messages ``parse_input`` reads with ``orjson``, with their fields: every number in
them is range-checked, so whatever ``orjson`` reads differently from the standard library (an integer
beyond 64 bits becomes a float) cannot pass validation, and a message with other fields (whose values
nobody checks) takes the standard path."""


def fast_fields_only(raw: dict) -> bool:
    kind = raw.get("type")
    keys = FAST_KEYS.get(kind) if type(kind) is str else None     # a list or an object is no key (nor a sample)
    if keys is None or not raw.keys() <= keys:
        return False
    samples = raw.get("samples")
    return samples is None or (type(samples) is list
                               and all(type(s) is dict and s.keys() <= _SAMPLE_KEYS for s in samples))


def parse_input(data: str | bytes, binary: bool = False, value: bool = True) -> tuple[object, object]:
    """``(decoded value, validated message)`` of one message as it arrives: ``decode`` then
    ``parse_message``, with the same results and the same ``ProtocolError`` for bad input. JSON
    samples and poses are read into compiled structs that the pydantic models accept as theirs
    (``protocol.fast``, the value by ``orjson``) where that path accepts them; else by ``orjson`` and
    pydantic; any other message, and any text ``orjson`` refuses or whose message fails validation,
    goes through the standard path, whose value or error is the answer (``FAST_KEYS``). ``value=False``:
    the caller needs no decoded value where the compiled structs read the message (``None`` in its
    place: the text is not decoded a second time)."""
    if not binary:
        if (msg := _fast.read(data)) is not None:
            return (orjson.loads(data) if value else None), msg
        try:
            raw = orjson.loads(data)
        except orjson.JSONDecodeError:
            raw = None
        if type(raw) is dict and fast_fields_only(raw):
            try:
                return raw, parse_message(raw)
            except ProtocolError:
                pass                        # the error reply comes from the standard path, as before
    raw = decode(data, binary)
    return raw, parse_message(raw)


def parse_line(line: str | bytes):
    """Decode one JSON text and validate it as a source message; raises ``ProtocolError``
    (``invalid_json`` for bad JSON, including the non-standard ``NaN``/``Infinity`` literals). The
    message of ``parse_input``, without its decoded value (samples and poses: ``protocol.fast`` only)."""
    msg = _fast.read(line)
    return parse_input(line)[1] if msg is None else msg


def read_recording(path: str | Path, on_error: Literal["raise", "skip"] = "raise",
                   skipped: Callable[[int, ProtocolError], None] | None = None) -> Iterator[tuple[int, object]]:
    """Yield ``(line_number, message)`` for every line of a recording (blank lines ignored).

    A bad line raises ``ProtocolError`` naming the file and the line (``on_error="raise"``), or is
    left out (``on_error="skip"``), after ``skipped(line_number, error)`` if given."""
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    with open(path, encoding="utf-8") as fh:
        for number, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                message = parse_line(line)
            except ProtocolError as err:
                if on_error == "raise":
                    raise ProtocolError(err.code, f"{path}:{number}: {err.detail}") from None
                if skipped is not None:
                    skipped(number, err)
                continue
            yield number, message
