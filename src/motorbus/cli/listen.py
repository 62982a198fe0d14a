"""``motorbus monitor --listen``: a live table of what other programs do on a bus.

Example::

    motorbus sim --link /tmp/ttyLA --tap /tmp/ttyLA.tap la:1-3 &
    motorbus monitor --listen --port /tmp/ttyLA.tap --interval 0.5

It opens the port with the transport alone, as ``capture`` does: no bus, and nothing
is ever written, so it can run beside the program that drives the bus.  Point it at a
tap (``motorbus sim --tap``) or at a second adapter on the RS-485 pair; on the driving
program's own port it would take that program's replies (docs/frame-log.md, "Trying
it without hardware").  For the LA it shows the last status each actuator sent back, a
row an ID; for the steppers, each device's last request and reply.  A refresh every
``--interval`` seconds; ``--count`` or ``--seconds`` end it, as does Ctrl-C (exit 0).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from motorbus import Transport
from motorbus.cli.bus_options import open_port
from motorbus.cli.capture import Recorder
from motorbus.cli.la import STATUS_HEADER, status_json, status_row
from motorbus.cli.output import LiveText, plural, print_json
from motorbus.errors import BusClosedError, MotorbusError
from motorbus.protocol import framelog, la, logview
from motorbus.protocol.base import Direction, Family, parse_hex
from motorbus.protocol.describe import Description

__all__ = ["Watch", "run_listen"]


@dataclass
class Device:
    """What was heard of one device."""

    requests: int = 0
    replies: int = 0
    last_request: Description | None = None
    last_reply: Description | None = None
    status: la.Status | None = None
    last: Description | None = None


@dataclass
class Watch:
    """Keeps, per device ID, what the frames heard on the bus say (a ``RecordSink``).

    Args:
        family: the bus's family.
        ids: show only these IDs (``None``: every ID heard).
    """

    family: Family
    ids: frozenset[int] | None = None
    devices: dict[int, Device] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def header(self, doc: Mapping[str, Any]) -> None:
        """A listener has nothing to do with the header."""

    def flush(self) -> None:
        """Nothing is buffered."""

    def write(self, record: Mapping[str, Any]) -> bool:
        """Take in one record heard on the bus; always kept."""
        for d in framelog.describe_record(record):
            key = d.direction if d.kind == "frame" and d.direction else d.kind
            self.counts[key] = self.counts.get(key, 0) + 1
            if d.kind != "frame":
                continue
            for ident in logview.record_ids(d.fields):
                if self.ids is not None and ident not in self.ids:
                    continue
                dev = self.devices.setdefault(ident, Device())
                dev.last = d
                if d.direction == Direction.REQUEST.value:
                    dev.requests += 1
                    dev.last_request = d
                else:
                    dev.replies += 1
                    dev.last_reply = d
                    if d.family == Family.LA.value and d.name == "Status":
                        with contextlib.suppress(MotorbusError, ValueError):
                            dev.status = la.decode_status(parse_hex(d.hex))
        return True

    def summary(self) -> str:
        """Counts of what was heard, one line: ``3 requests, 1 reply, 2 garbage runs``."""
        n = self.counts.get
        parts = [plural(n("request", 0), "request"), plural(n("reply", 0), "reply", "replies")]
        parts += [plural(n(k, 0), "event") for k in ("event",) if n(k)]
        parts += [plural(n(k, 0), "garbage run") for k in ("garbage",) if n(k)]
        return ", ".join(parts)

    def lines(self) -> list[str]:
        """The table: a row a device heard, by ID."""
        if self.family is Family.LA:
            rows = [STATUS_HEADER]
            for ident, dev in sorted(self.devices.items()):
                if dev.status is not None:
                    rows.append(status_row(dev.status))
                else:
                    rows.append(f"  {ident:3d}  no status heard yet ({_last(dev)})")
            return rows
        rows = ["  id  requests  replies  last frame"]
        for ident, dev in sorted(self.devices.items()):
            rows.append(f"  {ident:3d}  {dev.requests:8d}  {dev.replies:7d}  {_last(dev)}")
        return rows

    def to_json(self) -> list[dict[str, Any]]:
        """The table as JSON: a device a dict."""
        out = []
        for ident, dev in sorted(self.devices.items()):
            doc: dict[str, Any] = {"id": ident, "requests": dev.requests, "replies": dev.replies}
            if dev.status is not None:
                doc["status"] = status_json(dev.status)
            for key, d in (("last_request", dev.last_request), ("last_reply", dev.last_reply)):
                if d is not None:
                    doc[key] = {"name": d.name, "fields": d.fields}
            out.append(doc)
        return out


def _last(dev: Device) -> str:
    """The last frame heard for a device, one phrase."""
    d = dev.last
    if d is None:
        return "-"
    arrow = "->" if d.direction == Direction.REQUEST.value else "<-"
    fields = " ".join(f"{k}={v}" for k, v in d.fields.items() if k not in ("id", "motor"))
    return f"{arrow} {d.name}" + (f" {fields}" if fields else "")


def run_listen(args: argparse.Namespace, ids: list[int] | None, family: Family) -> int:
    """Run ``motorbus monitor --listen``; return 0 (also at Ctrl-C), 1 if the port was lost.

    Raises:
        UsageError: no ``--port``; OSError: the port cannot be opened.
    """
    transport = open_port(args)
    watch = Watch(family, frozenset(ids) if ids is not None else None)
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C is how an endless monitor ends
        asyncio.run(_listen(args, transport, watch))
    return 0


async def _listen(args: argparse.Namespace, transport: Transport, watch: Watch) -> None:
    loop = asyncio.get_running_loop()
    lost: asyncio.Future[BaseException | None] = loop.create_future()

    def on_lost(exc: BaseException | None) -> None:
        if not lost.done():
            lost.set_result(exc)

    started = time.monotonic()
    recorder = Recorder(watch.family, watch, lambda: time.monotonic() - started)
    try:
        await transport.open(recorder.feed, on_lost)
    except OSError as err:
        raise OSError(f"cannot open port {transport.url}: {err}") from err
    live = LiveText(sys.stdout)
    try:
        print(
            f"motorbus monitor: listening on {transport.url} ({watch.family.value}, "
            f"{transport.baudrate} Bd), sending nothing",
            file=sys.stderr,
            flush=True,
        )
        refreshes = 0
        end = None if args.seconds is None else started + args.seconds
        while args.count is None or refreshes < args.count:
            wait = args.interval
            if end is not None:
                wait = min(wait, end - time.monotonic())
            if wait > 0:
                with contextlib.suppress(TimeoutError):
                    cause = await asyncio.wait_for(asyncio.shield(lost), wait)
                    raise BusClosedError(f"port {transport.url} was lost: {cause}")
            refreshes += 1
            elapsed = time.monotonic() - started
            if args.json:
                print_json(
                    {"refresh": refreshes, "t": round(elapsed, 4), "heard": dict(watch.counts),
                     "devices": watch.to_json()}
                )  # fmt: skip
            else:
                head = f"t={elapsed:6.2f}s  {transport.url}  heard {watch.summary()}"
                live.show([head, *watch.lines()])
            if end is not None and time.monotonic() >= end:
                break
    finally:
        recorder.finish()
        await transport.close()
