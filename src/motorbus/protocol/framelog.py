"""The frame log: one JSON-lines format for what crossed a bus (docs/frame-log.md).

Written by ``motorbus capture``, by ``motorbus sim --log`` (and so by the demo's
``la-bus-frames.jsonl``), read by ``motorbus replay``.  Pure code: the callers open the
files and read the clock; this module builds, checks and translates the JSON values.

A log is a sequence of *sessions*.  Each starts with a header line::

    {"format": "motorbus-frame-log", "version": 1, "source": "capture", ...}

followed by one record a line::

    {"t": 0.012345, "kind": "frame", "direction": "request", "family": "la",
     "name": "Control", "fields": {...}, "hex": "55 AA 03 01 04 00 22 2A"}

``t`` counts seconds from the start of its session.  The simulator appends to its log,
so one file can hold several sessions; a reader keeps them apart by their headers.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Direction, Family, parse_hex
from motorbus.protocol.describe import (
    KIND_EVENT,
    KIND_FRAME,
    KIND_GARBAGE,
    NAME_GARBAGE,
    Description,
    describe,
)
from motorbus.protocol.reassembler import Reassembler

__all__ = [
    "FORMAT",
    "KINDS",
    "KIND_LINK",
    "MAX_T",
    "REQUIRED_KEYS",
    "SOURCES",
    "TIME_DECIMALS",
    "VERSION",
    "FrameLog",
    "continuous_times",
    "describe_record",
    "from_description",
    "from_sim",
    "header",
    "quote",
    "read_frame_log",
]

#: Value of the header's ``format`` key.
FORMAT = "motorbus-frame-log"
#: Version of the format this module writes; a reader refuses newer versions.
VERSION = 1
#: Decimal places of ``t`` (one microsecond).
TIME_DECIMALS = 6
#: Largest ``t`` a record may carry (seconds since its session started: about 116 days).
#: Anything larger is a broken file, not a recording (a replay would wait that long).
MAX_T = 10_000_000
#: Longest text of a bad value quoted in an error message.
_QUOTE_MAX = 40
#: A change of the simulated link (disconnect fault): ``name`` is ``"down"`` or ``"up"``.
KIND_LINK = "link"
KINDS = frozenset((KIND_FRAME, KIND_EVENT, KIND_GARBAGE, KIND_LINK))
#: Who wrote a session.
SOURCES = frozenset(("capture", "sim", "dashboard"))
#: Keys every record has.
REQUIRED_KEYS = ("t", "kind", "hex")
#: Keys of the simulator's own log callback records (``SimBus(log=...)``), which the
#: simulator wrote to its ``--log`` file before version 1.
_SIM_KEYS = ("t", "dir", "hex")
_DISCARDED = "discarded: "
_FAMILY_VALUES = frozenset(f.value for f in Family)
_DIRECTION_VALUES = frozenset(d.value for d in Direction)


def header(
    source: str,
    *,
    started_utc: str,
    families: Iterable[Family | str],
    baud: int | None = None,
    port: str | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """Return the header line of a new session.

    Args:
        source: ``"capture"``, ``"sim"`` or ``"dashboard"``.
        started_utc: wall-clock time of ``t = 0``, ISO 8601 in UTC (``...Z``).
        families: the device families on the bus.
        baud: the line rate in bit/s.
        port: the device path the writer served or listened on.
        extra: writer-specific keys (the simulator adds ``link`` and ``tap``).
    """
    names = sorted(f.value if isinstance(f, Family) else str(f) for f in families)
    doc: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "source": source,
        "started_utc": started_utc,
        "families": names,
        "baud": baud,
        "port": port,
    }
    doc.update({k: v for k, v in extra.items() if v is not None})
    return doc


def from_description(t: float, d: Description) -> dict[str, Any]:
    """Return the record of a described item seen ``t`` seconds into the session."""
    return {"t": round(t, TIME_DECIMALS), **d.to_json()}


def from_sim(record: Mapping[str, Any]) -> dict[str, Any]:
    """Translate one record of the simulator's log callback into a frame-log record.

    The simulator knows what it cut and sent, so the record says ``kind``, ``direction``
    and ``family`` without decoding (which would cost the simulator's thread ~50 us a
    frame); ``name`` and ``fields`` are left out, and readers decode ``hex`` themselves
    (:func:`describe_record`).

    Raises:
        KeyError: ``t``, ``dir`` or ``hex`` is missing.
    """
    direction = str(record["dir"])
    t = round(float(record["t"]), TIME_DECIMALS)
    hex_ = str(record["hex"])
    family = record.get("family")
    fault = record.get("fault")
    out: dict[str, Any]
    if direction == "link":
        out = {"t": t, "kind": KIND_LINK, "direction": None, "family": None}
        out["name"] = "down" if fault == "disconnect" else "up"
        out["hex"] = ""
    elif direction == "rx":
        out = {"t": t, "direction": Direction.REQUEST.value, "family": family}
        if family is None:
            out["kind"] = KIND_GARBAGE
            out["name"] = NAME_GARBAGE
            reason = str(fault or "discarded")
            out["reason"] = reason.removeprefix(_DISCARDED)
            fault = None
        else:
            out["kind"] = KIND_FRAME
        out["hex"] = hex_
    else:
        out = {"t": t, "direction": Direction.REPLY.value, "family": family}
        out["kind"] = KIND_EVENT if hex_ == "EE DD" else KIND_FRAME
        out["hex"] = hex_
    if fault is not None:
        out["fault"] = str(fault)
    return out


@dataclass(slots=True)
class FrameLog:
    """What :func:`read_frame_log` found.

    Attributes:
        headers: the header of each session, in file order (``{}`` for a session that
            had none: a capture written before version 1).
        records: every record, each with ``"session"`` (index into ``headers``) and
            ``"line"`` (its line number) added, old simulator records translated
            (:func:`from_sim`).
        translated: how many old simulator records were translated.
    """

    headers: list[dict[str, Any]] = field(default_factory=list)
    records: list[dict[str, Any]] = field(default_factory=list)
    translated: int = 0


def read_frame_log(lines: Iterable[str | bytes], name: str = "frame log") -> FrameLog:
    """Parse the lines of a frame log (blank lines are skipped).

    Also reads what older versions wrote: captures without a header line, and the
    simulator's ``{t, dir, hex, family, fault}`` lines, translated with :func:`from_sim`.
    Lines may be given as bytes (a file opened in binary mode), so that text that is not
    UTF-8 is reported with its line.

    Raises:
        LocalProtocolError: a line that is not UTF-8, not JSON (or nested too deeply),
            not an object, lacks a required key, has a bad ``t`` (not a number, or outside
            ``0..MAX_T``), ``kind``, ``hex``, ``family`` or ``direction``, a frame of a
            family its session's header does not name, or a header of another format, a
            newer version or without its list of families.  The message names ``name``,
            the line number and the key.
    """
    log = FrameLog()
    families: frozenset[str] | None = None  # of the current session; None: no header
    header_line = 0
    for n, raw in enumerate(lines, start=1):
        where = f"{name} line {n}"
        line = _text(raw, where)
        if not line.strip():
            continue
        value = _json(line, where)
        if not isinstance(value, dict):
            raise LocalProtocolError(
                f"{where} is not a frame-log record: a JSON {type(value).__name__}, "
                "expected an object",
                field="file",
            )
        if "format" in value:
            log.headers.append(_check_header(value, where))
            families = frozenset(value["families"])
            header_line = n
            continue
        if not log.headers:
            log.headers.append({})
        if "kind" not in value and all(k in value for k in _SIM_KEYS):
            value = from_sim(value)
            log.translated += 1
        record = _check_record(value, where)
        family = record.get("family")
        if families is not None and family is not None and family not in families:
            raise LocalProtocolError(
                f"{where}: a {family} {record['kind']} in a session whose header (line "
                f"{header_line}) names {', '.join(sorted(families)) or 'no family'}: "
                "refused (a log carries the families its header names)",
                field="file",
            )
        log.records.append({**record, "session": len(log.headers) - 1, "line": n})
    return log


def continuous_times(log: FrameLog) -> list[dict[str, Any]]:
    """Return the records of ``log`` with ``t`` relative to the first record.

    A later session (the simulator appends to its log) continues where the one before
    ended, so times never jump back at a session boundary.  ``t`` keeps 6 decimals.
    """
    records: list[dict[str, Any]] = []
    offset = 0.0
    session = 0
    first: float | None = None
    last = 0.0
    for record in log.records:
        t = float(record["t"])
        if first is None:
            first = t
        if record["session"] != session:
            session = record["session"]
            offset = last - t
        rel = round(t - first + offset, TIME_DECIMALS)
        last = rel + first
        records.append({**record, "t": rel})
    return records


def quote(value: object) -> str:
    """``repr(value)``, cut to a readable length for an error message."""
    text = repr(value)
    return text if len(text) <= _QUOTE_MAX else text[: _QUOTE_MAX - 3] + "..."


def _text(raw: str | bytes, where: str) -> str:
    if isinstance(raw, str):
        return raw
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        bad = raw[err.start : err.start + 1].hex().upper()
        raise LocalProtocolError(
            f"{where} is not UTF-8 text: byte 0x{bad} at column {err.start + 1} "
            "(a frame log is UTF-8 JSON lines)",
            field="file",
        ) from None


def _json(line: str, where: str) -> Any:
    try:
        return json.loads(line)
    except RecursionError:
        raise LocalProtocolError(
            f"{where} is not a frame-log record: JSON nested too deeply", field="file"
        ) from None
    except ValueError as err:
        raise LocalProtocolError(f"{where} is not JSON: {err}", field="file") from err


def _check_header(value: dict[str, Any], where: str) -> dict[str, Any]:
    if value.get("format") != FORMAT:
        raise LocalProtocolError(
            f"{where}: format={quote(value.get('format'))} is not {FORMAT!r}", field="file"
        )
    version = value.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= VERSION:
        raise LocalProtocolError(
            f"{where}: version={quote(version)} is not one this motorbus reads (1..{VERSION})",
            field="file",
        )
    families = value.get("families")
    if (
        not isinstance(families, list)
        or not families
        or not all(isinstance(f, str) and f in _FAMILY_VALUES for f in families)
    ):
        raise LocalProtocolError(
            f"{where}: families={quote(families)} is not a list of the bus's families "
            f"(each one of {', '.join(sorted(_FAMILY_VALUES))})",
            field="file",
        )
    return value


def _check_record(value: dict[str, Any], where: str) -> dict[str, Any]:
    for key in REQUIRED_KEYS:
        if key not in value:
            raise LocalProtocolError(
                f"{where} is not a frame-log record: missing key {key!r} "
                f"(every record has {', '.join(REQUIRED_KEYS)})",
                field="file",
            )
    t = value["t"]
    if isinstance(t, bool) or not isinstance(t, int | float) or t != t:
        raise LocalProtocolError(f"{where}: t={quote(t)} is not a number of seconds", field="file")
    # Compared before any float(): an int of 400 digits must not overflow here.
    if not (isinstance(t, int) or math.isfinite(t)) or not 0 <= t <= MAX_T:
        raise LocalProtocolError(
            f"{where}: t={quote(t)} is out of range: allowed 0..{MAX_T} "
            "(seconds since the session started)",
            field="file",
        )
    kind = value["kind"]
    if kind not in KINDS:
        raise LocalProtocolError(
            f"{where}: kind={quote(kind)} is not one of {', '.join(sorted(KINDS))}",
            field="file",
        )
    hex_ = value["hex"]
    if not isinstance(hex_, str):
        raise LocalProtocolError(f"{where}: hex={quote(hex_)} is not a string", field="file")
    try:
        parse_hex(hex_) if hex_ else b""
    except ValueError as err:
        raise LocalProtocolError(f"{where}: hex={quote(hex_)}: {err}", field="file") from err
    for key, allowed in (("family", _FAMILY_VALUES), ("direction", _DIRECTION_VALUES)):
        got = value.get(key)
        if got is not None and got not in allowed:
            raise LocalProtocolError(
                f"{where}: {key}={quote(got)} is not one of {', '.join(sorted(allowed))} (or null)",
                field="file",
            )
    for key, kinds, what in (("name", str, "a string"), ("fields", dict, "an object")):
        if key in value and not isinstance(value[key], kinds):
            raise LocalProtocolError(
                f"{where}: {key}={quote(value[key])} is not {what}", field="file"
            )
    return value


def describe_record(record: Mapping[str, Any]) -> list[Description]:
    """The description(s) of a record, for printing.

    A record that carries ``name`` (a capture) is described from its own keys.  One
    without (the simulator's) is decoded from ``hex``: cut with the reassembler of its
    direction and family, so a reply the simulator corrupted on purpose (``fault``)
    shows as the frame and garbage a listener would see.  A link record gives ``[]``.
    """
    kind = str(record["kind"])
    if kind == KIND_LINK:
        return []
    hex_ = str(record["hex"])
    if "name" in record:
        return [
            Description(
                kind=kind,
                family=record.get("family"),
                direction=record.get("direction"),
                name=str(record["name"]),
                fields=dict(record.get("fields") or {}),
                hex=hex_,
                reason=record.get("reason"),
            )
        ]
    if kind == KIND_GARBAGE:
        return [Description(KIND_GARBAGE, None, None, NAME_GARBAGE, {}, hex_, record.get("reason"))]
    raw = parse_hex(hex_)
    direction = _enum(Direction, record.get("direction"))
    family = _enum(Family, record.get("family"))
    cutter = Reassembler(
        direction=direction, families=(family,) if family is not None else tuple(Family)
    )
    items = cutter.feed(raw) + cutter.end_of_stream()
    return [describe(item, family_hint=family) for item in items]


def _enum(cls: Any, value: object) -> Any:
    try:
        return cls(value) if value is not None else None
    except ValueError:
        return None
