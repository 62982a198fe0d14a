"""One serial bus: one port, one queue, request/reply matching, spacing and deadlines.

The bus owns one port.  Everything written to the port goes through one queue, in
priority order (an emergency stop jumps it), and a frame's write starts only when

* at least ``min_spacing`` (1 ms, LA manual 3.4.2, docs/protocols.md C.6) has passed
  since the previous write *returned* (and the previous frame's own wire time, if
  longer): the moment the write call came back, not a timestamp taken before it (a
  process preempted between the two would write later than its timestamp says, and
  the kernel would see two frames closer than the rule);
* no reply is still owed: a request that expects a reply holds the bus until the
  reply is matched or its deadline runs out;
* it does not overlap a window reserved by a stream tick (``add_reservation_source``):
  a request that could still hold the bus when the tick is due waits until after it.

A reply's deadline is the wire time of the request and of its longest reply at the
bus's baud, plus the device turnaround (800 us for the LA), plus a host-latency margin,
counted from the completed write.  Deadlines and spacing run on the high-resolution
timer of ``motorbus.bus.timer`` (timerfd on Linux), because asyncio's own timers round
to whole milliseconds.

Every byte that arrives is fed to the sans-I/O reassembler; the bus matches frames to
the pending request, routes events (``EE DD``, quad "done" replies), and counts the
rest: garbage, late replies, unexpected frames.  A reply is accepted by causality: a
frame whose first byte arrived after the request was handed to the OS may be its reply,
however soon (a pty, a USB-CDC device or a TCP bridge does not pace bytes at the baud);
a frame that began before the write is older traffic.  "Before" is what the OS had
received, not what the loop had read: a request's write is preceded by a read of what
the OS already holds (``Transport.drain_input``), so a lagging loop cannot make an old
reply look newer than the request.  A deadline is decided when its callback runs, after
the same read: a reply the OS already held is taken, whichever callback a late loop runs
first (counted in ``stats.replies_past_deadline``).  A late reply is never given to a
later request: after a timeout, the next request to that device waits ``late_guard``,
and the late frame is recognised by its shape and counted.  The protocols carry no
sequence numbers, so a reply later than the guard with exactly the shape of a newer
request cannot be told apart: raise ``late_guard`` for such devices.
``wire_floor=True`` (for a real UART that paces bytes at the baud) also refuses frames
that completed sooner than the wire allows; each such frame is counted as
``early_replies`` and logged, never silently made a timeout.

Where each part lives: the rules are one pure core, driven by a time passed in
(``motorbus.bus.core``'s ``BusCore``: queue, spacing, late guards and reservations,
matching, a frame's bus time, the reassembler, the counts); ``motorbus.bus.engine``'s
``BusEngine`` holds it and drives it with the timer and the transport; ``Bus`` holds
the engine and is the public face.  The core never calls the bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Iterable, Mapping
from types import TracebackType
from typing import Generic, TypeVar

from motorbus import lifecycle
from motorbus.bus.core import BusCore
from motorbus.bus.engine import BusEngine, WireTap
from motorbus.bus.events import BusStateChanged
from motorbus.bus.jobs import BusJob, BusObserver, BusState, Refresh
from motorbus.bus.lease_shell import LeaseKeeper, finish_shielded, together
from motorbus.bus.leases import Lease, LeaseInfo
from motorbus.bus.occupancy import BusTiming, Occupancy, answer_window, reply_slack
from motorbus.bus.options import DEFAULT_HOST_MARGIN_S as DEFAULT_HOST_MARGIN_S
from motorbus.bus.options import DEFAULT_LATE_GUARD_S as DEFAULT_LATE_GUARD_S
from motorbus.bus.options import DEFAULT_TURNAROUND as DEFAULT_TURNAROUND
from motorbus.bus.options import MIN_SPACING_S as MIN_SPACING_S
from motorbus.bus.options import REQUEST_TIMEOUT_MAX_S as REQUEST_TIMEOUT_MAX_S
from motorbus.bus.options import BusConfig as BusConfig
from motorbus.bus.options import check_bus_options, check_request_options, check_timer
from motorbus.bus.schedule import Priority, ReservationSource
from motorbus.bus.timer import Timer, default_timer
from motorbus.errors import BusClosedError, LocalProtocolError, WrongLoopError
from motorbus.protocol import safety
from motorbus.protocol.base import Command, Family, check_flag
from motorbus.transport.base import Transport, check_transport
from motorbus.validation import check_families, check_name

__all__ = ["DEFAULT_TURNAROUND", "Bus", "BusObserver", "BusState", "PreparedSubmit", "Priority"]

log = logging.getLogger("motorbus.bus")

#: The decoded reply type of the command given to ``request`` / ``submit``.
R = TypeVar("R")


class PreparedSubmit(Generic[R]):
    """A ``submit`` checked and built ahead of its moment (``Bus.prepare``), sent once
    with ``Bus.send_prepared``: a record, which calls nothing."""

    __slots__ = ("bus", "job", "lease", "lease_version", "sent")

    def __init__(self, bus: Bus, job: BusJob, lease: Lease | None, lease_version: int) -> None:
        #: The bus that prepared it (another refuses it).
        self.bus = bus
        self.job = job
        self.lease = lease
        #: The lease table's version when its rule was checked (-1: check again).
        self.lease_version = lease_version
        self.sent = False


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
        wire_floor: also refuse (and count as ``early_replies``) a reply that completed
            sooner than the wire at the bus's baud allows; only for a link that provably
            paces bytes (a real UART).  Off by default: a reply is accepted by causality.
        safe_action: the safe action of motion sent outside any lease (the implicit
            lease, owner ``"program"``), applied when the bus closes: ``"pause"``
            (default), ``"estop"`` or ``"hold"`` (nothing).

    Every command that starts motion is owned (``motorbus.bus.leases``): by the explicit
    lease (``bus.lease(...)``) of the task that sends it, or else by the bus's implicit
    lease.  A device another explicit lease holds is refused with
    ``LeaseConflictError``, nothing sent.  When a lease ends - ``release()``, the end of
    its ``async with``, or the bus closing (after its streams stopped, before the port
    closes) - each of its devices gets its safe action, unless released with
    ``hold=True`` or already brought to it since its last motion.
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
        wire_floor: bool = False,
        safe_action: str = "pause",
    ) -> None:
        # Every option checked (type, finiteness, range) before anything is built.
        name = check_name("name", name, optional=True)
        families = check_families(families)
        self.config = check_bus_options(
            min_spacing=min_spacing,
            host_margin=host_margin,
            turnaround=turnaround,
            retries=retries,
            late_guard=late_guard,
            reconnect=reconnect,
            wire_floor=wire_floor,
        )
        self.safe_action = safety.check_safe_action(safe_action)
        self.transport = check_transport(transport)
        self.name: str = name or transport.url
        self.families = frozenset(families)
        self._timer = check_timer(timer)
        self._lease_keeper = LeaseKeeper(
            self.name, self.families, self.safe_action, self.request, lambda: self.state.value
        )
        #: The writer, deadlines, reader and reconnect, holding the pure core.
        self._engine = engine = BusEngine(
            transport, self.name, self.families, self.config, self._lease_keeper
        )
        #: The pure core (motorbus.bus.core): the queue, spacing, late guards and
        #: reservations, the matching of replies, the frames' bus time.
        self._core: BusCore[BusJob] = engine.core
        self.stats = engine.stats
        self.events = engine.events
        #: Set when close starts: motion is refused and dropped from then on.
        self._stopping = False
        self._close_hooks: list[Callable[[], Awaitable[None]]] = []
        self._close_task: asyncio.Future[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # -- life cycle --------------------------------------------------------------

    @property
    def state(self) -> BusState:
        """Where the bus is in its life: closed, open, or lost (reconnecting)."""
        return self._engine.state

    @property
    def timer(self) -> Timer:
        """The timer that paces this bus."""
        if self._timer is None:
            self._timer = default_timer()
        return self._timer

    @property
    def next_write_at(self) -> float:
        """The earliest time (``bus.timer`` clock) the spacing rule allows the next write."""
        return self._core.schedule.next_tx

    @property
    def baudrate(self) -> int:
        """The bus's baud rate (bits per second)."""
        return self.transport.baudrate

    async def open(self) -> None:
        """Open the port.  Raises ``OSError`` if the port cannot open."""
        if self.state is BusState.OPEN:
            return
        self._stopping = False
        self._loop = asyncio.get_running_loop()
        engine = self._engine
        engine.start(self.timer)
        lifecycle.bus_opening(self)  # the runtime: MOTORBUS_REALTIME / --realtime
        await self.transport.open(engine.on_data, engine.on_lost)
        engine.state = BusState.OPEN
        lifecycle.bus_opened(self)  # the runtime: SIGTERM/SIGHUP, a running guard
        self._check_adapter_latency()
        engine.publish_state("open")

    def _check_adapter_latency(self) -> None:
        """Warn if a USB adapter's latency timer leaves no deadline of this bus a chance.

        A reply arrives at the earliest after the device turnaround; what the adapter
        may hold it beyond that must fit in the turnaround plus the host margin.
        """
        warn = getattr(self.transport, "warn_if_latency_exceeds", None)
        if warn is None:
            return
        warn(reply_slack(self.timing, self.families))

    def add_close_hook(self, hook: Callable[[], Awaitable[None]]) -> None:
        """Run ``await hook()`` at the start of every ``close``, before the port closes.

        Streams use it to stop safely (their safe action) whatever ends the program:
        the bus is closed on every exit path.  The hooks run together; a hook's error is
        logged, and the others and the close go on.
        """
        self._close_hooks.append(hook)

    def remove_close_hook(self, hook: Callable[[], Awaitable[None]]) -> None:
        """Forget a hook added with ``add_close_hook``; unknown ones are ignored."""
        with contextlib.suppress(ValueError):
            self._close_hooks.remove(hook)

    async def close(self) -> None:
        """Stop what runs on the bus safely, fail what is queued, close the port.

        Idempotent, and safe to call from several tasks at once (they all wait for the
        one close).  Ctrl-C during the safe stop is deferred until it is done
        (``motorbus.lifecycle.deferred_interrupts``).
        """
        task = self._close_task
        if task is None:
            task = self._close_task = asyncio.ensure_future(self._close())
        try:
            await finish_shielded(task)
        finally:
            if task.done() and self._close_task is task:
                self._close_task = None

    async def _close(self) -> None:
        interrupted: BaseException | None = None  # a hook's, raised once the port closed
        with lifecycle.deferred_interrupts():
            # From here no motion is queued or sent: what is queued is dropped unsent,
            # what is submitted is refused, so nothing can follow the safe stops.
            self._stopping = True
            self._engine.drop_queued_motion()
            if self.state is BusState.OPEN:
                # Together: a silent actuator of one streamer holds up no other's stop.

                def failed(i: int, err: Exception) -> None:
                    log.error("bus %s: a close hook failed: %s", self.name, err)

                hooks = [hook() for hook in list(self._close_hooks)]
                interrupted = await together(hooks, failed)
            # The one place every lease still held ends: after the streams stopped (a
            # target after a pause would resume an LA), before the port closes.
            self._engine.drop_queued_motion()
            await self._lease_keeper.end_all()
        engine = self._engine
        await engine.stop(BusClosedError(f"bus {self.name} closed"))
        try:
            await self.transport.close()
        finally:
            lifecycle.bus_closed(self)
            if engine.state is not BusState.CLOSED:
                engine.state = BusState.CLOSED
                engine.publish_state("closed")
        if interrupted is not None:
            raise interrupted

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

    @property
    def timing(self) -> BusTiming:
        """The facts this bus's frame costs depend on: baud, spacing, margin, turnarounds."""
        return self._core.occupancies.timing

    def occupancy(self, cmd: Command[object], request_size: int | None = None) -> Occupancy:
        """How long ``cmd`` and its reply hold this bus (``motorbus.bus.occupancy``).

        ``request_size`` saves re-encoding when the caller has the bytes already.
        """
        return self._core.occupancy(cmd, request_size)

    def answer_window(self, reply_bytes: int) -> float:
        """How long after a request ends a device of this bus may still be answering
        with ``reply_bytes`` bytes (``motorbus.bus.occupancy.answer_window``)."""
        return answer_window(self.timing, self.families, reply_bytes)

    def reply_budget(self, cmd: Command[object], request_size: int | None = None) -> float:
        """Seconds from the completed write of ``cmd`` to its reply deadline.

        Wire time of the request and of its longest possible reply at this bus's baud,
        plus the family's turnaround and the host margin; 0 if no reply is expected
        (``Occupancy.budget``).
        """
        return self.occupancy(cmd, request_size).budget

    async def request(
        self,
        cmd: Command[R],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> R:
        """Send ``cmd`` and return its decoded reply (``None`` if it expects none).

        Args:
            cmd: a command value from ``motorbus.protocol``.
            timeout: reply budget in seconds from the completed write
                (default: ``reply_budget(cmd)``).
            retries: retries after a timeout (default: the bus's; always 0 for
                commands that start motion, which are never retried blindly).
            priority: queue order; ``Priority.EMERGENCY`` jumps the queue.

        Raises:
            ReplyTimeoutError: no matching reply before the deadline (after retries).
            BusClosedError: the bus is closed or its port was lost.
            RemoteProtocolError: the matching reply could not be decoded.
        """
        # submit()'s two steps, without the call between (issue 40).
        job = self._checked_job(cmd, timeout, retries, priority, None, reserved=False)
        self._engine.queue(job, None)
        future: asyncio.Future[R] = job.future
        try:
            return await future
        except asyncio.CancelledError:
            # The caller gave up: a queued job is dropped; a sent one still holds the
            # bus until its reply or deadline, so spacing and matching stay correct.
            future.cancel()
            raise

    def submit(
        self,
        cmd: Command[R],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
        start_by: float | None = None,
        reserved: bool = False,
        refresh: Refresh | None = None,
        lease: Lease | None = None,
    ) -> asyncio.Future[R]:
        """Queue ``cmd`` without waiting; an idle bus transmits it before this returns.

        Returns the future of its decoded reply (``request`` awaits it).  Cancelling the
        future drops the command if it is still queued.  For code that must send at an
        exact instant from a timer callback (the stream ticks); otherwise use
        ``request``.  Arguments and errors as for ``request``, raised at once, and:

        Args:
            start_by: absolute time (``bus.timer`` clock): if the frame has not been
                written by then, it is dropped unsent and the future fails with
                ``NotSentError`` (counted in ``stats.not_sent``).
            reserved: the frame belongs to a reserved window (a stream tick): it is
                not held back by reservations.
            refresh: called when the frame is about to be written; returns the command
                to write now (rebuilt from what is still wanted) or None to drop it
                unsent (the future then resolves to None).  A stream uses it so that a
                frame queued before the stream stopped is never written after.
            lease: the lease a motion command belongs to (default: the running task's
                explicit lease on this bus, else the implicit one).

        Raises (besides ``request``'s):
            LeaseConflictError: ``cmd`` starts motion of a device another owner holds.
            WrongLoopError: called from another event loop than the bus was opened on.
        """
        job = self._checked_job(
            cmd,
            timeout,
            retries,
            priority,
            start_by,
            reserved=reserved,
            refresh=refresh,
            lease=lease,
        )
        self._engine.queue(job, start_by)
        return job.future

    def prepare(
        self,
        cmd: Command[R],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
        reserved: bool = False,
        refresh: Refresh | None = None,
        lease: Lease | None = None,
    ) -> PreparedSubmit[R]:
        """Check and build a ``submit`` ahead of the moment it must be sent.

        Everything ``submit`` does before queueing is done now (checks, the lease rule,
        encoding, the job); ``send_prepared``, called at the deadline (from a
        timer callback: the stream ticks), only re-checks what may have changed since
        (the bus still open and not closing; the ``refresh``; the lease rule again if any
        lease changed) and sends it as ``submit`` does: an idle bus writes it then, with
        the bytes encoded here unless the refresh changed the frame; a frame that must
        wait runs its refresh again at its write.  Arguments and errors as for
        ``submit`` (without ``start_by``).
        """
        job = self._checked_job(
            cmd, timeout, retries, priority, None, reserved=reserved, refresh=refresh, lease=lease
        )
        table = self._lease_keeper.table
        # The lease rule holds until the table changes, for a lease given here: one
        # taken from the running task would depend on the task that sends.
        valid = lease is not None and lease.table is table and lease.active
        return PreparedSubmit(self, job, lease, table.version if valid else -1)

    def _wrong_loop_error(self, cmd: Command[object]) -> WrongLoopError:
        return WrongLoopError(
            f"bus {self.name} was opened on another event loop (thread) than the one "
            f"sending {type(cmd).__name__} to {cmd.device_key}: nothing sent; open a bus "
            "in this loop, or run the call on the bus's loop "
            "(asyncio.run_coroutine_threadsafe)"
        )

    def _closing_error(self, cmd: Command[object]) -> BusClosedError:
        # The bus is closing: its safe stops are going out, and no motion may follow
        # them (a target after a pause resumes an LA).
        return BusClosedError(
            f"bus {self.name} is closing: {type(cmd).__name__} to {cmd.device_key} "
            "refused (nothing sent); the devices are being stopped"
        )

    def send_prepared(self, prepared: PreparedSubmit[R]) -> asyncio.Future[R]:
        """Send what ``prepare`` made, now (an idle bus writes it before this returns);
        once only.  The cheap re-checks and the refresh, then the one send path
        (``BusEngine.queue``; see ``prepare``).

        Returns the future of its decoded reply, as ``submit`` does; it resolves to None
        at once if the ``refresh`` (run here, and again at a later write if the frame
        must wait) drops the frame.

        Raises:
            BusClosedError: the bus is no longer open, or is closing (motion).
            LeaseConflictError: a lease changed since and another owner holds a device.
            LocalProtocolError: it was sent already, or prepared by another bus.
        """
        if prepared.sent or prepared.bus is not self:
            raise LocalProtocolError(
                "a prepared submission is sent once, by the bus that prepared it",
                field="prepared",
            )
        prepared.sent = True
        job = prepared.job
        state = self._engine.state
        if state is not BusState.OPEN:
            raise self._engine.not_open_error()
        if asyncio.get_running_loop() is not self._loop:
            raise self._wrong_loop_error(job.cmd)
        if job.moves and self._stopping:
            raise self._closing_error(job.cmd)
        # The frame as it is now: checked once here, and written as it is if it goes
        # out from this call; one that must wait is checked again at its write.
        if job.refresh is not None and not self._engine.refresh(job):
            return job.future
        if job.moves and prepared.lease_version != self._lease_keeper.table.version:
            # A lease changed since: the rule again, for the frame as it is now.
            job.motion_keys = self._lease_keeper.claim(job.cmd, prepared.lease)
        self._engine.queue(job, None, checked=True)
        return job.future

    async def send(self, cmd: Command[object], *, priority: Priority = Priority.NORMAL) -> None:
        """Send a command that expects no reply (broadcast, 0x03, 0x19), paced like any other."""
        await self.request(cmd, priority=priority)

    # -- leases: one owner per moving device, a safe end for every motion --------------

    def lease(
        self,
        keys: Iterable[str] | str,
        *,
        owner: str,
        safe_action: str = "pause",
        bind: bool = True,
        safe_commands: Iterable[Command[object]] = (),
    ) -> Lease:
        """Hold ``keys`` (``"la:3"``, ``"project_stepper"``, ``"quad_stepper"``) for
        ``owner`` from now on; nothing is sent.

        Motion submitted from this task (and from tasks it starts afterwards) belongs to
        the lease; motion of these devices from anyone else is refused.  End it with
        ``await lease.release()`` (the safe action for each device) or
        ``await lease.release(hold=True)`` (nothing sent: the devices keep their last
        command), or use ``async with bus.lease(...) as lease:``, which releases it
        with the safe action however the block is left.  The bus closing ends it too.

        Args:
            keys: the devices; ``"la:255"`` stands for every LA that answered or was moved by ID.
            owner: a name for errors, logs and ``bus.leases`` (not ``"program"``).
            safe_action: ``"pause"``, ``"estop"`` or ``"hold"`` (steppers: any but hold
                sends their stop).
            bind: make it the running task's lease (default).  ``False`` for an owner
                that sends from elsewhere (a streamer's tick loop) and passes the lease
                to ``submit(..., lease=...)``: the caller's own motion stays apart.
            safe_commands: the owner's own safe end, as commands in the order to send
                them: for each device they address they replace ``safe_action``'s
                commands (the other devices keep those), are owed from now, are what
                ``bus.leases`` (and so a guard process) shows, and are never rewritten
                by the bus.  None may start motion.  ``ProjectStepper.upload`` leases
                the controller with the clear of the project it writes (0x1E).

        Raises:
            LeaseConflictError: another owner's lease holds one of the devices (devices
                moved outside any lease are taken over).
            LocalProtocolError: a bad key, owner or action, or a family the bus does
                not carry; a safe command that starts motion or addresses a device
                not among ``keys``.
        """
        return self._lease_keeper.lease(
            keys,
            owner,
            safe_action,
            bind=check_flag("bind", bind),
            safe_commands=safe_commands,
        )

    @property
    def lease_keeper(self) -> LeaseKeeper:
        """The one place that defines and sends this bus's safe actions (``stop``)."""
        return self._lease_keeper

    @property
    def leases(self) -> tuple[LeaseInfo, ...]:
        """Every leased device now: key, owner and the frames of its safe action."""
        return self._lease_keeper.table.snapshot()

    def add_lease_listener(self, fn: Callable[[tuple[LeaseInfo, ...]], None]) -> None:
        """Call ``fn(bus.leases)`` after every change of the leases (a guard process
        mirrors them).  ``fn`` runs synchronously inside the change: keep it short."""
        self._lease_keeper.table.add_listener(fn)

    def remove_lease_listener(self, fn: Callable[[tuple[LeaseInfo, ...]], None]) -> None:
        """Forget a listener added with ``add_lease_listener``; unknown ones are ignored."""
        self._lease_keeper.table.remove_listener(fn)

    def hand_over(self, lease: Lease, keys: Iterable[str]) -> None:
        """End ``lease`` on ``keys`` without sending anything: the devices pass to the
        bus's implicit lease and hold their last command until it ends (at the latest
        when the bus closes, with its safe action).  A stream whose ``safe_action`` is
        ``"hold"`` ends this way."""
        self._lease_keeper.hand_over(lease, keys)

    async def release(self, keys: Iterable[str] | None = None, *, hold: bool = False) -> None:
        """End the implicit lease (motion sent outside any lease) on ``keys`` (default:
        every device it holds): each gets its safe action now, unless ``hold=True``,
        which ends it on purpose and sends nothing (the devices keep their last command,
        and the bus's close will not stop them).

        Raises:
            LeaseConflictError: an explicit lease holds one of the devices: release
                that lease instead.
        """
        await self._lease_keeper.release_implicit(keys, hold)

    # -- observers and reservations --------------------------------------------------

    def add_observer(self, observer: BusObserver) -> None:
        """Tell ``observer`` of every frame written and every reply accepted, with the
        bus's own times (``bus.timer`` clock): ``on_write(cmd, at)`` at the completed
        write, ``on_reply(cmd, value, written_at, replied_at)`` when its reply's bytes
        were read.  Called synchronously from the bus: keep them short.  An observer
        that raises is logged and removed; the bus goes on.  Observing sends nothing."""
        if observer not in self._engine.observers:
            self._engine.observers.append(observer)

    def remove_observer(self, observer: BusObserver) -> None:
        """Stop telling ``observer`` (no error if it was not added)."""
        with contextlib.suppress(ValueError):
            self._engine.observers.remove(observer)

    def add_wire_tap(self, tap: WireTap) -> None:
        """Tell ``tap(outgoing, data, at)`` of every frame written and chunk read, in wire
        order (``BusEngine.add_wire_tap``; ``remove_wire_tap`` stops it)."""
        self._engine.add_wire_tap(tap)

    def remove_wire_tap(self, tap: WireTap) -> None:
        self._engine.remove_wire_tap(tap)

    def add_reservation_source(self, source: ReservationSource) -> None:
        """Register ``source(now) -> (start, end) | None``: the next reserved window.

        A frame that is not ``reserved`` is not started if it could still hold the bus
        (its write, its spacing, and its whole reply budget) when a reserved window
        begins; it waits until the window ends.  Emergency frames ignore reservations.
        Streams use this so that user requests never delay a tick.
        """
        self._core.schedule.reservation_sources.append(source)

    def remove_reservation_source(self, source: ReservationSource) -> None:
        """Forget a source added with ``add_reservation_source``; unknown ones are ignored."""
        with contextlib.suppress(ValueError):
            self._core.schedule.reservation_sources.remove(source)

    async def wait_state(self, state: BusState, timeout: float | None = None) -> None:
        """Wait until the bus reaches ``state`` (e.g. ``OPEN`` after a reconnect)."""
        state = BusState.checked(state)
        if self.state is state:
            return
        async with self.events.subscribe(BusStateChanged, lambda e: e.state == state.value) as sub:
            if self.state is state:
                return
            await sub.next(timeout)

    # -- requests: the checks and the one way out -----------------------------------

    def _checked_job(
        self,
        cmd: Command[R],
        timeout: float | None,
        retries: int | None,
        priority: Priority,
        start_by: float | None,
        *,
        reserved: bool,
        refresh: Refresh | None = None,
        lease: Lease | None = None,
    ) -> BusJob:
        """Check a submission (``submit``'s errors, in its order), claim its lease and
        build its job, not yet queued."""
        core = self._core
        if start_by is not None or type(cmd) not in core.checked_types:
            core.check(cmd, start_by)
        if timeout is not None or retries is not None or type(priority) is not Priority:
            check_request_options(timeout, retries, priority)
        if type(reserved) is not bool:  # a truthy text would skip the reservations
            check_flag("reserved", reserved)
        state = self._engine.state
        if state is not BusState.OPEN:
            raise self._engine.not_open_error()
        moves = cmd.starts_motion
        if self._stopping and moves:
            raise self._closing_error(cmd)
        loop = asyncio.get_running_loop()
        if loop is not self._loop:
            raise self._wrong_loop_error(cmd)
        keys = self._lease_keeper.claim(cmd, lease) if moves else None
        raw = cmd.encode()
        occ = core.occupancy(cmd, len(raw))
        n_retries = self.config.retries if retries is None else retries
        return BusJob(
            cmd=cmd,
            raw=raw,
            future=loop.create_future(),
            priority=int(priority),
            seq=0,  # set when queued
            timeout=occ.budget if timeout is None else float(timeout),
            retries_left=0 if moves or not occ.expects_reply else n_retries,
            key=cmd.device_key,
            reserved=reserved,
            refresh=refresh,
            after_write=occ.after_write,
            answered=occ.answered,
            expects=occ.expects_reply,
            moves=moves,
            motion_keys=keys,
        )
