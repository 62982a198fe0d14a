"""What the commands print: JSON lines, one-line results, counts, live text blocks."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, TextIO

__all__ = ["LiveText", "add_json_option", "error_doc", "fail", "plural", "print_json", "say"]


def add_json_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--json`` (print JSON instead of text) to ``parser``."""
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def plural(n: int, word: str, many: str | None = None) -> str:
    """``1 timeout``, ``2 timeouts``: a count with its noun in the right number."""
    return f"{n} {word if n == 1 else (many or word + 's')}"


def say(args: argparse.Namespace, doc: dict[str, Any], text: str) -> None:
    """Report a command's result: ``doc`` as JSON with ``--json``, else the line ``text``."""
    if getattr(args, "json", False):
        print_json(doc)
    else:
        print(text, flush=True)


def print_json(value: Any, out: TextIO | None = None) -> None:
    """Print ``value`` as one JSON document on one line and flush (JSON lines friendly)."""
    stream = out if out is not None else sys.stdout
    stream.write(json.dumps(value, ensure_ascii=False) + "\n")
    stream.flush()


def error_doc(command: str | None, message: str, code: int, **concerns: Any) -> dict[str, Any]:
    """The JSON object of a failure: ``error`` (the message), ``code`` (the exit code),
    ``command``, then what it concerns (``port``, ``file``, ``field`` and ``value``,
    ``ids``...; a value JSON cannot hold is given as text, ``None`` left out)."""
    doc: dict[str, Any] = {"error": message, "code": code, "command": command}
    for key, value in concerns.items():
        if value is None:
            continue
        if not isinstance(value, (str, int, float, bool, list, dict)):
            value = str(value)
        doc[key] = value
    return doc


def fail(args: argparse.Namespace, message: str, *, code: int = 1, **concerns: Any) -> int:
    """Report that the command failed, and return ``code``.

    One line ``motorbus COMMAND: message`` on standard error; with ``--json`` also one
    JSON object on standard output (:func:`error_doc`), so that a program reading the
    output sees the failure, its exit code and what it concerns (docs/cli.md).
    """
    command = getattr(args, "command", None)
    print(f"motorbus {command}: {message}", file=sys.stderr, flush=True)
    if getattr(args, "json", False):
        print_json(error_doc(command, message, code, **concerns))
    return code


class LiveText:
    """A block of text redrawn in place on a terminal, printed as plain lines elsewhere.

    Args:
        out: where to write (default standard error).
        tty: force terminal behaviour on or off (default: ``out.isatty()``).
    """

    def __init__(self, out: TextIO | None = None, *, tty: bool | None = None) -> None:
        self.out = out if out is not None else sys.stderr
        self.tty = self.out.isatty() if tty is None else tty
        self._drawn = 0

    def show(self, lines: list[str]) -> None:
        """Draw ``lines``: over the previous block on a terminal, appended otherwise."""
        if self.tty and self._drawn:
            # Cursor up to the first line of the previous block, then clear to the end.
            self.out.write(f"\x1b[{self._drawn}F\x1b[J")
        self.out.write("\n".join(lines) + "\n")
        self.out.flush()
        self._drawn = len(lines)

    def done(self) -> None:
        """Keep what is drawn; the next ``show`` starts a new block."""
        self._drawn = 0
