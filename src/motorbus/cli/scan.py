"""``motorbus scan``: find the LA actuators on a bus.

Example::

    $ motorbus scan --port /dev/ttyUSB0
    1,2,3
    $ motorbus scan --port /dev/ttyUSB0 --baud all
    19200: none
    57600: none
    115200: 7
    921600: 1,2,3

Each ID gets a status query; the IDs that did not answer get a second one with a
longer budget (``--passes 1`` turns that off).  The per-ID budget adapts to the bus:
the wire time of the query and its reply at the baud rate, the actuator's worst-case
turnaround (800 us), a small host allowance, or more if the replies seen need it; an
actuator whose answer came late is asked again with 50 ms.  254 IDs take about 0.85 s
at 921600 bit/s (more on a busy machine, where each absent ID also waits for its
wake-up: ``--realtime`` helps), against ~2.8 s with the old fixed 10 ms.  ``--timeout``
fixes the budget instead.

``--baud all`` tries every rate an LA actuator can be set to (19200, 57600, 115200,
921600 bit/s), reopening the port at each, and prints which IDs answered at which.

Progress goes to standard error: a bar redrawn in place on a terminal, a line every
tenth of the way otherwise, then one summary line.  The IDs that answered are printed
as a comma-separated list (ready for ``--ids``), or as JSON.  The exit code is 1 if no
actuator answered.

``--connect ENDPOINT`` scans a bus that ``motorbus serve`` owns, beside its application:
the IDs the server declares or has heard (or ``--ids``) are each asked a status through
the server; ``--baud all`` is refused there, and so is a ``--baud`` other than the
served bus's own rate.
"""

from __future__ import annotations

import argparse
import asyncio
import copy
import sys
from collections.abc import Callable, Sequence
from contextlib import AbstractAsyncContextManager
from typing import Any, TextIO

from motorbus import SCAN_PASSES_MAX, Bus, ScanReport, scan
from motorbus.cli.bus_options import LA_BAUD, add_bus_options, open_bus
from motorbus.cli.ids import parse_ids
from motorbus.cli.output import fail
from motorbus.cli.output import print_json as _print_json
from motorbus.cli.values import check_seconds
from motorbus.protocol import la
from motorbus.protocol.base import BAUD_MAX, BAUD_MIN, Family, check_int

__all__ = [
    "ALL_BAUDS",
    "SCAN_TIMEOUT_S",
    "ProgressBar",
    "parse_baud",
    "register",
    "run",
    "scan_bauds",
]

#: Default reply budget per ID: ``None`` is adaptive (see ``motorbus.devices.la.scan``).
#: Scans used a fixed 10 ms before, which kept 254 IDs near 3 s.
SCAN_TIMEOUT_S: float | None = None
#: ``--baud all``: every rate of the LA baud codes (control table 12, slowest first).
ALL_BAUDS = tuple(code.baud for code in la.BaudCode)
#: Width of the text progress bar, in characters.
BAR_WIDTH = 30
#: Without a terminal, a progress line is printed every this share of the IDs.
LINE_EVERY_SHARE = 0.1


def parse_baud(text: str) -> int | None:
    """``--baud``: a rate in bit/s, or ``all`` (returned as ``None``).

    Raises:
        argparse.ArgumentTypeError: anything else.
    """
    if text.strip().lower() == "all":
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--baud={text!r} is not a rate in bit/s or 'all' "
            f"({', '.join(str(b) for b in ALL_BAUDS)})"
        ) from None


class _GivenBaud(argparse.Action):
    """``--baud`` as given on the command line (``baud_given``: a served bus checks it
    against the server's rate rather than ignore it)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        setattr(namespace, self.dest, values)
        namespace.baud_given = True


def register(subparsers: Any) -> None:
    """Add the ``scan`` command."""
    p = subparsers.add_parser(
        "scan",
        help="find the LA actuators that answer on a bus",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        conflict_handler="resolve",  # our --baud (which takes "all") replaces the common one
    )
    p.add_argument(
        "--ids",
        help="IDs to try, e.g. 1-20,100 (default 1-254; with --connect: the IDs the server "
        "knows, declared or seen answering)",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=SCAN_TIMEOUT_S,
        help="fixed reply budget per ID in seconds (default: adaptive, ~1.4 ms at 921600)",
    )
    p.add_argument(
        "--passes",
        type=int,
        default=SCAN_PASSES_MAX,
        help=f"1: ask each ID once; 2: ask the missing IDs again (default {SCAN_PASSES_MAX})",
    )
    add_bus_options(p, default_baud=LA_BAUD, connect=True)
    p.add_argument(
        "--baud",
        type=parse_baud,
        action=_GivenBaud,
        default=LA_BAUD,
        help=f"bit/s (default {LA_BAUD}), or 'all': {', '.join(str(b) for b in ALL_BAUDS)}",
    )
    p.set_defaults(func=run)


class ProgressBar:
    """``progress(id, total, found)`` callback that draws scan progress on ``out``.

    Args:
        out: the stream (default standard error).
        tty: redraw one line in place (default: ``out.isatty()``); else print a line
            every :data:`LINE_EVERY_SHARE` of the way.
        label: printed before the counts (``--baud all`` names the rate).
    """

    def __init__(
        self, out: TextIO | None = None, *, tty: bool | None = None, label: str = ""
    ) -> None:
        self.out = out if out is not None else sys.stderr
        self.tty = self.out.isatty() if tty is None else tty
        self.label = label
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
            f": {_ids_text(self.found)}" if self.found else ""
        )
        label = f"{self.label} " if self.label else ""
        if self.tty:
            filled = round(BAR_WIDTH * share)
            bar = "#" * filled + "." * (BAR_WIDTH - filled)
            end = "\n" if self.done == total else ""
            self.out.write(f"\r{label}[{bar}] {self.done}/{total} IDs decided, {found_text}{end}")
            self.out.flush()
        elif share >= self._next_line or self.done == total:
            self._next_line = share + LINE_EVERY_SHARE
            self.out.write(f"scan: {label}{self.done}/{total} IDs decided, {found_text}\n")
            self.out.flush()


#: The most found IDs a progress line lists; the rest are counted.
PROGRESS_IDS_SHOWN = 6

#: Where to look when nothing answers (docs/hardware.md has the whole checklist).
NOTHING_ANSWERED_HINT = (
    "check power, wiring (RS-485 A/B swapped? common ground?), the port, the baud rate "
    "(--baud all tries the four LA rates) and an echoing adapter (remove_echo); "
    "docs/hardware.md has a first-contact checklist"
)


def _ids_text(found: list[int]) -> str:
    """``la:1,la:4`` for the IDs found so far, ascending; ``+N more`` past a few."""
    ids = sorted(found)
    shown = ",".join(f"la:{i}" for i in ids[:PROGRESS_IDS_SHOWN])
    more = len(ids) - PROGRESS_IDS_SHOWN
    return shown + (f" +{more} more" if more > 0 else "")


BusOpener = Callable[[int], AbstractAsyncContextManager[Bus]]


async def scan_bauds(
    open_at: BusOpener,
    ids: Sequence[int],
    bauds: Sequence[int] = ALL_BAUDS,
    *,
    timeout: float | None = None,
    passes: int = SCAN_PASSES_MAX,
    progress: Callable[[int], Callable[[int, int, bool], None] | None] | None = None,
) -> dict[int, ScanReport]:
    """Scan ``ids`` at each rate of ``bauds``, opening a fresh bus at each.

    Args:
        open_at: ``open_at(baud)`` is an async context manager yielding an open bus at
            that rate (the port is closed and reopened between rates).
        ids: the IDs to try at every rate.
        bauds: the rates in bit/s, in order.
        timeout, passes: as for :func:`motorbus.devices.la.scan`.
        progress: ``progress(baud)`` gives the progress callback of that rate's scan.

    Returns:
        The report of each rate, by rate.
    """
    reports: dict[int, ScanReport] = {}
    for baud in bauds:
        report = ScanReport()
        async with open_at(baud) as bus:
            await scan(
                bus,
                ids,
                timeout=timeout,
                passes=passes,
                progress=progress(baud) if progress is not None else None,
                report=report,
            )
        reports[baud] = report
    return reports


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus scan``; return 0 if some actuator answered, else 1.

    Raises:
        LocalProtocolError: a bad ``--ids``, ``--timeout`` or ``--passes`` (before
            anything is sent).
    """
    ids = parse_ids(args.ids or "1-254")
    check_seconds("--timeout", args.timeout, 1e-4)
    check_int("--passes", args.passes, 1, SCAN_PASSES_MAX)
    if args.baud is not None:
        check_int("--baud", args.baud, BAUD_MIN, BAUD_MAX)
    if getattr(args, "connect", None):
        from motorbus.cli.served import run_scan

        return asyncio.run(run_scan(args, ids if args.ids else None))
    return asyncio.run(_scan(args, ids))


def _summary(label: str, ids: Sequence[int], report: ScanReport) -> str:
    budgets = "/".join(f"{p.budget_s * 1e3:.2f}" for p in report.passes)
    text = (
        f"scan: {label}{len(ids)} IDs in {report.seconds:.2f} s "
        f"(budget per ID {budgets} ms), found {len(report.found)}"
    )
    if report.late:
        text += (
            f"; {', '.join(f'la:{i}' for i in report.late)} answered only after "
            "the budget: try --timeout 0.1"
        )
    return text


async def _scan(args: argparse.Namespace, ids: list[int]) -> int:
    if args.baud is None:
        return await _scan_all(args, ids)
    progress = ProgressBar()
    report = ScanReport()
    async with open_bus(args, [Family.LA]) as bus:
        found = await scan(
            bus, ids, timeout=args.timeout, passes=args.passes, progress=progress, report=report
        )
    print(_summary("", ids, report), file=sys.stderr)
    if args.json:
        _print_json({"ids": found, "tried": len(ids)})
    elif found:
        print(",".join(str(i) for i in found))
    if not found:
        return fail(
            args,
            f"no actuator answered ({len(ids)} IDs tried at {args.baud} bit/s): "
            + NOTHING_ANSWERED_HINT,
            port=args.port,
            tried=len(ids),
        )
    return 0


async def _scan_all(args: argparse.Namespace, ids: list[int]) -> int:
    def open_at(baud: int) -> AbstractAsyncContextManager[Bus]:
        at = copy.copy(args)
        at.baud = baud
        return _opened(at)

    reports = await scan_bauds(
        open_at,
        ids,
        timeout=args.timeout,
        passes=args.passes,
        progress=lambda baud: ProgressBar(label=f"{baud}:"),
    )
    for baud, report in reports.items():
        print(_summary(f"{baud} bit/s: ", ids, report), file=sys.stderr)
    if args.json:
        _print_json({"bauds": {str(b): r.found for b, r in reports.items()}, "tried": len(ids)})
    else:
        for baud, report in reports.items():
            print(f"{baud}: {','.join(str(i) for i in report.found) or 'none'}")
    if not any(r.found for r in reports.values()):
        return fail(
            args,
            f"no actuator answered at any baud rate ({len(ids)} IDs tried at "
            f"each of {', '.join(str(b) for b in reports)}): " + NOTHING_ANSWERED_HINT,
            port=args.port,
            tried=len(ids),
        )
    return 0


def _opened(args: argparse.Namespace) -> AbstractAsyncContextManager[Bus]:
    return open_bus(args, [Family.LA])
