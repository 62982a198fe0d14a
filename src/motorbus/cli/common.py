"""What the hardware commands share: bus options, opening a bus, ID lists, live output.

Every hardware command takes ``--port URL`` (or the ``MOTORBUS_PORT`` environment
variable), ``--baud`` (default per device family), ``--backend`` and ``--json``.
Input is checked before the port opens, so bad input never puts a byte on the wire.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from collections.abc import AsyncIterator, Iterable
from contextlib import asynccontextmanager
from typing import Any, TextIO

from motorbus.bus.bus import Bus
from motorbus.cli.main import UsageError
from motorbus.cli.realtime_option import add_realtime_option
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int
from motorbus.transport.base import Transport
from motorbus.transport.serial import BACKENDS, DEFAULT_BACKEND, open_transport

__all__ = [
    "LA_BAUD",
    "PORT_ENV",
    "STEPPER_BAUD",
    "LiveText",
    "add_bus_options",
    "add_json_option",
    "check_seconds",
    "open_bus",
    "open_port",
    "parse_ids",
    "print_json",
    "resolve_port",
    "say",
    "step_angle_x100",
]

#: Environment variable that supplies ``--port`` when it is not given.
PORT_ENV = "MOTORBUS_PORT"
#: Factory baud rate of the LA actuators, D-type interface (LA manual 3.1, control table 12).
LA_BAUD = 921600
#: Baud rate of both FF AA stepper controllers (doc 000 A.1; doc 001 A1-01).
STEPPER_BAUD = 9600
#: Host-latency allowance on every reply deadline of the one-shot commands (seconds).
#: The library's 2 ms default suits a tuned streaming loop; a command line tool starts
#: cold (first read of a fresh port, a busy machine, a USB adapter's 1..16 ms latency
#: timer, PLATFORM.md 5) and sends a handful of requests, so it trades a little time
#: for no false timeouts.  ``stream`` keeps the library default: its budget check needs it.
CLI_HOST_MARGIN_S = 0.050
#: Longest duration any CLI option accepts, seconds (one day): a guard against typos
#: such as ``--timeout 1e9``, not a device limit.
MAX_SECONDS = 86400.0


def add_json_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--json`` (print JSON instead of text) to ``parser``."""
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def add_bus_options(
    parser: argparse.ArgumentParser, *, default_baud: int | None, json_option: bool = True
) -> None:
    """Add ``--port``, ``--baud``, ``--backend`` (and ``--json``) to ``parser``.

    Args:
        parser: the command's parser.
        default_baud: the family's usual baud rate in bit/s; ``None`` when the command
            picks it later (``capture`` chooses by ``--family``).
        json_option: also add ``--json``.
    """
    parser.add_argument(
        "--port",
        metavar="URL",
        default=os.environ.get(PORT_ENV),
        help=f"serial port or pyserial URL (default: ${PORT_ENV})",
    )
    baud_help = f"bit/s (default {default_baud})" if default_baud else "bit/s"
    parser.add_argument("--baud", type=int, default=default_baud, help=baud_help)
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default=DEFAULT_BACKEND,
        help=f"serial backend (default {DEFAULT_BACKEND})",
    )
    add_realtime_option(parser)
    if json_option:
        add_json_option(parser)


def resolve_port(args: argparse.Namespace) -> str:
    """Return ``--port`` (or ``$MOTORBUS_PORT``).

    Raises:
        UsageError: neither is set (exit code 2).
    """
    port: str | None = getattr(args, "port", None)
    if not port:
        raise UsageError(f"--port is required (or set {PORT_ENV}): e.g. --port /dev/ttyUSB0")
    return port


def check_seconds(field: str, value: float | None, lo: float = 0.0) -> float | None:
    """Return a duration option if it is a finite number in ``lo..MAX_SECONDS`` (or ``None``).

    Raises:
        LocalProtocolError: naming the option, the value and the allowed range.
    """
    if value is None:
        return None
    if not math.isfinite(value) or not lo <= value <= MAX_SECONDS:
        raise LocalProtocolError(
            f"{field}={value} is out of range: allowed {lo:g}..{MAX_SECONDS:g} s",
            field=field,
            value=value,
        )
    return value


_RANGE = re.compile(r"\s*(\d+)\s*(?:-\s*(\d+))?\s*")


def parse_ids(text: str, field: str = "--ids") -> list[int]:
    """Parse an LA ID list such as ``"1-3,7"`` into ``[1, 2, 3, 7]`` (order kept, no repeats).

    Raises:
        LocalProtocolError: a bad token, an ID outside 1..254, an ID listed twice.
    """
    ids: list[int] = []
    for part in text.split(","):
        m = _RANGE.fullmatch(part)
        if m is None:
            raise LocalProtocolError(
                f"{field}={text!r}: {part!r} is not an ID or a range like 1-15",
                field=field,
                value=text,
            )
        lo = check_int(f"{field} id", int(m.group(1)), la.ID_MIN, la.ID_MAX)
        hi = check_int(f"{field} id", int(m.group(2) or lo), lo, la.ID_MAX)
        ids.extend(range(lo, hi + 1))
    if len(set(ids)) != len(ids):
        raise LocalProtocolError(f"{field}={text!r} lists an ID twice", field=field, value=text)
    return ids


def check_ids(values: Iterable[int], field: str = "id") -> list[int]:
    """Return LA IDs given as integers after checking each is 1..254.

    Raises:
        LocalProtocolError: naming the field, the value and the range.
    """
    return [check_int(field, v, la.ID_MIN, la.ID_MAX) for v in values]


def open_port(args: argparse.Namespace, *, url: str | None = None) -> Transport:
    """Return the (unopened) transport named by ``--port``/``--baud``/``--backend``.

    Raises:
        UsageError: no port, a bad baud rate, or the backend's package is missing.
    """
    port = url if url is not None else resolve_port(args)
    baud = check_int("--baud", args.baud, 1, 10_000_000)
    try:
        return open_transport(port, baudrate=baud, backend=args.backend)
    except ImportError as err:
        raise UsageError(f"--backend {args.backend} is not installed: {err}") from err


@asynccontextmanager
async def open_bus(
    args: argparse.Namespace,
    families: Iterable[Family],
    *,
    host_margin: float = CLI_HOST_MARGIN_S,
) -> AsyncIterator[Bus]:
    """Open a :class:`Bus` on ``--port`` for the given families; close it on the way out.

    The bus does not reconnect: a command line tool should fail fast and say why.

    Args:
        args: the parsed options (``--port``, ``--baud``, ``--backend``).
        families: the device families on the bus.
        host_margin: latency allowance added to every reply deadline, seconds.

    Raises:
        UsageError: see :func:`open_port`.
        OSError: the port cannot be opened (the message names it).
    """
    transport = open_port(args)
    bus = Bus(
        transport,
        name=transport.url,
        families=families,
        host_margin=host_margin,
        reconnect=False,
    )
    try:
        await bus.open()
    except OSError as err:
        raise OSError(f"cannot open port {transport.url}: {_one_line(err)}") from err
    try:
        yield bus
    finally:
        await bus.close()


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__


def say(args: argparse.Namespace, doc: dict[str, Any], text: str) -> None:
    """Report a command's result: ``doc`` as JSON with ``--json``, else the line ``text``."""
    if getattr(args, "json", False):
        print_json(doc)
    else:
        print(text, flush=True)


#: Step angles are stored in 0.01 degree (doc 000 A.4 cmd 01, A0-09; doc 001 section 一).
STEP_ANGLE_SCALE = 100


def step_angle_x100(field: str, degrees: object, maximum: int) -> int:
    """Convert a step angle in degrees (e.g. 1.8) to the stored 0.01-degree integer (180).

    Args:
        field: the option or key named in errors.
        degrees: the angle in degrees, at most two decimals.
        maximum: the largest stored value (255 for both stepper families).

    Raises:
        LocalProtocolError: not a number, more than two decimals, or out of range.
    """
    if isinstance(degrees, bool) or not isinstance(degrees, (int, float)):
        raise LocalProtocolError(
            f"{field}={degrees!r} must be a number of degrees, e.g. 1.8", field=field
        )
    scaled = degrees * STEP_ANGLE_SCALE
    if not math.isfinite(scaled) or abs(scaled - round(scaled)) > 1e-6:
        raise LocalProtocolError(
            f"{field}={degrees} is not a multiple of 0.01 degree (the stored resolution)",
            field=field,
            value=degrees,
        )
    x100 = round(scaled)
    if not 1 <= x100 <= maximum:
        raise LocalProtocolError(
            f"{field}={degrees} is out of range: allowed "
            f"{1 / STEP_ANGLE_SCALE}..{maximum / STEP_ANGLE_SCALE} degrees",
            field=field,
            value=degrees,
        )
    return x100


def print_json(value: Any, out: TextIO | None = None) -> None:
    """Print ``value`` as one JSON document on one line and flush (JSON lines friendly)."""
    stream = out if out is not None else sys.stdout
    stream.write(json.dumps(value, ensure_ascii=False) + "\n")
    stream.flush()


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
