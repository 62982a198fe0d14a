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

Before the first tick every listed actuator must answer a status query and report
no fault (else nothing is streamed, exit code 1), and is enabled ("work", so an
e-stopped actuator moves again; --no-enable sends nothing of the kind: the LA status
does not report its power state, so a paused or e-stopped actuator is then only found
out by not moving).  Each is ramped from the position it reports to its first target
over --ramp seconds (default 1; --ramp 0 jumps straight there), so the first row does
not become a full-speed lunge.

The stream checks that the actuators follow: it polls their status in the slots a tick
leaves free (or reads the feedback replies) and reads each position at the end.  An
actuator asked to move more than 10 units that never moved more than 10 units from
where it started is reported ("did not follow") and makes the exit code 1; once a
status read 0.5 s after it was asked to move shows that, the stream stops there (the
others would go on without it).  Where no poll fits between the ticks (a host margin
longer than a tick leaves free; a served bus's is the server's), only the final
position is read: an actuator that ended at its last target is taken to have followed.

At the end (the last row, or a failure) the actuators are paused.  If the port is lost
and comes back, the stream reads each position and ramps back to the trajectory at
500 units/s, and the gap is reported.

Without --feedback the targets go out as 0xF3 broadcasts, one frame a tick; with
it, each actuator gets a 0x20 frame and answers with its status.  Live statistics
(ticks, late, skipped, jitter p99) go to standard error once a second; the final
summary to standard output (JSON with --json).  Skipped ticks (targets never sent)
or unanswered feedback make the exit code 1, and standard error says which.
Ctrl-C stops the stream and pauses the actuators (exit code 130).

With --bus-file F --process NAME the bus is one of that process group's (its only one
needs no --bus), and the stream runs on the CPUs the group's [process.NAME] table gives.

With --connect ENDPOINT [--bus NAME] the bus is one a `motorbus serve` serves there: the
stream ticks on the server's timer, this command sends the rows ahead of their ticks
(docs/serve.md), and its safe end is the server's too, however this command ends.
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
from motorbus.cli.bus_options import (
    LA_BAUD,
    add_bus_options,
    add_guard_option,
    add_process_option,
    open_bus,
)
from motorbus.cli.ids import check_ids, parse_ids
from motorbus.cli.output import error_doc, plural, print_json
from motorbus.cli.values import check_seconds
from motorbus.errors import (
    CommandFailed,
    LocalProtocolError,
    MotorbusError,
    ReplyTimeoutError,
    StreamEnded,
    UsageError,
)
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int

__all__ = [
    "FollowCheck",
    "Trajectory",
    "check_actuators",
    "ramp_rows",
    "read_trajectory",
    "register",
    "run",
]

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
#: An actuator asked to move farther than this (position units) must move farther than
#: this from where it started, or it did not follow.
FOLLOW_TOLERANCE = 10
#: An actuator whose status this long after it was asked to move shows it has not stops
#: the stream (seconds): the LA follows a target within a tick or two.
FOLLOW_GRACE_S = 0.5


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
    p.add_argument(
        "--no-enable",
        action="store_true",
        help='do not send "work" first (a paused or e-stopped actuator will not follow)',
    )
    p.add_argument("--loop", type=int, default=1, help="play the rows N times (default 1)")
    p.add_argument(
        "--ramp",
        type=float,
        default=DEFAULT_RAMP_S,
        metavar="SECONDS",
        help=f"move from the reported positions to the first row over this time "
        f"(default {DEFAULT_RAMP_S:g}; 0 = no ramp)",
    )
    add_bus_options(p, default_baud=LA_BAUD, connect=True)
    add_process_option(p)
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
    """Run ``motorbus stream``; return 0 if every tick went out and every actuator
    followed, 1 if some ticks were skipped or some actuator did not follow.

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
    if getattr(args, "connect", None) and (args.process or args.guard):
        raise UsageError("--connect streams on the server: --process and --guard are its own")
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


async def check_actuators(bus: Bus, ids: list[int], baud: int) -> list[la.Status]:
    """Every actuator's status; refuses to go on if one does not answer or is faulted.

    Raises:
        CommandFailed: some actuator did not answer, or reports a fault (nothing was
            streamed).
    """
    statuses: list[la.Status] = []
    silent: list[int] = []
    for ident in ids:
        try:
            status = await bus.request(
                la.Control(ident, la.ControlAction.QUERY_STATUS), timeout=CHECK_TIMEOUT_S
            )
        except ReplyTimeoutError:
            silent.append(ident)
            continue
        statuses.append(status)
    if silent:
        raise CommandFailed(
            f"{plural(len(silent), 'actuator')} of {len(ids)} did not answer a status query "
            f"({', '.join(f'la:{i}' for i in silent)}): nothing streamed; check --ids "
            f"(motorbus scan lists the IDs that answer) and --baud {baud}"
        )
    faulted = [s for s in statuses if s.fault]
    if faulted:
        names = "; ".join(f"la:{s.id} {_fault_names(s)}" for s in faulted)
        raise CommandFailed(
            f"{plural(len(faulted), 'actuator')} of {len(ids)} report a fault ({names}): "
            f"nothing streamed; a faulted actuator does not move (motorbus la clear "
            f"{','.join(str(s.id) for s in faulted)} clears stall, over-current and "
            "motor-abnormal faults)"
        )
    return statuses


def _fault_names(status: la.Status) -> str:
    """``stall``, ``over-current|stall``...: the defined fault bits a status reports."""
    faults = status.errors & la.KNOWN_ERROR_BITS
    return " and ".join(
        flag.name.lower().replace("_", "-")
        for flag in la.ErrorFlags
        if flag & faults and flag.name is not None
    )


async def _enable(bus: Bus, ids: list[int]) -> None:
    """Send "work" to every actuator (an e-stopped LA ignores targets until then)."""
    for ident in ids:
        await bus.request(
            la.Control(ident, la.ControlAction.WORK), timeout=CHECK_TIMEOUT_S, retries=1
        )


async def _final_positions(bus: Bus, ids: list[int]) -> dict[int, int]:
    """Each actuator's position after the stream (those that answer)."""
    found: dict[int, int] = {}
    for ident in ids:
        try:
            status = await bus.request(
                la.Control(ident, la.ControlAction.QUERY_STATUS), timeout=CHECK_TIMEOUT_S
            )
        except MotorbusError:
            continue
        found[ident] = status.position
    return found


class FollowCheck:
    """Whether each actuator moved when the targets asked it to.

    ``source`` is the stream's target function: it plays ``rows`` and records how far
    each actuator's reported position (polls or feedback) got from where it started.
    Where the stream read no status of an actuator (its polls did not fit between the
    ticks: a host margin longer than a tick leaves, as a served bus may have), only its
    final position is known: it is taken to have followed if that is its last target.
    An actuator asked to move beyond ``FOLLOW_TOLERANCE`` whose status, first read
    ``FOLLOW_GRACE_S`` or more after that, shows it has not ends the stream there
    (``CommandFailed``; ``stopped_at`` is the tick): the others would go on without it.
    """

    def __init__(self, ids: list[int], start: tuple[int, ...], rows: list[tuple[int, ...]]):
        self.ids = ids
        self.start = dict(zip(ids, start, strict=True))
        #: How far the targets sent so far asked each actuator to move.
        self.asked = dict.fromkeys(ids, 0)
        self.moved = dict.fromkeys(ids, 0)
        self.rows = rows
        self.stopped_at: int | None = None
        #: Per actuator, the last status the stream read and the tick it was first seen.
        self.fresh: dict[int, tuple[la.Status, int]] = {}
        #: The last row sent.
        self.last: tuple[int, ...] | None = None

    def source(self, period: float) -> Any:
        rows, start, moved, asked, ids = self.rows, self.start, self.moved, self.asked, self.ids
        grace = max(1, round(FOLLOW_GRACE_S / period))
        asked_at: dict[int, int] = {}  # the first tick whose target is beyond tolerance
        fresh = self.fresh

        def targets(t: float, statuses: dict[int, la.Status]) -> tuple[int, ...] | None:
            k = round(t / period)
            for ident, status in statuses.items():
                seen = fresh.get(ident)
                if seen is None or seen[0] is not status:
                    fresh[ident] = (status, k)
                    moved[ident] = max(moved[ident], abs(status.position - start[ident]))
            stuck = [
                i
                for i, since in asked_at.items()
                if moved[i] <= FOLLOW_TOLERANCE and i in fresh and fresh[i][1] >= since + grace
            ]
            if stuck:
                self.stopped_at = k
                raise CommandFailed(
                    f"{', '.join(f'la:{i}' for i in stuck)} did not move "
                    f"{FOLLOW_GRACE_S:g} s after being asked to: stream stopped"
                )
            if k >= len(rows):
                return None
            row = self.last = rows[k]
            for n, ident in enumerate(ids):
                distance = abs(row[n] - start[ident])
                if distance > asked[ident]:
                    asked[ident] = distance
                    if distance > FOLLOW_TOLERANCE and ident not in asked_at:
                        asked_at[ident] = k
            return row

        return targets

    def not_following(self, final: dict[int, int]) -> list[int]:
        """The actuators asked to move beyond ``FOLLOW_TOLERANCE`` that never did.

        One of which the stream read no status and that ended at its last target (a
        trajectory back to where it started) is not among them: nothing says that it
        did not follow.
        """
        for ident, position in final.items():
            self.moved[ident] = max(self.moved[ident], abs(position - self.start[ident]))
        last = dict(zip(self.ids, self.last or (), strict=False))

        def at_last_target(i: int) -> bool:
            return i in final and i in last and abs(final[i] - last[i]) <= FOLLOW_TOLERANCE

        return [
            i
            for i in self.ids
            if self.asked[i] > FOLLOW_TOLERANCE
            and self.moved[i] <= FOLLOW_TOLERANCE
            and (i in self.fresh or not at_last_target(i))
        ]


async def _stream(args: argparse.Namespace, trajectory: Trajectory) -> int:
    rows = trajectory.rows * args.loop
    async with open_bus(args, [Family.LA], host_margin=STREAM_HOST_MARGIN_S) as bus:
        statuses = await check_actuators(bus, trajectory.ids, args.baud)
        current = tuple(min(max(s.position, 0), la.POSITION_MAX) for s in statuses)
        if not args.no_enable:
            await _enable(bus, trajectory.ids)
        ramp = ramp_rows(current, rows[0], round(args.ramp / args.period)) if args.ramp else []
        rows = ramp + rows
        check = FollowCheck(trajectory.ids, current, rows)
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in trajectory.ids]
        stream = streamer.follow(
            actuators,
            check.source(args.period),
            period=args.period,
            feedback=args.feedback,
            poll_status=not args.feedback,
            safe_action=SafeAction.PAUSE,
        )
        try:
            while not stream.done:
                try:
                    await asyncio.wait_for(stream.wait(), STATS_EVERY_S)
                except TimeoutError:
                    st = stream.stats.as_dict()
                    print(
                        f"stream: {st['ticks']}/{len(rows)} ticks, {st['late']} late, "
                        f"{st['skipped']} skipped, jitter p99 {st['jitter_p99_us']:.0f} us",
                        file=sys.stderr,
                        flush=True,
                    )
            await stream.wait()  # raises StreamEnded if the stream failed
        except StreamEnded as err:
            if not isinstance(err.__cause__, CommandFailed):
                await stream.stop()
                raise
            # The follow check stopped the stream (with its pause): reported below.
        except BaseException:
            # Ctrl-C (cancellation) or a failure: pause the actuators before the port closes.
            await stream.stop()
            raise
        finally:
            await streamer.close()
        # The stream ended with its safe action (a pause): where did each actuator get?
        final = await _final_positions(bus, trajectory.ids)
    lagging = check.not_following(final)
    summary: dict[str, Any] = {
        "ids": trajectory.ids,
        "rows": len(rows) - len(ramp),
        "ramp_ticks": len(ramp),
        "ramp_from": list(current),
        "period_s": args.period,
        "enabled": not args.no_enable,
        "not_following": lagging,
        **stream.stats.as_dict(),
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
    failures: list[str] = []
    if lagging:
        hint = (
            "--no-enable was given: are they paused or e-stopped (motorbus la enable)?"
            if args.no_enable
            else "faulted, blocked, or not powered?"
        )
        moved = ", ".join(
            f"la:{i} asked to move {check.asked[i]}, moved {check.moved[i]}" for i in lagging
        )
        stopped = (
            f"; stopped at tick {check.stopped_at} of {len(rows)}"
            if check.stopped_at is not None
            else ""
        )
        failures.append(
            f"{plural(len(lagging), 'actuator')} of "
            f"{len(trajectory.ids)} did not follow ({moved}; tolerance {FOLLOW_TOLERANCE}"
            f"{stopped}): {hint}"
        )
    if summary["gaps"]:
        print(
            f"motorbus stream: warning: {plural(summary['gaps'], 'gap')} (the port was lost, "
            "or the host stalled): the stream read the positions and ramped back",
            file=sys.stderr,
        )
    missing = plural(summary["feedback_timeouts"], "feedback reply", "feedback replies")
    if summary["skipped"]:
        cause = (
            f"the actuators answered late ({missing} missing)"
            if summary["feedback_timeouts"] and args.feedback
            else "the host or the port could not keep up (a loaded machine, a slow adapter)"
        )
        failures.append(
            f"{plural(summary['skipped'], 'tick')} of {len(rows)} "
            f"skipped - those targets were never sent, because a tick started more than a "
            f"period ({args.period * 1e3:g} ms) late: {cause}"
        )
    elif summary["feedback_timeouts"] and args.feedback and not failures:
        print(f"motorbus stream: warning: {missing} missing (late or lost)", file=sys.stderr)
    if not failures:
        return 0
    for text in failures:
        print(f"motorbus stream: failed: {text}", file=sys.stderr)
    if args.json:  # one error object after the summary, naming every failure
        doc = error_doc("stream", "failed: " + "; ".join(failures), 1, port=args.port)
        print_json({**doc, "not_following": lagging, "skipped": summary["skipped"]})
    return 1
