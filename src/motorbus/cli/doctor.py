"""``motorbus doctor``: what is wrong with a bus, and how fast it can go.

Example::

    $ motorbus doctor --port /dev/ttyUSB0 --baud 921600
    $ motorbus doctor --bus-file buses.toml --bus arm --period 20 --json

A short, bounded, read-only sequence (status queries only; ``--fix`` may set the USB
adapter's latency timer to 1 ms, ``--stream`` adds a real follow stream to the positions
the actuators report) prints one line per check, green, yellow or red, each yellow or
red line with the one thing to do about it:

* port: exists, permissions (the exact usermod line), another process holding it,
  the USB adapter (VID:PID, driver, serial number);
* latency: the adapter's latency timer and ASYNC_LOW_LATENCY, what they cost, and the
  udev rule that sets them for good;
* echo: an adapter that sends our own bytes back (remove_echo = true);
* devices: which LA actuators answer at the baud, and where they do if none does;
* turnaround la:N: p50/p99/max against the 800 us budget, late and lost replies;
* line: lost replies, garbage bytes, unexpected frames;
* budget: the occupancy model's cycle budget at --period beside a measurement;
* host: timer, real-time grant, CPU governor, other real-time processes.

``--connect ENDPOINT`` runs the read-only checks on a bus that ``motorbus serve`` owns
(devices, turnaround and line from the server's counters); the others are listed as
skipped, saying why.

Exit status: 0 when nothing is red, 1 otherwise (a port that does not exist included),
2 for bad arguments (nothing sent).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
from typing import Any

from motorbus import DoctorConfig, default_bus_file, diagnose
from motorbus.cli.bus_options import (
    BUS_ENV,
    BUS_FILE_ENV,
    LA_BAUD,
    PORT_ENV,
    add_bus_options,
    available_ports,
    resolve_port,
)
from motorbus.cli.ids import parse_ids
from motorbus.cli.main import UsageError
from motorbus.cli.output import error_doc, plural, print_json
from motorbus.errors import CommandFailed, LocalProtocolError

__all__ = ["register", "run"]

#: Default stream period of the cycle budget, milliseconds (LA manual 3.5.3: 10..50).
DEFAULT_PERIOD_MS = 10.0


def register(subparsers: Any) -> None:
    """Add the ``doctor`` command."""
    p = subparsers.add_parser(
        "doctor",
        help="check a bus: port, adapter, echo, baud, devices, timing, what it can sustain",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_bus_options(p, default_baud=LA_BAUD, connect=True)
    p.add_argument(
        "--period",
        type=float,
        default=DEFAULT_PERIOD_MS,
        metavar="MS",
        help=f"stream period of the cycle budget, 10..50 ms (default {DEFAULT_PERIOD_MS:g})",
    )
    p.add_argument("--ids", help="LA IDs to check, e.g. 1-8 (default: the bus file's, else 1-254)")
    p.add_argument(
        "--requests", type=int, default=30, help="status queries per device (default 30)"
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=2.0,
        help="how long the cycle budget is measured (default 2; 0: theory only)",
    )
    p.add_argument(
        "--fix",
        action="store_true",
        help="set the USB adapter's latency timer to 1 ms if it is longer (needs the right)",
    )
    p.add_argument(
        "--stream",
        action="store_true",
        help="also measure a real broadcast follow stream sending each actuator the position "
        "it reports (nothing travels; a paused actuator is powered again: the LA reports no "
        "pause state to restore)",
    )
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> DoctorConfig:
    """The config from the options; every value checked here (exit 2, nothing sent)."""
    options: dict[str, Any] = {
        "period_s": args.period / 1e3,
        "requests": args.requests,
        "measure_s": args.seconds,
        "fix": args.fix,
        "stream": args.stream,
    }
    if args.ids:
        options["ids"] = tuple(parse_ids(args.ids))
    if args.period != args.period or not 10.0 - 1e-6 <= args.period <= 50.0 + 1e-6:
        raise UsageError(f"--period={args.period:g} is out of range: allowed 10..50 ms")
    port = args.port or os.environ.get(PORT_ENV)
    bus_file = args.bus_file or os.environ.get(BUS_FILE_ENV)
    bus = args.bus or os.environ.get(BUS_ENV)
    if not port and not bus_file:
        default = default_bus_file()
        if default is not None and default.is_file():
            bus_file = str(default)
    try:
        if bus_file and not port:
            if not os.path.isfile(bus_file):
                raise UsageError(f"--bus-file {bus_file}: no such file")
            if args.baud is not None or args.backend is not None:
                raise UsageError("--baud/--backend come from the bus file with --bus-file")
            return DoctorConfig.from_bus_file(bus_file, bus, **options)
        resolve_port(args)
        return DoctorConfig(args.port, args.baud, backend=args.backend, **options)
    except LocalProtocolError as err:
        if err.field == "port":
            # A port that is not there is a fault of the bus, not of the input: exit 1,
            # as every command that opens a port (docs/cli.md, exit codes).
            args.port = err.value
            raise CommandFailed(
                f"cannot open port {err.value}: No such file or directory; {available_ports()}"
            ) from err
        raise


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus doctor``; return 0 when nothing is red, else 1 (2: bad arguments)."""
    if args.connect:
        report = _served(args)
        target = args.connect
    else:
        config = _config(args)
        report = asyncio.run(diagnose(config))
        target = config.url
    if args.json:
        print_json(report.as_dict())
        red = [f.check for f in report.findings if f.level.value == "red"]
        if red:  # the report, then one error object naming the red checks
            text = f"{plural(len(red), 'check')} red: {', '.join(red)}"
            print_json(error_doc("doctor", text, report.exit_code, port=target, checks=red))
    else:
        print(report.format_text(colour=sys.stdout.isatty()), flush=True)
    code: int = report.exit_code
    return code


def _served(args: argparse.Namespace) -> Any:
    """``--connect``: the read-only checks through the server (``cli.served``)."""
    from motorbus.cli.served import run_doctor
    from motorbus.protocol.base import check_int

    if args.period != args.period or not 10.0 - 1e-6 <= args.period <= 50.0 + 1e-6:
        raise UsageError(f"--period={args.period:g} is out of range: allowed 10..50 ms")
    check_int("--requests", args.requests, 1, 1000)
    ids = parse_ids(args.ids) if args.ids else None
    return asyncio.run(run_doctor(args, ids, args.period / 1e3))
