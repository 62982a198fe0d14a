"""``motorbus monitor``: a live table of LA actuator status, polled round-robin.

Example::

    motorbus monitor --port /dev/ttyUSB0 --ids 1-3 --interval 0.2

Each refresh queries every listed actuator once, in turn, then waits ``--interval``.
On a terminal the table is redrawn in place; otherwise each refresh prints a block of
lines (or, with ``--json``, one JSON object a line).  An actuator that does not answer
shows as ``timeout`` and does not stop the monitor.  ``--count N`` ends after N
refreshes (exit code 1 if an actuator did not answer the last one, as ``la status``);
otherwise Ctrl-C ends it (exit code 0: that is how an endless monitor ends).
Without ``--ids`` the bus is scanned first.

``--plot`` draws position, target and force of each actuator against time instead of
the table: in the terminal with plain characters (``--plot`` or ``--plot terminal``),
or in a matplotlib window (``--plot window``, which needs a display).  The terminal
plot shows the last refreshes that fit its width.

``--listen`` sends nothing: it watches what another program does on the bus, from a tap
(``motorbus sim --tap``) or a second adapter on the line, and shows the last status each
actuator sent (``--family`` for a stepper bus; ``--seconds`` ends it)::

    motorbus monitor --listen --port /tmp/ttyLA.tap

With ``--bus-file F --process NAME`` the bus is one of that process group's (its only
one needs no ``--bus``), and the monitor runs on the group's CPUs.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import shutil
import sys
import time
from typing import Any

from motorbus import Bus, InspireLA, scan
from motorbus.cli import listen, plot
from motorbus.cli.bus_options import LA_BAUD, add_bus_options, add_process_option, open_bus
from motorbus.cli.capture import FAMILY_BAUD
from motorbus.cli.ids import parse_ids
from motorbus.cli.la import STATUS_HEADER, status_json, status_row
from motorbus.cli.main import UsageError
from motorbus.cli.output import LiveText, fail, plural, print_json
from motorbus.cli.scan import SCAN_TIMEOUT_S
from motorbus.cli.values import check_seconds
from motorbus.errors import ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int

__all__ = ["register", "run"]

#: Shortest ``--interval``: well above one round trip, so the table stays readable.
MIN_INTERVAL_S = 0.01
#: Largest ``--count``.
MAX_COUNT = 10**9
#: Refreshes a plot window keeps (at 0.2 s a refresh, the last 10 minutes).
WINDOW_SAMPLES = 3000


def register(subparsers: Any) -> None:
    """Add the ``monitor`` command."""
    p = subparsers.add_parser(
        "monitor",
        help="live table of LA actuator status",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--ids", help="IDs to poll, e.g. 1-3,7 (default: scan the bus first)")
    p.add_argument(
        "--interval", type=float, default=0.2, help="seconds between refreshes (default 0.2)"
    )
    p.add_argument("--count", type=int, help="stop after N refreshes")
    p.add_argument(
        "--plot",
        nargs="?",
        const="terminal",
        choices=("terminal", "window"),
        help="plot position, target and force against time (default: in the terminal)",
    )
    p.add_argument(
        "--listen",
        action="store_true",
        help="send nothing: show what another program's traffic says (on a tap, or a second "
        "adapter on the line)",
    )
    p.add_argument(
        "--family",
        choices=[f.value for f in Family],
        help="with --listen: the bus's family (default la)",
    )
    p.add_argument("--seconds", type=float, help="with --listen: stop after this long")
    add_bus_options(p, default_baud=LA_BAUD, connect=True)
    add_process_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus monitor``; return 0 (1 if a scan found nothing to monitor).

    Raises:
        LocalProtocolError: a bad ``--ids``, ``--interval`` or ``--count``.
    """
    ids = parse_ids(args.ids) if args.ids is not None else None
    check_seconds("--interval", args.interval, MIN_INTERVAL_S)
    if args.count is not None:
        check_int("--count", args.count, 1, MAX_COUNT)
    if args.listen:
        if args.plot is not None:
            raise UsageError("--plot does not go with --listen")
        if args.process is not None:
            raise UsageError("--process goes with a monitor that drives its bus, not --listen")
        check_seconds("--seconds", args.seconds, 1e-3)
        family = Family(args.family or Family.LA.value)
        args._default_baud = FAMILY_BAUD[family]
        return listen.run_listen(args, ids, family)
    if args.family is not None or args.seconds is not None:
        raise UsageError("--family and --seconds go with --listen")
    plot_mode = getattr(args, "plot", None)
    if plot_mode is not None and args.json:
        raise UsageError("--plot and --json do not go together: choose one")
    if plot_mode == "window":
        plot.check_window()
    try:
        return asyncio.run(_monitor(args, ids))
    except KeyboardInterrupt:
        return 0  # Ctrl-C is how an endless monitor ends


async def _monitor(args: argparse.Namespace, ids: list[int] | None) -> int:
    live = LiveText(sys.stdout)
    async with open_bus(args, [Family.LA]) as bus:
        if ids is None and getattr(args, "connect", None):
            served: Any = bus
            ids = list((await served.fetch_devices()).known_la)  # the server's IDs: no scan
            if not ids:
                print(
                    "motorbus monitor: the server knows no LA actuator on its bus: give --ids",
                    file=sys.stderr,
                )
                return 1
        if ids is None:
            ids = await scan(bus, timeout=SCAN_TIMEOUT_S)
            if not ids:
                print("motorbus monitor: no actuator answered a scan of 1..254", file=sys.stderr)
                return 1
        refreshes = 0
        rows: list[la.Status | str] = []
        started = time.monotonic()
        plotter = _Plotter(getattr(args, "plot", None), ids, live)
        while args.count is None or refreshes < args.count:
            if refreshes:
                await asyncio.sleep(args.interval)
            rows = await _poll(bus, ids)
            refreshes += 1
            elapsed = time.monotonic() - started
            if args.json:
                print_json(
                    {
                        "refresh": refreshes,
                        "t": round(elapsed, 4),
                        "statuses": [
                            status_json(s) if isinstance(s, la.Status) else {"id": i, "error": s}
                            for i, s in zip(ids, rows, strict=True)
                        ],
                    }
                )
                continue
            if plotter.mode is not None:
                if not plotter.show(elapsed, dict(zip(ids, rows, strict=True))):
                    break  # the plot window was closed
                continue
            lines = [f"refresh {refreshes}  t={elapsed:6.2f}s  bus {bus.name}", STATUS_HEADER]
            for i, s in zip(ids, rows, strict=True):
                lines.append(status_row(s) if isinstance(s, la.Status) else f"  {i:3d}  {s}")
            live.show(lines)
    silent = [i for i, s in zip(ids, rows, strict=True) if not isinstance(s, la.Status)]
    if silent and args.count is not None:
        # A bounded monitor reports as ``la status`` does: a listed actuator that did
        # not answer its last query makes the exit code 1.
        return fail(
            args,
            f"{plural(len(silent), 'actuator')} of {len(ids)} did not answer the last "
            f"refresh ({', '.join(f'la:{i}' for i in silent)}): check --ids (motorbus scan "
            f"lists the IDs that answer) and --baud {args.baud}",
            port=args.port,
            ids=silent,
        )
    return 0


class _Plotter:
    """Keeps the refreshes a plot shows and draws them (``--plot``)."""

    def __init__(self, mode: str | None, ids: list[int], live: LiveText) -> None:
        self.mode = mode
        self.ids = ids
        self.live = live
        self.window = plot.WindowPlot(ids) if mode == "window" else None
        columns = shutil.get_terminal_size().columns - plot.LABEL_WIDTH - 1
        self.width = max(plot.MIN_WIDTH, columns)
        self.samples: collections.deque[plot.Sample] = collections.deque(
            maxlen=self.width if self.window is None else WINDOW_SAMPLES
        )

    def show(self, t: float, statuses: dict[int, la.Status | str]) -> bool:
        """Add a refresh and redraw; False once a plot window was closed."""
        self.samples.append((t, statuses))
        if self.window is not None:
            if not self.window.open:
                return False
            self.window.update(list(self.samples))
            return True
        self.live.show(plot.render(list(self.samples), self.ids, width=self.width))
        return True


async def _poll(bus: Bus, ids: list[int]) -> list[la.Status | str]:
    rows: list[la.Status | str] = []
    for i in ids:
        try:
            rows.append(await InspireLA(bus, i).status())
        except ReplyTimeoutError:
            rows.append("timeout")
    return rows
