"""``motorbus ports``: the serial adapters plugged in, and how to name each for good.

Example::

    $ motorbus ports
    port          usb        serial  driver      latency  name for a bus file
    /dev/ttyUSB0  0403:6001  A12345  ftdi_sio    16 ms    usb:serial=A12345
                  FTDI FT232R USB UART
                  /dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A12345-if00-port0
    /dev/ttyUSB1  1a86:7523  -       ch341-uart  -        usb:1a86:7523
                  USB2.0-Serial
                  /dev/serial/by-id/usb-1a86_USB2.0-Serial-if00-port0
    $ motorbus ports --json

One row a port, read from sysfs (Linux): the device, its USB vendor:product ID, serial
number, driver and receive latency timer (FTDI; "-" where the driver has none), then
the adapter's manufacturer and product strings and udev's ``/dev/serial/by-id`` links.
The last column is the ``usb:`` URL that finds the adapter again whatever number it gets
(``url = "usb:serial=A12345"`` in a bus file, or ``--port``): by serial number where the
adapter has one that no other adapter shares, else by vendor:product if that is unique,
else none ("-": name it by its ``/dev/serial/by-path`` link).

USB adapters only, unless ``--all`` (then also on-board UARTs and the ``ttyS`` ports the
kernel always lists, present or not).  No adapter is not an error: the command says so
and exits 0.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence
from typing import Any

from motorbus import SerialPortInfo, list_serial_ports
from motorbus.cli.output import add_json_option, print_json

__all__ = ["register", "run", "stable_url", "table"]

_HEADER = ("port", "usb", "serial", "driver", "latency", "name for a bus file")


def register(subparsers: Any) -> None:
    """Add the ``ports`` command."""
    p = subparsers.add_parser(
        "ports",
        help="list the serial ports: USB IDs, serial number, driver, latency timer",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--all",
        action="store_true",
        help="also list the ports that are not on USB (on-board UARTs, ttyS*)",
    )
    add_json_option(p)
    p.set_defaults(func=run)


def stable_url(port: SerialPortInfo, ports: Sequence[SerialPortInfo]) -> str | None:
    """The ``usb:`` URL that names ``port`` alone among ``ports``, or None.

    Its serial number if it has one no other port shares (an FT2232 has two ports
    under one serial number), else its vendor:product ID if no other port has it.
    """
    if not port.is_usb:
        return None
    serials = Counter(p.serial for p in ports if p.is_usb and p.serial)
    if port.serial and serials[port.serial] == 1:
        return f"usb:serial={port.serial}"
    ids = Counter((p.vid, p.pid) for p in ports if p.is_usb)
    if ids[(port.vid, port.pid)] == 1:
        return f"usb:{port.vid}:{port.pid}"
    return None


def _row(port: SerialPortInfo, ports: Sequence[SerialPortInfo]) -> tuple[str, ...]:
    latency = "-" if port.latency_timer_ms is None else f"{port.latency_timer_ms} ms"
    return (
        port.device,
        f"{port.vid}:{port.pid}" if port.is_usb else "-",
        port.serial or "-",
        port.driver or "-",
        latency,
        stable_url(port, ports) or "-",
    )


def table(ports: Sequence[SerialPortInfo]) -> list[str]:
    """The text lines ``motorbus ports`` prints for ``ports``."""
    rows = [_HEADER, *(_row(p, ports) for p in ports)]
    widths = [max(len(r[i]) for r in rows) for i in range(len(_HEADER) - 1)]
    indent = " " * (widths[0] + 2)

    def line(row: tuple[str, ...]) -> str:
        cells = [cell.ljust(w) for cell, w in zip(row, widths, strict=False)]
        return "  ".join([*cells, row[-1]]).rstrip()

    lines = [line(_HEADER)]
    for port, row in zip(ports, rows[1:], strict=True):
        lines.append(line(row))
        strings = " ".join(s for s in (port.manufacturer, port.product) if s)
        lines += [indent + extra for extra in (strings, *port.by_id) if extra]
    return lines


def run(args: argparse.Namespace) -> int:
    """List the ports; exit 0 (none found is not an error)."""
    ports = list_serial_ports(usb_only=not args.all)
    if args.json:
        print_json(
            {"ports": [p.as_dict() | {"url": stable_url(p, ports)} for p in ports]},
        )
        return 0
    if not ports:
        what = "serial ports" if args.all else "USB serial adapters"
        hint = "" if args.all else " (--all lists the other serial ports)"
        print(f"no {what} found{hint}", file=sys.stdout)
        return 0
    print("\n".join(table(ports)))
    return 0
