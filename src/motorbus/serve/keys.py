"""The key expressions and payloads of a served bus, version 1 (pure: no I/O, no Zenoh).

A served bus (``motorbus serve``) speaks over Eclipse Zenoh.  Everything lives under
``motorbus/v1/``; a change that an old client could misread gets a new version prefix.
Every payload is one UTF-8 JSON object; frames travel as hex strings of their exact
bytes (``"55aa0301..."``), so a program in any language with a Zenoh binding and a
JSON parser can use a served bus (docs/serve.md lists every key and field).

Keys (``{bus}`` is a bus name, ``{client}`` a client id, both single key chunks):

* ``motorbus/v1/info`` (query): the server's instance id, liveness timeout and buses.
* ``motorbus/v1/bus/{bus}/request`` (query): one request frame; the reply is the reply
  frame, or an error.
* ``motorbus/v1/bus/{bus}/lease`` (query): acquire, add to, release, hand over leases.
* ``motorbus/v1/bus/{bus}/leases`` (query, and a publication on every change): who
  holds which device.
* ``motorbus/v1/bus/{bus}/stats`` (query): the bus's counters.
* ``motorbus/v1/bus/{bus}/event/{kind}`` (publications): device events.
* ``motorbus/v1/bus/{bus}/devices`` (query): the devices the server's bus declares,
  those that answered it, and its timing (``motorbus scan``/``doctor --connect``).
* ``motorbus/v1/bus/{bus}/frames`` (publication, while someone subscribes): every frame
  written and every chunk read, in batches (``motorbus capture --connect``).
* ``motorbus/v1/client/{client}`` (liveliness token) and
  ``motorbus/v1/client/{client}/alive`` (heartbeat publication): the deadman.
* ``motorbus/v1/server/{instance}`` (liveliness token): the server is up.

This module builds and checks those payloads; ``motorbus.serve.server`` and
``motorbus.serve.client`` move them.  A payload that does not fit is refused with
``PayloadError`` naming the field, the value and what is allowed.
"""

from __future__ import annotations

import importlib
import json
import logging
import math
import re
import time
from collections.abc import Mapping, Sequence
from typing import Any

from motorbus.bus.events import (
    BusEvent,
    BusStateChanged,
    FaultChanged,
    ProjectFinished,
    QuadDone,
)
from motorbus.errors import (
    BusClosedError,
    LeaseConflictError,
    LocalProtocolError,
    NotSentError,
    PayloadError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.protocol import la
from motorbus.protocol.base import Command, Family, format_hex

_log = logging.getLogger("motorbus.serve")

__all__ = [
    "CLIENT_PREFIX",
    "ERROR_KINDS",
    "LIVENESS_DEFAULT_S",
    "LIVENESS_MAX_S",
    "LIVENESS_MIN_S",
    "PREFIX",
    "PRIORITIES",
    "VERSION",
    "PayloadError",
    "bus_key",
    "check_chunk",
    "check_liveness",
    "client_key",
    "decode_frame",
    "decode_json",
    "encode_json",
    "error_of",
    "error_payload",
    "event_from",
    "event_payload",
    "field_of",
    "hex_field",
    "only_fields",
    "server_key",
]

#: The protocol version in every key: ``motorbus/v1/...``.
VERSION = 1
PREFIX = f"motorbus/v{VERSION}"
CLIENT_PREFIX = f"{PREFIX}/client"

#: How long a client may stay silent (no heartbeat) before the server ends its leases
#: with their safe actions.  A client heartbeats four times per timeout.
LIVENESS_DEFAULT_S = 1.0
LIVENESS_MIN_S = 0.1
LIVENESS_MAX_S = 60.0

#: Request priorities by name (``motorbus.Priority``'s members, lower case).
PRIORITIES = ("normal", "high", "emergency", "background")

#: The ``error`` names a reply may carry; each maps to the exception the client raises.
ERROR_KINDS = (
    "bad_payload",  # LocalProtocolError: a field is missing, of the wrong type or range
    "unknown_key",  # LocalProtocolError: no such bus, operation or lease
    "lease_conflict",  # LeaseConflictError: holder in "owner"
    "lease_gone",  # BusClosedError: the lease ended (server restart, client expired)
    "timeout",  # ReplyTimeoutError
    "not_sent",  # NotSentError
    "closed",  # BusClosedError
    "remote",  # RemoteProtocolError: the device's reply did not decode
    "refused",  # PermissionError: the server lets this client only watch
    "internal",  # anything else, with its message
)

#: One key chunk: no ``/``, no Zenoh wildcard or selector characters.
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-:@+=]{1,128}$")

#: The module of each family's ``decode_request``, loaded when a bus carrying that family
#: is asked to decode (a served bus of LA actuators never loads the stepper protocols).
_DECODERS = {
    Family.LA: "motorbus.protocol.la",
    Family.PROJECT_STEPPER: "motorbus.protocol.project_stepper",
    Family.QUAD_STEPPER: "motorbus.protocol.quad_stepper",
}


def check_chunk(field: str, value: object) -> str:
    """A bus name or client id usable as one key chunk (letters, digits, ``_.-:@+=``)."""
    if not isinstance(value, str) or not _CHUNK.match(value):
        raise PayloadError(
            f"{field}={value!r} is not usable in a key: 1..128 of letters, digits and _.-:@+=",
            field=field,
            value=value,
        )
    return value


def check_liveness(value: object) -> float:
    """A server's ``liveness`` in seconds (``LIVENESS_MIN_S``..``LIVENESS_MAX_S``)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not LIVENESS_MIN_S <= value <= LIVENESS_MAX_S
    ):
        raise LocalProtocolError(
            f"liveness={value!r} is out of range: allowed {LIVENESS_MIN_S:g}..{LIVENESS_MAX_S:g} s",
            field="liveness",
            value=value,
        )
    return float(value)


def bus_key(bus: str, what: str) -> str:
    """``motorbus/v1/bus/{bus}/{what}`` (``what``: request, lease, leases, stats, event/*)."""
    return f"{PREFIX}/bus/{check_chunk('bus', bus)}/{what}"


def client_key(client: str) -> str:
    """The liveliness token key of a client."""
    return f"{CLIENT_PREFIX}/{check_chunk('client', client)}"


def server_key(instance: str) -> str:
    """The liveliness token key of a server instance."""
    return f"{PREFIX}/server/{check_chunk('instance', instance)}"


def encode_json(value: Mapping[str, Any]) -> bytes:
    """A payload as compact UTF-8 JSON."""
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


def decode_json(raw: bytes) -> dict[str, Any]:
    """A payload as a JSON object; anything else is a ``PayloadError``."""
    try:
        value = json.loads(bytes(raw).decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise PayloadError(f"payload is not UTF-8 JSON: {err}", field="payload") from None
    if not isinstance(value, dict):
        raise PayloadError(
            f"payload must be a JSON object, got {type(value).__name__}", field="payload"
        )
    return value


def field_of(
    payload: Mapping[str, Any],
    name: str,
    kind: type | tuple[type, ...],
    *,
    optional: bool = False,
    default: Any = None,
) -> Any:
    """``payload[name]``, checked to be of ``kind`` (``bool`` is never an int here)."""
    if name not in payload or payload[name] is None:
        if optional:
            return default
        raise PayloadError(f"payload has no {name!r}", field=name)
    value = payload[name]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    ok = False if isinstance(value, bool) and bool not in kinds else isinstance(value, kinds)
    if ok and isinstance(value, float) and not math.isfinite(value):
        ok = False
    if not ok:
        allowed = " or ".join(k.__name__ for k in kinds)
        raise PayloadError(f"{name}={value!r} must be {allowed}", field=name, value=value)
    return value


def hex_field(payload: Mapping[str, Any], name: str) -> bytes:
    """A frame given as a hex string."""
    text = field_of(payload, name, str)
    try:
        return bytes.fromhex(text)
    except ValueError:
        raise PayloadError(f"{name}={text!r} is not a hex string", field=name, value=text) from None


def decode_frame(raw: bytes, families: Sequence[Family], field: str = "frame") -> Command[object]:
    """The command a request frame encodes, for a bus carrying ``families``.

    The frame's header and length say its family; it is decoded by that family's
    ``decode_request`` and must re-encode to the same bytes.

    Raises:
        PayloadError: not a request frame of a family the bus carries (names the field).
    """
    errors = []
    for family in families:
        try:
            decode = importlib.import_module(_DECODERS[family]).decode_request
            cmd: Command[object] = decode(raw)
        except (LocalProtocolError, ValueError, IndexError) as err:
            errors.append(f"{family.value}: {err}")
            continue
        except Exception as err:  # RemoteProtocolError and the like: not this family
            errors.append(f"{family.value}: {err}")
            continue
        if cmd.encode() != bytes(raw):
            errors.append(f"{family.value}: does not re-encode to the same bytes")
            continue
        return cmd
    raise PayloadError(
        f"{field}={format_hex(raw) or '(empty)'} is not a request frame of this bus "
        f"({'; '.join(errors) or 'no family'})",
        field=field,
        value=format_hex(raw),
    )


def error_payload(
    kind: str, message: str, *, field: str | None = None, value: object = None, **extra: Any
) -> dict[str, Any]:
    """The JSON object of an error reply (``kind`` one of ``ERROR_KINDS``)."""
    if kind not in ERROR_KINDS:
        raise ValueError(f"unknown error kind {kind!r}")
    out: dict[str, Any] = {"ok": False, "error": kind, "message": message}
    if field is not None:
        out["field"] = field
    if value is not None:
        out["value"] = value if isinstance(value, int | float | str | bool) else repr(value)
    out.update(extra)
    return out


# -- bus events: the publication and back -------------------------------------------


def event_payload(event: BusEvent) -> dict[str, Any] | None:
    """The publication of a bus event (``keys`` module docstring; docs/serve.md)."""
    if isinstance(event, ProjectFinished):
        return {"kind": "project_finished", "time": event.time}
    if isinstance(event, QuadDone):
        return {
            "kind": "quad_done",
            "time": event.time,
            "done": event.kind,
            "address": event.address,
            "led": event.led,
            "raw": event.raw.hex(),
        }
    if isinstance(event, FaultChanged):
        raw = getattr(event.status, "raw", None)
        return {
            "kind": "fault_changed",
            "time": event.time,
            "id": event.id,
            "before": event.before,
            "after": event.after,
            "status": raw.hex() if isinstance(raw, bytes) else None,
        }
    if isinstance(event, BusStateChanged):
        return {"kind": "state", "time": event.time, "state": event.state, "detail": event.detail}
    return None


def event_from(bus: str, body: dict[str, Any]) -> BusEvent | None:
    """A bus event from its publication (``event_payload``), at the local time."""
    now = time.monotonic()
    kind = body.get("kind")
    if kind == "project_finished":
        return ProjectFinished(bus, now)
    if kind == "quad_done":
        return QuadDone(
            bus,
            now,
            str(body["done"]),
            int(body["address"]),
            body.get("led"),
            bytes.fromhex(body["raw"]),
        )
    if kind == "fault_changed":
        status = body.get("status")
        decoded = la.decode_reply(bytes.fromhex(status)) if status else None
        return FaultChanged(
            bus, now, int(body["id"]), int(body["before"]), int(body["after"]), decoded
        )
    if kind == "state":
        return BusStateChanged(bus, now, str(body["state"]), str(body.get("detail", "")))
    return None


def only_fields(payload: dict[str, Any], allowed: frozenset[str]) -> None:
    """Refuse a field the query does not take (a misspelt option must not be ignored)."""
    for name in payload:
        if name not in allowed:
            raise PayloadError(
                f"unknown field {name!r}: allowed {', '.join(sorted(allowed))}",
                field=name,
                value=payload[name],
            )


def error_of(err: Exception) -> dict[str, Any]:
    """The error reply for an exception raised while serving a request."""
    if isinstance(err, LeaseConflictError):
        return error_payload(
            "lease_conflict", str(err), key=err.key, owner=err.owner, refused=err.refused
        )
    if isinstance(err, LocalProtocolError):
        return error_payload("bad_payload", str(err), field=err.field, value=err.value)
    if isinstance(err, ReplyTimeoutError):
        return error_payload("timeout", str(err))
    if isinstance(err, NotSentError):
        return error_payload("not_sent", str(err))
    if isinstance(err, BusClosedError):
        return error_payload("closed", str(err))
    if isinstance(err, RemoteProtocolError):
        return error_payload("remote", str(err), raw=format_hex(err.raw))
    if isinstance(err, KeyError):
        return error_payload("unknown_key", f"no such bus: {err}")
    _log.exception("serving a request failed")
    return error_payload("internal", f"{type(err).__name__}: {err}")
