"""The asyncio machinery ``Bus`` holds: the writer, deadlines, the reader, port loss.

``Bus`` (``motorbus.bus.bus``) is the public face: options, requests, leases,
observers, open and close.  It holds one :class:`BusEngine`, which holds the pure core
(``motorbus.bus.core``'s ``BusCore``) and drives it with the bus's timer and transport:

* the writer: ``_pump`` asks the core what to send at the time now, writes it, or sets
  the timer for when it may; there is no writer task.  ``queue`` is the one way out,
  for requests and stream ticks alike;
* deadlines: a request that expects a reply holds the bus until the core accepts its
  reply or its deadline's timer runs out; then it is retried (at most ``retries``
  times, never motion) or failed, and the core holds that device for ``late_guard``;
* the reader: every byte that arrives is fed to the core; what it hands back is turned
  into a future's result or an event (``QuadDone``, ``ProjectFinished``,
  ``FaultChanged``);
* port loss: everything queued fails with ``BusClosedError``; the port is reopened with
  backoff if ``reconnect`` is on.

Futures, timer handles and the transport stay here, beside the core's records
(``BusJob``, ``motorbus.bus.jobs``); the core never sees them.  Neither the core nor
this class calls the ``Bus`` that holds them, with one exception: after a reconnect
the safe actions owed meanwhile go out through the ``LeaseKeeper``, whose sender is
``Bus.request``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

from motorbus.bus.core import HOST_STALL_S, BusCore
from motorbus.bus.events import BusStateChanged, EventHub, FaultChanged, ProjectFinished, QuadDone
from motorbus.bus.jobs import BusJob, BusObserver, BusState
from motorbus.bus.lease_shell import LeaseKeeper
from motorbus.bus.matching import Verdict
from motorbus.bus.occupancy import BusTiming
from motorbus.bus.options import BusConfig
from motorbus.bus.schedule import Wait
from motorbus.bus.stats import BusStats
from motorbus.bus.timer import Timer, TimerHandle
from motorbus.errors import BusClosedError, NotSentError, RemoteProtocolError, ReplyTimeoutError
from motorbus.protocol import safety
from motorbus.protocol.base import Family, format_hex
from motorbus.protocol.reassembler import ProjectFinishedMarker
from motorbus.transport.base import Transport

__all__ = ["BusEngine", "WireTap"]

log = logging.getLogger("motorbus.bus")

#: Reconnect backoff after a lost port: first delay, factor, ceiling (seconds).
RECONNECT_FIRST_S = 0.05
RECONNECT_FACTOR = 2.0
RECONNECT_MAX_S = 2.0
#: A port lost again within this long of reopening was not back (a serial server that
#: accepts the connection, then closes it: ser2net's "Port already in use"): the next
#: reopen goes on from the delay before, instead of again from ``RECONNECT_FIRST_S``.
RECONNECT_STABLE_S = 5.0

#: ``tap(outgoing, data, at)``: a frame written (``outgoing``) or bytes read, at the bus
#: clock's ``at`` (``Bus.add_wire_tap``).
WireTap = Callable[[bool, bytes, float], None]


class BusEngine:
    """The writer, deadlines, reader and port loss of one bus (see the module docstring)."""

    #: The bus's timer, set by ``start`` (the bus opens on a running loop).
    clock: Timer

    def __init__(
        self,
        transport: Transport,
        name: str,
        families: frozenset[Family],
        config: BusConfig,
        lease_keeper: LeaseKeeper,
    ) -> None:
        self.transport = transport
        self.name = name
        self.config = config
        self.stats = BusStats()
        self.events = EventHub()
        self.state = BusState.CLOSED
        #: Why the port was last lost ("" before any loss): errors raised while it is
        #: lost say it (a server's "Device open failure", a pulled adapter).
        self.lost_detail = ""
        #: The wait before the next reopen, and when the port was last reopened.
        self.reconnect_delay = RECONNECT_FIRST_S
        self.reopened_at: float | None = None
        #: The pure core: when frames may start, whose frame a received one is.
        timing = BusTiming(
            transport.baudrate, config.min_spacing, config.host_margin, config.turnaround
        )
        self.core: BusCore[BusJob] = BusCore(
            name,
            families,
            timing,
            self.stats,
            late_guard=config.late_guard,
            wire_floor=config.wire_floor,
        )
        self.lease_keeper = lease_keeper
        self._leases = lease_keeper.table  # the hot paths' direct reference
        self.observers: list[BusObserver] = []
        #: Set when the bus closes for good: a lost port is not reopened.
        self.closing = False
        self.pump_handle: TimerHandle | None = None
        self._pump_at = 0.0
        self._pumping = False
        self.reconnect_task: asyncio.Task[None] | None = None
        #: Told of every chunk on the wire (``add_wire_tap``).
        self.wire_taps: list[WireTap] = []

    def add_wire_tap(self, tap: WireTap) -> None:
        """Tell ``tap(outgoing, data, at)`` of every frame written (``outgoing`` true)
        and every chunk of bytes read, with the bus clock's time, in wire order (a
        served bus's frame feed, ``motorbus capture --connect``).  Called synchronously
        from the bus: keep it to an append.  A tap that raises is logged and removed."""
        if tap not in self.wire_taps:
            self.wire_taps.append(tap)

    def remove_wire_tap(self, tap: WireTap) -> None:
        """Stop telling ``tap`` (no error if it was not added)."""
        with contextlib.suppress(ValueError):
            self.wire_taps.remove(tap)

    def tap_wire(self, outgoing: bool, data: bytes, at: float) -> None:
        for tap in list(self.wire_taps):
            try:
                tap(outgoing, data, at)
            except Exception:
                log.exception("%s: wire tap %r failed; removed", self.name, tap)
                self.remove_wire_tap(tap)

    def start(self, timer: Timer) -> None:
        """The port is about to open: a fresh received stream, on ``timer``."""
        self.clock = timer
        self.closing = False
        self.core.new_stream()

    def queue(self, job: BusJob, start_by: float | None, *, checked: bool = False) -> None:
        """The one way a checked job goes out (``submit``, ``send_prepared``): an
        idle bus whose rules let it start now writes it here, before this returns;
        otherwise it is queued (with its ``start_by`` expiry) for ``_pump``.

        ``checked``: its ``refresh`` ran just now, in this same callback (a prepared
        stream tick at its deadline): a write from here does not run it again.  A job
        that waits runs it at its write, whenever that is.
        """
        core, timer = self.core, self.clock
        job.seq = core.schedule.next_seq()
        if not self._pumping and self.state is BusState.OPEN and core.starts_now(job, timer.now()):
            self._pumping = True
            try:
                self._transmit(job, checked=checked)  # sets one timer: no hold needed
            finally:
                self._pumping = False
            if core.schedule.heap:  # queued meanwhile (by an observer, a wire tap)
                self._pump()
            return
        # The expiry and the write's timer (spacing, or a reply deadline) arm it once.
        timer.hold_arming()
        try:
            if start_by is not None:
                job.start_by = float(start_by)
                job.expiry = timer.call_at(
                    job.start_by, lambda: self._drop_unsent(job), precise=False
                )
            core.schedule.push(job)
            self._pump()
        finally:
            timer.release_arming()

    # -- writer ------------------------------------------------------------------
    #
    # There is no writer task: ``_pump`` sends what the core says may go now, and is
    # called whenever that may have changed (a request queued, a reply matched, a
    # deadline run out, the port back) or by the timer when the spacing, a late guard or
    # a reservation ends.  A task would add an event-loop step (~55 us p50 on this VM,
    # benchmarks/bench_wakeups.py) to every command; a timer callback sends on time.

    def _pump(self) -> None:
        if self._pumping:
            return  # called back from inside a transmission: the loop below goes on
        self._pumping = True
        try:
            core, timer = self.core, self.clock
            # (Nothing queued: nothing to decide, and no clock to read.)
            while self.state is BusState.OPEN and core.schedule.heap:
                decision = core.next(timer.now())
                if decision is None:
                    return
                if type(decision) is Wait:  # (not isinstance: a call fewer)
                    self._pump_later(decision.at, precise=decision.precise)
                    return
                self._transmit(decision)  # type: ignore[arg-type]  # a job, not a Wait
        finally:
            self._pumping = False

    def _pump_later(self, start: float, *, precise: bool = True) -> None:
        handle = self.pump_handle
        if handle is not None:
            if self._pump_at == start and handle.precise == precise:
                return
            handle.cancel()
        self._pump_at = start
        self.pump_handle = self.clock.call_at(start, self._on_pump_timer, precise=precise)

    def _on_pump_timer(self) -> None:
        self.pump_handle = None
        self._pump()

    def drop_queued_motion(self) -> None:
        """Fail every queued (unwritten) motion frame: the bus is closing."""
        for job in self.core.drop_motion():
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

    def refresh(self, job: BusJob) -> bool:
        """Run ``job``'s refresh: False (and its future resolved to None) if it is to be
        dropped unsent; a frame that changed is encoded again (else its bytes stay)."""
        assert job.refresh is not None
        fresh = job.refresh()
        if fresh is None:
            self.stats.dropped_by_refresh += 1
            if not job.future.done():
                job.future.set_result(None)
            return False
        if fresh is not job.cmd:
            job.cmd = fresh
            job.motion_keys = None  # the claim's: the write works out the fresh frame's
            job.key = fresh.device_key
            job.raw = fresh.encode()
            occ = self.core.occupancy(fresh, len(job.raw))
            job.after_write, job.expects, job.moves = (
                occ.after_write,
                occ.expects_reply,
                fresh.starts_motion,
            )
        return True

    def _transmit(self, job: BusJob, *, checked: bool = False) -> None:
        if job.expiry is not None:
            job.expiry.cancel()
            job.expiry = None
        if job.refresh is not None and not checked and not self.refresh(job):
            return
        cmd, core, timer, expects = job.cmd, self.core, self.clock, job.expects
        job.attempts += 1
        if expects:
            # Bytes the OS already holds came before this write, whenever the loop gets
            # round to them: read them first, so that they fall before the mark.
            self.transport.drain_input()
            core.sending(job, expects)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s TX %s (%s)", self.name, format_hex(job.raw), type(cmd).__name__)
        before = timer.now()
        try:
            self.transport.write(job.raw)
        except BusClosedError as err:
            core.count_sent(job, expects)
            self._finish(job, error=err)
            return
        after = timer.now()
        if self.wire_taps:
            self.tap_wire(True, job.raw, after)
        # Counted after the write, which then follows the frame's deadline sooner;
        # spacing counts from the completed write (module docstring).
        core.wrote(job, expects, before, after, self.transport.baudrate)
        if self.observers:
            self._tell(lambda o: o.on_write(cmd, after))
        if job.moves:
            self._leases.moved(cmd, job.motion_keys)
        elif not expects:
            self._leases.sent(cmd, job.key)
        if expects:
            # Usually cancelled by the reply: the wake-up source is armed for it only in
            # its last stretch (Timer.call_at_lazily), decided as precisely.
            job.handle = timer.call_at_lazily(job.deadline, self._on_deadline, after)
        elif not job.future.done():
            job.future.set_result(None)

    def _finish(self, job: BusJob, value: Any = None, error: BaseException | None = None) -> None:
        """Resolve ``job`` with ``value`` (or fail it with ``error``) and free the bus."""
        if job.handle is not None:
            job.handle.cancel()
            job.handle = None
        if job.expiry is not None:
            job.expiry.cancel()
            job.expiry = None
        self.core.matcher.release(job)
        if not job.future.done():
            if error is not None:
                self.stats.failed += 1
                job.future.set_exception(error)
            else:
                job.future.set_result(value)
        if self.core.schedule.heap:
            self._pump()

    # -- deadlines ---------------------------------------------------------------

    def _on_deadline(self) -> None:
        matcher = self.core.matcher
        job = matcher.pending
        if job is None:
            return
        job.handle = None
        # The deadline is decided now, after reading what the OS already holds: a reply
        # that is there came before the bus looked, however late the loop looks (a
        # stall, a busy core), so it is taken, whichever of this callback and the
        # reader's a late loop runs first (matching.py).  A prompt loop looks at the
        # deadline itself, where only a reply that is late finds nothing.
        self.transport.drain_input()
        if matcher.pending is job:
            self._expire(job, self.clock.now())

    def _expire(self, job: BusJob, now: float) -> None:
        """``job``'s deadline has passed (seen at ``now``): retry it or fail it."""
        if job.handle is not None:
            job.handle.cancel()
            job.handle = None
        if not job.moves:  # a stop unanswered may still have stopped its device
            self._leases.unanswered(job.cmd, job.key)
        # A caller that cancelled while its request was on the wire awaits no retry.
        retried, stalled = self.core.timed_out(job, now)
        log.debug(
            "%s timeout: %s to %s after %.0f us%s",
            self.name,
            type(job.cmd).__name__,
            job.key,
            (now - job.tx_time) * 1e6,
            f" (decided {stalled * 1e3:.1f} ms late: host stall)" if stalled > HOST_STALL_S else "",
        )
        if retried:
            self._pump()
            return
        self._finish(
            job,
            error=ReplyTimeoutError(
                f"no reply from {job.key} to {type(job.cmd).__name__} "
                f"({format_hex(job.raw)}) within {job.timeout * 1e3:.2f} ms"
                + (f" after {job.attempts} attempts" if job.attempts > 1 else "")
            ),
        )

    # -- reader ------------------------------------------------------------------

    def on_data(self, data: bytes) -> None:
        timer = self.clock
        # A reply cancels its deadline and the freed bus schedules its next write: the
        # timer is re-armed once, after both.
        timer.hold_arming()
        try:
            now = timer.now()
            if self.wire_taps:
                self.tap_wire(False, data, now)
            for what, about, raw in self.core.feed(data, now):
                if what is Verdict.ACCEPTED:
                    self._accept(about, raw, now)
                elif what is Verdict.DONE:
                    rest = safety.at_rest_after_done(about.cmd)
                    if rest is not None:
                        self._leases.sent(rest, written=False)  # the run is over: not owed
                    self._publish(QuadDone(self.name, now, about.kind, raw[2], about.led, raw))
                elif what is ProjectFinishedMarker:
                    self._leases.sent(safety.AT_REST_AFTER_PROJECT_END, written=False)
                    self._publish(ProjectFinished(self.name, now))
                elif log.isEnabledFor(logging.DEBUG):  # Discarded, counted by the reassembler
                    log.debug("%s discarded %s (%s)", self.name, format_hex(raw), about.reason)
        finally:
            timer.release_arming()

    def _accept(self, job: BusJob, raw: bytes, now: float) -> None:
        core = self.core
        core.accepted(job, now)
        try:
            value: Any = job.cmd.decode_matched(raw)  # matches_reply accepted it
        except RemoteProtocolError as err:
            self._finish(job, error=err)
            return
        self._leases.note(job.key)  # it answered: "la:255" stands for it too
        if not job.moves:
            self._leases.sent(job.cmd, job.key)  # a safe action answered: no longer owed
        core.watch_done(job.cmd)
        fault = job.cmd.fault_state(value)
        if fault is not None and (before := core.fault_change(fault)) is not None:
            event = FaultChanged(self.name, now, fault.device_id, before, fault.errors, value)
            self._publish(event)
        if self.observers:
            cmd, written = job.cmd, job.tx_time
            self._tell(lambda o: o.on_reply(cmd, value, written, now))
        self._finish(job, value)

    def _publish(self, event: Any) -> None:
        self.stats.events += 1
        self.events.publish(event)

    def not_open_error(self) -> BusClosedError:
        """Why nothing is sent now: the bus's state, and the last loss while it is lost."""
        lost = self.state is BusState.LOST and self.lost_detail
        return BusClosedError(
            f"bus {self.name} is {self.state.value}" + (f" ({self.lost_detail})" if lost else "")
        )

    def publish_state(self, state: str, detail: str = "") -> None:
        self.events.publish(BusStateChanged(self.name, self.clock.now(), state, detail))

    def _tell(self, call: Callable[[BusObserver], None]) -> None:
        for observer in list(self.observers):
            try:
                call(observer)
            except Exception:
                log.exception("%s: observer %r failed; removed", self.name, observer)
                self.observers.remove(observer)

    # -- port loss and reconnect ---------------------------------------------------

    def fail_all(self, err: BaseException) -> None:
        job = self.core.matcher.pending
        if job is not None:
            self._finish(job, error=err)
        for job in self.core.schedule.drain():
            if not job.future.done():
                self.stats.failed += 1
                job.future.set_exception(err)

    async def stop(self, err: BaseException) -> None:
        """The bus is closing for good: no reconnect, no pump, everything left fails
        with ``err`` (the port is still to close)."""
        self.closing = True
        task = self.reconnect_task
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self.reconnect_task = None
        if self.pump_handle is not None:
            self.pump_handle.cancel()
            self.pump_handle = None
        self.fail_all(err)

    def on_lost(self, exc: BaseException | None) -> None:
        if self.closing:
            return
        self.stats.disconnects += 1
        self.state = BusState.LOST
        detail = f"{type(exc).__name__}: {exc}" if exc else "port closed"
        self.lost_detail = detail
        log.warning("bus %s lost its port (%s)", self.name, detail)
        self.fail_all(BusClosedError(f"bus {self.name} lost its port: {detail}"))
        self.core.new_stream()
        self.publish_state("lost", detail)
        if self.reopened_at is None or self.clock.now() - self.reopened_at >= RECONNECT_STABLE_S:
            self.reconnect_delay = RECONNECT_FIRST_S
        if self.config.reconnect:
            self.reconnect_task = asyncio.get_running_loop().create_task(
                self._reconnect(), name=f"motorbus reconnect {self.name}"
            )

    async def _reconnect(self) -> None:
        delay = self.reconnect_delay
        while not self.closing:
            await asyncio.sleep(delay)
            self.publish_state("reconnecting")
            try:
                await self.transport.open(self.on_data, self.on_lost)
            except (OSError, BusClosedError) as err:
                log.debug("bus %s reopen failed: %s", self.name, err)
                delay = min(delay * RECONNECT_FACTOR, RECONNECT_MAX_S)
                continue
            self.stats.reconnects += 1
            self.reconnect_delay = min(delay * RECONNECT_FACTOR, RECONNECT_MAX_S)
            self.reopened_at = self.clock.now()
            self.state = BusState.OPEN
            self.core.schedule.restart()
            # Safe actions owed since the loss go out first (emergency priority).
            await self.lease_keeper.pay_owed()
            self.publish_state("open", "reconnected")
            self._pump()
            return
