"""``motorbus capture`` and ``motorbus replay``: record what crosses a bus, show it, send it again.

Examples::

    motorbus capture --port /dev/ttyUSB0 --family la --seconds 10 --out session.jsonl
    motorbus replay session.jsonl                 # decoded, with relative times
    motorbus replay session.jsonl --to /dev/pts/7 # re-send the requests, same timing

``capture`` only listens: it opens the port with the transport alone (no bus, nothing
is ever written) and cuts whatever arrives - requests and replies alike, as a sniffer
on an RS-485 line sees them - into frames, ``EE DD`` events and runs of garbage.  Each
becomes one JSON line: ``t`` (seconds since the capture started, at the arrival of the
chunk that completed it) and the fields of ``motorbus decode --json`` (kind, family,
direction, name, fields, hex, reason).  It prints "listening" on standard error once
the port is open, and ends after ``--seconds`` or at Ctrl-C (exit code 0).

``replay FILE`` prints a capture like ``decode`` does, with times relative to the first
record.  ``replay FILE --to URL`` writes the recorded host-to-device frames (requests)
to URL with their original spacing, and prints the replies that come back.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TextIO

from motorbus.cli.common import (
    LA_BAUD,
    STEPPER_BAUD,
    add_bus_options,
    add_json_option,
    check_seconds,
    open_port,
    print_json,
    resolve_port,
)
from motorbus.cli.decode import GarbageJoiner
from motorbus.errors import BusClosedError, LocalProtocolError
from motorbus.protocol.base import Direction, Family, parse_hex
from motorbus.protocol.describe import KIND_FRAME, Description, describe
from motorbus.protocol.reassembler import Item, Reassembler
from motorbus.transport.base import Transport
from motorbus.transport.serial import BACKENDS, DEFAULT_BACKEND

__all__ = ["Recorder", "load_records", "register", "run_capture", "run_replay"]

#: After the last replayed request, replies are awaited this long by default (seconds):
#: far more than any documented turnaround (LA 800 us, stepper replies tens of ms).
DEFAULT_REPLY_WAIT_S = 0.5
#: Decimal places of the recorded times (microseconds).
TIME_DECIMALS = 6
#: Default baud rate of each family (LA manual 3.1; doc 000 A.1; doc 001 A1-01).
FAMILY_BAUD = {
    Family.LA: LA_BAUD,
    Family.PROJECT_STEPPER: STEPPER_BAUD,
    Family.QUAD_STEPPER: STEPPER_BAUD,
}


def register(subparsers: Any) -> None:
    """Add the ``capture`` and ``replay`` commands."""
    p = subparsers.add_parser(
        "capture",
        help="record every frame on a bus as JSON lines (listen only)",
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
        help="print a capture, or re-send its requests to a port",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", metavar="FILE.jsonl")
    p.add_argument("--to", metavar="URL", help="re-send the recorded requests to this port")
    p.add_argument("--baud", type=int, help="bit/s for --to (default: by the recorded family)")
    p.add_argument("--backend", choices=BACKENDS, default=DEFAULT_BACKEND, help="for --to")
    p.add_argument(
        "--wait",
        type=float,
        default=DEFAULT_REPLY_WAIT_S,
        help=f"seconds to await replies after the last request (default {DEFAULT_REPLY_WAIT_S})",
    )
    add_json_option(p)
    p.set_defaults(func=run_replay)


class Recorder:
    """Cuts received bytes into described items and writes one JSON line each.

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

    def feed(self, data: bytes) -> None:
        """Describe and write every item ``data`` completes."""
        self._write(self._joiner.push(self._reassembler.feed(data)))

    def finish(self) -> None:
        """Write what is left at the end of the capture (a partial frame as garbage)."""
        self._write(self._joiner.push(self._reassembler.end_of_stream()))
        self._write(self._joiner.flush())

    def _write(self, items: Iterable[Item]) -> None:
        t = round(self.clock(), TIME_DECIMALS)
        wrote = False
        for item in items:
            d = describe(item, family_hint=self.family)
            self.counts[d.kind] = self.counts.get(d.kind, 0) + 1
            self.out.write(json.dumps({"t": t, **d.to_json()}, ensure_ascii=False) + "\n")
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
        recorder = Recorder(family, out, _since(time.monotonic()))
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
    """Read a capture file: one JSON object a line with at least ``t``, ``kind`` and ``hex``.

    Raises:
        LocalProtocolError: a line is not such an object (the message names the line).
        OSError: the file cannot be read.
    """
    records: list[dict[str, Any]] = []
    with path.open(encoding="utf-8") as fh:
        for n, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
                if not isinstance(record, dict):
                    raise ValueError("not an object")
                float(record["t"])
                parse_hex(str(record["hex"]))
                str(record["kind"])
            except (ValueError, KeyError, TypeError) as err:
                raise LocalProtocolError(
                    f"{path} line {n} is not a capture record (t, kind, hex): {err}",
                    field="file",
                ) from err
            records.append(record)
    return records


def _description(record: dict[str, Any]) -> Description:
    return Description(
        kind=str(record["kind"]),
        family=record.get("family"),
        direction=record.get("direction"),
        name=str(record.get("name", "?")),
        fields=dict(record.get("fields") or {}),
        hex=str(record["hex"]),
        reason=record.get("reason"),
    )


def run_replay(args: argparse.Namespace) -> int:
    """Run ``motorbus replay``; return 0.

    Raises:
        LocalProtocolError: a bad file, ``--wait`` or ``--baud``.
        OSError: the file or the ``--to`` port cannot be opened.
    """
    check_seconds("--wait", args.wait)
    records = load_records(Path(args.file))
    if args.to is None:
        t0 = float(records[0]["t"]) if records else 0.0
        for record in records:
            t = round(float(record["t"]) - t0, TIME_DECIMALS)
            if args.json:
                print_json({**record, "t": t})
            else:
                print(f"{t:10.6f}  {_description(record).to_line()}")
        return 0
    families = {Family(r["family"]) for r in records if r.get("family")}
    if args.baud is None:
        args.baud = min((FAMILY_BAUD[f] for f in families), default=LA_BAUD)
    requests = [
        (float(r["t"]), parse_hex(str(r["hex"])))
        for r in records
        if r["kind"] == KIND_FRAME and r.get("direction") == Direction.REQUEST.value
    ]
    transport = open_port(args, url=args.to)
    return asyncio.run(_replay(args, transport, requests, families or set(Family)))


async def _replay(
    args: argparse.Namespace,
    transport: Transport,
    requests: list[tuple[float, bytes]],
    families: set[Family],
) -> int:
    hint = next(iter(families)) if len(families) == 1 else None
    reassembler = Reassembler(direction=Direction.REPLY, families=families)
    started = time.monotonic()
    replies = 0

    def on_data(data: bytes) -> None:
        nonlocal replies
        t = round(time.monotonic() - started, TIME_DECIMALS)
        for item in reassembler.feed(data):
            replies += 1
            _show(args, t, describe(item, family_hint=hint))

    def on_lost(exc: BaseException | None) -> None:
        print(f"motorbus replay: port {transport.url} lost: {exc}", file=sys.stderr)

    try:
        await transport.open(on_data, on_lost)
    except OSError as err:
        raise OSError(f"cannot open port {transport.url}: {err}") from err
    try:
        t0 = requests[0][0] if requests else 0.0
        for t, raw in requests:
            delay = started + (t - t0) - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            transport.write(raw)
            item = _items(raw, families)
            for request in item:
                _show(args, round(time.monotonic() - started, TIME_DECIMALS), describe(request))
        await asyncio.sleep(args.wait)
    finally:
        await transport.close()
    print(
        f"motorbus replay: {len(requests)} requests sent to {transport.url}, {replies} replies",
        file=sys.stderr,
    )
    return 0


def _items(raw: bytes, families: set[Family]) -> list[Item]:
    cutter = Reassembler(direction=Direction.REQUEST, families=families)
    return cutter.feed(raw) + cutter.end_of_stream()


def _show(args: argparse.Namespace, t: float, d: Description) -> None:
    if args.json:
        print_json({"t": t, **d.to_json()})
    else:
        print(f"{t:10.6f}  {d.to_line()}", flush=True)
