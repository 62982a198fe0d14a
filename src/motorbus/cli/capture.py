"""``motorbus capture``: record what crosses a bus as a frame log (listen only).

Example::

    motorbus capture --port /dev/ttyUSB0 --family la --seconds 10 --out session.jsonl

Without hardware, ``motorbus sim --tap PATH`` serves a copy of the simulator's traffic
on a second pty for ``capture --port PATH`` to listen to.

``capture`` only listens: it opens the port with the transport alone (no bus, nothing
is ever written) and cuts whatever arrives - requests and replies alike, as a sniffer
on an RS-485 line sees them - into frames, ``EE DD`` events and runs of garbage.  It
writes a frame log (docs/frame-log.md): a header line, then one JSON line per item with
``t`` (seconds since the capture started, at the arrival of the chunk that completed
it) and the fields of ``motorbus decode --json`` (kind, family, direction, name, fields,
hex, reason).  It prints "listening" on standard error once the port is open, and ends
after ``--seconds`` or at Ctrl-C (exit code 0).  ``motorbus replay FILE`` shows the log
again; ``replay FILE --to URL`` sends its requests again.
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
from typing import Any, TextIO

from motorbus import Transport
from motorbus.cli.common import (
    LA_BAUD,
    STEPPER_BAUD,
    add_bus_options,
    check_seconds,
    open_port,
    plural,
    resolve_port,
)
from motorbus.cli.decode import GarbageJoiner
from motorbus.errors import BusClosedError
from motorbus.protocol import framelog
from motorbus.protocol.base import Family
from motorbus.protocol.describe import describe
from motorbus.protocol.reassembler import Item, Reassembler

__all__ = ["FAMILY_BAUD", "Recorder", "register", "run_capture", "utc_now"]

#: Default baud rate of each family (LA manual 3.1; doc 000 A.1; doc 001 A1-01).
FAMILY_BAUD = {
    Family.LA: LA_BAUD,
    Family.PROJECT_STEPPER: STEPPER_BAUD,
    Family.QUAD_STEPPER: STEPPER_BAUD,
}


def register(subparsers: Any) -> None:
    """Add the ``capture`` command."""
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
        counts = ", ".join(_counted(n, k) for k, n in sorted(recorder.counts.items()))
        counts = counts or "nothing"
        print(f"motorbus capture: {counts}", file=sys.stderr)
    finally:
        if out is not sys.stdout:
            out.close()
    return 0


def _counted(n: int, kind: str) -> str:
    """``206 frames``, ``1 event``, ``3 garbage runs``: a count of one kind of item."""
    return f"{n} garbage {'run' if n == 1 else 'runs'}" if kind == "garbage" else plural(n, kind)


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
