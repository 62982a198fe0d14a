"""``motorbus stream``: play a CSV trajectory to LA actuators in follow mode.

Example::

    motorbus stream path.csv --ids 1-3 --period 0.01 --port /dev/ttyUSB0

The CSV has one row per tick.  Its first column is the time in seconds and each
further column a position 0..2000 for one actuator:

* with a header row "t,1,2,3" the header names the actuator of each column
  (--ids, if given, must name the same actuators);
* without one, the columns follow the --ids order (1,2,3 or 1-3).

Rows are sent one per tick at --period (10..50 ms, LA manual 3.5.3); the time
column does not pace anything, it is only checked to increase by the period from row
to row (within 1 %), so a file made for another rate is refused instead of played at
the wrong speed.  --loop N plays the rows N times.

Before the first tick every listed actuator must answer a status query (else
nothing is streamed, exit code 1), and each is ramped from the position it reports
to its first target over --ramp seconds (default 1; --ramp 0 jumps straight there),
so the first row does not become a full-speed lunge.

Without --feedback the targets go out as 0xF3 broadcasts, one frame a tick; with
it, each actuator gets a 0x20 frame and answers with its status.  Live statistics
(ticks, late, skipped, jitter p99) go to standard error once a second; the final
summary to standard output (JSON with --json).  Skipped ticks (targets never sent)
or unanswered feedback make the exit code 1, and standard error says which.
Ctrl-C stops the stream and pauses the actuators (exit code 130).
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import math
import sys
from pathlib import Path
from typing import Any

from motorbus import (
    DEFAULT_HOST_MARGIN_S,
    PERIOD_MAX_S,
    PERIOD_MIN_S,
    Bus,
    InspireLA,
    SafeAction,
    Streamer,
)
from motorbus.cli.common import (
    LA_BAUD,
    add_bus_options,
    add_guard_option,
    check_ids,
    check_seconds,
    open_bus,
    parse_ids,
    plural,
    print_json,
)
from motorbus.cli.main import CommandFailed
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int

__all__ = ["Trajectory", "ramp_rows", "read_trajectory", "register", "run"]

#: The time column may differ from ``k * period`` steps by this share of the period.
TIME_TOLERANCE = 0.01
#: Live statistics are printed this often (seconds).
STATS_EVERY_S = 1.0
#: Streams keep the library's host margin: the tick budget check counts it per frame.
STREAM_HOST_MARGIN_S = DEFAULT_HOST_MARGIN_S
#: Largest ``--loop``.
MAX_LOOPS = 1_000_000
#: Reply budget of the status query that checks each actuator before the stream: the
#: stream's own tight host margin is for a warmed-up loop, not a port's first request.
CHECK_TIMEOUT_S = 0.1
#: Default ``--ramp``: seconds from the reported positions to the first row.
DEFAULT_RAMP_S = 1.0
#: Longest ``--ramp`` (seconds).
MAX_RAMP_S = 60.0


def register(subparsers: Any) -> None:
    """Add the ``stream`` command."""
    p = subparsers.add_parser(
        "stream",
        help="stream a CSV trajectory to LA actuators (follow mode)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", metavar="FILE.csv")
    p.add_argument("--ids", help="actuator of each position column, e.g. 1,2,3")
    p.add_argument("--period", type=float, default=0.01, help="seconds per row, 0.01..0.05")
    p.add_argument("--feedback", action="store_true", help="0x20 with status replies per id")
    p.add_argument("--loop", type=int, default=1, help="play the rows N times (default 1)")
    p.add_argument(
        "--ramp",
        type=float,
        default=DEFAULT_RAMP_S,
        metavar="SECONDS",
        help=f"move from the reported positions to the first row over this time "
        f"(default {DEFAULT_RAMP_S:g}; 0 = no ramp)",
    )
    add_bus_options(p, default_baud=LA_BAUD)
    add_guard_option(p)
    p.set_defaults(func=run)


class Trajectory:
    """Rows of positions read from a CSV file.

    Attributes:
        ids: the actuator of each column.
        rows: one tuple of positions (0..2000) per tick, in ``ids`` order.
    """

    def __init__(self, ids: list[int], rows: list[tuple[int, ...]]) -> None:
        self.ids = ids
        self.rows = rows


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise LocalProtocolError(f"{what}: {text.strip()!r} is not a number", field=what) from None
    if not math.isfinite(value):
        raise LocalProtocolError(f"{what}: {text.strip()!r} is not finite", field=what)
    return value


def read_trajectory(path: Path, ids: list[int] | None, period: float) -> Trajectory:
    """Read and check a trajectory CSV (see the module help for the format).

    Args:
        path: the CSV file.
        ids: ``--ids``; required when the file has no header row.
        period: seconds per row; the time column must step by it.

    Raises:
        LocalProtocolError: a bad header, cell, position or time step; the message
            names the line and the column.
        OSError: the file cannot be read.
    """
    with path.open(newline="", encoding="utf-8") as fh:
        table = [row for row in csv.reader(fh) if row and any(c.strip() for c in row)]
    if not table:
        raise LocalProtocolError(f"{path}: no rows", field="file")
    first = table[0]
    line0 = 1
    if first[0].strip().lower() in ("t", "time", "time_s"):
        header_ids = check_ids(
            [int(_number(c, f"{path} header column {n}")) for n, c in enumerate(first[1:], 2)],
            "header id",
        )
        if ids is not None and ids != header_ids:
            raise LocalProtocolError(
                f"--ids {','.join(map(str, ids))} differs from the header's "
                f"{','.join(map(str, header_ids))}",
                field="--ids",
            )
        if len(set(header_ids)) != len(header_ids):
            raise LocalProtocolError(f"{path}: the header lists an ID twice", field="header")
        ids = header_ids
        table = table[1:]
        line0 = 2
    if ids is None:
        raise LocalProtocolError(
            f"{path} has no header row 't,<id>,...': give --ids", field="--ids"
        )
    if not table:
        raise LocalProtocolError(f"{path}: no data rows", field="file")
    rows: list[tuple[int, ...]] = []
    previous: float | None = None
    for n, row in enumerate(table, start=line0):
        where = f"{path} line {n}"
        if len(row) != len(ids) + 1:
            raise LocalProtocolError(
                f"{where}: {len(row)} columns, expected {len(ids) + 1} (time and {len(ids)} ids)",
                field="file",
            )
        t = _number(row[0], f"{where} time")
        if previous is not None and abs(t - previous - period) > TIME_TOLERANCE * period:
            raise LocalProtocolError(
                f"{where}: time {t} does not follow {previous} by the period {period} s "
                f"(the file must hold one row per tick)",
                field="time",
                value=t,
            )
        previous = t
        positions = []
        for col, (ident, cell) in enumerate(zip(ids, row[1:], strict=True), start=2):
            value = _number(cell, f"{where} column {col}")
            positions.append(
                check_int(f"{where} position of la:{ident}", round(value), 0, la.POSITION_MAX)
            )
        rows.append(tuple(positions))
    return Trajectory(ids, rows)


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus stream``; return 0 if every tick went out, 1 if some were skipped.

    Raises:
        LocalProtocolError: a bad file, ``--ids``, ``--period`` or ``--loop``.
    """
    if not PERIOD_MIN_S - 1e-12 <= args.period <= PERIOD_MAX_S + 1e-12:
        raise LocalProtocolError(
            f"--period={args.period} is out of range: allowed {PERIOD_MIN_S}..{PERIOD_MAX_S} s "
            "(LA manual 3.5.3)",
            field="--period",
            value=args.period,
        )
    check_int("--loop", args.loop, 1, MAX_LOOPS)
    check_seconds("--ramp", args.ramp, 0.0)
    if args.ramp > MAX_RAMP_S:
        raise LocalProtocolError(
            f"--ramp={args.ramp} is out of range: allowed 0..{MAX_RAMP_S:g} s",
            field="--ramp",
            value=args.ramp,
        )
    ids = parse_ids(args.ids) if args.ids else None
    trajectory = read_trajectory(Path(args.file), ids, args.period)
    return asyncio.run(_stream(args, trajectory))


def ramp_rows(start: tuple[int, ...], end: tuple[int, ...], ticks: int) -> list[tuple[int, ...]]:
    """``ticks`` rows moving linearly from ``start`` to ``end`` (the last row is ``end``)."""
    return [
        tuple(round(a + (b - a) * k / ticks) for a, b in zip(start, end, strict=True))
        for k in range(1, ticks + 1)
    ]


async def _positions(bus: Bus, ids: list[int], baud: int) -> tuple[int, ...]:
    """Every actuator's reported position; refuses to go on if one does not answer.

    Raises:
        CommandFailed: some actuator did not answer (nothing was streamed).
    """
    positions: list[int] = []
    silent: list[int] = []
    for ident in ids:
        try:
            status = await bus.request(
                la.Control(ident, la.ControlAction.QUERY_STATUS), timeout=CHECK_TIMEOUT_S
            )
        except ReplyTimeoutError:
            silent.append(ident)
            continue
        positions.append(min(max(status.position, 0), la.POSITION_MAX))
    if silent:
        raise CommandFailed(
            f"{plural(len(silent), 'actuator')} of {len(ids)} did not answer a status query "
            f"({', '.join(f'la:{i}' for i in silent)}): nothing streamed; check --ids "
            f"(motorbus scan lists the IDs that answer) and --baud {baud}"
        )
    return tuple(positions)


async def _stream(args: argparse.Namespace, trajectory: Trajectory) -> int:
    rows = trajectory.rows * args.loop
    async with open_bus(args, [Family.LA], host_margin=STREAM_HOST_MARGIN_S) as bus:
        current = await _positions(bus, trajectory.ids, args.baud)
        ramp = ramp_rows(current, rows[0], round(args.ramp / args.period)) if args.ramp else []
        rows = ramp + rows
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in trajectory.ids]
        stream = streamer.follow(
            actuators,
            rows,
            period=args.period,
            feedback=args.feedback,
            safe_action=SafeAction.PAUSE,
        )
        try:
            while not stream.done:
                try:
                    await asyncio.wait_for(stream.wait(), STATS_EVERY_S)
                except TimeoutError:
                    st = stream.stats.summary()
                    print(
                        f"stream: {st['ticks']}/{len(rows)} ticks, {st['late']} late, "
                        f"{st['skipped']} skipped, jitter p99 {st['jitter_p99_us']:.0f} us",
                        file=sys.stderr,
                        flush=True,
                    )
            await stream.wait()  # raises StreamEnded if the stream failed
        except BaseException:
            # Ctrl-C (cancellation) or a failure: pause the actuators before the port closes.
            await stream.stop(safe=True)
            raise
        finally:
            await streamer.close(safe=False)
    summary: dict[str, Any] = {
        "ids": trajectory.ids,
        "rows": len(rows) - len(ramp),
        "ramp_ticks": len(ramp),
        "ramp_from": list(current),
        "period_s": args.period,
        **stream.stats.summary(),
    }
    if args.json:
        print_json(summary)
    else:
        ramp_text = f" ({len(ramp)} of them the ramp)" if ramp else ""
        print(
            f"streamed {summary['ticks']} of {len(rows)} ticks{ramp_text} to la:"
            f"{','.join(map(str, trajectory.ids))} at {args.period * 1e3:g} ms: "
            f"{summary['late']} late, {summary['skipped']} skipped, "
            f"jitter p50 {summary['jitter_p50_us']:.0f} us, p99 {summary['jitter_p99_us']:.0f} us"
        )
    missing = plural(summary["feedback_timeouts"], "feedback reply", "feedback replies")
    if summary["skipped"]:
        cause = (
            f"the actuators answered late ({missing} missing)"
            if summary["feedback_timeouts"]
            else "the host or the port could not keep up (a loaded machine, a slow adapter)"
        )
        print(
            f"motorbus stream: failed: {plural(summary['skipped'], 'tick')} of {len(rows)} "
            f"skipped - those targets were never sent, because a tick started more than a "
            f"period ({args.period * 1e3:g} ms) late: {cause}",
            file=sys.stderr,
        )
        return 1
    if summary["feedback_timeouts"]:
        print(f"motorbus stream: warning: {missing} missing (late or lost)", file=sys.stderr)
    return 0
