"""The doctor's report: its findings, exit status, text and JSON forms."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from motorbus.doctor.checks import Finding, Level

__all__ = ["SCHEMA", "DoctorReport"]

#: ``schema`` of the JSON form; bumped when a key changes meaning.
SCHEMA = "motorbus-doctor/1"

_TAGS = {Level.GREEN: "green ", Level.YELLOW: "yellow", Level.RED: "red   ", Level.SKIP: "skip  "}
_COLOURS = {Level.GREEN: "32", Level.YELLOW: "33", Level.RED: "31", Level.SKIP: "2"}


@dataclass(slots=True)
class DoctorReport:
    """What :func:`motorbus.doctor.diagnose` found on one bus.

    Attributes:
        target: the port URL (and bus name, from a bus file).
        baud: the configured rate, bit/s.
        period_s: the stream period the budget was computed for.
        findings: one per check, in the order they ran.
        read_only: nothing that moves or changes a setting was sent.
    """

    target: str
    baud: int
    period_s: float
    findings: list[Finding] = field(default_factory=list)
    read_only: bool = True

    @property
    def worst(self) -> Level:
        levels = {f.level for f in self.findings}
        for level in (Level.RED, Level.YELLOW):
            if level in levels:
                return level
        return Level.GREEN

    @property
    def exit_code(self) -> int:
        """0 when nothing is red, else 1."""
        return 1 if self.worst is Level.RED else 0

    def finding(self, check: str) -> Finding:
        """The finding of ``check`` (``KeyError`` if it did not run)."""
        for f in self.findings:
            if f.check == check:
                return f
        raise KeyError(check)

    def by_level(self, level: Level) -> list[Finding]:
        return [f for f in self.findings if f.level is level]

    def as_dict(self) -> dict[str, Any]:
        """The JSON form (``schema`` names its version)."""
        return {
            "schema": SCHEMA,
            "target": self.target,
            "baud": self.baud,
            "period_ms": self.period_s * 1e3,
            "read_only": self.read_only,
            "worst": self.worst.value,
            "exit_code": self.exit_code,
            "checks": [f.as_dict() for f in self.findings],
        }

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), indent=2, default=str)

    def format_text(self, *, colour: bool = False) -> str:
        """One line per check: level, name, summary, and for red/yellow what to do."""
        width = max((len(f.check) for f in self.findings), default=5)
        head = f"motorbus doctor: {self.target} at {self.baud} bit/s"
        lines = [f"{head}, period {self.period_s * 1e3:g} ms"]
        for f in self.findings:
            tag = _TAGS[f.level]
            if colour:
                tag = f"\x1b[{_COLOURS[f.level]}m{tag}\x1b[0m"
            line = f"{tag} {f.check:<{width}}  {f.summary}"
            if f.fix and f.level in (Level.RED, Level.YELLOW):
                line += f"  -> {f.fix}"
            lines.append(line)
        red, yellow = len(self.by_level(Level.RED)), len(self.by_level(Level.YELLOW))
        lines.append(f"{red} red, {yellow} yellow, exit {self.exit_code}")
        return "\n".join(lines)
