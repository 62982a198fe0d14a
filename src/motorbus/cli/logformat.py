"""Output formats and filters of frame logs, for ``capture`` and ``replay``.

``--format jsonl`` writes the frame log itself (docs/frame-log.md); ``csv`` and ``text``
are views for reading (``motorbus.protocol.logview``).  The filters ``--id``,
``--family`` (replay), ``--dir`` and ``--command`` keep the records asked for; a
filtered ``jsonl`` log says so in its header's ``filter`` key.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from typing import Any, TextIO

from motorbus.cli.ids import parse_ids
from motorbus.protocol import framelog, logview
from motorbus.protocol.base import Direction, Family
from motorbus.protocol.describe import Description

__all__ = ["LogWriter", "add_filter_options", "add_format_option", "record_filter"]

#: Keys the reader adds to a record (not part of the format).
_READER_KEYS = ("session", "line")
#: IDs ``--id`` accepts: LA 1..254 and broadcast 255, the quad's motors 1..4.
ID_MIN, ID_MAX = 0, 255


def add_format_option(parser: argparse.ArgumentParser, default: str | None) -> None:
    """Add ``--format jsonl|csv|text``."""
    shown = f" (default {default})" if default else ""
    parser.add_argument(
        "--format",
        choices=logview.FORMATS,
        default=default,
        help="jsonl: the frame log (what replay reads); csv: a row a record; "
        f"text: a line a record, in columns like candump{shown}",
    )


def add_filter_options(parser: argparse.ArgumentParser, *, family: bool) -> None:
    """Add ``--id``, ``--dir``, ``--command`` and (if ``family``) ``--family``."""
    parser.add_argument(
        "--id",
        metavar="IDS",
        help="keep frames naming these device IDs, e.g. 1-3,7 (LA id, IDs in a broadcast, "
        "quad motor)",
    )
    if family:
        parser.add_argument(
            "--family",
            dest="family_filter",
            metavar="FAMILIES",
            help=f"keep frames of these families ({', '.join(f.value for f in Family)})",
        )
    parser.add_argument(
        "--dir",
        choices=[d.value for d in Direction],
        help="keep requests (host to device) or replies (device to host) only",
    )
    parser.add_argument(
        "--command",
        dest="command_filter",
        metavar="NAMES",
        help="keep frames of these commands or replies, by decoded name or LA control "
        "action, e.g. MoveTo,Status,QUERY_STATUS (any case)",
    )


def record_filter(args: argparse.Namespace) -> logview.RecordFilter:
    """The filter the options of :func:`add_filter_options` ask for.

    Raises:
        LocalProtocolError: a bad ID list, family or command list.
    """
    ids = parse_ids(args.id, "--id", ID_MIN, ID_MAX) if args.id is not None else None
    families = getattr(args, "family_filter", None)
    return logview.RecordFilter.build(
        ids=ids,
        families=_split(families),
        directions=[args.dir] if args.dir is not None else None,
        commands=_split(args.command_filter),
    )


def _split(text: str | None) -> list[str] | None:
    return None if text is None else [x.strip() for x in text.split(",")]


class LogWriter:
    """Writes frame-log records to ``out`` in one format, keeping those ``keep`` passes.

    Args:
        out: where the lines go.
        fmt: ``"jsonl"``, ``"csv"`` or ``"text"``.
        keep: the filter.
    """

    def __init__(self, out: TextIO, fmt: str, keep: logview.RecordFilter) -> None:
        self.out = out
        self.fmt = fmt
        self.keep = keep
        self.kept = 0
        self.dropped = 0
        self._csv_started = False

    def header(self, doc: Mapping[str, Any]) -> None:
        """Start a session: its header line in ``jsonl`` (with the filter), the CSV header
        row once in ``csv``, nothing in ``text``."""
        if self.fmt == "jsonl":
            doc = dict(doc)
            if self.keep.active:
                doc["filter"] = self.keep.to_json()
            self.out.write(json.dumps(doc, ensure_ascii=False) + "\n")
        elif self.fmt == "csv" and not self._csv_started:
            self.out.write(logview.csv_header())
            self._csv_started = True

    def write(self, record: Mapping[str, Any]) -> bool:
        """Write ``record`` if it passes the filter; return whether it did."""
        described = framelog.describe_record(record)
        if not self.keep.keeps(record, described):
            self.dropped += 1
            return False
        self.kept += 1
        if self.fmt == "jsonl":
            doc = {k: v for k, v in record.items() if k not in _READER_KEYS}
            self.out.write(json.dumps(doc, ensure_ascii=False) + "\n")
        elif self.fmt == "csv":
            if not self._csv_started:
                self.header({})
            for d in _or_link(described):
                self.out.write(logview.csv_row(record, d))
        else:
            for d in _or_link(described):
                self.out.write(logview.text_line(record, d) + "\n")
        return True

    def flush(self) -> None:
        """Flush ``out`` (a capture flushes after each chunk it heard)."""
        self.out.flush()


def _or_link(described: list[Description]) -> list[Description | None]:
    """The descriptions to render; ``[None]`` for a link record (which has none)."""
    return list(described) if described else [None]
