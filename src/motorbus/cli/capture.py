"""``motorbus capture`` and ``motorbus replay``: record what crosses a bus, show it, send it again.

Examples::

    motorbus capture --port /dev/ttyUSB0 --family la --seconds 10 --out session.jsonl
    motorbus replay session.jsonl                   # decoded, with relative times
    motorbus replay session.jsonl --to /dev/ttyUSB1 --dry-run   # what would be sent
    motorbus replay session.jsonl --to /dev/ttyUSB1 # re-send the requests, same timing

Without hardware, ``motorbus sim --tap PATH`` serves a copy of the simulator's traffic
on a second pty for ``capture --port PATH`` to listen to.

``capture`` only listens: it opens the port with the transport alone (no bus, nothing
is ever written) and cuts whatever arrives - requests and replies alike, as a sniffer
on an RS-485 line sees them - into frames, ``EE DD`` events and runs of garbage.  It
writes a frame log (docs/frame-log.md): a header line, then one JSON line per item with
``t`` (seconds since the capture started, at the arrival of the chunk that completed
it) and the fields of ``motorbus decode --json`` (kind, family, direction, name, fields,
hex, reason).  It prints "listening" on standard error once the port is open, and ends
after ``--seconds`` or at Ctrl-C (exit code 0).

``replay FILE`` prints a frame log - a capture, or a simulator's ``--log`` such as the
demo's ``la-bus-frames.jsonl`` - like ``decode`` does, with times relative to the first
record.  ``replay FILE --to URL`` sends the recorded host-to-device frames (requests)
through a ``Bus`` on URL, at their original times as far as the bus's spacing and reply
waits allow, and prints what goes out and what comes back.  A file with motion commands
is sent only after a yes at the terminal, or with ``--yes``; with no terminal and no
``--yes`` it is refused (exit code 2).  ``--dry-run`` prints what would be sent and
opens nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime
import json
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from motorbus import (
    BACKENDS,
    DEFAULT_BACKEND,
    Bus,
    DataCallback,
    LostCallback,
    Priority,
    Transport,
    TransportStats,
)
from motorbus.cli.common import (
    CLI_HOST_MARGIN_S,
    LA_BAUD,
    STEPPER_BAUD,
    add_bus_options,
    add_guard_option,
    add_json_option,
    check_seconds,
    open_port,
    print_json,
    resolve_port,
)
from motorbus.cli.decode import GarbageJoiner
from motorbus.cli.main import UsageError
from motorbus.errors import BusClosedError, LocalProtocolError, MotorbusError
from motorbus.protocol import framelog, la, project_stepper, quad_stepper
from motorbus.protocol.base import Command, Direction, Family, format_hex, parse_hex
from motorbus.protocol.describe import KIND_FRAME, Description, describe
from motorbus.protocol.reassembler import Frame, Item, Reassembler

__all__ = ["Recorder", "load_records", "register", "run_capture", "run_replay"]

#: After the last replayed request, replies are awaited this long by default (seconds):
#: far more than any documented turnaround (LA 800 us, stepper replies tens of ms).
DEFAULT_REPLY_WAIT_S = 0.5
#: Decimal places of the recorded times (microseconds).
TIME_DECIMALS = framelog.TIME_DECIMALS
#: Default baud rate of each family (LA manual 3.1; doc 000 A.1; doc 001 A1-01).
FAMILY_BAUD = {
    Family.LA: LA_BAUD,
    Family.PROJECT_STEPPER: STEPPER_BAUD,
    Family.QUAD_STEPPER: STEPPER_BAUD,
}
#: Exit status of a refused replay (bad file, motion without consent).
EXIT_USAGE = 2
_DECODERS: dict[Family, Callable[[bytes], Command[object]]] = {
    Family.LA: la.decode_request,
    Family.PROJECT_STEPPER: project_stepper.decode_request,
    Family.QUAD_STEPPER: quad_stepper.decode_request,
}


def register(subparsers: Any) -> None:
    """Add the ``capture`` and ``replay`` commands."""
    p = subparsers.add_parser(
        "capture",
        help="record every frame on a bus as a frame log (listen only)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--family", required=True, choices=[f.value for f in Family], help="the bus's family"
    )
    p.add_argument("--seconds", type=float, help="stop after this long (default: at Ctrl-C)")
    p.add_argument("--out", metavar="FILE.jsonl", help="write here (default: standard output)")
    add_bus_options(p, default_baud=None, json_option=False)
    p.set_defaults(func=run_capture)

    p = subparsers.add_parser(
        "replay",
        help="print a frame log, or send its requests again through a bus",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", metavar="FILE.jsonl")
    p.add_argument("--to", metavar="URL", help="send the recorded requests to this port")
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
        "--dry-run", action="store_true", help="with --to: print what would be sent, send nothing"
    )
    p.add_argument(
        "--yes", action="store_true", help="with --to: send motion commands without asking"
    )
    add_json_option(p)
    p.set_defaults(func=run_replay)


def utc_now() -> str:
    """The wall-clock time now, ISO 8601 in UTC, for a frame-log header."""
    now = datetime.datetime.now(datetime.UTC)
    return now.isoformat(timespec="microseconds").replace("+00:00", "Z")


class Recorder:
    """Cuts received bytes into described items and writes one frame-log record each.

    Args:
        family: the family on the bus (also the hint for look-alike stepper replies).
        out: where the JSON lines go.
        clock: returns seconds since the capture started.
    """

    def __init__(self, family: Family, out: TextIO, clock: Callable[[], float]) -> None:
        self.family = family
        self.out = out
        self.clock = clock
        self.counts: dict[str, int] = {}
        self._reassembler = Reassembler(direction=None, families=(family,))
        self._joiner = GarbageJoiner()

    def start(self, port: str, baud: int) -> None:
        """Write the header line (call once, when ``clock`` reads 0)."""
        doc = framelog.header(
            "capture", started_utc=utc_now(), families=[self.family], baud=baud, port=port
        )
        self.out.write(json.dumps(doc) + "\n")
        self.out.flush()

    def feed(self, data: bytes) -> None:
        """Describe and write every item ``data`` completes."""
        self._write(self._joiner.push(self._reassembler.feed(data)))

    def finish(self) -> None:
        """Write what is left at the end of the capture (a partial frame as garbage)."""
        self._write(self._joiner.push(self._reassembler.end_of_stream()))
        self._write(self._joiner.flush())

    def _write(self, items: Iterable[Item]) -> None:
        t = self.clock()
        wrote = False
        for item in items:
            d = describe(item, family_hint=self.family)
            self.counts[d.kind] = self.counts.get(d.kind, 0) + 1
            record = framelog.from_description(t, d)
            self.out.write(json.dumps(record, ensure_ascii=False) + "\n")
            wrote = True
        if wrote:
            self.out.flush()


def run_capture(args: argparse.Namespace) -> int:
    """Run ``motorbus capture``; return 0 (also after Ctrl-C), 1 if the port was lost.

    Raises:
        LocalProtocolError: a bad ``--seconds``; UsageError: no ``--port``.
        OSError: the port or the output file cannot be opened.
    """
    check_seconds("--seconds", args.seconds, 1e-3)
    resolve_port(args)
    family = Family(args.family)
    if args.baud is None:
        args.baud = FAMILY_BAUD[family]
    transport = open_port(args)
    out: TextIO = open(args.out, "w", encoding="utf-8") if args.out else sys.stdout  # noqa: SIM115
    try:
        recorder = Recorder(family, out, lambda: 0.0)
        # Ctrl-C is the ordinary end of an open-ended capture.
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(_capture(args, transport, recorder))
        counts = ", ".join(f"{n} {k}" for k, n in sorted(recorder.counts.items())) or "nothing"
        print(f"motorbus capture: {counts}", file=sys.stderr)
    finally:
        if out is not sys.stdout:
            out.close()
    return 0


def _since(start: float) -> Callable[[], float]:
    return lambda: time.monotonic() - start


async def _capture(args: argparse.Namespace, transport: Transport, recorder: Recorder) -> None:
    loop = asyncio.get_running_loop()
    lost: asyncio.Future[BaseException | None] = loop.create_future()

    def on_lost(exc: BaseException | None) -> None:
        if not lost.done():
            lost.set_result(exc)

    recorder.clock = _since(time.monotonic())
    recorder.start(transport.url, transport.baudrate)
    try:
        await transport.open(recorder.feed, on_lost)
    except OSError as err:
        raise OSError(f"cannot open port {transport.url}: {err}") from err
    try:
        print(
            f"motorbus capture: listening on {transport.url} ({recorder.family.value}, "
            f"{transport.baudrate} Bd)" + (f" for {args.seconds:g} s" if args.seconds else ""),
            file=sys.stderr,
            flush=True,
        )
        try:
            cause = await asyncio.wait_for(asyncio.shield(lost), args.seconds)
        except TimeoutError:
            return
        raise BusClosedError(f"port {transport.url} was lost: {cause}")
    finally:
        recorder.finish()
        await transport.close()


# -- replay ------------------------------------------------------------------------------


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


class _Tee(Transport):
    """A transport that shows what passes through it, both ways, then hands it on."""

    def __init__(
        self,
        inner: Transport,
        on_sent: Callable[[bytes], None],
        on_received: Callable[[bytes], None],
    ) -> None:
        self.inner = inner
        self.url = inner.url
        self.baudrate = inner.baudrate
        self._on_sent = on_sent
        self._on_received = on_received

    @property
    def stats(self) -> TransportStats:  # type: ignore[override]
        return self.inner.stats

    async def open(self, on_data: DataCallback, on_lost: LostCallback) -> None:
        def data(chunk: bytes) -> None:
            self._on_received(chunk)
            on_data(chunk)

        await self.inner.open(data, on_lost)

    def write(self, data: bytes) -> None:
        self.inner.write(data)
        self._on_sent(bytes(data))

    async def close(self) -> None:
        await self.inner.close()

    @property
    def is_open(self) -> bool:
        return self.inner.is_open


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
        _Tee(transport, on_sent, on_received),
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
