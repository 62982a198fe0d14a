"""Views of a frame log: filters, and the ``jsonl``, ``csv`` and ``text`` output formats.

Pure code shared by ``motorbus capture`` (which writes what it hears) and ``motorbus
replay`` (which shows a log): a :class:`RecordFilter` keeps the records a user asked
for, and :func:`csv_row` / :func:`text_line` render a record for reading.  Only
``jsonl`` is the frame log itself (docs/frame-log.md), the one format ``replay`` reads;
``csv`` (one row a record, a header row first) and ``text`` (one line a record, in
columns, like candump) are for people and spreadsheets.

``text`` columns: time in seconds, family, direction (``->`` host to device, ``<-``
device to host, `` ?`` unknown), device ID (``-`` when the frame has none), byte count,
the bytes, then the decoded name and fields::

    (    0.692181) la              ->   1 [  8] 55 AA 03 01 04 00 22 2A  Control action=QUERY_STATUS
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Direction, Family
from motorbus.protocol.describe import Description

__all__ = [
    "CSV_COLUMNS",
    "FORMATS",
    "RecordFilter",
    "csv_header",
    "csv_row",
    "record_ids",
    "text_line",
]

#: Output formats: the frame log itself, and two views of it.
FORMATS = ("jsonl", "csv", "text")
#: Columns of the ``csv`` format, in order.
CSV_COLUMNS = (
    "t",
    "kind",
    "family",
    "direction",
    "id",
    "name",
    "hex",
    "reason",
    "fault",
    "fields",
)
_ARROWS = {Direction.REQUEST.value: "->", Direction.REPLY.value: "<-"}
_FAMILY_WIDTH = max(len(f.value) for f in Family)


def record_ids(fields: Mapping[str, Any]) -> list[int]:
    """The device IDs a frame's decoded fields name.

    The LA's ``id`` (``255`` for a broadcast), the IDs inside an LA broadcast's
    ``entries``, and the quad stepper's ``motor``.  ``[]`` when the frame names none.
    """
    ids: list[int] = []
    for key in ("id", "motor"):
        value = fields.get(key)
        if isinstance(value, int) and not isinstance(value, bool):
            ids.append(value)
    entries = fields.get("entries")
    if isinstance(entries, list):
        ids.extend(e["id"] for e in entries if isinstance(e, dict) and isinstance(e.get("id"), int))
    return ids


@dataclass(frozen=True, slots=True)
class RecordFilter:
    """Which records to keep; each criterion left ``None`` keeps every record.

    Attributes:
        ids: keep frames naming one of these device IDs (:func:`record_ids`).
        families: keep frames of these families (``"la"``, ...).
        directions: keep ``"request"`` and/or ``"reply"`` frames.
        commands: keep frames whose decoded ``name`` (``Control``, ``MoveTo``,
            ``Status``...) or LA control ``action`` (``QUERY_STATUS``...) is one of these,
            in any case.

    A record passes when it meets every criterion given; garbage and link records,
    which have no family, ID or name, pass only a filter with none of those given.
    """

    ids: frozenset[int] | None = None
    families: frozenset[str] | None = None
    directions: frozenset[str] | None = None
    commands: frozenset[str] | None = None

    @classmethod
    def build(
        cls,
        *,
        ids: Iterable[int] | None = None,
        families: Iterable[str] | None = None,
        directions: Iterable[str] | None = None,
        commands: Iterable[str] | None = None,
    ) -> RecordFilter:
        """Check and build a filter.

        Raises:
            LocalProtocolError: an unknown family or direction, or an empty command name.
        """
        fams = _known("--family", families, [f.value for f in Family])
        dirs = _known("--dir", directions, [d.value for d in Direction])
        names = None
        if commands is not None:
            names = frozenset(c.strip().upper() for c in commands)
            if not names or "" in names:
                raise LocalProtocolError(
                    "--command must name one or more commands, e.g. MoveTo,Status",
                    field="--command",
                )
        return cls(frozenset(ids) if ids is not None else None, fams, dirs, names)

    @property
    def active(self) -> bool:
        """True if any criterion is given."""
        return any(x is not None for x in (self.ids, self.families, self.directions, self.commands))

    def to_json(self) -> dict[str, list[Any]]:
        """The criteria given, for a frame-log header's ``filter`` key."""
        out: dict[str, list[Any]] = {}
        for key, value in (
            ("id", self.ids),
            ("family", self.families),
            ("direction", self.directions),
            ("command", self.commands),
        ):
            if value is not None:
                out[key] = sorted(value)
        return out

    def keeps(self, record: Mapping[str, Any], described: Sequence[Description]) -> bool:
        """True if the record passes; ``described`` is its description (``describe_record``)."""
        if self.families is not None and record.get("family") not in self.families:
            return False
        if self.directions is not None and record.get("direction") not in self.directions:
            return False
        if self.ids is None and self.commands is None:
            return True
        frames = [d for d in described if d.kind != "garbage"]
        if not frames:
            return False
        if self.ids is not None and not any(
            i in self.ids for d in frames for i in record_ids(d.fields)
        ):
            return False
        if self.commands is not None:
            names = {d.name.upper() for d in frames}
            names |= {str(d.fields["action"]).upper() for d in frames if "action" in d.fields}
            if not names & self.commands:
                return False
        return True


def _known(field: str, values: Iterable[str] | None, allowed: list[str]) -> frozenset[str] | None:
    if values is None:
        return None
    got = frozenset(values)
    bad = sorted(got - set(allowed))
    if bad or not got:
        raise LocalProtocolError(
            f"{field}={','.join(bad) or '(none)'} is not one of {', '.join(allowed)}",
            field=field,
        )
    return got


def csv_header() -> str:
    """The ``csv`` format's header row (with its line end)."""
    return _csv_line(CSV_COLUMNS)


def csv_row(record: Mapping[str, Any], d: Description | None) -> str:
    """One ``csv`` row (with its line end): a record, described by ``d`` (None: a link)."""
    fields = d.fields if d is not None else {}
    ids = record_ids(fields)
    return _csv_line(
        (
            f"{float(record['t']):.6f}",
            d.kind if d is not None else record["kind"],
            (d.family if d is not None else record.get("family")) or "",
            (d.direction if d is not None else record.get("direction")) or "",
            ids[0] if len(ids) == 1 else " ".join(map(str, ids)),
            d.name if d is not None else record.get("name") or "",
            d.hex if d is not None else record.get("hex", ""),
            (d.reason if d is not None else None) or "",
            record.get("fault") or "",
            json.dumps(fields, ensure_ascii=False, separators=(",", ":")) if fields else "",
        )
    )


def text_line(record: Mapping[str, Any], d: Description | None) -> str:
    """One ``text`` line (no line end): a record, described by ``d`` (None: a link)."""
    t = f"({float(record['t']):13.6f})"
    fault = record.get("fault")
    tail = f"  fault={fault}" if fault else ""
    if d is None:
        return f"{t} {'link':<{_FAMILY_WIDTH}} {record.get('name')}{tail}"
    ids = record_ids(d.fields)
    ident = str(ids[0]) if len(ids) == 1 and "entries" not in d.fields else "-"
    n = len(d.hex.split()) if d.hex else 0
    arrow = _ARROWS.get(d.direction or "", " ?")
    what = d.name
    extra = " ".join(f"{k}={_plain(v)}" for k, v in d.fields.items() if k not in ("id", "motor"))
    if extra:
        what += " " + extra
    if d.reason:
        what += f" ({d.reason})"
    family = d.family or "-"
    return f"{t} {family:<{_FAMILY_WIDTH}} {arrow} {ident:>3} [{n:>3}] {d.hex}  {what}{tail}"


def _plain(value: Any) -> str:
    if isinstance(value, list | dict):
        return json.dumps(value, ensure_ascii=False, separators=(",", ":"))
    return str(value)


def _csv_line(values: Iterable[object]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(values)
    return buf.getvalue()
