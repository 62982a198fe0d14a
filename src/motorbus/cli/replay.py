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
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from motorbus import BACKENDS, DEFAULT_BACKEND, Bus, Priority, Transport
from motorbus.cli.capture import FAMILY_BAUD
from motorbus.cli.common import (
    CLI_HOST_MARGIN_S,
    LA_BAUD,
    add_json_option,
    check_seconds,
    open_port,
    print_json,
)
from motorbus.cli.main import UsageError
from motorbus.cli.tee import Tee
from motorbus.errors import LocalProtocolError, MotorbusError
from motorbus.protocol import framelog, la, project_stepper, quad_stepper
from motorbus.protocol.base import Command, Direction, Family, format_hex, parse_hex
from motorbus.protocol.describe import KIND_FRAME, Description, describe
from motorbus.protocol.reassembler import Frame, Reassembler

__all__ = ["describe_command", "load_records", "register", "run_replay"]

#: After the last replayed request, replies are awaited this long by default (seconds):
#: far more than any documented turnaround (LA 800 us, stepper replies tens of ms).
DEFAULT_REPLY_WAIT_S = 0.5
#: Decimal places of the recorded times (microseconds).
TIME_DECIMALS = framelog.TIME_DECIMALS
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
    p.add_argument("--baud", type=int, help="bit/s for --to (default: by the recorded family)")
    p.add_argument("--backend", choices=BACKENDS, default=DEFAULT_BACKEND, help="for --to")
    p.add_argument(
        "--wait",
        type=float,
        default=DEFAULT_REPLY_WAIT_S,
        help=f"seconds to await replies after the last request (default {DEFAULT_REPLY_WAIT_S})",
    )
    p.add_argument(
        "--dry-run", action="store_true", help="with --to: print what would be sent, send nothing"
    )
    p.add_argument(
        "--yes", action="store_true", help="with --to: send motion commands without asking"
    )
    add_json_option(p)
    p.set_defaults(func=run_replay)


def load_records(path: Path) -> list[dict[str, Any]]:
    """Read a frame log (docs/frame-log.md); return its records, times made continuous.

    Each record gets ``t`` relative to the first record of the file: a later session
    (the simulator appends to its log) continues where the one before ended, so times
    only grow.  The simulator's pre-version-1 lines are translated.

    Raises:
        LocalProtocolError: a line is not a frame-log record (the message names the line
            and the missing or bad key).
        OSError: the file cannot be read.
    """
    with path.open(encoding="utf-8") as fh:
        log = framelog.read_frame_log(fh, str(path))
    records: list[dict[str, Any]] = []
    offset = 0.0
    session = 0
    first: float | None = None
    last = 0.0
    for record in log.records:
        t = float(record["t"])
        if first is None:
            first = t
        if record["session"] != session:
            session = record["session"]
            offset = last - t
        rel = round(t - first + offset, TIME_DECIMALS)
        last = rel + first
        records.append({**record, "t": rel})
    return records


@dataclass(frozen=True, slots=True)
class _Planned:
    """One recorded request, decoded back into the command a ``Bus`` sends."""

    t: float
    cmd: Command[object]
    priority: Priority


def run_replay(args: argparse.Namespace) -> int:
    """Run ``motorbus replay``; return 0, or 2 when motion is refused.

    Raises:
        LocalProtocolError: a bad file, ``--wait`` or ``--baud``.
        UsageError: ``--dry-run`` or ``--yes`` without ``--to``.
        OSError: the file or the ``--to`` port cannot be opened.
    """
    check_seconds("--wait", args.wait)
    records = load_records(Path(args.file))
    if args.to is None:
        if args.dry_run or args.yes:
            raise UsageError("--dry-run and --yes go with --to URL")
        for record in records:
            _print_record(args, record)
        return 0
    families = {Family(r["family"]) for r in records if r.get("family") in _FAMILY_VALUES}
    if args.baud is None:
        args.baud = min((FAMILY_BAUD[f] for f in families), default=LA_BAUD)
    plan = _plan(records, Path(args.file))
    families |= {item.cmd.family for item in plan}
    if args.dry_run:
        for item in plan:
            d = describe_command(item.cmd)
            _show(args, item.t, d, prefix="would send ")
        print(
            f"motorbus replay: dry run, {len(plan)} requests would be sent to {args.to}",
            file=sys.stderr,
        )
        return 0
    motion = [item for item in plan if item.cmd.starts_motion]
    if motion and not args.yes and not _confirm(args, len(plan), motion):
        return EXIT_USAGE
    transport = open_port(args, url=args.to)
    return asyncio.run(_replay(args, transport, plan, families or {Family.LA}))


_FAMILY_VALUES = frozenset(f.value for f in Family)


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


def _plan(records: list[dict[str, Any]], path: Path) -> list[_Planned]:
    """Decode every recorded request into a command; refuse what cannot be re-sent.

    Raises:
        LocalProtocolError: a request no decoder accepts, or one whose command would not
            encode to the recorded bytes (naming the record and its bytes); nothing is sent.
    """
    plan: list[_Planned] = []
    for record in records:
        n = record.get("line", "?")
        if record["kind"] != KIND_FRAME or record.get("direction") != Direction.REQUEST.value:
            continue
        raw = parse_hex(str(record["hex"]))
        family = _family_of(record, raw)
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
        plan.append(_Planned(float(record["t"]), cmd, _priority(cmd)))
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
    started = time.monotonic()
    counts = {"replies": 0}

    def now() -> float:
        return round(time.monotonic() - started, TIME_DECIMALS)

    def on_sent(data: bytes) -> None:
        for item in requests.feed(data):
            _show(args, now(), describe(item, family_hint=hint))

    def on_received(data: bytes) -> None:
        for item in replies.feed(data):
            counts["replies"] += 1
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
    futures: list[asyncio.Future[Any]] = []
    try:
        t0 = plan[0].t if plan else 0.0
        for item in plan:
            delay = started + (item.t - t0) - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            # No retries: a replay sends what was recorded, once.
            futures.append(bus.submit(item.cmd, retries=0, priority=item.priority))
        outcomes = await asyncio.gather(*futures, return_exceptions=True)
        await asyncio.sleep(args.wait)
    finally:
        await bus.close()
    failed = [o for o in outcomes if isinstance(o, BaseException)]
    for failure in failed[:3]:
        print(f"motorbus replay: {failure}", file=sys.stderr)
    print(
        f"motorbus replay: {len(plan)} requests sent to {transport.url} through a bus, "
        f"{counts['replies']} replies, {len(failed)} failed (timeouts or bad replies)",
        file=sys.stderr,
    )
    return 0


def _show(args: argparse.Namespace, t: float, d: Description, prefix: str = "") -> None:
    if args.json:
        print_json({"t": t, **d.to_json()})
    else:
        print(f"{prefix}{t:10.6f}  {d.to_line()}", flush=True)
