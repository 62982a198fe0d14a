"""What the hardware commands share: bus options, opening a bus, ID lists, live output.

Every hardware command takes ``--port URL``, ``--baud`` (default per device family),
``--backend`` and ``--json``, or ``--bus-file F --bus NAME`` to take them from one
``[[bus]]`` table of a BusManager TOML file.  Each setting comes from the first of:
the command line, the environment (``MOTORBUS_PORT``, ``MOTORBUS_BAUD``,
``MOTORBUS_BACKEND``; ``MOTORBUS_BUS_FILE``, ``MOTORBUS_BUS``), the bus file (default
``$XDG_CONFIG_HOME/motorbus/buses.toml``, i.e. ``~/.config/motorbus/buses.toml``).
Input is checked before the port opens, so bad input never puts a byte on the wire.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import tomllib
from collections.abc import AsyncIterator, Iterable, Mapping
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, TextIO

from motorbus import BACKENDS, DEFAULT_BACKEND, Bus, Transport, open_transport
from motorbus.cli.main import UsageError
from motorbus.cli.realtime_option import add_realtime_option
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int
from motorbus.protocol.families import LA_DEFAULT_BAUD, STEPPER_DEFAULT_BAUD
from motorbus.protocol.ids import IdListError, parse_id_list

__all__ = [
    "BACKEND_ENV",
    "BAUD_ENV",
    "BUS_ENV",
    "BUS_FILE_ENV",
    "ENV_VARS",
    "LA_BAUD",
    "PORT_ENV",
    "STEPPER_BAUD",
    "LiveText",
    "add_bus_options",
    "add_guard_option",
    "add_ids_argument",
    "add_json_option",
    "check_seconds",
    "open_bus",
    "open_port",
    "parse_id_args",
    "parse_ids",
    "plural",
    "print_json",
    "resolve_port",
    "say",
    "step_angle_x100",
]

#: Environment variable that supplies ``--port`` when it is not given.
PORT_ENV = "MOTORBUS_PORT"
#: ... ``--baud``.
BAUD_ENV = "MOTORBUS_BAUD"
#: ... ``--backend``.
BACKEND_ENV = "MOTORBUS_BACKEND"
#: ... ``--bus-file``.
BUS_FILE_ENV = "MOTORBUS_BUS_FILE"
#: ... ``--bus``.
BUS_ENV = "MOTORBUS_BUS"
#: Every environment variable the bus options read.
ENV_VARS = (PORT_ENV, BAUD_ENV, BACKEND_ENV, BUS_FILE_ENV, BUS_ENV)
#: Factory baud rate of the LA actuators (the family registry, protocol/families.py).
LA_BAUD = LA_DEFAULT_BAUD
#: Baud rate of both FF AA stepper controllers (the family registry).
STEPPER_BAUD = STEPPER_DEFAULT_BAUD
#: Host-latency allowance on every reply deadline of the one-shot commands (seconds).
#: The library's 2 ms default suits a tuned streaming loop; a command line tool starts
#: cold (first read of a fresh port, a busy machine, a USB adapter's 1..16 ms latency
#: timer, docs/platform.md 5) and sends a handful of requests, so it trades a little time
#: for no false timeouts.  ``stream`` keeps the library default: its budget check needs it.
CLI_HOST_MARGIN_S = 0.050
#: Longest duration any CLI option accepts, seconds (one day): a guard against typos
#: such as ``--timeout 1e9``, not a device limit.
MAX_SECONDS = 86400.0


def add_json_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--json`` (print JSON instead of text) to ``parser``."""
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


GUARD_HELP = (
    "start a guard process (Linux) that sends the safe action to every device this "
    "command moves if the command is killed outright (SIGKILL, the OOM killer); "
    "see motorbus.guard"
)


def add_guard_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--guard`` to a command that moves things (``main`` starts the guard)."""
    parser.add_argument("--guard", action="store_true", help=GUARD_HELP)


def add_bus_options(
    parser: argparse.ArgumentParser, *, default_baud: int | None, json_option: bool = True
) -> None:
    """Add ``--port``, ``--baud``, ``--backend``, ``--bus-file``, ``--bus`` (and ``--json``).

    The values are resolved later, by :func:`resolve_port`: an option left out is
    taken from the environment, then from the bus file, then from the defaults.

    Args:
        parser: the command's parser.
        default_baud: the family's usual baud rate in bit/s; ``None`` when the command
            picks it later (``capture`` chooses by ``--family``).
        json_option: also add ``--json``.
    """
    parser.add_argument(
        "--port",
        metavar="URL",
        help=f"serial port or pyserial URL (default: ${PORT_ENV}, then the bus file)",
    )
    baud_help = f"bit/s (default: ${BAUD_ENV}, the bus file, then {default_baud})"
    if not default_baud:
        baud_help = f"bit/s (default: ${BAUD_ENV}, the bus file, then the family's rate)"
    parser.add_argument("--baud", type=int, help=baud_help)
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        help=f"serial backend (default: ${BACKEND_ENV}, the bus file, then {DEFAULT_BACKEND})",
    )
    parser.add_argument(
        "--bus-file",
        metavar="FILE",
        help=f"BusManager TOML file to take url, baud and backend from (default: "
        f"${BUS_FILE_ENV}, then ~/.config/motorbus/buses.toml if it exists)",
    )
    parser.add_argument(
        "--bus",
        metavar="NAME",
        help=f"the [[bus]] table of the bus file to use (default: ${BUS_ENV}; "
        "needed if the file has several)",
    )
    add_realtime_option(parser)
    parser.set_defaults(_default_baud=default_baud)
    if json_option:
        add_json_option(parser)


def _bus_table(args: argparse.Namespace, *, port_given: bool) -> Mapping[str, Any] | None:
    """The ``[[bus]]`` table chosen by ``--bus-file``/``--bus`` (or their defaults).

    A file named by ``--bus-file`` (or ``$MOTORBUS_BUS_FILE``) always applies; the
    user's default file only when a bus is named or no port is given otherwise, so
    its baud rate never silently applies to a port typed on the command line.

    Raises:
        UsageError: the file is missing, not TOML, or has no such bus (exit code 2).
    """
    from motorbus import default_bus_file  # imported when needed: anyio & co.

    explicit = getattr(args, "bus_file", None) or os.environ.get(BUS_FILE_ENV)
    name = getattr(args, "bus", None) or os.environ.get(BUS_ENV)
    if not explicit and port_given and not name:
        return None
    path = Path(explicit) if explicit else default_bus_file()
    if path is None or not path.is_file():
        if explicit:
            raise UsageError(f"--bus-file {path}: no such file")
        if name:
            raise UsageError(
                f"--bus {name}: no bus file: give --bus-file or create {_user_file_hint()}"
            )
        return None  # the default user file is optional
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise UsageError(f"{path}: not valid TOML: {err}") from err
    except OSError as err:
        raise UsageError(f"{path}: cannot read: {_one_line(err)}") from err
    tables = data.get("bus")
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise UsageError(f"{path}: needs [[bus]] tables (name, url, baud, backend, ...)")
    names = [str(t.get("name", f"bus{i}")) for i, t in enumerate(tables)]
    if name:
        if name not in names:
            raise UsageError(
                f"--bus {name}: {path} has no such bus: choose one of {', '.join(names)}"
            )
        table: Mapping[str, Any] = tables[names.index(name)]
        return table
    if len(tables) == 1:
        only: Mapping[str, Any] = tables[0]
        return only
    if explicit:
        raise UsageError(f"{path} has {len(tables)} buses: choose one with --bus {'|'.join(names)}")
    return None  # a user file with several buses only applies when one is named


def _user_file_hint() -> str:
    return "~/.config/motorbus/buses.toml"


def resolve_port(args: argparse.Namespace) -> str:
    """Fill in ``args.port``, ``args.baud`` and ``args.backend``; return the port.

    Each comes from the command line, else the environment, else the bus file
    (``--bus-file``/``--bus``), else the default (baud: the family's; backend: fast).

    Raises:
        UsageError: no port anywhere, a bad ``$MOTORBUS_BAUD``/``$MOTORBUS_BACKEND``,
            or a bad bus file (exit code 2).
    """
    port: str | None = getattr(args, "port", None) or os.environ.get(PORT_ENV)
    table = _bus_table(args, port_given=bool(port))
    file_values: Mapping[str, Any] = table or {}
    if not port and "url" in file_values:
        port = str(file_values["url"])
    if not port:
        raise UsageError(
            f"--port is required (or set {PORT_ENV}, or use --bus-file): e.g. --port /dev/ttyUSB0"
        )
    args.port = port
    if getattr(args, "baud", None) is None:
        env_baud = os.environ.get(BAUD_ENV)
        if env_baud:
            try:
                args.baud = int(env_baud)
            except ValueError:
                raise UsageError(f"{BAUD_ENV}={env_baud!r} is not an integer bit rate") from None
        elif "baud" in file_values:
            args.baud = file_values["baud"]
        else:
            args.baud = getattr(args, "_default_baud", None)
    if getattr(args, "backend", None) is None:
        backend = os.environ.get(BACKEND_ENV) or file_values.get("backend") or DEFAULT_BACKEND
        if backend not in BACKENDS:
            allowed = ", ".join(BACKENDS)
            raise UsageError(f"backend={backend!r} is not allowed: choose one of {allowed}")
        args.backend = str(backend)
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


def parse_ids(
    text: str, field: str = "--ids", lo: int = la.ID_MIN, hi: int = la.ID_MAX
) -> list[int]:
    """Parse an ID list such as ``"1-3,7"`` into ``[1, 2, 3, 7]`` (order kept, no repeats).

    Args:
        text: comma-separated IDs and ranges ``A-B`` (``A <= B``).
        field: the option or argument named in errors.
        lo, hi: the allowed IDs (LA actuators: 1..254).

    Raises:
        LocalProtocolError: a bad token, a reversed range, an ID outside ``lo..hi``,
            an ID listed twice.
    """
    id_field = field if field == "id" else f"{field} id"
    try:
        return parse_id_list(text, lo=lo, hi=hi, id_field=id_field)
    except IdListError as err:
        if err.problem == "range":
            raise  # "--ids id=255 is out of range: allowed 1..254"
        sep = " " if err.problem == "duplicate" else ": "
        raise LocalProtocolError(
            f"{field}={text!r}{sep}{err.reason}", field=field, value=text
        ) from None


def parse_id_args(values: Iterable[str], field: str = "id") -> list[int]:
    """Join ID arguments such as ``["1-3", "7,9", "12"]`` into one list (see :func:`parse_ids`).

    Raises:
        LocalProtocolError: a bad token or range, an ID out of range or listed twice.
    """
    ids: list[int] = []
    for value in values:
        ids.extend(parse_ids(value, field))
    return parse_ids(",".join(map(str, ids)), field) if ids else ids


def add_ids_argument(parser: argparse.ArgumentParser) -> None:
    """Add the positional ``ID...`` of a multi-actuator command (``1 2 3``, ``1-3,7``)."""
    parser.add_argument(
        "ids",
        metavar="ID",
        nargs="+",
        help="actuator IDs 1..254: one or more of 3, 1,2,3 or 1-3,7",
    )


def plural(n: int, word: str, many: str | None = None) -> str:
    """``1 timeout``, ``2 timeouts``: a count with its noun in the right number."""
    return f"{n} {word if n == 1 else (many or word + 's')}"


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
        raise OSError(port_error(transport.url, err, args.baud)) from err
    try:
        yield bus
    finally:
        await bus.close()


_ERRNO_TEXT = re.compile(r"\[Errno -?\d+\] ([^:\]]+)")


def port_error(url: str, err: BaseException, baud: int | None) -> str:
    """One line saying why ``url`` did not open, which ports exist, and what to check.

    pyserial nests its errors (``could not open port X: [Errno 2] could not open port
    X: [Errno 2] No such file or directory: 'X'``); the innermost reason is enough.
    """
    reasons = _ERRNO_TEXT.findall(str(err))
    reason = reasons[-1].strip() if reasons else _one_line(err)
    if isinstance(err, OSError) and err.strerror and not reasons:
        reason = err.strerror
    return f"cannot open port {url}: {reason}; {available_ports()}"


def available_ports() -> str:
    """``available ports: /dev/ttyUSB0 (FT232R), ...`` or ``no serial ports found``."""
    try:
        from serial.tools import list_ports

        found = sorted(list_ports.comports(), key=lambda p: p.device)
    except Exception:  # a listing failure must not hide the real error
        found = []
    if not found:
        return "no serial ports found on this machine"
    names = [
        f"{p.device} ({p.description})" if p.description and p.description != "n/a" else p.device
        for p in found
    ]
    return "available ports: " + ", ".join(names)


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
