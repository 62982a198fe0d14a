"""The bus options of the hardware commands, and opening the bus they name.

Every hardware command takes ``--port URL``, ``--baud`` (default per device family),
``--backend`` and ``--json``, or ``--bus-file F --bus NAME`` to take them from one
``[[bus]]`` table of a bus file.  Each setting comes from the first of: the command
line, the environment (``MOTORBUS_PORT``, ``MOTORBUS_BAUD``, ``MOTORBUS_BACKEND``;
``MOTORBUS_BUS_FILE``, ``MOTORBUS_BUS``), the bus file (default
``$XDG_CONFIG_HOME/motorbus/buses.toml``, i.e. ``~/.config/motorbus/buses.toml``).

The bus file is read by the library's own reader (:mod:`motorbus.busfile`): the whole
file is checked as ``BusManager.from_toml`` checks it (a typo or a bad value exits 2
with the file, the bus, the key, the value and what is allowed), and the chosen bus
opens with every key its table sets: ``rs485``, ``remove_echo``, ``low_latency``,
``share``, ``min_spacing_ms``, ``host_margin_ms``, ``retries``.  Input is checked
before the port opens, so bad input never puts a byte on the wire.

The commands that serve buses for a while (``stream``, ``monitor``, ``dashboard``) also
take ``--process NAME``: the bus is chosen among that process group's buses (the only
one needs no ``--bus``), and the command runs on the group's ``cpus`` while its bus is
open (:mod:`motorbus.runtime.process_groups`).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
from collections.abc import AsyncIterator, Iterable
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any, cast

import motorbus
from motorbus import (
    BACKENDS,
    DEFAULT_BACKEND,
    DEFAULT_HOST_MARGIN_S,
    Bus,
    Transport,
    open_transport,
)
from motorbus.cli.main import UsageError
from motorbus.cli.output import add_json_option
from motorbus.cli.realtime_option import add_realtime_option
from motorbus.errors import PortInUseError
from motorbus.protocol.base import BAUD_MAX, BAUD_MIN, Family, check_int
from motorbus.protocol.families import LA_DEFAULT_BAUD, STEPPER_DEFAULT_BAUD
from motorbus.runtime import realtime

if TYPE_CHECKING:
    from motorbus import BusSpec, ProcessGroup

__all__ = [
    "BACKEND_ENV",
    "BAUD_ENV",
    "BUS_ENV",
    "BUS_FILE_ENV",
    "CLI_HOST_MARGIN_S",
    "ENV_VARS",
    "LA_BAUD",
    "PORT_ENV",
    "STEPPER_BAUD",
    "add_bus_options",
    "add_guard_option",
    "add_process_option",
    "available_ports",
    "bus_timing",
    "chosen_bus",
    "open_bus",
    "open_port",
    "port_error",
    "resolve_port",
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
#: ``MOTORBUS_HOST_MARGIN_MS`` raises it too, when it asks for more (it is "every bus" of
#: the program, docs/hardware.md); a bus file's ``host_margin_ms`` replaces it.
CLI_HOST_MARGIN_S = max(0.050, DEFAULT_HOST_MARGIN_S)
#: Where :func:`resolve_port` keeps the chosen ``[[bus]]`` (a ``BusSpec``) on ``args``,
#: and the keys its table sets.
_SPEC_ATTR = "bus_spec"
_GIVEN_ATTR = "bus_keys"
#: ... and the process group ``--process`` chose (a ``ProcessGroup``).
_GROUP_ATTR = "process_group"


GUARD_HELP = (
    "start a guard process (Linux) that sends the safe action to every device this "
    "command moves if the command is killed outright (SIGKILL, the OOM killer); "
    "see motorbus.runtime.guard"
)


def add_guard_option(parser: argparse.ArgumentParser, help_text: str = GUARD_HELP) -> None:
    """Add ``--guard`` to a command that moves things, or leaves a device unsafe if it
    is killed part way (``project upload``); ``main`` starts the guard."""
    parser.add_argument("--guard", action="store_true", help=help_text)


def add_process_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--process NAME``: serve a process group of the bus file, on its CPUs."""
    parser.add_argument(
        "--process",
        metavar="NAME",
        help="the process group of the bus file to serve: its buses only ([[bus]] process = "
        "NAME), and run on its CPUs ([process.NAME] cpus) while they are open",
    )


def add_bus_options(
    parser: argparse.ArgumentParser,
    *,
    default_baud: int | None,
    json_option: bool = True,
    connect: bool = False,
) -> None:
    """Add ``--port``, ``--baud``, ``--backend``, ``--bus-file``, ``--bus`` (and ``--json``).

    The values are resolved later, by :func:`resolve_port`: an option left out is
    taken from the environment, then from the bus file, then from the defaults.

    Args:
        parser: the command's parser.
        default_baud: the family's usual baud rate in bit/s; ``None`` when the command
            picks it later (``capture`` chooses by ``--family``).
        json_option: also add ``--json``.
        connect: also add ``--connect ENDPOINT``: use a bus that ``motorbus serve``
            serves there (``--bus NAME`` where it serves several) instead of a port.
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
        help=f"bus file (TOML) whose [[bus]] table gives the port and every bus option "
        f"(default: ${BUS_FILE_ENV}, then ~/.config/motorbus/buses.toml if it exists)",
    )
    parser.add_argument(
        "--bus",
        metavar="NAME",
        help=f"the [[bus]] table of the bus file to use (default: ${BUS_ENV}; "
        "needed if the file has several)",
    )
    if connect:
        parser.add_argument(
            "--connect",
            metavar="ENDPOINT",
            help="use the bus a `motorbus serve` serves at this Zenoh endpoint "
            "(e.g. tcp/127.0.0.1:7447; --bus NAME where it serves several)",
        )
    add_realtime_option(parser)
    parser.set_defaults(_default_baud=default_baud)
    if json_option:
        add_json_option(parser)


def chosen_bus(
    args: argparse.Namespace, *, port_given: bool
) -> tuple[BusSpec, frozenset[str]] | None:
    """The ``[[bus]]`` chosen by ``--bus-file``/``--bus`` (or their defaults) and the keys
    its table sets, or ``None`` when no bus file applies.

    A file named by ``--bus-file`` (or ``$MOTORBUS_BUS_FILE``) always applies; the
    user's default file only when a bus is named or no port is given otherwise, so
    its baud rate never silently applies to a port typed on the command line.  The
    whole file is checked, by the library's reader.

    Raises:
        UsageError: the file is missing or unreadable, or has no such bus (exit code 2).
        LocalProtocolError: the file is not UTF-8 or not TOML, or a key of any bus is
            unknown, of the wrong type or out of range (exit code 2; the message names
            the file, the bus, the key, the value and what is allowed).
    """
    explicit = getattr(args, "bus_file", None) or os.environ.get(BUS_FILE_ENV)
    name = getattr(args, "bus", None) or os.environ.get(BUS_ENV)
    process = getattr(args, "process", None)
    if not explicit and port_given and not name and not process:
        return None
    # The bus file reader (tomllib, every family's checks) only when a file may apply:
    # ``motorbus la status 1 --port P`` starts without it.
    from pathlib import Path

    from motorbus import default_bus_file, load_bus_file

    path = Path(explicit) if explicit else default_bus_file()
    if path is None or not path.is_file():
        if explicit:
            raise UsageError(f"--bus-file {path}: no such file")
        for option, value in (("--bus", name), ("--process", process)):
            if value:
                raise UsageError(
                    f"{option} {value}: no bus file: give --bus-file or create {_USER_FILE_HINT}"
                )
        return None  # the default user file is optional
    try:
        # A calibration file not yet written must not stop ``la calibrate`` writing it.
        bus_file = load_bus_file(path, missing_calibration_ok=True)
    except OSError as err:
        raise UsageError(f"{path}: cannot read: {_one_line(err)}") from err
    names = bus_file.names()
    among = f"{path} has"
    if process:
        group = bus_file.group(process)  # no such group: exit 2, naming the groups
        setattr(args, _GROUP_ATTR, group)
        names = list(group.buses)
        among = f"process group {process} of {path} has"
    if name:
        if name not in names:
            raise UsageError(f"--bus {name}: {among} no such bus: choose one of {', '.join(names)}")
        spec = bus_file.spec(name)
    elif len(names) == 1:
        spec = bus_file.spec(names[0])
    elif explicit or process:
        raise UsageError(f"{among} {len(names)} buses: choose one with --bus {'|'.join(names)}")
    else:
        return None  # a user file with several buses only applies when one is named
    return spec, bus_file.given[spec.name]


_USER_FILE_HINT = "~/.config/motorbus/buses.toml"


def resolve_port(args: argparse.Namespace) -> str:
    """Fill in ``args.port``, ``args.baud`` and ``args.backend``; return the port.

    Each comes from the command line, else the environment, else the bus file
    (``--bus-file``/``--bus``), else the default (baud: the family's; backend: fast).
    The chosen bus (a ``BusSpec``) is kept on ``args`` for :func:`open_port` and
    :func:`open_bus`, which apply its other keys.

    Raises:
        UsageError: no port anywhere, a bad ``$MOTORBUS_BAUD``/``$MOTORBUS_BACKEND``,
            or a missing bus file or bus (exit code 2).
        LocalProtocolError: a bad bus file (exit code 2).
    """
    port: str | None = getattr(args, "port", None) or os.environ.get(PORT_ENV)
    chosen = chosen_bus(args, port_given=bool(port))
    spec, given = chosen if chosen is not None else (None, frozenset[str]())
    setattr(args, _SPEC_ATTR, spec)
    setattr(args, _GIVEN_ATTR, given)
    if not port and spec is not None:
        port = spec.url
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
        elif spec is not None:
            args.baud = spec.baud
        else:
            args.baud = getattr(args, "_default_baud", None)
    if getattr(args, "backend", None) is None:
        backend = os.environ.get(BACKEND_ENV) or (
            spec.backend if spec is not None and "backend" in given else DEFAULT_BACKEND
        )
        if backend not in BACKENDS:
            allowed = ", ".join(BACKENDS)
            raise UsageError(f"backend={backend!r} is not allowed: choose one of {allowed}")
        args.backend = str(backend)
    return port


def _spec(args: argparse.Namespace) -> tuple[BusSpec | None, frozenset[str]]:
    return getattr(args, _SPEC_ATTR, None), getattr(args, _GIVEN_ATTR, frozenset())


def open_port(args: argparse.Namespace, *, url: str | None = None) -> Transport:
    """Return the (unopened) transport named by ``--port``/``--baud``/``--backend``, with
    the chosen bus file table's ``rs485``, ``remove_echo``, ``low_latency`` and ``share``.

    Raises:
        UsageError: no port, a bad baud rate, or the backend's package is missing.
    """
    port = url if url is not None else resolve_port(args)
    baud = check_int("--baud", args.baud, BAUD_MIN, BAUD_MAX)
    spec, _ = _spec(args)
    options: dict[str, Any] = spec.transport_options() if spec is not None else {}
    try:
        return open_transport(port, baudrate=baud, backend=args.backend, **options)
    except ImportError as err:
        raise UsageError(f"--backend {args.backend} is not installed: {err}") from err


def with_cli_margin(
    spec: BusSpec, given: frozenset[str], host_margin: float = CLI_HOST_MARGIN_S
) -> BusSpec:
    """``spec`` as a command line tool opens it: with its table's ``host_margin_ms`` if
    the table sets one, else with ``host_margin`` (seconds; ``CLI_HOST_MARGIN_S``), not
    the library's default.  ``given``: the keys the table set (``BusFile.given``)."""
    if "host_margin_ms" in given:
        return spec
    return dataclasses.replace(spec, host_margin_ms=host_margin * 1e3)


def bus_timing(args: argparse.Namespace, host_margin: float) -> dict[str, Any]:
    """The ``Bus`` timing options: the chosen bus file table's ``min_spacing_ms`` and
    ``retries`` (their defaults are the library's), and its host margin as
    :func:`with_cli_margin` decides it, with ``host_margin`` (seconds)."""
    spec, given = _spec(args)
    if spec is None:
        return {"host_margin": host_margin}
    spec = with_cli_margin(spec, given, host_margin)
    return {
        "min_spacing": spec.min_spacing_ms / 1e3,
        "retries": spec.retries,
        "host_margin": spec.host_margin_ms / 1e3,
    }


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
        args: the parsed options (``--port``, ``--baud``, ``--backend``, the bus file).
        families: the device families on the bus.
        host_margin: latency allowance added to every reply deadline, seconds (a bus
            file's ``host_margin_ms`` replaces it).

    Raises:
        UsageError: see :func:`open_port`.
        PortInUseError: another program holds the port (the message names it).
        OSError: the port cannot be opened (the message names it), or the kernel
            refused the CPUs of the ``--process`` group (the message names the group).
    """
    endpoint = getattr(args, "connect", None)
    if endpoint:
        if args.port or args.bus_file:
            raise UsageError("--connect uses a served bus: give it without --port or --bus-file")
        async with served_bus(endpoint, args.bus) as bus:
            yield bus
        return
    transport = open_port(args)
    pinning = _pin(getattr(args, _GROUP_ATTR, None))  # before the bus opens, as BusManager
    try:
        async with _opened_bus(args, transport, families, host_margin) as bus:
            yield bus
    finally:
        if pinning is not None:
            pinning.restore()


@asynccontextmanager
async def served_bus(endpoint: str, name: str | None) -> AsyncIterator[Bus]:
    """The bus ``name`` of the ``motorbus serve`` at ``endpoint`` (a ``ServedBus``: it
    has the members of ``Bus`` that the devices use, which is all the commands that
    take ``--connect`` use)."""
    try:
        import zenoh  # noqa: F401  (only to tell a missing extra from other errors)
    except ImportError:
        raise UsageError("--connect needs the serve extra: pip install 'motorbus[serve]'") from None
    async with motorbus.connect(endpoint) as site:
        yield cast(Bus, site.bus(name))


def _pin(group: ProcessGroup | None) -> realtime.Pinning | None:
    """Run on the CPUs of the group ``--process`` chose, if it gives any."""
    if group is None or group.cpus is None:
        return None
    try:
        return realtime.pin(group.cpus)
    except OSError as err:
        raise OSError(err.errno, f"--process {group.name}: {err.strerror}") from err


@asynccontextmanager
async def _opened_bus(
    args: argparse.Namespace, transport: Transport, families: Iterable[Family], host_margin: float
) -> AsyncIterator[Bus]:
    bus = Bus(
        transport,
        name=transport.url,
        families=families,
        reconnect=False,
        **bus_timing(args, host_margin),
    )
    try:
        await bus.open()
    except PortInUseError:
        raise  # names the port and its holder already
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
    text = str(err)
    reasons = _ERRNO_TEXT.findall(text) if "could not open port" in text else []
    reason = reasons[-1].strip() if reasons else _one_line(err).removeprefix(f"{url}: ")
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
