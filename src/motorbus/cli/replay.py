"""``motorbus replay``: print a frame log, or send its requests again through a bus.

Examples::

    motorbus replay session.jsonl                   # decoded, with relative times
    motorbus replay session.jsonl --to /dev/ttyUSB1 --dry-run   # what would be sent
    motorbus replay session.jsonl --to /dev/ttyUSB1 # re-send the requests, same timing

``replay FILE`` prints a frame log (docs/frame-log.md) - a capture, or a simulator's
``--log`` such as the demo's ``la-bus-frames.jsonl`` - like ``decode`` does, with times
relative to the first record.  ``replay FILE --to URL`` sends the recorded host-to-device
frames (requests) through a ``Bus`` on URL, at their original times as far as the bus's
spacing and reply waits allow, and prints what goes out and what comes back.  A file
with motion commands is sent only after a yes at the terminal, or with ``--yes``; with
no terminal and no ``--yes`` it is refused (exit code 2).  ``--dry-run`` prints what
would be sent and opens nothing.

``--format jsonl|csv|text`` shows the log as a frame log again (a filtered copy),
as CSV, or as candump-like columns; ``--id``, ``--family``, ``--dir`` and ``--command``
keep only the frames asked for, also for ``--to`` (only the requests they keep are
sent).

``--speed F`` plays the log F times as fast (0.5: half speed).  ``--loop N`` plays it
N times; a pass lasts the recording's span plus its mean gap between requests, so a
periodic recording keeps its rhythm.  Each request goes out from a callback of the
bus's own timer (timerfd on Linux) at its recorded time, as a stream tick does.  A wait
of more than ``--max-gap`` seconds (default 60) between two requests is refused before
anything is sent: a broken or edited file must not leave a replay asleep for days.  A
replay ends through its bus's close, also at Ctrl-C.  ``--connect ENDPOINT`` (instead
of ``--to``) sends the requests through a bus that ``motorbus serve`` owns.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from motorbus import BACKENDS, DEFAULT_BACKEND, Bus, PreparedSubmit, Priority, Transport
from motorbus.cli.bus_options import CLI_HOST_MARGIN_S, LA_BAUD, add_guard_option, open_port
from motorbus.cli.capture import FAMILY_BAUD
from motorbus.cli.logformat import (
    LogWriter,
    add_filter_options,
    add_format_option,
    record_filter,
)
from motorbus.cli.main import UsageError
from motorbus.cli.output import add_json_option, fail, print_json
from motorbus.cli.tee import Tee
from motorbus.cli.values import check_seconds
from motorbus.errors import LocalProtocolError, MotorbusError
from motorbus.protocol import framelog, la, logview, project_stepper, quad_stepper
from motorbus.protocol.base import Command, Direction, Family, check_int, format_hex, parse_hex
from motorbus.protocol.describe import KIND_FRAME, Description, describe
from motorbus.protocol.reassembler import Frame, Reassembler

__all__ = ["describe_command", "load_records", "register", "run_replay"]

#: After the last replayed request, replies are awaited this long by default (seconds):
#: far more than any documented turnaround (LA 800 us, stepper replies tens of ms).
DEFAULT_REPLY_WAIT_S = 0.5
#: Decimal places of the recorded times (microseconds).
TIME_DECIMALS = framelog.TIME_DECIMALS
#: Longest wait between two requests a replay accepts without ``--max-gap`` (seconds).
DEFAULT_MAX_GAP_S = 60.0
#: ``--speed`` range: a thousandth to a thousand times the recorded pace.
MIN_SPEED = 1e-3
MAX_SPEED = 1e3
#: Largest ``--loop``.
MAX_LOOP = 1_000_000
#: Failures shown one by one at the end of a replay (the rest are only counted).
SHOWN_FAILURES = 3
#: Exit status of a refused replay (bad file, motion without consent).
EXIT_USAGE = 2
_DECODERS: dict[Family, Callable[[bytes], Command[object]]] = {
    Family.LA: la.decode_request,
    Family.PROJECT_STEPPER: project_stepper.decode_request,
    Family.QUAD_STEPPER: quad_stepper.decode_request,
}


def register(subparsers: Any) -> None:
    """Add the ``replay`` command."""
    p = subparsers.add_parser(
        "replay",
        help="print a frame log, or send its requests again through a bus",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", metavar="FILE.jsonl")
    p.add_argument("--to", metavar="URL", help="send the recorded requests to this port")
    p.add_argument(
        "--connect",
        metavar="ENDPOINT",
        help="send them instead through the bus a `motorbus serve` serves at this Zenoh "
        "endpoint (--bus NAME where it serves several)",
    )
    p.add_argument("--bus", metavar="NAME", help="with --connect: the served bus to use")
    add_guard_option(p)
    p.add_argument("--baud", type=int, help="bit/s for --to (default: by the recorded family)")
    p.add_argument("--backend", choices=BACKENDS, default=DEFAULT_BACKEND, help="for --to")
    p.add_argument(
        "--wait",
        type=float,
        default=DEFAULT_REPLY_WAIT_S,
        help=f"seconds to await replies after the last request (default {DEFAULT_REPLY_WAIT_S})",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        metavar="FACTOR",
        help=f"with --to: play FACTOR times as fast ({MIN_SPEED:g}..{MAX_SPEED:g}, default 1)",
    )
    p.add_argument(
        "--loop",
        type=int,
        default=1,
        metavar="N",
        help=f"with --to: play the log N times, one pass after the other (1..{MAX_LOOP})",
    )
    p.add_argument(
        "--max-gap",
        type=float,
        default=DEFAULT_MAX_GAP_S,
        metavar="SECONDS",
        help="with --to: refuse a wait between two requests longer than this "
        f"(default {DEFAULT_MAX_GAP_S:g} s, at --speed)",
    )
    p.add_argument(
        "--dry-run", action="store_true", help="with --to: print what would be sent, send nothing"
    )
    p.add_argument(
        "--yes", action="store_true", help="with --to: send motion commands without asking"
    )
    add_format_option(p, None)
    add_filter_options(p, family=True)
    add_json_option(p)
    p.set_defaults(func=run_replay)


def load_log(path: Path) -> framelog.FrameLog:
    """Read a frame log (docs/frame-log.md), every line checked.

    Raises:
        LocalProtocolError: a line is not a frame-log record (the message names the
            file, the line and the missing or bad key).
        OSError: the file cannot be read.
    """
    with path.open("rb") as fh:  # bytes: a line that is not UTF-8 is named
        return framelog.read_frame_log(fh, str(path))


def load_records(path: Path) -> list[dict[str, Any]]:
    """Read a frame log; return its records, times made continuous.

    Each record gets ``t`` relative to the first record of the file: a later session
    (the simulator appends to its log) continues where the one before ended, so times
    only grow.  The simulator's pre-version-1 lines are translated.

    Raises:
        LocalProtocolError, OSError: as :func:`load_log`.
    """
    return framelog.continuous_times(load_log(path))


@dataclass(frozen=True, slots=True)
class _Planned:
    """One recorded request, decoded back into the command a ``Bus`` sends."""

    t: float
    cmd: Command[object]
    priority: Priority
    line: int


def run_replay(args: argparse.Namespace) -> int:
    """Run ``motorbus replay``; return 0, 1 if a request sent failed, 2 when motion is refused.

    Raises:
        LocalProtocolError: a bad file, ``--wait``, ``--baud``, ``--speed``, ``--loop`` or
            ``--max-gap``, or a wait between two requests over ``--max-gap``.
        UsageError: ``--dry-run``, ``--yes``, ``--speed``, ``--loop`` or ``--max-gap``
            without ``--to``; ``--format`` with ``--json`` or ``--to``.
        OSError: the file or the ``--to`` port cannot be opened.
    """
    check_seconds("--wait", args.wait)
    check_seconds("--max-gap", args.max_gap, 1e-3)
    if not MIN_SPEED <= args.speed <= MAX_SPEED:  # False for nan too
        raise LocalProtocolError(
            f"--speed={args.speed} is out of range: allowed {MIN_SPEED:g}..{MAX_SPEED:g} "
            "(times the recorded pace)",
            field="--speed",
            value=args.speed,
        )
    check_int("--loop", args.loop, 1, MAX_LOOP)
    keep = record_filter(args)
    if args.connect is not None:
        if args.to is not None:
            raise UsageError("--connect uses a served bus: give it without --to")
        if args.baud is not None:
            raise UsageError("--baud goes with --to: a served bus has its server's rate")
        args.to = f"bus {args.bus or '(the only one)'} at {args.connect}"
    elif args.bus is not None:
        raise UsageError("--bus goes with --connect ENDPOINT")
    if args.format is not None and (args.json or args.to is not None):
        raise UsageError("--format shows a log: it goes neither with --json nor with --to")
    path = Path(args.file)
    log = load_log(path)
    records = framelog.continuous_times(log)
    if args.to is None:
        if args.dry_run or args.yes:
            raise UsageError("--dry-run and --yes go with --to URL")
        if (args.speed, args.loop, args.max_gap) != (1.0, 1, DEFAULT_MAX_GAP_S):
            raise UsageError("--speed, --loop and --max-gap go with --to URL")
        _show_log(args, log, records, keep)
        return 0
    records = [r for r in records if keep.keeps(r, framelog.describe_record(r))]
    families = _families(log, records)
    if args.baud is None:
        args.baud = min((FAMILY_BAUD[f] for f in families), default=LA_BAUD)
    plan = _plan(log, records, path)
    _check_gaps(plan, args.speed, args.max_gap, path)
    families |= {item.cmd.family for item in plan}
    if args.dry_run:
        for item in plan:
            d = describe_command(item.cmd)
            _show(args, round(item.t / args.speed, TIME_DECIMALS), d, prefix="would send ")
        passes = f", {args.loop} times" if args.loop > 1 else ""
        print(
            f"motorbus replay: dry run, {len(plan)} requests would be sent to {args.to}{passes}",
            file=sys.stderr,
        )
        return 0
    motion = [item for item in plan if item.cmd.starts_motion]
    if motion and not args.yes and not _confirm(args, len(plan), motion):
        return EXIT_USAGE
    if args.connect is not None:
        return asyncio.run(_replay_served(args, plan))
    transport = open_port(args, url=args.to)
    return asyncio.run(_replay(args, transport, plan, families or {Family.LA}))


def _families(log: framelog.FrameLog, records: list[dict[str, Any]]) -> set[Family]:
    """The families of the bus to replay on: its headers' (a headerless log: its records')."""
    named = {Family(f) for h in log.headers for f in h.get("families", ())}
    return named or {Family(r["family"]) for r in records if r.get("family") is not None}


def _check_gaps(plan: list[_Planned], speed: float, max_gap: float, path: Path) -> None:
    """Refuse a wait longer than ``max_gap`` between two requests (at ``speed``).

    Raises:
        LocalProtocolError: naming both lines, the wait and ``--max-gap``.
    """
    latest: _Planned | None = None
    for item in plan:
        if latest is not None:
            gap = (item.t - latest.t) / speed
            if gap > max_gap:
                raise LocalProtocolError(
                    f"{path} line {item.line}: a wait of {gap:.6g} s after the request on "
                    f"line {latest.line} is over --max-gap={max_gap:g} s (pass a larger "
                    "--max-gap to replay it); nothing was sent",
                    field="--max-gap",
                    value=gap,
                )
        if latest is None or item.t > latest.t:
            latest = item


_FAMILY_VALUES = frozenset(f.value for f in Family)


def _show_log(
    args: argparse.Namespace,
    log: framelog.FrameLog,
    records: list[dict[str, Any]],
    keep: logview.RecordFilter,
) -> None:
    """Print the records ``keep`` passes, in ``--format`` (default: decoded lines)."""
    if args.format is None:
        for record in records:
            if keep.keeps(record, framelog.describe_record(record)):
                _print_record(args, record)
        return
    writer = LogWriter(sys.stdout, args.format, keep)
    if args.format == "jsonl":
        # A frame log again: each session's header, the records with their own times.
        session = -1
        for record in log.records:
            if record["session"] != session:
                session = record["session"]
                if log.headers[session]:
                    writer.header(log.headers[session])
            writer.write(record)
        return
    writer.header({})
    for record in records:
        writer.write(record)


def _print_record(args: argparse.Namespace, record: dict[str, Any]) -> None:
    t = float(record["t"])
    fault = record.get("fault")
    if record["kind"] == framelog.KIND_LINK:
        if args.json:
            print_json({k: v for k, v in record.items() if k not in ("session", "line")})
        else:
            print(f"{t:10.6f}  link {record.get('name')}" + (f"  fault={fault}" if fault else ""))
        return
    for d in framelog.describe_record(record):
        if args.json:
            doc: dict[str, Any] = {"t": t, **d.to_json()}
            if fault:
                doc["fault"] = fault
            print_json(doc)
        else:
            print(f"{t:10.6f}  {d.to_line()}" + (f"  fault={fault}" if fault else ""))


def _plan(log: framelog.FrameLog, records: list[dict[str, Any]], path: Path) -> list[_Planned]:
    """Decode every recorded request into a command; refuse what cannot be re-sent.

    Raises:
        LocalProtocolError: a request no decoder accepts, or one whose command would not
            encode to the recorded bytes, or a frame of a family its session's header
            does not name (naming the record and its bytes); nothing is sent.
    """
    plan: list[_Planned] = []
    for record in records:
        n = record.get("line", "?")
        if record["kind"] != KIND_FRAME or record.get("direction") != Direction.REQUEST.value:
            continue
        raw = parse_hex(str(record["hex"]))
        family = _family_of(record, raw)
        named = log.headers[record["session"]].get("families")
        if named is not None and family.value not in named:
            raise LocalProtocolError(
                f"{path} line {n}: request {format_hex(raw)} is a {family.value} frame; "
                f"the session's header names {', '.join(named)}; nothing was sent",
                field="file",
            )
        try:
            cmd = _DECODERS[family](raw)
        except (MotorbusError, ValueError) as err:
            raise LocalProtocolError(
                f"{path} line {n}: request {format_hex(raw)} cannot be re-sent: {err}; "
                "nothing was sent",
                field="file",
            ) from err
        if cmd.encode() != raw:
            raise LocalProtocolError(
                f"{path} line {n}: request {format_hex(raw)} decodes to "
                f"{type(cmd).__name__}, which encodes as {format_hex(cmd.encode())}; "
                "nothing was sent",
                field="file",
            )
        plan.append(_Planned(float(record["t"]), cmd, _priority(cmd), int(n)))
    return plan


def _family_of(record: dict[str, Any], raw: bytes) -> Family:
    value = record.get("family")
    if value in _FAMILY_VALUES:
        return Family(value)
    cutter = Reassembler(direction=Direction.REQUEST, families=tuple(Family))
    frames = [i for i in cutter.feed(raw) + cutter.end_of_stream() if isinstance(i, Frame)]
    return frames[0].family if frames else Family.LA


def _priority(cmd: Command[object]) -> Priority:
    """The priority the device layer gives such a command (``devices.la``)."""
    if isinstance(cmd, la.Control):
        if cmd.action is la.ControlAction.ESTOP:
            return Priority.EMERGENCY
        if cmd.action is not la.ControlAction.QUERY_STATUS:
            return Priority.HIGH
    return Priority.NORMAL


def describe_command(cmd: Command[object]) -> Description:
    """The description of a command's request bytes."""
    cutter = Reassembler(direction=Direction.REQUEST, families=(cmd.family,))
    items = cutter.feed(cmd.encode()) + cutter.end_of_stream()
    return describe(items[0])


def _confirm(args: argparse.Namespace, total: int, motion: list[_Planned]) -> bool:
    """Ask at the terminal before sending motion; ``False`` (and a message) to refuse."""
    names = sorted({type(item.cmd).__name__ for item in motion})
    what = (
        f"{args.file} has {len(motion)} motion command{'s' if len(motion) != 1 else ''} "
        f"({', '.join(names)}) among {total} requests"
        + (f", played {args.loop} times" if args.loop > 1 else "")
    )
    if not sys.stdin.isatty():
        print(
            f"motorbus replay: {what}; not sent: pass --yes to send them "
            "(no terminal to ask on), or --dry-run to see them",
            file=sys.stderr,
        )
        return False
    print(f"motorbus replay: {what}. Send them to {args.to}? [y/N] ", end="", file=sys.stderr)
    sys.stderr.flush()
    try:
        answer = sys.stdin.readline()
    except KeyboardInterrupt:
        answer = ""
    if answer.strip().lower() in ("y", "yes"):
        return True
    print("motorbus replay: not sent", file=sys.stderr)
    return False


async def _replay(
    args: argparse.Namespace,
    transport: Transport,
    plan: list[_Planned],
    families: set[Family],
) -> int:
    hint = next(iter(families)) if len(families) == 1 else None
    replies = Reassembler(direction=Direction.REPLY, families=families)
    requests = Reassembler(direction=Direction.REQUEST, families=families)
    # What the replay sent and heard, and apart from it what the bus sent as it closed
    # (the safe action owed for motion the replay started: leases, docs/leases.md).
    counts = {"replies": 0, "safe": 0, "closing": 0}
    started = time.monotonic()  # the bus timer's clock; reset when sending starts

    def now() -> float:
        return round(time.monotonic() - started, TIME_DECIMALS)

    def on_sent(data: bytes) -> None:
        for item in requests.feed(data):
            counts["safe"] += counts["closing"]
            _show(args, now(), describe(item, family_hint=hint))

    def on_received(data: bytes) -> None:
        for item in replies.feed(data):
            counts["replies"] += 1 - counts["closing"]
            _show(args, now(), describe(item, family_hint=hint))

    bus = Bus(
        Tee(transport, on_sent, on_received),
        name=transport.url,
        families=families,
        host_margin=CLI_HOST_MARGIN_S,
        reconnect=False,
    )
    try:
        await bus.open()
    except OSError as err:
        raise OSError(f"cannot open port {transport.url}: {err}") from err
    try:
        started = bus.timer.now()
        sender = _Sender(bus, _schedule(plan, started, args.speed, args.loop))
        await sender.run()
        await bus.timer.sleep_until(bus.timer.now() + args.wait)
    finally:
        counts["closing"] = 1
        await bus.close()
    for failure in sender.failures:
        print(f"motorbus replay: {failure}", file=sys.stderr)
    passes = f" ({args.loop} passes)" if args.loop > 1 else ""
    safe = counts["safe"]
    closing = (
        f"; then {safe} safe-stop frame{'s' if safe != 1 else ''} as the bus closed" if safe else ""
    )
    print(
        f"motorbus replay: {sender.sent} requests sent to {transport.url} through a bus"
        f"{passes}, {counts['replies']} replies, {sender.failed} failed (timeouts or bad "
        f"replies){closing}",
        file=sys.stderr,
    )
    if sender.failed:  # a device that did not answer fails the command, as everywhere
        return fail(
            args,
            f"{sender.failed} of {sender.sent} requests failed (timeouts or bad replies)",
            port=transport.url,
        )
    return 0


async def _replay_served(args: argparse.Namespace, plan: list[_Planned]) -> int:
    """``--connect``: each request through the served bus at its recorded time (the
    server paces the wire; its reply comes back decoded, so the replies are counted).
    Motion the replay started ends with the client: the server sends its safe action."""
    from motorbus.cli.bus_options import served_bus

    async with served_bus(args.connect, args.bus) as bus:
        timer = bus.timer
        start = timer.now()
        sent = replies = 0
        failures: list[BaseException] = []
        pending: list[asyncio.Future[Any]] = []
        for deadline, item in _schedule(plan, start, args.speed, args.loop):
            await timer.sleep_until(deadline)
            _show(args, round(timer.now() - start, TIME_DECIMALS), describe_command(item.cmd))
            pending.append(bus.submit(item.cmd, retries=0, priority=item.priority))
            sent += 1
        for future in pending:
            try:
                value = await future
            except MotorbusError as err:
                failures.append(err)
            else:
                replies += value is not None
        await timer.sleep_until(timer.now() + args.wait)
    for failure in failures[:SHOWN_FAILURES]:
        print(f"motorbus replay: {failure}", file=sys.stderr)
    passes = f" ({args.loop} passes)" if args.loop > 1 else ""
    print(
        f"motorbus replay: {sent} requests sent to {args.to} through a served bus{passes}, "
        f"{replies} replies, {len(failures)} failed (timeouts or bad replies)",
        file=sys.stderr,
    )
    if failures:
        return fail(
            args,
            f"{len(failures)} of {sent} requests failed (timeouts or bad replies)",
            port=args.to,
        )
    return 0


def _schedule(
    plan: list[_Planned], start: float, speed: float, loops: int
) -> Iterator[tuple[float, _Planned]]:
    """Yield (deadline on the bus timer's clock, request) for every pass of the plan.

    A pass lasts the plan's span plus its mean gap between requests, so a periodic
    recording keeps its rhythm across passes (requests at 0, 10 and 20 ms repeat at 30,
    40 and 50 ms); a one-request plan repeats back to back, as fast as the bus allows.
    Times are divided by ``speed``.
    """
    if not plan:
        return
    t0 = plan[0].t
    span = max(item.t for item in plan) - t0
    period = span + span / (len(plan) - 1) if len(plan) > 1 else 0.0
    for k in range(loops):
        for item in plan:
            yield start + (k * period + max(0.0, item.t - t0)) / speed, item


class _Sender:
    """Submits each request to the bus from a timer callback at its deadline.

    One timer handle at a time: each callback submits its request and arms the next.
    The bus paces what it is given (spacing, one request while a reply is owed), so a
    request due while the bus is busy goes out as soon as the bus allows.
    """

    def __init__(self, bus: Bus, schedule: Iterator[tuple[float, _Planned]]) -> None:
        self.bus = bus
        self.schedule = schedule
        self.sent = 0
        self.failed = 0
        self.failures: list[BaseException] = []
        self._outstanding = 0
        self._submitted_all = False
        self._done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._cancel: Callable[[], None] | None = None  # the armed timer handle's

    async def run(self) -> None:
        """Send every request; return once each has its reply, timeout or error.

        Raises:
            MotorbusError: the bus refused a request (its port was lost, say).
        """
        self._arm_next()
        try:
            await self._done
        finally:
            if self._cancel is not None:
                self._cancel()

    def _arm_next(self) -> None:
        entry = next(self.schedule, None)
        if entry is None:
            self._submitted_all = True
            self._check_done()
            return
        deadline, item = entry
        try:
            # Checked and built now, so that at the deadline only the write is left (as a
            # stream tick is). No retries: a replay sends what was recorded, once.
            prepared = self.bus.prepare(item.cmd, retries=0, priority=item.priority)
        except MotorbusError as err:
            self._done.set_exception(err)
            return
        self._cancel = self.bus.timer.call_at(deadline, lambda: self._fire(prepared)).cancel

    def _fire(self, prepared: PreparedSubmit[Any]) -> None:
        self._cancel = None
        if self._done.done():
            return
        try:
            future = self.bus.send_prepared(prepared)
        except MotorbusError as err:
            self._done.set_exception(err)
            return
        self.sent += 1
        self._outstanding += 1
        future.add_done_callback(self._on_reply)
        self._arm_next()

    def _on_reply(self, future: asyncio.Future[Any]) -> None:
        self._outstanding -= 1
        if not future.cancelled() and future.exception() is not None:
            self.failed += 1
            if len(self.failures) < SHOWN_FAILURES:
                self.failures.append(future.exception())  # type: ignore[arg-type]
        self._check_done()

    def _check_done(self) -> None:
        if self._submitted_all and self._outstanding == 0 and not self._done.done():
            self._done.set_result(None)


def _show(args: argparse.Namespace, t: float, d: Description, prefix: str = "") -> None:
    if args.json:
        print_json({"t": t, **d.to_json()})
    else:
        print(f"{prefix}{t:10.6f}  {d.to_line()}", flush=True)
