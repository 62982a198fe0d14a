"""``motorbus decode``: describe the frames in hex dumped from a bus.

Example::

    $ motorbus decode 55 AA 04 01 21 37 14 05 76
    la request MoveTo id=1 position=1300 reply=True  [55 AA 04 01 21 37 14 05 76]

Hex comes from the arguments or, if there are none, from standard input, one chunk a
line (spaces optional; the three families may be mixed).  Every frame, ``EE DD`` event
and run of garbage becomes one line, or one JSON object a line with ``--json``.
Opcodes and command bytes are shown in hex in text lines (opcode=0x5E); JSON keeps
them as integers.  Garbage is reported, not an error: the exit status is 0 unless the
input is not hex (2).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Iterable, Iterator
from typing import Any, TextIO

from motorbus.protocol import la
from motorbus.protocol.base import (
    FF_AA,
    LA_REPLY_HEADER,
    LA_REQUEST_HEADER,
    Direction,
    Family,
    parse_hex,
    sum8,
)
from motorbus.protocol.describe import KIND_GARBAGE, Description, describe
from motorbus.protocol.reassembler import Discarded, Item, Reassembler

__all__ = ["GarbageJoiner", "add_arguments", "decode_lines", "register", "run", "text_line"]

#: Fields that hold an opcode or a command byte: shown as 0x.. in text lines.
HEX_FIELDS = frozenset({"opcode", "command", "cmd", "sub"})

#: ``--direction`` values; ``any`` lets the reassembler look for requests and replies.
DIRECTION_ANY = "any"
_DIRECTIONS = {
    DIRECTION_ANY: None,
    Direction.REQUEST.value: Direction.REQUEST,
    Direction.REPLY.value: Direction.REPLY,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``decode`` arguments and options to ``parser``."""
    parser.add_argument(
        "hex",
        metavar="HEX",
        nargs="*",
        help="bytes in hex, e.g. '55 AA 04 01 21 37 14 05 76' or 55aa0401; "
        "read from standard input if none are given",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object per line")
    parser.add_argument(
        "--family",
        choices=[f.value for f in Family],
        help="the only family on the stream; tells look-alike FF AA replies apart (A0-05)",
    )
    parser.add_argument(
        "--direction",
        choices=list(_DIRECTIONS),
        default=DIRECTION_ANY,
        help="which way the bytes travel (default: any)",
    )


def register(subparsers: Any) -> None:
    """Add the ``decode`` command to an ``argparse`` subparsers object."""
    parser = subparsers.add_parser(
        "decode",
        help="describe frames given in hex",
        description="Describe every frame, event and run of garbage in hex input.",
    )
    add_arguments(parser)
    parser.set_defaults(func=run)


class GarbageJoiner:
    """Joins consecutive discarded runs into one, so a run of garbage prints as one line.

    The reassembler splits a run where its reason changes (a header with a bad checksum
    costs one byte, then plain garbage follows) and at ``feed`` boundaries; a reader
    wants one run with every reason.
    """

    def __init__(self) -> None:
        self._pending: Discarded | None = None

    def push(self, items: Iterable[Item]) -> Iterator[Item]:
        """Yield the items that are settled; a trailing garbage run is held back."""
        for item in items:
            if isinstance(item, Discarded):
                self._pending = self._join(self._pending, item)
                continue
            if self._pending is not None:
                yield self._pending
                self._pending = None
            yield item

    def flush(self) -> Iterator[Item]:
        """Yield the garbage run still held back, if any (call at end of input)."""
        if self._pending is not None:
            yield self._pending
            self._pending = None

    @staticmethod
    def _join(first: Discarded | None, second: Discarded) -> Discarded:
        if first is None:
            return second
        reasons = first.reason.split("; ")
        if second.reason not in reasons:
            reasons.append(second.reason)
        return Discarded(first.raw + second.raw, "; ".join(reasons))


def decode_lines(
    lines: Iterable[str],
    *,
    family: Family | None = None,
    direction: Direction | None = None,
    number_lines: bool = True,
) -> Iterator[Description]:
    """Describe everything in hex ``lines``, yielding each item as soon as it is complete.

    Args:
        lines: hex text, one chunk a line (a line may hold several frames or part of one).
        family: the only family on the stream, or ``None`` for all three.
        direction: ``REQUEST``, ``REPLY`` or ``None`` for both.
        number_lines: name the line in error messages (off for command-line arguments).

    Raises:
        ValueError: a line is not hex; the message names the bad token (and the line).
    """
    families = (family,) if family is not None else tuple(Family)
    reassembler = Reassembler(direction=direction, families=families)
    joiner = GarbageJoiner()
    for number, line in enumerate(lines, start=1):
        try:
            data = parse_hex(line)
        except ValueError as err:
            if not number_lines:
                raise
            raise ValueError(f"line {number}: {err}") from err
        for item in joiner.push(reassembler.feed(data)):
            yield describe(item, family_hint=family)
    for item in joiner.push(reassembler.end_of_stream()):
        yield describe(item, family_hint=family)
    for item in joiner.flush():
        yield describe(item, family_hint=family)


def text_line(description: Description) -> str:
    """``description`` as one line, with opcodes and command bytes in hex (``opcode=0x5E``)."""
    fields = {
        key: f"0x{value:02X}"
        if key in HEX_FIELDS and isinstance(value, int) and not isinstance(value, bool)
        else value
        for key, value in description.fields.items()
    }
    return dataclasses.replace(description, fields=fields).to_line()


def checksum_hint(raw: bytes) -> str | None:
    """For a run discarded for a bad checksum: the checksum found and the one expected.

    Looks at a frame header at the start of ``raw``: an LA frame (``55 AA``/``AA 55``,
    its length byte, the sum of Len..DN) or a 9- or 11-byte ``FF AA`` stepper request
    (the sum of every byte before the checksum).  ``None`` if no header there fits.
    """
    if raw[:2] in (LA_REQUEST_HEADER, LA_REPLY_HEADER) and len(raw) >= 3:
        size = raw[2] + 5
        if len(raw) >= size:
            want = la.la_checksum(raw[: size - 1])
            if want != raw[size - 1]:
                return f"la checksum {raw[size - 1]:02X}, expected {want:02X}"
    if raw[:2] == FF_AA:
        for size in (11, 9):
            if len(raw) >= size and sum8(raw[: size - 1]) != raw[size - 1]:
                want = sum8(raw[: size - 1])
                return (
                    f"{size}-byte FF AA request checksum {raw[size - 1]:02X}, expected {want:02X}"
                )
    return None


def _with_hint(description: Description) -> Description:
    if description.kind != KIND_GARBAGE or "bad checksum" not in (description.reason or ""):
        return description
    hint = checksum_hint(parse_hex(description.hex))
    if hint is None:
        return description
    return dataclasses.replace(description, reason=f"{description.reason}: {hint}")


def run(args: argparse.Namespace, stdin: TextIO | None = None) -> int:
    """Run ``motorbus decode``; return the exit status (0).

    Raises:
        ValueError: the input is not hex (``main`` prints it and exits with 2).
    """
    source: Iterable[str] = stdin if stdin is not None else sys.stdin
    lines = [" ".join(args.hex)] if args.hex else source
    family = Family(args.family) if args.family else None
    out = sys.stdout
    descriptions = decode_lines(
        lines,
        family=family,
        direction=_DIRECTIONS[args.direction],
        number_lines=not args.hex,
    )
    for description in map(_with_hint, descriptions):
        if args.json:
            out.write(json.dumps(description.to_json(), ensure_ascii=False) + "\n")
        else:
            out.write(text_line(description) + "\n")
        # A live pipe (a sniffer feeding stdin) should see each frame as it completes.
        out.flush()
    return 0
