"""Recording what the dashboard saw: a frame log per bus and a CSV of the plotted values.

The frame log is the project's one format (docs/frame-log.md, ``motorbus.protocol.
framelog``), source ``"dashboard"``: every frame the bus wrote and every reply it
accepted, described the way ``motorbus capture`` describes them, so ``motorbus replay``
prints it and ``replay --to`` sends its requests again.  Times are the bus's own (the
observer's ``at``/``replied_at``), relative to the start of the recording.

``plots.csv`` holds one row per LA status the poller got: what the plots show.
"""

from __future__ import annotations

import csv
import datetime
import json
import re
from pathlib import Path
from typing import IO, Any

from motorbus.protocol import framelog, la
from motorbus.protocol.base import Command, Direction, Family
from motorbus.protocol.describe import describe
from motorbus.protocol.reassembler import Reassembler

__all__ = ["CSV_HEADER", "SOURCE", "Recorder", "reply_bytes"]

#: The frame log's ``source`` for a dashboard recording.
SOURCE = "dashboard"
#: Columns of ``plots.csv`` (units: the protocol's; temperature in degC).
CSV_HEADER = (
    "t_s",
    "bus",
    "id",
    "position",
    "target",
    "current_ma",
    "force_g",
    "temperature_c",
    "errors",
)


def reply_bytes(value: object) -> bytes | None:
    """The bytes of a decoded reply: its ``raw`` if it kept them, else its ``encode()``."""
    raw = getattr(value, "raw", None)
    if isinstance(raw, bytes | bytearray) and raw:
        return bytes(raw)
    encode = getattr(value, "encode", None)
    if callable(encode):
        out = encode()
        if isinstance(out, bytes):
            return out
    return None


def _file_name(bus: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", bus).strip("_") or "bus"


class _BusLog:
    def __init__(self, fh: IO[str], families: frozenset[Family]) -> None:
        self.fh = fh
        self.families = tuple(sorted(families, key=lambda f: f.value))
        self.frames = 0

    def write(self, t: float, raw: bytes, direction: Direction, family: Family) -> None:
        cutter = Reassembler(direction=direction, families=(family,))
        for item in cutter.feed(raw) + cutter.end_of_stream():
            record = framelog.from_description(t, describe(item, family_hint=family))
            self.fh.write(json.dumps(record, ensure_ascii=False) + "\n")
            self.frames += 1


class Recorder:
    """Writes ``<bus>-frames.jsonl`` for each bus and ``plots.csv`` into ``folder``.

    Args:
        folder: created if missing.
        buses: bus name -> (families on it, baud, port URL).
        t0: the bus-clock time the recording starts at (``t = 0``).
    """

    def __init__(
        self,
        folder: Path,
        buses: dict[str, tuple[frozenset[Family], int, str]],
        t0: float,
    ) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.t0 = t0
        started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
        self.logs: dict[str, _BusLog] = {}
        self.paths: list[Path] = []
        for name, (families, baud, port) in buses.items():
            path = folder / f"{_file_name(name)}-frames.jsonl"
            fh = path.open("a", encoding="utf-8")
            doc = framelog.header(
                SOURCE, started_utc=started, families=families, baud=baud, port=port, bus=name
            )
            fh.write(json.dumps(doc) + "\n")
            self.logs[name] = _BusLog(fh, families)
            self.paths.append(path)
        self.csv_path = folder / "plots.csv"
        new = not self.csv_path.exists()
        self._csv_fh = self.csv_path.open("a", encoding="utf-8", newline="")
        self._csv = csv.writer(self._csv_fh)
        if new:
            self._csv.writerow(CSV_HEADER)
        self.paths.append(self.csv_path)
        self.rows = 0

    def on_write(self, bus: str, cmd: Command[object], at: float) -> None:
        """A frame the bus wrote."""
        log = self.logs.get(bus)
        if log is not None:
            log.write(at - self.t0, cmd.encode(), Direction.REQUEST, cmd.family)

    def on_reply(self, bus: str, cmd: Command[object], value: Any, replied_at: float) -> None:
        """A reply the bus accepted; an LA status also becomes a CSV row."""
        log = self.logs.get(bus)
        raw = reply_bytes(value)
        if log is not None and raw is not None:
            log.write(replied_at - self.t0, raw, Direction.REPLY, cmd.family)
        if isinstance(value, la.Status):
            errors = int(value.errors)
            self._csv.writerow(
                (
                    f"{replied_at - self.t0:.6f}",
                    bus,
                    value.id,
                    value.position,
                    value.target,
                    value.current,
                    value.force,
                    value.temperature,
                    errors,
                )
            )
            self.rows += 1

    def flush(self) -> None:
        """Push what was written to the files."""
        for log in self.logs.values():
            log.fh.flush()
        self._csv_fh.flush()

    def close(self) -> None:
        """Flush and close every file (idempotent)."""
        for log in self.logs.values():
            if not log.fh.closed:
                log.fh.close()
        if not self._csv_fh.closed:
            self._csv_fh.close()
