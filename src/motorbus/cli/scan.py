"""``motorbus scan``: find the LA actuators on a bus.

Example::

    $ motorbus scan --port /dev/ttyUSB0 --ids 1-20
    1,2,3

Each ID gets one status query (no retry).  Progress goes to standard error: a bar
redrawn in place on a terminal, a line every tenth of the way otherwise.  The IDs that
answered are printed as a comma-separated list (ready for ``--ids``), or as JSON.
The exit code is 1 if no actuator answered.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import Any, TextIO

from motorbus.cli.common import LA_BAUD, add_bus_options, check_seconds, open_bus, parse_ids
from motorbus.cli.common import print_json as _print_json
from motorbus.devices.la import scan
from motorbus.protocol.base import Family

__all__ = ["SCAN_TIMEOUT_S", "ProgressBar", "register", "run"]

#: Default reply budget per ID (seconds): the LA answers within 800 us (manual 3.4.2);
#: 10 ms also covers a USB adapter's latency timer, and keeps a full scan near 3 s.
SCAN_TIMEOUT_S = 0.010
#: Width of the text progress bar, in characters.
BAR_WIDTH = 30
#: Without a terminal, a progress line is printed every this share of the IDs.
LINE_EVERY_SHARE = 0.1


def register(subparsers: Any) -> None:
    """Add the ``scan`` command."""
    p = subparsers.add_parser(
        "scan",
        help="find the LA actuators that answer on a bus",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--ids", default="1-254", help="IDs to try, e.g. 1-20,100 (default 1-254)")
    p.add_argument(
        "--timeout",
        type=float,
        default=SCAN_TIMEOUT_S,
        help=f"reply budget per ID in seconds (default {SCAN_TIMEOUT_S})",
    )
    add_bus_options(p, default_baud=LA_BAUD)
    p.set_defaults(func=run)


class ProgressBar:
    """``progress(id, total, found)`` callback that draws scan progress on ``out``.

    Args:
        out: the stream (default standard error).
        tty: redraw one line in place (default: ``out.isatty()``); else print a line
            every :data:`LINE_EVERY_SHARE` of the way.
    """

    def __init__(self, out: TextIO | None = None, *, tty: bool | None = None) -> None:
        self.out = out if out is not None else sys.stderr
        self.tty = self.out.isatty() if tty is None else tty
        self.done = 0
        self.found: list[int] = []
        self._next_line = 0.0

    def __call__(self, ident: int, total: int, found: bool) -> None:
        """Record one tried ID and redraw."""
        self.done += 1
        if found:
            self.found.append(ident)
        share = self.done / total if total else 1.0
        found_text = f"found {len(self.found)}" + (
            f" (last la:{self.found[-1]})" if self.found else ""
        )
        if self.tty:
            filled = round(BAR_WIDTH * share)
            bar = "#" * filled + "." * (BAR_WIDTH - filled)
            end = "\n" if self.done == total else ""
            self.out.write(f"\r[{bar}] {self.done}/{total} {found_text}{end}")
            self.out.flush()
        elif share >= self._next_line or self.done == total:
            self._next_line = share + LINE_EVERY_SHARE
            self.out.write(f"scan: {self.done}/{total} tried, {found_text}\n")
            self.out.flush()


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus scan``; return 0 if some actuator answered, else 1.

    Raises:
        LocalProtocolError: a bad ``--ids`` or ``--timeout`` (before anything is sent).
    """
    ids = parse_ids(args.ids)
    check_seconds("--timeout", args.timeout, 1e-4)
    return asyncio.run(_scan(args, ids))


async def _scan(args: argparse.Namespace, ids: list[int]) -> int:
    progress = ProgressBar()
    async with open_bus(args, [Family.LA]) as bus:
        found = await scan(bus, ids, timeout=args.timeout, progress=progress)
    if args.json:
        _print_json({"ids": found, "tried": len(ids)})
    elif found:
        print(",".join(str(i) for i in found))
    if not found:
        print(f"motorbus scan: no actuator answered ({len(ids)} IDs tried)", file=sys.stderr)
        return 1
    return 0
