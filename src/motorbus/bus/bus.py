"""One serial bus: one port, one queue, request/reply matching, spacing and deadlines.

The bus owns one port.  Everything written to the port goes through one queue, in
priority order (an emergency stop jumps it), and starts only when

* the previous request started at least ``min_spacing`` earlier (1 ms, LA manual
  3.4.2 / PROTOCOLS C.6) and its own bytes are off the wire, and
* no reply is still owed: a request that expects a reply holds the bus until the
  reply is matched or its deadline runs out.

A reply's deadline is the wire time of the request and of its longest reply at the
bus's baud, plus the device turnaround (800 us for the LA), plus a host-latency margin.
Deadlines and spacing run on the high-resolution timer of ``motorbus.bus.timer``
(timerfd on Linux), because asyncio's own timers round to whole milliseconds.

Every byte that arrives is fed to the sans-I/O reassembler; the bus matches frames to
the pending request, routes events (``EE DD``, quad "done" replies), and counts the
rest: garbage, late replies, unexpected frames.  A late reply is not given to a later
request: it completes earlier than that request's reply physically can, or it comes
within the per-device late guard that holds the next request (``_is_late``).  The
protocols carry no sequence numbers, so a reply later than the guard with exactly the
shape of a newer request cannot be told apart: raise ``late_guard`` for such devices.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import enum
import heapq
import itertools
import logging
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from motorbus.bus.events import (
    BusStateChanged,
    EventHub,
    FaultChanged,
    ProjectFinished,
    QuadDone,
)
from motorbus.bus.stats import BusStats
from motorbus.bus.timer import Timer, TimerHandle, default_timer
from motorbus.errors import (
    BusClosedError,
    LocalProtocolError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.protocol import la
from motorbus.protocol.base import (
    Command,
    Family,
    FrameShape,
    check_flag,
    check_int,
    check_timeout,
    format_hex,
    wire_time,
)
from motorbus.protocol.reassembler import Discarded, Frame, Reassembler
from motorbus.protocol.reassembler import ProjectFinished as ProjectFinishedItem
from motorbus.transport.base import Transport
from motorbus.validation import (
    HOST_MARGIN_MAX_S,
    LATE_GUARD_MAX_S,
    MIN_SPACING_MAX_S,
    RETRIES_MAX,
    check_families,
    check_name,
    check_number,
    check_turnaround,
)

__all__ = ["DEFAULT_TURNAROUND", "Bus", "BusState", "Priority"]

log = logging.getLogger("motorbus.bus")

#: Minimum start-to-start spacing of two frames: "keep the command interval >= 1 ms"
#: (LA manual 3.4.2, PROTOCOLS.md C.6).
MIN_SPACING_S = 1e-3
#: Worst-case device turnaround, request end to reply start.  LA: "120 us typical, up
#: to 800 us" (manual 3.4.2).  The stepper manuals give none; A0-14 recommends a
#: timeout of at least 50 ms for a 6-byte reply at 9600 baud, which 11.5 ms (request)
#: + 6.25 ms (reply) + 30 ms turnaround + the margin meets.
DEFAULT_TURNAROUND: Mapping[Family, float] = {
    Family.LA: 800e-6,
    Family.PROJECT_STEPPER: 30e-3,
    Family.QUAD_STEPPER: 30e-3,
}
#: Host-side latency allowance added to every deadline: scheduling, the pty or the USB
#: adapter (an FTDI in low-latency mode holds bytes up to 1 ms, PLATFORM.md 5).  The
#: demo's LA round trips over a pty to a simulator process on this 2-core machine had a
#: p99 near 2 ms (benchmarks/bench_bus.py measures it), hence 2 ms.  On a loaded or
#: slow host, raise it for every bus at once with ``MOTORBUS_HOST_MARGIN_MS``.
DEFAULT_HOST_MARGIN_S = float(os.environ.get("MOTORBUS_HOST_MARGIN_MS", "2")) / 1e3
#: After a timeout, the next request to the same device waits this long, so that the
#: device's late answer (if it comes) arrives before a new question it could be
#: mistaken for.  Requests to other devices are not held.
DEFAULT_LATE_GUARD_S = 20e-3
#: Quad stepper "done" replies awaited at once, at most: more outstanding runs than
#: this means done replies are being lost (four motors and the LEDs fit easily).
MAX_DONE_WATCHES = 16
#: How long a timed-out request is remembered to recognise its late reply.
LATE_WINDOW_S = 2.0
#: A reply cannot complete before its request and itself have crossed the wire; we
#: allow 10 % for baud-rate tolerance before calling a frame "too early to be ours".
_EARLIEST_FACTOR = 0.9
#: Reconnect backoff after a lost port: first delay, factor, ceiling (seconds).
RECONNECT_FIRST_S = 0.05
RECONNECT_FACTOR = 2.0
RECONNECT_MAX_S = 2.0


class Priority(enum.IntEnum):
    """Queue order; lower goes first."""

    EMERGENCY = 0  # e-stop, stop-all: jump the queue
    HIGH = 1
    NORMAL = 2
    BACKGROUND = 3  # status polling that yields to everything else


class BusState(enum.Enum):
    """Where the bus is in its life."""

    CLOSED = "closed"
    OPEN = "open"
    LOST = "lost"  # the port went away; reconnecting if enabled


def device_key(cmd: Command) -> str:
    """Stats key of the device a command addresses: ``"la:3"``, ``"quad_stepper"``..."""
    if cmd.family is Family.LA:
        address: int = getattr(cmd, "id", la.BROADCAST_ID)
        return f"la:{address}"
    return str(cmd.family.value)


@dataclass(slots=True, eq=False)
class _Job:
    """One request travelling through the bus."""

    cmd: Command
    raw: bytes
    future: asyncio.Future[Any]
    priority: int
    seq: int
    timeout: float
    retries_left: int
    key: str
    tx_time: float = 0.0
    earliest: float = 0.0
    deadline: float = 0.0
    handle: TimerHandle | None = None
    attempts: int = 0

    def __lt__(self, other: _Job) -> bool:
        return (self.priority, self.seq) < (other.priority, other.seq)


@dataclass(slots=True)
class _Timeout:
    cmd: Command
    key: str
    until: float


@dataclass(slots=True)
class _DoneWatch:
    """A quad stepper command whose "done" reply is still to come."""

    shapes: tuple[FrameShape, ...]
    kind: str
    led: int | None


@dataclass(slots=True)
class BusConfig:
    """Timing policy of one bus (all durations in seconds)."""

    min_spacing: float = MIN_SPACING_S
    host_margin: float = DEFAULT_HOST_MARGIN_S
    turnaround: dict[Family, float] = field(default_factory=lambda: dict(DEFAULT_TURNAROUND))
    retries: int = 1
    late_guard: float = DEFAULT_LATE_GUARD_S
    reconnect: bool = True


class Bus:
    """A serial bus of devices: ``await bus.request(command)`` returns the decoded reply.

    Args:
        transport: an opened-on-demand :class:`~motorbus.transport.base.Transport`.
        name: a label for logs, events and stats (default: the transport URL).
        families: device families present on the bus (shapes the reassembler).
        min_spacing: minimum start-to-start spacing of frames, seconds (default 1 ms).
        host_margin: latency allowance added to every reply deadline, seconds.
        turnaround: per-family worst-case device turnaround, seconds.
        retries: default retries of a timed-out query or setting (never of motion).
        late_guard: after a timeout, hold the next request to that device this long.
        reconnect: reopen the port with backoff if it is lost.
        timer: the timer for spacing and deadlines (default: the loop's high-res timer).
    """

    def __init__(
        self,
        transport: Transport,
        *,
        name: str | None = None,
        families: Iterable[Family] = tuple(Family),
        min_spacing: float = MIN_SPACING_S,
        host_margin: float = DEFAULT_HOST_MARGIN_S,
        turnaround: Mapping[Family, float] | None = None,
        retries: int = 1,
        late_guard: float = DEFAULT_LATE_GUARD_S,
        reconnect: bool = True,
        timer: Timer | None = None,
    ) -> None:
        # Every option checked (type, finiteness, range) before anything is built.
        name = check_name("name", name, optional=True)
        families = check_families(families)
        min_spacing = check_number("min_spacing", min_spacing, 0.0, MIN_SPACING_MAX_S, "s")
        host_margin = check_number("host_margin", host_margin, 0.0, HOST_MARGIN_MAX_S, "s")
        turnaround = check_turnaround(turnaround)
        retries = check_int("retries", retries, 0, RETRIES_MAX)
        late_guard = check_number("late_guard", late_guard, 0.0, LATE_GUARD_MAX_S, "s")
        reconnect = check_flag("reconnect", reconnect)
        self.transport = transport
        self.name = name or transport.url
        self.families = frozenset(families)
        self.config = BusConfig(
            min_spacing=min_spacing,
            host_margin=host_margin,
            turnaround={**DEFAULT_TURNAROUND, **(turnaround or {})},
            retries=retries,
            late_guard=late_guard,
            reconnect=reconnect,
        )
        self.stats = BusStats()
        self.events = EventHub()
        self.state = BusState.CLOSED
        self._timer = timer
        self._reassembler = Reassembler(families=self.families)
        self._heap: list[_Job] = []
        self._seq = itertools.count()
        self._pending: _Job | None = None
        self._next_tx = 0.0
        self._pump_handle: TimerHandle | None = None
        self._pump_at = 0.0
        self._pumping = False
        self._reconnect_task: asyncio.Task[None] | None = None
        self._timeouts: collections.deque[_Timeout] = collections.deque()
        self._guard_until: dict[str, float] = {}
        self._done_watches: list[_DoneWatch] = []
        self._last_errors: dict[int, int] = {}
        self._closing = False

    # -- life cycle --------------------------------------------------------------

    @property
    def timer(self) -> Timer:
        """The timer that paces this bus."""
        if self._timer is None:
            self._timer = default_timer()
        return self._timer

    @property
    def baudrate(self) -> int:
        """The bus's baud rate (bits per second)."""
        return self.transport.baudrate

    async def open(self) -> None:
        """Open the port.  Raises ``OSError`` if the port cannot open."""
        if self.state is BusState.OPEN:
            return
        self._closing = False
        await self.transport.open(self._on_data, self._on_lost)
        self.state = BusState.OPEN
        self._check_adapter_latency()
        self._publish_state("open")

    def _check_adapter_latency(self) -> None:
        """Warn if a USB adapter's latency timer leaves no deadline of this bus a chance.

        A reply arrives at the earliest after the device turnaround; what the adapter
        may hold it beyond that must fit in the turnaround plus the host margin.
        """
        warn = getattr(self.transport, "warn_if_latency_exceeds", None)
        if warn is None:
            return
        slack = min(self.config.turnaround[f] for f in self.families) + self.config.host_margin
        warn(slack)

    async def close(self) -> None:
        """Fail what is queued, stop reconnecting and close the port; idempotent."""
        self._closing = True
        task = self._reconnect_task
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._reconnect_task = None
        if self._pump_handle is not None:
            self._pump_handle.cancel()
            self._pump_handle = None
        self._fail_all(BusClosedError(f"bus {self.name} closed"))
        await self.transport.close()
        if self.state is not BusState.CLOSED:
            self.state = BusState.CLOSED
            self._publish_state("closed")

    async def __aenter__(self) -> Bus:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # -- requests ----------------------------------------------------------------

    def reply_budget(self, cmd: Command, request_size: int | None = None) -> float:
        """Seconds from the start of ``cmd``'s transmission to its reply deadline.

        Wire time of the request and of its longest possible reply at this bus's baud,
        plus the family's turnaround and the host margin; 0 if no reply is expected.
        ``request_size`` saves re-encoding when the caller has the bytes already.
        """
        lengths = cmd.reply_lengths()
        if not lengths:
            return 0.0
        baud = self.baudrate
        raw_len = len(cmd.encode()) if request_size is None else request_size
        return (
            wire_time(raw_len, baud)
            + wire_time(max(lengths), baud)
            + self.config.turnaround[cmd.family]
            + self.config.host_margin
        )

    async def request(
        self,
        cmd: Command,
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> Any:
        """Send ``cmd`` and return its decoded reply (``None`` if it expects none).

        Args:
            cmd: a command value from ``motorbus.protocol``.
            timeout: reply budget in seconds from the start of transmission
                (default: ``reply_budget(cmd)``).
            retries: retries after a timeout (default: the bus's; always 0 for
                commands that start motion, which are never retried blindly).
            priority: queue order; ``Priority.EMERGENCY`` jumps the queue.

        Raises:
            ReplyTimeoutError: no matching reply before the deadline (after retries).
            BusClosedError: the bus is closed or its port was lost.
            RemoteProtocolError: the matching reply could not be decoded.
        """
        future = self.submit(cmd, timeout=timeout, retries=retries, priority=priority)
        try:
            return await future
        except asyncio.CancelledError:
            # The caller gave up: a queued job is dropped; a sent one still holds the
            # bus until its reply or deadline, so spacing and matching stay correct.
            future.cancel()
            raise

    def submit(
        self,
        cmd: Command,
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> asyncio.Future[Any]:
        """Queue ``cmd`` without waiting; an idle bus transmits it before this returns.

        Returns the future of its decoded reply (``request`` awaits it).  Cancelling the
        future drops the command if it is still queued.  For code that must send at an
        exact instant from a timer callback (the stream ticks); otherwise use
        ``request``.  Arguments and errors as for ``request``, raised at once.
        """
        if not isinstance(cmd, Command):
            raise LocalProtocolError(
                f"cmd must be a motorbus Command, got {type(cmd).__name__}", field="cmd"
            )
        if cmd.family not in self.families:
            raise LocalProtocolError(
                f"cmd is a {cmd.family.value} command; bus {self.name} carries "
                f"{', '.join(sorted(f.value for f in self.families))}",
                field="cmd",
            )
        _check_request_options(timeout, retries, priority)
        if self.state is not BusState.OPEN:
            raise BusClosedError(f"bus {self.name} is {self.state.value}")
        raw = cmd.encode()
        budget = self.reply_budget(cmd, len(raw)) if timeout is None else float(timeout)
        n_retries = self.config.retries if retries is None else retries
        if cmd.starts_motion or not cmd.expects_reply:
            n_retries = 0
        job = _Job(
            cmd=cmd,
            raw=raw,
            future=asyncio.get_running_loop().create_future(),
            priority=int(priority),
            seq=next(self._seq),
            timeout=budget,
            retries_left=n_retries,
            key=device_key(cmd),
        )
        heapq.heappush(self._heap, job)
        self._pump()  # an idle bus sends right here
        return job.future

    async def send(self, cmd: Command, *, priority: Priority = Priority.NORMAL) -> None:
        """Send a command that expects no reply (broadcast, 0x03, 0x19), paced like any other."""
        await self.request(cmd, priority=priority)

    # -- writer ------------------------------------------------------------------
    #
    # There is no writer task: ``_pump`` sends the head of the queue as soon as the bus
    # allows it, and is called whenever that may have changed (a request queued, a reply
    # matched, a deadline run out, the port back) or by the timer when the spacing or a
    # late guard ends.  A task would add an event-loop step (~55 us p50 on this VM,
    # benchmarks/bench_wakeups.py) to
    # every command; a timer callback sends on time.

    def _pump(self) -> None:
        if self._pumping:
            return  # called back from inside a transmission: the loop below goes on
        self._pumping = True
        try:
            heap = self._heap
            while heap and self._pending is None and self.state is BusState.OPEN:
                job = heap[0]
                if job.future.done():
                    heapq.heappop(heap)  # cancelled while queued
                    continue
                start = max(self._next_tx, self._guard_until.get(job.key, 0.0))
                if start > self.timer.now():
                    self._pump_later(start)
                    return
                heapq.heappop(heap)
                self._transmit(job)
        finally:
            self._pumping = False

    def _pump_later(self, start: float) -> None:
        if self._pump_handle is not None:
            if self._pump_at == start:
                return
            self._pump_handle.cancel()
        self._pump_at = start
        self._pump_handle = self.timer.call_at(start, self._on_pump_timer)

    def _on_pump_timer(self) -> None:
        self._pump_handle = None
        self._pump()

    def _transmit(self, job: _Job) -> None:
        now = self.timer.now()
        cmd = job.cmd
        baud = self.baudrate
        tx_wire = wire_time(len(job.raw), baud)
        self._next_tx = now + max(self.config.min_spacing, tx_wire)
        job.attempts += 1
        stats = self.stats
        stats.requests += 1
        stats.bytes_out += len(job.raw)
        device = stats.device(job.key)
        device.requests += 1
        if cmd.expects_reply:
            job.tx_time = now
            job.earliest = now + _EARLIEST_FACTOR * (
                tx_wire + wire_time(min(cmd.reply_lengths()), baud)
            )
            job.deadline = now + job.timeout
            self._pending = job
            if cmd.family is not Family.LA:
                self._reassembler.expect(self._stepper_shapes(cmd))
            job.handle = self.timer.call_at(job.deadline, self._on_deadline)
        else:
            stats.no_reply_frames += 1
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s TX %s (%s)", self.name, format_hex(job.raw), type(cmd).__name__)
        try:
            self.transport.write(job.raw)
        except BusClosedError as err:
            self._finish(job, err)
            return
        if not cmd.expects_reply and not job.future.done():
            job.future.set_result(None)

    def _stepper_shapes(self, cmd: Command) -> list[FrameShape]:
        shapes = list(cmd.reply_shapes())
        for watch in self._done_watches:
            shapes.extend(watch.shapes)
        return shapes

    def _finish(self, job: _Job, outcome: Any) -> None:
        """Resolve ``job`` with a value or an exception and free the bus."""
        if job.handle is not None:
            job.handle.cancel()
            job.handle = None
        if self._pending is job:
            self._pending = None
            if job.cmd.family is not Family.LA:
                self._reassembler.expect(self._idle_shapes())
        if not job.future.done():
            if isinstance(outcome, BaseException):
                self.stats.failed += 1
                job.future.set_exception(outcome)
            else:
                job.future.set_result(outcome)
        self._pump()

    def _idle_shapes(self) -> list[FrameShape] | None:
        if not self._done_watches:
            return None
        return [s for w in self._done_watches for s in w.shapes]

    # -- deadlines ---------------------------------------------------------------

    def _on_deadline(self) -> None:
        job = self._pending
        if job is None:
            return
        now = self.timer.now()
        job.handle = None
        self.stats.timeouts += 1
        self.stats.device(job.key).timeouts += 1
        self._timeouts.append(_Timeout(job.cmd, job.key, now + LATE_WINDOW_S))
        self._guard_until[job.key] = now + self.config.late_guard
        log.debug(
            "%s timeout: %s to %s after %.0f us",
            self.name,
            type(job.cmd).__name__,
            job.key,
            (now - job.tx_time) * 1e6,
        )
        # A caller that cancelled while its request was on the wire awaits no retry.
        if job.retries_left > 0 and not job.future.done():
            job.retries_left -= 1
            self.stats.retries += 1
            self.stats.device(job.key).retries += 1
            self._pending = None
            job.priority = min(job.priority, int(Priority.HIGH))
            heapq.heappush(self._heap, job)
            self._pump()
            return
        self._finish(
            job,
            ReplyTimeoutError(
                f"no reply from {job.key} to {type(job.cmd).__name__} "
                f"({format_hex(job.raw)}) within {job.timeout * 1e3:.2f} ms"
                + (f" after {job.attempts} attempts" if job.attempts > 1 else "")
            ),
        )

    # -- reader ------------------------------------------------------------------

    def _on_data(self, data: bytes) -> None:
        now = self.timer.now()
        self.stats.bytes_in += len(data)
        for item in self._reassembler.feed(data):
            if type(item) is Frame:
                self._on_frame(item, now)
            elif type(item) is Discarded:
                self.stats.garbage_bytes += len(item.raw)
                by_reason = self.stats.discarded_by_reason
                by_reason[item.reason] = by_reason.get(item.reason, 0) + len(item.raw)
                self.stats.resyncs += 1
                log.debug("%s discarded %s (%s)", self.name, format_hex(item.raw), item.reason)
            elif type(item) is ProjectFinishedItem:
                self._publish(ProjectFinished(self.name, now))

    def _on_frame(self, frame: Frame, now: float) -> None:
        raw = frame.raw
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s RX %s", self.name, format_hex(raw))
        job = self._pending
        if job is not None and now >= job.earliest and job.cmd.matches_reply(raw):
            latency = now - job.tx_time
            self.stats.replies += 1
            self.stats.latency.record(latency)
            device = self.stats.device(job.key)
            device.replies += 1
            device.latency.record(latency)
            try:
                value: Any = job.cmd.decode_reply(raw)
            except RemoteProtocolError as err:
                self._finish(job, err)
                return
            if job.cmd.done_shapes():
                self._watch_done(_done_watch(job.cmd))
            self._observe(value, now)
            self._finish(job, value)
            return
        if self._match_done(raw, now):
            return
        if self._is_late(raw, now):
            return
        self.stats.unexpected_frames += 1
        log.debug("%s unexpected frame %s", self.name, format_hex(raw))

    def _watch_done(self, watch: _DoneWatch) -> None:
        """Remember a "done" reply to come, keeping at most ``MAX_DONE_WATCHES``.

        A done reply that is lost on the line would otherwise be awaited forever, and
        the list (and the reply shapes the reassembler is given) would grow with every
        run.  Past the bound the oldest is forgotten and counted.
        """
        self._done_watches.append(watch)
        if len(self._done_watches) > MAX_DONE_WATCHES:
            del self._done_watches[0]
            self.stats.done_watches_dropped += 1

    def _match_done(self, raw: bytes, now: float) -> bool:
        for i, watch in enumerate(self._done_watches):
            if any(len(raw) == s.length and s.matches(raw) for s in watch.shapes):
                del self._done_watches[i]
                self._publish(QuadDone(self.name, now, watch.kind, raw[2], watch.led, raw))
                return True
        return False

    def _is_late(self, raw: bytes, now: float) -> bool:
        """Recognise the answer to a request whose deadline already ran out.

        Such a frame is never given to the pending request: either it matched no
        pending request at all, or it completed earlier than a reply to the pending
        request physically can (``_Job.earliest``), or the per-device late guard kept
        a same-device request from being sent while it could still arrive.
        """
        timeouts = self._timeouts
        while timeouts and timeouts[0].until < now:
            timeouts.popleft()
        for t in reversed(timeouts):
            if t.cmd.matches_reply(raw):
                self.stats.late_replies += 1
                self.stats.device(t.key).late_replies += 1
                log.debug("%s late reply from %s: %s", self.name, t.key, format_hex(raw))
                return True
        return False

    def _observe(self, value: Any, now: float) -> None:
        """Turn LA status replies into fault-change events."""
        if isinstance(value, la.Status):
            errors = int(value.errors)
            before = self._last_errors.get(value.id, 0)
            self._last_errors[value.id] = errors
            if errors != before:
                self._publish(FaultChanged(self.name, now, value.id, before, errors, value))

    def _publish(self, event: Any) -> None:
        self.stats.events += 1
        self.events.publish(event)

    def _publish_state(self, state: str, detail: str = "") -> None:
        self.events.publish(BusStateChanged(self.name, self.timer.now(), state, detail))

    # -- port loss and reconnect ---------------------------------------------------

    def _fail_all(self, err: BaseException) -> None:
        if self._pending is not None:
            self._finish(self._pending, err)
        while self._heap:
            job = heapq.heappop(self._heap)
            if not job.future.done():
                self.stats.failed += 1
                job.future.set_exception(err)

    def _on_lost(self, exc: BaseException | None) -> None:
        if self._closing:
            return
        self.stats.disconnects += 1
        self.state = BusState.LOST
        detail = f"{type(exc).__name__}: {exc}" if exc else "port closed"
        log.warning("bus %s lost its port (%s)", self.name, detail)
        self._fail_all(BusClosedError(f"bus {self.name} lost its port: {detail}"))
        self._reassembler = Reassembler(families=self.families)
        self._publish_state("lost", detail)
        if self.config.reconnect:
            self._reconnect_task = asyncio.get_running_loop().create_task(
                self._reconnect(), name=f"motorbus reconnect {self.name}"
            )

    async def _reconnect(self) -> None:
        delay = RECONNECT_FIRST_S
        while not self._closing:
            await asyncio.sleep(delay)
            self._publish_state("reconnecting")
            try:
                await self.transport.open(self._on_data, self._on_lost)
            except (OSError, BusClosedError) as err:
                log.debug("bus %s reopen failed: %s", self.name, err)
                delay = min(delay * RECONNECT_FACTOR, RECONNECT_MAX_S)
                continue
            self.stats.reconnects += 1
            self.state = BusState.OPEN
            self._next_tx = 0.0
            self._publish_state("open", "reconnected")
            self._pump()
            return

    async def wait_state(self, state: BusState, timeout: float | None = None) -> None:
        """Wait until the bus reaches ``state`` (e.g. ``OPEN`` after a reconnect)."""
        if self.state is state:
            return
        async with self.events.subscribe(BusStateChanged, lambda e: e.state == state.value) as sub:
            if self.state is state:
                return
            await sub.next(timeout)


#: Ceiling on a per-request reply budget: far beyond any reply the three manuals
#: describe (the 226-byte 0x3E dump takes 0.24 s at 9600 bit/s), it only refuses nonsense.
REQUEST_TIMEOUT_MAX_S = 3600.0
#: Ceiling on per-request retries, the same as the bus-wide ``retries`` option.
REQUEST_RETRIES_MAX = 10


def _check_request_options(timeout: object, retries: object, priority: object) -> None:
    """Refuse a bad ``timeout``/``retries``/``priority`` before anything is queued."""
    if timeout is not None:
        check_timeout("timeout", timeout, REQUEST_TIMEOUT_MAX_S)
    if retries is not None and (
        isinstance(retries, bool)
        or not isinstance(retries, int)
        or not 0 <= retries <= REQUEST_RETRIES_MAX
    ):
        raise LocalProtocolError(
            f"retries={retries!r} is out of range: allowed 0..{REQUEST_RETRIES_MAX} or None",
            field="retries",
            value=retries,
        )
    if isinstance(priority, bool) or priority not in set(Priority):
        raise LocalProtocolError(
            f"priority={priority!r} is not allowed: choose one of "
            f"{', '.join(p.name for p in Priority)}",
            field="priority",
            value=priority,
        )


def _done_watch(cmd: Command) -> _DoneWatch:
    led = getattr(cmd, "led", None)
    return _DoneWatch(cmd.done_shapes(), "led" if led is not None else "run", led)
