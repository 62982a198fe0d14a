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

``--format csv`` or ``--format text`` (one line a frame, in columns like candump) write
a view for reading instead of the frame log.  ``--id``, ``--dir`` and ``--command`` keep
only the frames asked for, e.g. ``--id 3 --command MoveTo,Status``; a filtered frame log
names its filter in its header.

``--connect ENDPOINT`` captures a bus that ``motorbus serve`` owns, beside its
application: the server publishes every frame its bus writes and reads while a capture
subscribes, and the capture writes the same frame log (``t`` on the server's clock).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Protocol, TextIO

from motorbus import Transport
from motorbus.cli.bus_options import (
    LA_BAUD,
    STEPPER_BAUD,
    add_bus_options,
    open_port,
    resolve_port,
)
from motorbus.cli.decode import GarbageJoiner
from motorbus.cli.logformat import (
    LogWriter,
    add_filter_options,
    add_format_option,
    record_filter,
)
from motorbus.cli.output import plural
from motorbus.cli.values import check_seconds
from motorbus.errors import BusClosedError, UsageError
from motorbus.protocol import framelog
from motorbus.protocol.base import Family
from motorbus.protocol.describe import describe
from motorbus.protocol.reassembler import Item, Reassembler

__all__ = ["FAMILY_BAUD", "RecordSink", "Recorder", "register", "run_capture", "utc_now"]

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
    p.add_argument("--out", metavar="FILE", help="write here (default: standard output)")
    add_format_option(p, "jsonl")
    add_filter_options(p, family=False)
    add_bus_options(p, default_baud=None, json_option=False, connect=True)
    p.set_defaults(func=run_capture)


def utc_now() -> str:
    """The wall-clock time now, ISO 8601 in UTC, for a frame-log header."""
    now = datetime.datetime.now(datetime.UTC)
    return now.isoformat(timespec="microseconds").replace("+00:00", "Z")


class RecordSink(Protocol):
    """Where a :class:`Recorder` puts what it heard (a :class:`LogWriter`, a monitor)."""

    def header(self, doc: Mapping[str, Any]) -> None:
        """Start the session with its header."""

    def write(self, record: Mapping[str, Any]) -> bool:
        """Take one frame-log record; return whether it was kept."""

    def flush(self) -> None:
        """Called after the records of one chunk."""


class Recorder:
    """Cuts received bytes into described items and hands one frame-log record each on.

    Args:
        family: the family on the bus (also the hint for look-alike stepper replies).
        sink: takes the header and the records.
        clock: returns seconds since the capture started.
    """

    def __init__(self, family: Family, sink: RecordSink, clock: Callable[[], float]) -> None:
        self.family = family
        self.sink = sink
        self.clock = clock
        #: Items kept, by kind (``frame``, ``garbage``, ``event``).
        self.counts: dict[str, int] = {}
        #: Items the sink's filter left out.
        self.dropped = 0
        self._reassembler = Reassembler(direction=None, families=(family,))
        self._joiner = GarbageJoiner()

    def start(self, port: str, baud: int) -> None:
        """Write the header (call once, when ``clock`` reads 0)."""
        doc = framelog.header(
            "capture", started_utc=utc_now(), families=[self.family], baud=baud, port=port
        )
        self.sink.header(doc)
        self.sink.flush()

    def feed(self, data: bytes) -> None:
        """Describe and hand on every item ``data`` completes."""
        self._write(self._joiner.push(self._reassembler.feed(data)))

    def finish(self) -> None:
        """Hand on what is left at the end of the capture (a partial frame as garbage)."""
        self._write(self._joiner.push(self._reassembler.end_of_stream()))
        self._write(self._joiner.flush())

    def _write(self, items: Iterable[Item]) -> None:
        t = self.clock()
        wrote = False
        for item in items:
            d = describe(item, family_hint=self.family)
            if self.sink.write(framelog.from_description(t, d)):
                self.counts[d.kind] = self.counts.get(d.kind, 0) + 1
            else:
                self.dropped += 1
            wrote = True
        if wrote:
            self.sink.flush()


def run_capture(args: argparse.Namespace) -> int:
    """Run ``motorbus capture``; return 0 (also after Ctrl-C), 1 if the port was lost.

    Raises:
        LocalProtocolError: a bad ``--seconds``; UsageError: no ``--port``.
        OSError: the port or the output file cannot be opened.
    """
    check_seconds("--seconds", args.seconds, 1e-3)
    keep = record_filter(args)
    family = Family(args.family)
    transport: Transport | None = None
    if args.connect:
        if args.port or args.bus_file or args.baud is not None:
            raise UsageError(
                "--connect uses a served bus: give it without --port, --bus-file or --baud"
            )
    else:
        resolve_port(args)
        if args.baud is None:
            args.baud = FAMILY_BAUD[family]
        transport = open_port(args)
    out: TextIO = open(args.out, "w", encoding="utf-8") if args.out else sys.stdout  # noqa: SIM115
    try:
        recorder = Recorder(family, LogWriter(out, args.format, keep), lambda: 0.0)
        # Ctrl-C is the ordinary end of an open-ended capture.
        with contextlib.suppress(KeyboardInterrupt):
            if transport is None:
                asyncio.run(_capture_served(args, recorder))
            else:
                asyncio.run(_capture(args, transport, recorder))
        counts = ", ".join(_counted(n, k) for k, n in sorted(recorder.counts.items()))
        counts = counts or "nothing"
        if recorder.dropped:
            counts += f" ({recorder.dropped} left out by the filter)"
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


#: Longest wait for the server to start publishing its bus's frames (seconds).
TAP_WAIT_S = 5.0


async def _capture_served(args: argparse.Namespace, recorder: Recorder) -> None:
    """``--connect``: the frames the server's bus writes and reads, as the server
    publishes them (it taps its bus while someone subscribes; the application that
    drives the bus goes on undisturbed).  ``t`` is the server bus's clock since the
    capture started; each chunk is cut as a sniffer's would be."""
    from motorbus.cli.bus_options import served_bus

    async with served_bus(args.connect, args.bus) as bus:
        served: Any = bus  # a ServedBus: fetch_devices, frames
        async with served.frames() as batches:
            await _listen_served(args, recorder, served, batches)


async def _listen_served(
    args: argparse.Namespace, recorder: Recorder, bus: Any, batches: asyncio.Queue[Any]
) -> None:
    """Feed ``recorder`` the server's batches until ``--seconds`` (or Ctrl-C)."""
    # Listening from the moment the server has tapped its bus: no frame is missed.
    waited_until = time.monotonic() + TAP_WAIT_S
    devices = await bus.fetch_devices()
    while not devices.frames_tapped:
        if time.monotonic() > waited_until:
            raise BusClosedError(f"the server at {args.connect} publishes no frames")
        await asyncio.sleep(0.01)
        devices = await bus.fetch_devices()
    start, chunk_t = devices.now, [0.0]
    recorder.clock = lambda: chunk_t[0]
    where = f"bus {bus.name} at {args.connect}"
    recorder.start(where, bus.baudrate)
    print(
        f"motorbus capture: listening on {where} ({recorder.family.value}, "
        f"{bus.baudrate} Bd, served)" + (f" for {args.seconds:g} s" if args.seconds else ""),
        file=sys.stderr,
        flush=True,
    )
    end = None if args.seconds is None else time.monotonic() + args.seconds
    try:
        while end is None or time.monotonic() < end:
            left = None if end is None else end - time.monotonic()
            try:
                batch = await asyncio.wait_for(batches.get(), left)
            except TimeoutError:
                break
            for t, _, data in batch.get("frames", []):
                if float(t) >= start:
                    chunk_t[0] = float(t) - start
                    recorder.feed(bytes.fromhex(data))
    finally:
        recorder.finish()


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
