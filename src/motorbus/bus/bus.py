"""One serial bus: one port, one queue, request/reply matching, spacing and deadlines.

The bus owns one port.  Everything written to the port goes through one queue, in
priority order (an emergency stop jumps it), and a frame's write starts only when

* at least ``min_spacing`` (1 ms, LA manual 3.4.2, docs/protocols.md C.6) has passed
  since the previous write *returned* (and the previous frame's own wire time, if
  longer).  The anchor
  is the moment the write call came back, not a timestamp taken before it: a process
  preempted between reading the clock and writing would otherwise write later than
  its timestamp says, and the kernel would see two frames closer than the rule;
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
reply look newer than the request.  Whether a reply is on time is
decided by when its bytes were seen against the deadline, whichever callback runs
first.  A late reply is never given to a later request: after a timeout, the next
request to that device waits ``late_guard``, and the late frame is recognised by its
shape and counted.  The protocols carry no sequence numbers, so a reply later than the
guard with exactly the shape of a newer request cannot be told apart: raise
``late_guard`` for such devices.  ``wire_floor=True`` (for a real UART that paces bytes
at the baud) also refuses frames that completed sooner than the wire allows; each such
frame is counted as ``early_replies`` and logged, never silently made a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
import os
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol, TypeVar

from motorbus import realtime, shutdown
from motorbus.bus.events import (
    BusStateChanged,
    EventHub,
    FaultChanged,
    ProjectFinished,
    QuadDone,
)
from motorbus.bus.lease_shell import LeaseKeeper
from motorbus.bus.leases import Lease, LeaseInfo
from motorbus.bus.matching import DoneWatch, Matcher, TimedOut, Verdict
from motorbus.bus.occupancy import BusTiming, Occupancy, command_occupancy
from motorbus.bus.schedule import Job, Priority, ReservationSource, Scheduler, Wait
from motorbus.bus.stats import BusStats
from motorbus.bus.timer import Timer, TimerHandle, default_timer
from motorbus.errors import (
    BusClosedError,
    LocalProtocolError,
    NotSentError,
    RemoteProtocolError,
    ReplyTimeoutError,
    WrongLoopError,
)
from motorbus.protocol import families, safety
from motorbus.protocol.base import (
    Command,
    Family,
    FaultState,
    FrameShape,
    check_flag,
    check_int,
    check_timeout,
    format_hex,
)
from motorbus.protocol.reassembler import Discarded, Frame, ProjectFinishedMarker, Reassembler
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

__all__ = ["DEFAULT_TURNAROUND", "Bus", "BusObserver", "BusState", "Priority"]

log = logging.getLogger("motorbus.bus")

#: The decoded reply type of the command given to ``request`` / ``submit``.
R = TypeVar("R")

#: Minimum start-to-start spacing of two frames: "keep the command interval >= 1 ms"
#: (LA manual 3.4.2, docs/protocols.md C.6).
MIN_SPACING_S = 1e-3
#: Worst-case device turnaround, request end to reply start, per family: the registry's
#: ``FamilyInfo.turnaround_s`` (protocol/families.py says where each figure comes from).
DEFAULT_TURNAROUND: Mapping[Family, float] = families.DEFAULT_TURNAROUND
#: Host-side latency allowance added to every deadline: scheduling, the pty or the USB
#: adapter (an FTDI in low-latency mode holds bytes up to 1 ms, docs/platform.md 5).  The
#: demo's LA round trips over a pty to a simulator process on this 2-core machine had a
#: p99 near 2 ms (benchmarks/bench_bus.py measures it), hence 2 ms.  On a loaded or
#: slow host, raise it for every bus at once with ``MOTORBUS_HOST_MARGIN_MS``.
DEFAULT_HOST_MARGIN_S = float(os.environ.get("MOTORBUS_HOST_MARGIN_MS", "2")) / 1e3
#: After a timeout, the next request to the same device waits this long, so that the
#: device's late answer (if it comes) arrives before a new question it could be
#: mistaken for.  Requests to other devices are not held.
DEFAULT_LATE_GUARD_S = 20e-3
#: A timer callback that runs this much after its deadline means the host (not the
#: device) stalled: a full garbage collection, another process on the core.  Timeouts
#: and late replies decided then are counted apart (``BusStats.host_stalls``).
HOST_STALL_S = 1e-3
#: Retries of each safe-action command a lease's end sends (pause, e-stop, stop project,
#: stop all are idempotent: sending one twice is harmless, missing one is not).
SAFE_STOP_RETRIES = 2
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


@dataclass(slots=True, eq=False, kw_only=True)
class _Job(Job):
    """One request travelling through the bus: the pure core's record (``Job``), and
    beside it what the asyncio shell keeps: its future and its timer handles."""

    future: asyncio.Future[Any]
    handle: TimerHandle | None = None  # its reply deadline
    refresh: Refresh | None = None
    start_by: float = math.inf
    expiry: TimerHandle | None = None  # its start_by

    def gone(self) -> bool:
        return self.future.done()


@dataclass(slots=True)
class BusConfig:
    """Timing policy of one bus (all durations in seconds)."""

    min_spacing: float = MIN_SPACING_S
    host_margin: float = DEFAULT_HOST_MARGIN_S
    turnaround: dict[Family, float] = field(default_factory=lambda: dict(DEFAULT_TURNAROUND))
    retries: int = 1
    late_guard: float = DEFAULT_LATE_GUARD_S
    reconnect: bool = True
    wire_floor: bool = False


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
        min_spacing = check_number("min_spacing", min_spacing, 0.0, MIN_SPACING_MAX_S, "s")
        host_margin = check_number("host_margin", host_margin, 0.0, HOST_MARGIN_MAX_S, "s")
        turnaround = check_turnaround(turnaround)
        retries = check_int("retries", retries, 0, RETRIES_MAX)
        late_guard = check_number("late_guard", late_guard, 0.0, LATE_GUARD_MAX_S, "s")
        reconnect = check_flag("reconnect", reconnect)
        wire_floor = check_flag("wire_floor", wire_floor)
        self.safe_action = safety.check_safe_action(safe_action)
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
            wire_floor=wire_floor,
        )
        self.stats = BusStats()
        self.events = EventHub()
        self.state = BusState.CLOSED
        self._timer = timer
        self._reassembler = Reassembler(families=self.families, stats=self.stats.reassembler)
        # The pure core: when frames may start (queue, spacing, late guards,
        # reservations), and whose frame a received one is (pending request, late
        # window, done-watches, the shapes the reassembler may cut).
        self._schedule: Scheduler[_Job] = Scheduler()
        self._matcher: Matcher[_Job] = Matcher(
            self.families, wire_floor=wire_floor, on_shapes=self._expect_shapes
        )
        self._rx_total = 0  # bytes handed to the reassembler since the port opened
        self._close_hooks: list[Callable[[], Awaitable[None]]] = []
        self._close_task: asyncio.Future[None] | None = None
        self._pump_handle: TimerHandle | None = None
        self._pump_at = 0.0
        self._pumping = False
        self._reconnect_task: asyncio.Task[None] | None = None
        self._last_errors: dict[int, int] = {}
        self._closing = False
        self._observers: list[BusObserver] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lease_keeper = LeaseKeeper(
            self.name,
            self.families,
            self.safe_action,
            lambda cmd: self.request(cmd, priority=Priority.EMERGENCY, retries=SAFE_STOP_RETRIES),
            lambda: self.state.value,
        )
        self._leases = self._lease_keeper.table  # the hot paths' direct reference
        #: The time budget this bus's streams share (``motorbus.streaming.budget``), set
        #: by its first ``Streamer``: the bus owns it, whichever streamer serves a stream.
        self.stream_budget: Any = None

    # -- life cycle --------------------------------------------------------------

    @property
    def timer(self) -> Timer:
        """The timer that paces this bus."""
        if self._timer is None:
            self._timer = default_timer()
        return self._timer

    @property
    def next_write_at(self) -> float:
        """The earliest time (``bus.timer`` clock) the spacing rule allows the next write."""
        return self._schedule.next_tx

    @property
    def baudrate(self) -> int:
        """The bus's baud rate (bits per second)."""
        return self.transport.baudrate

    async def open(self) -> None:
        """Open the port.  Raises ``OSError`` if the port cannot open."""
        if self.state is BusState.OPEN:
            return
        self._closing = False
        self._loop = asyncio.get_running_loop()
        self._new_reassembler()
        realtime.on_bus_open()  # MOTORBUS_REALTIME / --realtime, once per process
        await self.transport.open(self._on_data, self._on_lost)
        self.state = BusState.OPEN
        shutdown.register_bus(self)
        self._check_adapter_latency()
        self._publish_state("open")

    def _new_reassembler(self) -> None:
        """A fresh stream (on open and after a lost port): nothing buffered, offsets at 0."""
        self._reassembler = Reassembler(families=self.families, stats=self.stats.reassembler)
        self._rx_total = 0
        self._matcher.update_shapes(force=True)

    def _check_adapter_latency(self) -> None:
        """Warn if a USB adapter's latency timer leaves no deadline of this bus a chance.

        A reply arrives at the earliest after the device turnaround; what the adapter
        may hold it beyond that must fit in the turnaround plus the host margin.
        """
        warn = getattr(self.transport, "warn_if_latency_exceeds", None)
        if warn is None:
            return
        # A reply's slack beyond the wire: turnaround + margin (Occupancy.budget's terms).
        slack = min(self.config.turnaround[f] for f in self.families) + self.config.host_margin
        warn(slack)

    def add_close_hook(self, hook: Callable[[], Awaitable[None]]) -> None:
        """Run ``await hook()`` at the start of every ``close``, before the port closes.

        Streams use it to stop safely (their safe action) whatever ends the program:
        the bus is closed on every exit path.  A hook's error is logged; the others and
        the close go on.
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
        (``motorbus.shutdown.deferred_interrupts``).
        """
        task = self._close_task
        if task is None:
            task = self._close_task = asyncio.ensure_future(self._close())
        try:
            await asyncio.shield(task)
        finally:
            if task.done() and self._close_task is task:
                self._close_task = None

    async def _close(self) -> None:
        with shutdown.deferred_interrupts():
            if self.state is BusState.OPEN:
                for hook in list(self._close_hooks):
                    try:
                        await hook()
                    except Exception as err:
                        log.error("bus %s: a close hook failed: %s", self.name, err)
            # The one place every lease still held ends: after the streams stopped (a
            # target after a pause would resume an LA), before the port closes.
            await self._lease_keeper.end_all()
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
        try:
            await self.transport.close()
        finally:
            shutdown.unregister_bus(self)
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

    @property
    def timing(self) -> BusTiming:
        """The facts this bus's frame costs depend on: baud, spacing, margin, turnarounds."""
        cfg = self.config
        return BusTiming(self.baudrate, cfg.min_spacing, cfg.host_margin, cfg.turnaround)

    def occupancy(self, cmd: Command[object], request_size: int | None = None) -> Occupancy:
        """How long ``cmd`` and its reply hold this bus (``motorbus.bus.occupancy``).

        ``request_size`` saves re-encoding when the caller has the bytes already.
        """
        return command_occupancy(self.timing, cmd, request_size)

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
        if start_by is not None and not (
            isinstance(start_by, int | float) and not isinstance(start_by, bool)
        ):
            raise LocalProtocolError(
                f"start_by must be a time in seconds, got {start_by!r}", field="start_by"
            )
        if self.state is not BusState.OPEN:
            raise BusClosedError(f"bus {self.name} is {self.state.value}")
        loop = asyncio.get_running_loop()
        if loop is not self._loop:
            raise WrongLoopError(
                f"bus {self.name} was opened on another event loop (thread) than the one "
                f"sending {type(cmd).__name__} to {cmd.device_key}: nothing sent; open a bus "
                "in this loop, or run the call on the bus's loop "
                "(asyncio.run_coroutine_threadsafe)"
            )
        if cmd.starts_motion:
            self._lease_keeper.claim(cmd, lease)
        raw = cmd.encode()
        occ = self.occupancy(cmd, len(raw))
        budget = occ.budget if timeout is None else float(timeout)
        n_retries = self.config.retries if retries is None else retries
        if cmd.starts_motion or not cmd.expects_reply:
            n_retries = 0
        job = _Job(
            cmd=cmd,
            raw=raw,
            future=loop.create_future(),
            priority=int(priority),
            seq=self._schedule.next_seq(),
            timeout=budget,
            retries_left=n_retries,
            key=cmd.device_key,
            reserved=reserved,
            refresh=refresh,
            after_write=occ.after_write,
        )
        if start_by is not None:
            job.start_by = float(start_by)
            job.expiry = self.timer.call_at(
                job.start_by, lambda: self._drop_unsent(job), precise=False
            )
        self._schedule.push(job)
        self._pump()  # an idle bus sends right here
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

        Raises:
            LeaseConflictError: another owner's lease holds one of the devices (devices
                moved outside any lease are taken over).
            LocalProtocolError: a bad key, owner or action, or a family the bus does
                not carry.
        """
        return self._lease_keeper.lease(keys, owner, safe_action, bind=check_flag("bind", bind))

    @property
    def leases(self) -> tuple[LeaseInfo, ...]:
        """Every leased device now: key, owner and the frames of its safe action."""
        return self._leases.snapshot()

    def add_lease_listener(self, fn: Callable[[tuple[LeaseInfo, ...]], None]) -> None:
        """Call ``fn(bus.leases)`` after every change of the leases (a guard process
        mirrors them).  ``fn`` runs synchronously inside the change: keep it short."""
        self._leases.add_listener(fn)

    def remove_lease_listener(self, fn: Callable[[tuple[LeaseInfo, ...]], None]) -> None:
        """Forget a listener added with ``add_lease_listener``; unknown ones are ignored."""
        self._leases.remove_listener(fn)

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

    # -- reservations --------------------------------------------------------------

    def add_observer(self, observer: BusObserver) -> None:
        """Tell ``observer`` of every frame written and every reply accepted, with the
        bus's own times (``bus.timer`` clock): ``on_write(cmd, at)`` at the completed
        write, ``on_reply(cmd, value, written_at, replied_at)`` when its reply's bytes
        were read.  Called synchronously from the bus: keep them short.  An observer
        that raises is logged and removed; the bus goes on.  Observing sends nothing."""
        if observer not in self._observers:
            self._observers.append(observer)

    def remove_observer(self, observer: BusObserver) -> None:
        """Stop telling ``observer`` (no error if it was not added)."""
        with contextlib.suppress(ValueError):
            self._observers.remove(observer)

    def _tell(self, call: Callable[[BusObserver], None]) -> None:
        for observer in list(self._observers):
            try:
                call(observer)
            except Exception:
                log.exception("%s: observer %r failed; removed", self.name, observer)
                self.remove_observer(observer)

    def add_reservation_source(self, source: ReservationSource) -> None:
        """Register ``source(now) -> (start, end) | None``: the next reserved window.

        A frame that is not ``reserved`` is not started if it could still hold the bus
        (its write, its spacing, and its whole reply budget) when a reserved window
        begins; it waits until the window ends.  Emergency frames ignore reservations.
        Streams use this so that user requests never delay a tick.
        """
        self._schedule.reservation_sources.append(source)

    def remove_reservation_source(self, source: ReservationSource) -> None:
        """Forget a source added with ``add_reservation_source``; unknown ones are ignored."""
        with contextlib.suppress(ValueError):
            self._schedule.reservation_sources.remove(source)

    # -- writer ------------------------------------------------------------------
    #
    # There is no writer task: ``_pump`` sends the head of the queue as soon as the bus
    # allows it, and is called whenever that may have changed (a request queued, a reply
    # matched, a deadline run out, the port back) or by the timer when the spacing, a
    # late guard or a reservation ends.  A task would add an event-loop step (~55 us p50
    # on this VM, benchmarks/bench_wakeups.py) to every command; a timer callback sends
    # on time.

    def _pump(self) -> None:
        if self._pumping:
            return  # called back from inside a transmission: the loop below goes on
        self._pumping = True
        try:
            matcher, schedule, timer = self._matcher, self._schedule, self.timer
            while matcher.pending is None and self.state is BusState.OPEN:
                decision = schedule.poll(timer.now())
                if decision is None:
                    return
                if isinstance(decision, Wait):
                    self._pump_later(decision.at, precise=decision.precise)
                    return
                self._transmit(decision)
        finally:
            self._pumping = False

    def _pump_later(self, start: float, *, precise: bool = True) -> None:
        handle = self._pump_handle
        if handle is not None:
            if self._pump_at == start and handle.precise == precise:
                return
            handle.cancel()
        self._pump_at = start
        self._pump_handle = self.timer.call_at(start, self._on_pump_timer, precise=precise)

    def _on_pump_timer(self) -> None:
        self._pump_handle = None
        self._pump()

    def _drop_unsent(self, job: _Job) -> None:
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

    def _transmit(self, job: _Job) -> None:
        if job.expiry is not None:
            job.expiry.cancel()
            job.expiry = None
        if job.refresh is not None:
            fresh = job.refresh()
            if fresh is None:
                self.stats.dropped_by_refresh += 1
                if not job.future.done():
                    job.future.set_result(None)
                return
            if fresh is not job.cmd:
                job.cmd = fresh
                job.raw = fresh.encode()
                job.after_write = self.occupancy(fresh, len(job.raw)).after_write
        cmd = job.cmd
        job.attempts += 1
        stats = self.stats
        stats.requests += 1
        stats.bytes_out += len(job.raw)
        device = stats.device(job.key)
        device.requests += 1
        expects = cmd.expects_reply
        if expects:
            # Bytes the OS already holds came before this write, whenever the loop gets
            # round to them: read them first, so that they fall before the mark.
            self.transport.drain_input()
            # Registered before the write: no callback can run during it, and whatever
            # the reassembler holds or has consumed so far came before it.
            job.rx_mark = self._rx_total
            self._matcher.sent(job)
        else:
            stats.no_reply_frames += 1
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s TX %s (%s)", self.name, format_hex(job.raw), type(cmd).__name__)
        timer = self.timer
        before = timer.now()
        try:
            self.transport.write(job.raw)
        except BusClosedError as err:
            self._finish(job, err)
            return
        after = timer.now()
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

    def _expect_shapes(self, shapes: tuple[FrameShape, ...]) -> None:
        """The matcher's shapes changed: tell the reassembler (``Matcher.update_shapes``)."""
        self._reassembler.expect(shapes)

    def _finish(self, job: _Job, outcome: Any) -> None:
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
        self._expire(job, self.timer.now())

    def _expire(self, job: _Job, now: float) -> None:
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
        now = self.timer.now()
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
        elif verdict is Verdict.OVERDUE:
            # Seen after the deadline, whichever callback runs first: late.  The
            # deadline's own callback has not run yet (the loop was held up), so the
            # timeout is decided here, and the frame is counted as its late reply.
            assert job is not None
            self._expire(job, now)
            verdict, about = matcher.classify(raw, start, now)
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

    def _accept(self, job: _Job, raw: bytes, now: float) -> None:
        latency = now - job.tx_time
        stats = self.stats
        stats.replies += 1
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


#: Every priority, built once: the check runs on every submit (the stream's hot path).
_PRIORITIES = frozenset(Priority)


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
    if isinstance(priority, bool) or priority not in _PRIORITIES:
        raise LocalProtocolError(
            f"priority={priority!r} is not allowed: choose one of "
            f"{', '.join(p.name for p in Priority)}",
            field="priority",
            value=priority,
        )
