"""The machinery of ``Bus``'s asyncio shell: the writer, deadlines, the reader, port loss.

``Bus`` (``motorbus.bus.bus``) is the public face: options, ``request``/``submit``,
leases, observers, open and close.  It inherits this class, which drives the pure core
with the bus's timer and transport:

* the writer: ``_pump`` asks the scheduler (``motorbus.bus.schedule``) what to send at
  the time now, writes it, or sets the timer for when it may; there is no writer task;
* deadlines: a request that expects a reply holds the bus until the matcher
  (``motorbus.bus.matching``) accepts its reply or its deadline's timer runs out; then it
  is retried (at most ``retries`` times, never motion) or failed, and the scheduler
  holds that device for ``late_guard``;
* the reader: every byte that arrives is fed to the sans-I/O reassembler; each frame is
  given to the matcher, and its verdict turned into a future's result, an event
  (``QuadDone``, ``ProjectFinished``, ``FaultChanged``) or a count in ``BusStats``;
* port loss: everything queued fails with ``BusClosedError``; the port is reopened with
  backoff if ``reconnect`` is on.

Futures, timer handles and the transport stay here, beside the core's records
(``BusJob`` extends the core's ``Job``); the core never sees them.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import heapq
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from motorbus.bus.events import (
    BusStateChanged,
    EventHub,
    FaultChanged,
    ProjectFinished,
    QuadDone,
)
from motorbus.bus.lease_shell import LeaseKeeper
from motorbus.bus.leases import Lease, LeaseTable
from motorbus.bus.matching import DoneWatch, Matcher, TimedOut, Verdict
from motorbus.bus.occupancy import Occupancy
from motorbus.bus.options import BusConfig
from motorbus.bus.schedule import Job, Priority, Scheduler, Wait
from motorbus.bus.stats import BusStats
from motorbus.bus.timer import Timer, TimerHandle
from motorbus.errors import (
    BusClosedError,
    LocalProtocolError,
    NotSentError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.protocol import safety
from motorbus.protocol.base import Command, Family, FaultState, FrameShape, format_hex
from motorbus.protocol.reassembler import Discarded, Frame, ProjectFinishedMarker, Reassembler
from motorbus.transport.base import Transport

__all__ = ["BusEngine", "BusJob", "BusObserver", "BusState", "PreparedSubmit", "Refresh"]

R = TypeVar("R")

log = logging.getLogger("motorbus.bus")

#: A timer callback that runs this much after its deadline means the host (not the
#: device) stalled: a full garbage collection, another process on the core.  Timeouts
#: decided then are counted apart (``BusStats.timeouts_in_host_stall``).
HOST_STALL_S = 1e-3
#: Reconnect backoff after a lost port: first delay, factor, ceiling (seconds).
RECONNECT_FIRST_S = 0.05
RECONNECT_FACTOR = 2.0
RECONNECT_MAX_S = 2.0


class BusObserver(Protocol):
    """What ``Bus.add_observer`` calls (see there)."""

    def on_write(self, cmd: Command[object], at: float) -> None: ...

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None: ...


class BusState(enum.Enum):
    """Where the bus is in its life."""

    CLOSED = "closed"
    OPEN = "open"
    LOST = "lost"  # the port went away; reconnecting if enabled


#: Called at the moment a queued frame is written: returns the command to send now
#: (rebuilt from what is still wanted) or None to drop it unsent.
Refresh = Callable[[], "Command[object] | None"]
#: ``tap(outgoing, data, at)``: a frame written (``outgoing``) or bytes read, at the bus
#: clock's ``at`` (``Bus.add_wire_tap``).
WireTap = Callable[[bool, bytes, float], None]


@dataclass(slots=True, eq=False, kw_only=True)
class BusJob(Job):
    """One request travelling through the bus: the pure core's record (``Job``), and
    beside it what the asyncio shell keeps: its future and its timer handles."""

    future: asyncio.Future[Any]
    handle: TimerHandle | None = None  # its reply deadline
    refresh: Refresh | None = None
    start_by: float = math.inf
    expiry: TimerHandle | None = None  # its start_by

    def gone(self) -> bool:
        return self.future.done()


class PreparedSubmit(Generic[R]):
    """A ``submit`` checked and built ahead of its moment (``Bus.prepare``)."""

    __slots__ = ("_send", "job", "lease", "lease_version", "sent")

    def __init__(
        self,
        send: Callable[[PreparedSubmit[R]], asyncio.Future[R]],
        job: BusJob,
        lease: Lease | None,
        lease_version: int,
    ) -> None:
        self._send = send
        self.job = job
        self.lease = lease
        #: The lease table's version when its rule was checked (-1: check again).
        self.lease_version = lease_version
        self.sent = False

    def send(self) -> asyncio.Future[R]:
        """Queue it now (an idle bus writes it before this returns); once only.

        Returns the future of its decoded reply, as ``Bus.submit`` does; it resolves
        to None at once if the ``refresh`` (run here, and again at a later write if the
        frame must wait) drops the frame.

        Raises:
            BusClosedError: the bus is no longer open, or is closing (motion).
            LeaseConflictError: a lease changed since and another owner holds a device.
            LocalProtocolError: it was sent already.
        """
        if self.sent:
            raise LocalProtocolError("a prepared submission is sent once", field="prepared")
        self.sent = True
        return self._send(self)


class BusEngine:
    """The writer, deadlines, reader and port loss of one bus (see the module docstring)."""

    #: Set by ``Bus`` (its leases, fed by what is written and answered).
    _leases: LeaseTable
    _lease_keeper: LeaseKeeper

    def __init__(
        self,
        transport: Transport,
        name: str,
        families: frozenset[Family],
        config: BusConfig,
        timer: Timer | None,
    ) -> None:
        self.transport = transport
        self.name = name
        self.families = families
        self.config = config
        self.stats = BusStats()
        self.events = EventHub()
        self.state = BusState.CLOSED
        self._timer = timer
        self._reassembler = Reassembler(families=self.families, stats=self.stats.reassembler)
        # The pure core: when frames may start (queue, spacing, late guards,
        # reservations), and whose frame a received one is (pending request, late
        # window, done-watches, the shapes the reassembler may cut).
        self._schedule: Scheduler[BusJob] = Scheduler()
        self._matcher: Matcher[BusJob] = Matcher(
            self.families, wire_floor=config.wire_floor, on_shapes=self._expect_shapes
        )
        self._rx_total = 0  # bytes handed to the reassembler since the port opened
        self._pump_handle: TimerHandle | None = None
        self._pump_at = 0.0
        self._pumping = False
        self._reconnect_task: asyncio.Task[None] | None = None
        self._last_errors: dict[int, int] = {}
        self._closing = False
        #: Set when close starts: motion is refused and dropped from then on.
        self._stopping = False
        self._observers: list[BusObserver] = []
        #: Told of every chunk on the wire (``add_wire_tap``).
        self._wire_taps: list[WireTap] = []

    if TYPE_CHECKING:  # what Bus defines and this class uses

        @property
        def timer(self) -> Timer: ...

        @property
        def baudrate(self) -> int: ...

        def remove_observer(self, observer: BusObserver) -> None: ...

        def occupancy(self, cmd: Command[object], request_size: int | None = None) -> Occupancy: ...

    def _new_reassembler(self) -> None:
        """A fresh stream (on open and after a lost port): nothing buffered, offsets at 0."""
        self._reassembler = Reassembler(families=self.families, stats=self.stats.reassembler)
        self._rx_total = 0
        self._matcher.update_shapes(force=True)

    def _tell(self, call: Callable[[BusObserver], None]) -> None:
        for observer in list(self._observers):
            try:
                call(observer)
            except Exception:
                log.exception("%s: observer %r failed; removed", self.name, observer)
                self.remove_observer(observer)

    def add_wire_tap(self, tap: WireTap) -> None:
        """Tell ``tap(outgoing, data, at)`` of every frame written (``outgoing`` true)
        and every chunk of bytes read, with the bus clock's time, in wire order (a
        served bus's frame feed, ``motorbus capture --connect``).  Called synchronously
        from the bus: keep it to an append.  A tap that raises is logged and removed."""
        if tap not in self._wire_taps:
            self._wire_taps.append(tap)

    def remove_wire_tap(self, tap: WireTap) -> None:
        """Stop telling ``tap`` (no error if it was not added)."""
        with contextlib.suppress(ValueError):
            self._wire_taps.remove(tap)

    def _tap_wire(self, outgoing: bool, data: bytes, at: float) -> None:
        for tap in list(self._wire_taps):
            try:
                tap(outgoing, data, at)
            except Exception:
                log.exception("%s: wire tap %r failed; removed", self.name, tap)
                self.remove_wire_tap(tap)

    # -- writer ------------------------------------------------------------------
    #
    # There is no writer task: ``_pump`` sends the head of the queue as soon as the bus
    # allows it, and is called whenever that may have changed (a request queued, a reply
    # matched, a deadline run out, the port back) or by the timer when the spacing, a
    # late guard or a reservation ends.  A task would add an event-loop step (~55 us p50
    # on this VM, benchmarks/bench_wakeups.py) to every command; a timer callback sends
    # on time.

    def _pump(self) -> None:
        # ``self._timer or self.timer`` on the hot paths: the attribute once the bus has
        # its timer, without the property's call (issue 40 counts the calls).
        if self._pumping:
            return  # called back from inside a transmission: the loop below goes on
        self._pumping = True
        try:
            matcher, schedule, timer = self._matcher, self._schedule, (self._timer or self.timer)
            while schedule.heap and matcher.pending is None and self.state is BusState.OPEN:
                decision = schedule.poll(timer.now())
                if decision is None:
                    return
                if isinstance(decision, Wait):
                    self._pump_later(decision.at, precise=decision.precise)
                    return
                self._transmit(decision)
        finally:
            self._pumping = False

    def _queue(self, job: BusJob, start_by: float | None, *, checked: bool = False) -> None:
        """The one way a checked job goes out (``submit``, ``PreparedSubmit.send``): an
        idle bus whose rules let it start now writes it here, before this returns;
        otherwise it is queued (with its ``start_by`` expiry) for ``_pump``.

        ``checked``: its ``refresh`` ran just now, in this same callback (a prepared
        stream tick at its deadline): a write from here does not run it again.  A job
        that waits runs it at its write, whenever that is.
        """
        schedule, timer = self._schedule, (self._timer or self.timer)
        job.seq = schedule.next_seq()
        # The expiry and the write's timer (spacing, or a reply deadline) arm it once.
        timer.hold_arming()
        try:
            if (
                not schedule.heap
                and self._matcher.pending is None
                and not self._pumping
                and self.state is BusState.OPEN
                and schedule.start_at(job, now := timer.now()) <= now
            ):
                # What _pump would decide for it, with the queue left out: it is empty.
                self._pumping = True
                try:
                    self._transmit(job, checked=checked)
                finally:
                    self._pumping = False
            else:
                if start_by is not None:
                    job.start_by = float(start_by)
                    job.expiry = timer.call_at(
                        job.start_by, lambda: self._drop_unsent(job), precise=False
                    )
                schedule.push(job)
            self._pump()
        finally:
            timer.release_arming()

    def _pump_later(self, start: float, *, precise: bool = True) -> None:
        handle = self._pump_handle
        if handle is not None:
            if self._pump_at == start and handle.precise == precise:
                return
            handle.cancel()
        self._pump_at = start
        self._pump_handle = (self._timer or self.timer).call_at(
            start, self._on_pump_timer, precise=precise
        )

    def _on_pump_timer(self) -> None:
        self._pump_handle = None
        self._pump()

    def _drop_queued_motion(self) -> None:
        """Fail every queued (unwritten) motion frame: the bus is closing."""
        heap = self._schedule.heap
        kept: list[BusJob] = []
        for job in heap:
            if not job.cmd.starts_motion or job.attempts:
                kept.append(job)
                continue
            if job.expiry is not None:
                job.expiry.cancel()
                job.expiry = None
            if not job.future.done():
                self.stats.not_sent += 1
                job.future.set_exception(
                    BusClosedError(
                        f"bus {self.name} closed before {type(job.cmd).__name__} to "
                        f"{job.key} was sent; nothing was sent"
                    )
                )
                job.future.exception()  # retrieved: a stream tick need not be awaited
        if len(kept) != len(heap):
            heapq.heapify(kept)
            self._schedule.heap = kept

    def _drop_unsent(self, job: BusJob) -> None:
        """``start_by`` passed with ``job`` still queued: fail it, nothing was written."""
        job.expiry = None
        if job.attempts or job.future.done():
            return
        self.stats.not_sent += 1
        job.future.set_exception(
            NotSentError(
                f"{type(job.cmd).__name__} to {job.key} could not start by its start_by "
                "time; nothing was sent"
            )
        )
        job.future.exception()  # retrieved: a poller that gave up need not await it
        self._pump()  # it may have been the head of the queue

    def _refresh(self, job: BusJob) -> bool:
        """Run ``job``'s refresh: False (and its future resolved to None) if it is to be
        dropped unsent; a frame that changed is encoded again."""
        assert job.refresh is not None
        fresh = job.refresh()
        if fresh is None:
            self.stats.dropped_by_refresh += 1
            if not job.future.done():
                job.future.set_result(None)
            return False
        if fresh is not job.cmd:
            job.cmd = fresh
            job.raw = fresh.encode()
            job.after_write = self.occupancy(fresh, len(job.raw)).after_write
        return True

    def _transmit(self, job: BusJob, *, checked: bool = False) -> None:
        if job.expiry is not None:
            job.expiry.cancel()
            job.expiry = None
        if job.refresh is not None and not checked and not self._refresh(job):
            return
        cmd = job.cmd
        job.attempts += 1
        expects = cmd.expects_reply
        if expects:
            # Bytes the OS already holds came before this write, whenever the loop gets
            # round to them: read them first, so that they fall before the mark.
            self.transport.drain_input()
            # Registered before the write: no callback can run during it, and whatever
            # the reassembler holds or has consumed so far came before it.
            job.rx_mark = self._rx_total
            self._matcher.sent(job)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s TX %s (%s)", self.name, format_hex(job.raw), type(cmd).__name__)
        timer = self._timer or self.timer
        before = timer.now()
        try:
            self.transport.write(job.raw)
        except BusClosedError as err:
            self._count_sent(job, expects)
            self._finish(job, err)
            return
        after = timer.now()
        if self._wire_taps:
            self._tap_wire(True, job.raw, after)
        # Counted after the write, which then follows the frame's deadline sooner.
        self._count_sent(job, expects)
        # Spacing counts from the completed write (module docstring).
        self._schedule.wrote(job, before, after)
        job.tx_time = after
        if self._observers:
            self._tell(lambda o: o.on_write(cmd, after))
        if cmd.starts_motion:
            self._leases.moved(cmd)
        elif not expects:
            self._leases.sent(cmd)
        if expects:
            self._matcher.written(job, before, after, self.baudrate)
            job.handle = timer.call_at(job.deadline, self._on_deadline)
        elif not job.future.done():
            job.future.set_result(None)

    def _count_sent(self, job: BusJob, expects: bool) -> None:
        stats = self.stats
        stats.requests += 1
        stats.bytes_out += len(job.raw)
        stats.device(job.key).requests += 1
        if not expects:
            stats.no_reply_frames += 1

    def _expect_shapes(self, shapes: tuple[FrameShape, ...]) -> None:
        """The matcher's shapes changed: tell the reassembler (``Matcher.update_shapes``)."""
        self._reassembler.expect(shapes)

    def _finish(self, job: BusJob, outcome: Any) -> None:
        """Resolve ``job`` with a value or an exception and free the bus."""
        if job.handle is not None:
            job.handle.cancel()
            job.handle = None
        if job.expiry is not None:
            job.expiry.cancel()
            job.expiry = None
        self._matcher.release(job)
        if not job.future.done():
            if isinstance(outcome, BaseException):
                self.stats.failed += 1
                job.future.set_exception(outcome)
            else:
                job.future.set_result(outcome)
        self._pump()

    # -- deadlines ---------------------------------------------------------------

    def _on_deadline(self) -> None:
        job = self._matcher.pending
        if job is None:
            return
        job.handle = None
        # The deadline is decided now, after reading what the OS already holds: a reply
        # that is there came before the bus looked, however late the loop looks (a
        # stall, a busy core), so it is taken, whichever of this callback and the
        # reader's a late loop runs first (matching.py).  A prompt loop looks at the
        # deadline itself, where only a reply that is late finds nothing.
        self.transport.drain_input()
        if self._matcher.pending is job:
            self._expire(job, self.timer.now())

    def _expire(self, job: BusJob, now: float) -> None:
        """``job``'s deadline has passed (seen at ``now``): retry it or fail it."""
        if job.handle is not None:
            job.handle.cancel()
            job.handle = None
        stats = self.stats
        stats.timeouts += 1
        stats.device(job.key).timeouts += 1
        stalled = now - job.deadline
        if stalled > HOST_STALL_S:
            # The deadline was decided this late: the host, not the device, was slow.
            stats.timeouts_in_host_stall += 1
            stats.host_stall_max = max(stats.host_stall_max, stalled)
        self._matcher.timed_out(job, now)
        self._schedule.guard(job.key, now + self.config.late_guard)
        log.debug(
            "%s timeout: %s to %s after %.0f us%s",
            self.name,
            type(job.cmd).__name__,
            job.key,
            (now - job.tx_time) * 1e6,
            f" (decided {stalled * 1e3:.1f} ms late: host stall)" if stalled > HOST_STALL_S else "",
        )
        # A caller that cancelled while its request was on the wire awaits no retry.
        if job.retries_left > 0 and not job.future.done():
            job.retries_left -= 1
            stats.retries += 1
            stats.device(job.key).retries += 1
            self._matcher.release(job)
            self._schedule.requeue(job, Priority.HIGH)
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
        timer = self._timer or self.timer
        # A reply cancels its deadline and the freed bus schedules its next write: the
        # timer is re-armed once, after both.
        timer.hold_arming()
        try:
            self._read(data, timer.now())
        finally:
            timer.release_arming()

    def _read(self, data: bytes, now: float) -> None:
        if self._wire_taps:
            self._tap_wire(False, data, now)
        stats = self.stats
        stats.bytes_in += len(data)
        reassembler = self._reassembler
        # Stream offset of the first byte the reassembler still holds: the items it
        # returns cover the stream from there, contiguously and in order.
        offset = self._rx_total - reassembler.buffered
        self._rx_total += len(data)
        for item in reassembler.feed(data):
            start = offset
            offset += len(item.raw)
            if type(item) is Frame:
                self._on_frame(item, start, now)
            elif type(item) is Discarded:
                # Counted by the reassembler, in stats.reassembler (garbage_bytes, ...).
                if log.isEnabledFor(logging.DEBUG):
                    log.debug("%s discarded %s (%s)", self.name, format_hex(item.raw), item.reason)
            elif type(item) is ProjectFinishedMarker:
                self._leases.sent(safety.AT_REST_AFTER_PROJECT_END)  # the run is over
                self._publish(ProjectFinished(self.name, now))

    def _on_frame(self, frame: Frame, start: int, now: float) -> None:
        raw = frame.raw
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s RX %s", self.name, format_hex(raw))
        matcher = self._matcher
        job = matcher.pending
        verdict, about = matcher.classify(raw, start, now)
        if verdict is Verdict.ACCEPTED:
            assert job is not None
            self._accept(job, raw, now)
        elif verdict is Verdict.EARLY:
            assert job is not None
            self.stats.early_replies += 1
            log.debug(
                "%s frame %s too early for the wire (%.0f us before the floor)",
                self.name,
                format_hex(raw),
                (job.earliest - now) * 1e6,
            )
            return
        if verdict is Verdict.DONE:
            assert isinstance(about, DoneWatch)
            rest = safety.at_rest_after_done(about.cmd)
            if rest is not None:
                self._leases.sent(rest)  # the run is over: its stop is not owed
            self._publish(QuadDone(self.name, now, about.kind, raw[2], about.led, raw))
        elif verdict is Verdict.LATE:
            assert isinstance(about, TimedOut)
            stats = self.stats
            stats.late_replies += 1
            stats.late_reply_max = max(stats.late_reply_max, now - about.deadline)
            stats.device(about.key).late_replies += 1
            log.debug("%s late reply from %s: %s", self.name, about.key, format_hex(raw))
        elif verdict is Verdict.UNEXPECTED:
            self.stats.unexpected_frames += 1
            log.debug("%s unexpected frame %s", self.name, format_hex(raw))

    def _accept(self, job: BusJob, raw: bytes, now: float) -> None:
        latency = now - job.tx_time
        stats = self.stats
        stats.replies += 1
        if now > job.deadline:  # read late, before the deadline was decided (matching.py)
            stats.replies_past_deadline += 1
        stats.latency.record(latency)
        device = stats.device(job.key)
        device.replies += 1
        device.latency.record(latency)
        try:
            value: Any = job.cmd.decode_reply(raw)
        except RemoteProtocolError as err:
            self._finish(job, err)
            return
        self._leases.note(job.key)  # it answered: "la:255" stands for it too
        if not job.cmd.starts_motion:
            self._leases.sent(job.cmd)  # a safe action answered: no longer owed
        if job.cmd.done_shapes() and self._matcher.watch_done(job.cmd):
            # Past MAX_DONE_WATCHES: a done reply lost on the line, the oldest forgotten.
            self.stats.done_watches_dropped += 1
        self._observe(job.cmd.fault_state(value), value, now)
        if self._observers:
            cmd, written = job.cmd, job.tx_time
            self._tell(lambda o: o.on_reply(cmd, value, written, now))
        self._finish(job, value)

    def _observe(self, fault: FaultState | None, value: Any, now: float) -> None:
        """Turn the fault flags a reply reports (``Command.fault_state``: the LA's
        status replies) into fault-change events."""
        if fault is not None:
            before = self._last_errors.get(fault.device_id, 0)
            self._last_errors[fault.device_id] = fault.errors
            if fault.errors != before:
                self._publish(
                    FaultChanged(self.name, now, fault.device_id, before, fault.errors, value)
                )

    def _publish(self, event: Any) -> None:
        self.stats.events += 1
        self.events.publish(event)

    def _publish_state(self, state: str, detail: str = "") -> None:
        self.events.publish(BusStateChanged(self.name, self.timer.now(), state, detail))

    # -- port loss and reconnect ---------------------------------------------------

    def _fail_all(self, err: BaseException) -> None:
        job = self._matcher.pending
        if job is not None:
            self._finish(job, err)
        for job in self._schedule.drain():
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
        self._new_reassembler()
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
            self._schedule.restart()
            # Safe actions owed since the loss go out first (emergency priority).
            await self._lease_keeper.pay_owed()
            self._publish_state("open", "reconnected")
            self._pump()
            return
