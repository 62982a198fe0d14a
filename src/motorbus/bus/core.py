"""The pure core of one bus: what may be sent when, whose frame a received one is.

Pure (no asyncio, no clock, no futures, no timer handles, no transport): the time is
passed in and the answers are decisions and records, as in the simulators.
``BusEngine`` (``motorbus.bus.engine``, which ``Bus`` holds) holds one :class:`BusCore`
and is the only thing that drives it, with the bus's timer and transport; the core
never calls either.  It composes the
other pure modules of the bus:

* ``motorbus.bus.schedule``: the queue, the spacing rule, the late guards and the
  reserved windows (when the next frame may start);
* ``motorbus.bus.matching``: the pending request, late replies and done-watches (whose
  frame a received one is), and from them the shapes the reassembler may cut;
* ``motorbus.bus.occupancy``: how long a frame and its reply hold the bus;
* ``motorbus.protocol.reassembler``: frames out of the received bytes;
* ``motorbus.bus.stats``: the counts of all of it.

The shell's job records (``BusJob``) extend the core's ``Job`` with their future and
timer handles; the core handles them only as ``Job``.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator
from typing import Any, Generic, TypeVar

from motorbus.bus.matching import Matcher, TimedOut, Verdict
from motorbus.bus.occupancy import BusTiming, Occupancy, OccupancyTable
from motorbus.bus.schedule import Job, Priority, Scheduler, Wait
from motorbus.bus.stats import BusStats, record_twice
from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Command, Family, FaultState, FrameShape, format_hex
from motorbus.protocol.reassembler import Discarded, Frame, ProjectFinishedMarker, Reassembler

__all__ = ["HOST_STALL_S", "BusCore", "Received"]

J = TypeVar("J", bound=Job)

log = logging.getLogger("motorbus.bus")

#: A deadline decided this much after its time means the host (not the device) stalled:
#: a full garbage collection, another process on the core.  Timeouts decided then are
#: counted apart (``BusStats.timeouts_in_host_stall``).
HOST_STALL_S = 1e-3

#: What a received item is for the shell, in order: ``(Verdict.ACCEPTED, job, raw)``,
#: ``(Verdict.DONE, DoneWatch, raw)``, ``(Discarded, item, raw)``, ``(ProjectFinishedMarker,
#: None, raw)``; frames only counted (late, unexpected, early) are not handed out.
Received = tuple[Any, Any, bytes]


class BusCore(Generic[J]):
    """The queue, spacing, reservations, matching, occupancy and framing of one bus."""

    def __init__(
        self,
        name: str,
        families: frozenset[Family],
        timing: BusTiming,
        stats: BusStats,
        *,
        late_guard: float,
        wire_floor: bool,
    ) -> None:
        self.name = name
        self.families = families
        self.late_guard = late_guard
        self.stats = stats
        self.schedule: Scheduler[J] = Scheduler()
        self.matcher: Matcher[J] = Matcher(
            families, wire_floor=wire_floor, on_shapes=self._expect_shapes
        )
        # The options are frozen and a transport keeps its baud: the costs are fixed.
        self.occupancies = OccupancyTable(timing)
        self.reassembler = Reassembler(families=families, stats=stats.reassembler)
        self.rx_total = 0  # bytes handed to the reassembler since the port opened
        #: The command types already checked to be commands of a family of this bus
        #: (``check`` has nothing to do for them without a ``start_by``).
        self.checked_types: set[type] = set()
        self._last_errors: dict[int, int] = {}

    # -- submissions -------------------------------------------------------------

    def check(
        self,
        cmd: Command[object],
        start_by: float | None,
    ) -> None:
        """``Bus.submit``'s checks of the command and ``start_by`` (nothing built yet;
        the request options are ``motorbus.bus.options.check_request_options``'s).

        Raises:
            LocalProtocolError: not a command, a family the bus does not carry, a bad
                ``start_by``.
        """
        kind = type(cmd)
        if kind not in self.checked_types:
            if not isinstance(cmd, Command):
                raise LocalProtocolError(
                    f"cmd must be a motorbus Command, got {kind.__name__}", field="cmd"
                )
            if cmd.family not in self.families:
                raise LocalProtocolError(
                    f"cmd is a {cmd.family.value} command; bus {self.name} carries "
                    f"{', '.join(sorted(f.value for f in self.families))}",
                    field="cmd",
                )
            if isinstance(getattr(kind, "family", None), Family):
                self.checked_types.add(kind)  # a class attribute: every instance is the same
        if start_by is not None and not (
            isinstance(start_by, int | float)
            and not isinstance(start_by, bool)
            and start_by == start_by  # NaN: its timer callback failed, and the bus hung
        ):
            raise LocalProtocolError(
                f"start_by must be a time in seconds on the bus.timer clock (a number, "
                f"not NaN), got {start_by!r}; nothing sent",
                field="start_by",
                value=start_by,
            )

    def occupancy(self, cmd: Command[object], request_size: int | None = None) -> Occupancy:
        """How long ``cmd`` and its reply hold the bus (``motorbus.bus.occupancy``)."""
        return self.occupancies.of(cmd, request_size)

    # -- the writer's decisions ----------------------------------------------------

    def next(self, now: float) -> J | Wait | None:
        """What to send at ``now``: a job, a ``Wait`` until the rules allow one, or
        None (nothing queued, or a reply still owed)."""
        if not self.schedule.heap or self.matcher.pending is not None:
            return None
        return self.schedule.poll(now)

    def starts_now(self, job: J, now: float) -> bool:
        """Whether ``job`` may be written at ``now`` on an idle bus: nothing queued, no
        reply owed, and its rules (spacing, guard, reservations) let it start."""
        return (
            not self.schedule.heap
            and self.matcher.pending is None
            and self.schedule.start_at(job, now) <= now
        )

    def sending(self, job: J, expects: bool) -> None:
        """``job`` is about to be written: if it expects a reply, it is the pending
        request from here, and its reply is what is received after this point."""
        if expects:
            # Registered before the write: no callback can run during it, and whatever
            # the reassembler holds or has consumed so far came before it.
            job.rx_mark = self.rx_total
            self.matcher.sent(job)

    def wrote(self, job: J, expects: bool, before: float, after: float, baud: int) -> None:
        """``job``'s write ran from ``before`` to ``after``: count it; spacing counts
        from the completed write; a request's deadline is set from it."""
        self.count_sent(job, expects)
        self.schedule.wrote(job, before, after)
        job.tx_start, job.tx_time = before, after
        if expects:
            self.matcher.written(job, before, after, baud)

    def count_sent(self, job: J, expects: bool) -> None:
        """Count ``job`` as sent (also a write that failed: the bytes may have left)."""
        stats = self.stats
        stats.requests += 1
        stats.bytes_out += len(job.raw)
        try:
            device = stats.devices[job.key]  # (not device(): a call fewer a frame)
        except KeyError:
            device = stats.device(job.key)
        device.requests += 1
        if not expects:
            stats.no_reply_frames += 1

    def timed_out(self, job: J, now: float) -> tuple[bool, float]:
        """``job``'s deadline was decided at ``now`` with no reply: count it, guard its
        device, and requeue it if it has a retry left (True) or release the bus for
        its failure (False).  Returns that and how late the decision came."""
        stats = self.stats
        stats.timeouts += 1
        stats.device(job.key).timeouts += 1
        stalled = now - job.deadline
        if stalled > HOST_STALL_S:
            # The deadline was decided this late: the host, not the device, was slow.
            stats.timeouts_in_host_stall += 1
            stats.host_stall_max = max(stats.host_stall_max, stalled)
        self.matcher.timed_out(job, now)
        self.schedule.guard(job.key, now + self.late_guard)
        if job.retries_left > 0 and not job.gone():
            job.retries_left -= 1
            stats.retries += 1
            stats.device(job.key).retries += 1
            self.matcher.release(job)
            self.schedule.requeue(job, Priority.HIGH)
            return True, stalled
        return False, stalled

    def drop_motion(self) -> list[J]:
        """Take every queued motion frame never written out of the queue (the bus is
        closing); returns them, for the shell to fail."""
        schedule = self.schedule
        kept: list[J] = []
        dropped: list[J] = []
        for job in schedule.heap:
            (dropped if job.cmd.starts_motion and not job.attempts else kept).append(job)
        if dropped:
            heapq.heapify(kept)
            schedule.heap = kept
        return dropped

    # -- the reader ------------------------------------------------------------------

    def new_stream(self) -> None:
        """A fresh stream (on open and after a lost port): nothing buffered, offsets at 0."""
        self.reassembler = Reassembler(families=self.families, stats=self.stats.reassembler)
        self.rx_total = 0
        self.matcher.update_shapes(force=True)

    def _expect_shapes(self, shapes: tuple[FrameShape, ...]) -> None:
        """The matcher's shapes changed: tell the reassembler (``Matcher.update_shapes``)."""
        self.reassembler.expect(shapes)

    def feed(self, data: bytes, now: float) -> Iterator[Received]:
        """Received ``data`` at ``now``: the frames cut from it, matched and counted.

        Yields what the shell acts on, in order (``Received``): a reply accepted for
        the pending request (still pending until the shell releases it), a done reply,
        a discarded run of bytes (already counted, for the log), the end of a project
        run.  Lazily: the shell acts on each before the next is cut and matched (a
        reply taken changes the shapes awaited and the pending request).
        """
        stats = self.stats
        size = len(data)
        stats.bytes_in += size
        reassembler = self.reassembler
        matcher = self.matcher
        # Stream offset of the first byte the reassembler still holds: the items it
        # returns cover the stream from there, contiguously and in order.
        offset = self.rx_total - reassembler.buffered
        self.rx_total += size
        for item in reassembler.feed(data):
            start = offset
            raw = item.raw
            offset += len(raw)
            kind = type(item)
            if kind is Frame:
                job = matcher.pending
                verdict, about = matcher.classify(raw, start, now)
                if verdict is Verdict.ACCEPTED:
                    yield verdict, job, raw
                elif verdict is Verdict.DONE:
                    yield verdict, about, raw
                elif verdict is Verdict.LATE:
                    assert isinstance(about, TimedOut)
                    stats.late_replies += 1
                    stats.late_reply_max = max(stats.late_reply_max, now - about.deadline)
                    stats.device(about.key).late_replies += 1
                    log.debug("%s late reply from %s: %s", self.name, about.key, format_hex(raw))
                elif verdict is Verdict.EARLY:
                    assert job is not None
                    stats.early_replies += 1
                    log.debug(
                        "%s frame %s too early for the wire (%.0f us before the floor)",
                        self.name,
                        format_hex(raw),
                        (job.earliest - now) * 1e6,
                    )
                elif verdict is Verdict.UNEXPECTED:
                    stats.unexpected_frames += 1
                    log.debug("%s unexpected frame %s", self.name, format_hex(raw))
            elif kind is Discarded or kind is ProjectFinishedMarker:
                # Discards are counted by the reassembler, in stats.reassembler.
                yield kind, item, raw

    def accepted(self, job: J, now: float) -> None:
        """Count the reply accepted for ``job`` at ``now`` (its decoding is the shell's)."""
        latency = now - job.tx_time
        stats = self.stats
        stats.replies += 1
        if now > job.deadline:  # read late, before the deadline was decided (matching.py)
            stats.replies_past_deadline += 1
        try:
            device = stats.devices[job.key]  # made when its request was counted
        except KeyError:
            device = stats.device(job.key)
        device.replies += 1
        record_twice(stats.latency, device.latency, latency)

    def watch_done(self, cmd: Command[object]) -> None:
        """``cmd`` was answered: await its done reply, if it has one."""
        if type(cmd).done_shapes is Command.done_shapes:
            return  # the base's: none (most commands; no call to find out)
        if cmd.done_shapes() and self.matcher.watch_done(cmd):
            # Past MAX_DONE_WATCHES: a done reply lost on the line, the oldest forgotten.
            self.stats.done_watches_dropped += 1

    def fault_change(self, fault: FaultState | None) -> int | None:
        """The fault flags a reply reports (``Command.fault_state``): the device's flags
        before, if they changed, else None."""
        if fault is None:
            return None
        before = self._last_errors.get(fault.device_id, 0)
        self._last_errors[fault.device_id] = fault.errors
        return before if fault.errors != before else None
