"""``SimBus``: the pure core of a simulated serial bus.

No asyncio, no clock, no I/O: a driver (``MemorySim``, ``PtySim``) passes in the bytes
the host wrote and the time they arrived, asks for the bytes due toward the host, and
sleeps until ``next_wakeup()``.

Timing model
------------
``pacing="wire"`` (the default) models a device on a real UART behind the host's own
UART: a pty or in-memory link delivers bytes instantly, so the core emulates the wire:

* **Requests.** The host's bytes are taken as sent back to back: a chunk arriving at
  ``now`` starts on the wire at ``max(now, line_free)`` and takes ``wire_time`` of its
  length; each byte's end time follows, so a request cut from the middle of a chunk
  ends when its own last byte does.  Models see ``handle(request, t_end)``.
* **Replies.** A reply starts ``model.turnaround(rng)`` after the request's end, no
  earlier than the end of the previous transmission toward the host (replies of
  several devices are serialised rather than collided), and takes its own wire time.
  It is **delivered when its last byte would have arrived**: the host's reassembler
  sees a whole frame at the moment a real UART would have completed it, so a host
  timeout measured to the last byte behaves as on hardware; splitting delivery is the
  transport's business (``MemoryPeer`` delivery modes).
* **Unsolicited output** (``model.poll`` when ``next_event_time`` comes due: ``EE DD``,
  "done" replies) starts at the event time (no turnaround: the device is not answering
  anything), serialised on the line the same way, delivered at its last byte.
* **Half duplex.** A device that is transmitting while a request is on the wire does
  not hear it: the request is not passed to that model, the miss is counted in
  ``stats.ignored_while_transmitting`` and the rx log line says ``"half_duplex"``.
  Collisions between the host and a device are not modelled beyond that.

``pacing="prompt"`` models a link that does not pace bytes and a device that answers
at once: a USB-CDC device, a TCP bridge that forwards whole frames, a pty to a fast
peer.  Nothing takes wire time: a request is complete the moment its last byte arrives,
the device answers it with turnaround 0, and its reply is due the moment it is produced.
Unsolicited output is due at its event time.  Replies of several devices are still
serialised in order.  What stays:

* **Half duplex.** A transmission lasts an instant (it is delivered when produced): a
  device misses a request that arrives at the very instant it puts out bytes (the
  check uses closed intervals in this mode, so zero-length ones can meet).  That
  includes a request written in the same chunk right behind one the device answered:
  its reply goes out at that instant.  A host that waits for each reply never meets it.
* **Faults.** All of them apply.  A *late* reply is due ``late_reply_delay_s`` after the
  moment a prompt reply would have been (the end of the request); duplicates follow at
  once; silent windows and disconnects follow the same schedule.

This is the mode that tests a host's matching against replies that come sooner than
the wire time: a host that assumes the wire paces replies fails here.

Faults (``FaultConfig``) apply to the device -> host direction; see ``faults``.
Times are seconds on the driver's clock; ``epoch`` is the origin of the fault schedule.

Actuators set up one by one: ``unplug(i)`` takes model ``i`` off the line (it hears and
says nothing) and ``plug(i, now)`` puts it back, powered up afresh (``power_cycle``: a
baud rate saved to flash becomes its rate).  With ``device_bauds=True`` each model with
a ``baud`` (the LA's own rate, from its baud code) hears only while the host speaks at
that rate (``set_line_rate``, which the driver calls with the host's rate), as a UART
set to another rate reads framing errors; the wire is timed at the host's rate.
"""

from __future__ import annotations

import enum
import heapq
import math
import random
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Direction, Family, format_hex
from motorbus.protocol.reassembler import Discarded, Frame, Reassembler
from motorbus.sim.faults import FAULT_KINDS, FaultConfig, FaultInjector
from motorbus.sim.model import DeviceModel
from motorbus.sim.timing import byte_time, wire_time

__all__ = [
    "PACING_MODES",
    "STUCK_MODEL_RETRY_S",
    "LinkEvent",
    "LogRecord",
    "Pacing",
    "SimBus",
    "SimStats",
    "check_pacing",
]

#: How a simulator times its bytes: emulate the wire ("wire") or not at all ("prompt").
Pacing = Literal["wire", "prompt"]
#: Every pacing mode, in the order tests parametrise them.
PACING_MODES: tuple[Pacing, ...] = ("wire", "prompt")


def check_pacing(pacing: object) -> Pacing:
    """Return ``pacing`` if it is one of ``PACING_MODES``.

    Raises:
        LocalProtocolError: any other value, naming the allowed ones.
    """
    if pacing == "wire":
        return "wire"
    if pacing == "prompt":
        return "prompt"
    raise LocalProtocolError(
        f"pacing={pacing!r} is not allowed: choose 'wire' (emulate the wire time at the "
        "baud) or 'prompt' (no wire time, turnaround 0)",
        field="pacing",
        value=pacing,
    )


#: A log line: {"t": seconds since ``epoch``, "dir", "hex", "family", "fault"}.
LogRecord = dict[str, object]

#: A model whose ``next_event_time`` stays at or before the time it was just polled at
#: (and whose poll returned nothing) is asked again this much later, not in a busy loop.
STUCK_MODEL_RETRY_S = 1e-3
#: Bound on the poll calls of one advance, so a misbehaving model cannot hang a driver.
MAX_POLLS_PER_ADVANCE = 10_000
#: Transmit intervals remembered per model for the half-duplex check; older ones are
#: long over (they are pruned as requests pass anyway), this only bounds memory.
MAX_TRACKED_TRANSMISSIONS = 64


class LinkEvent(enum.Enum):
    """A change of the simulated link, for the driver to act on."""

    DOWN = "down"  # close the pty master / unplug the memory peer
    UP = "up"  # open a new pty / plug the peer back in


@dataclass(slots=True)
class SimStats:
    """Counters of one ``SimBus`` (mutable; read them, do not write them)."""

    #: Request frames cut from the host's bytes.
    requests: int = 0
    #: Frames the models answered requests with (before faults).
    replies: int = 0
    #: Frames the models sent on their own (``poll``).
    unsolicited: int = 0
    #: (request, device) pairs where the device was transmitting and missed the request.
    ignored_while_transmitting: int = 0
    #: Host bytes that formed no request (garbage, bad checksums).
    discarded_bytes: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    #: Bytes either way lost because the link was down.
    lost_while_down: int = 0
    #: Faults injected, by kind (see ``faults.FAULT_KINDS``).
    faults_injected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FAULT_KINDS, 0))


@dataclass(order=True, slots=True)
class _Pending:
    due: float
    seq: int
    data: bytes = field(compare=False)
    family: Family = field(compare=False)
    fault: str | None = field(compare=False)


class SimBus:
    """A simulated bus: device models behind an emulated half-duplex wire.

    Args:
        models: the devices on the bus; requests are routed to models of their family.
        baud: the wire rate in bit/s (the same for every device on the bus).
        faults: faults to inject into the device -> host direction (``None``: none).
        seed: seeds turnaround draws and faults; same seed, same inputs, same bytes out.
        log: called with one dict per frame either way (see the module docstring of
            ``motorbus.sim``); also for discarded host bytes and link changes.
        epoch: time origin (s) of silent windows and the disconnect schedule; drivers
            set it to their clock when they start serving.
        pacing: ``"wire"`` emulates the wire time of every byte at ``baud`` and the
            models' turnarounds; ``"prompt"`` emulates neither (see the module docstring).
        device_bauds: each model with a ``baud`` hears only at that rate (see the module
            docstring).

    Raises:
        LocalProtocolError: ``baud`` is not a positive integer, or ``pacing`` is not
            ``"wire"`` or ``"prompt"``.
    """

    def __init__(
        self,
        models: Sequence[DeviceModel],
        *,
        baud: int,
        faults: FaultConfig | None = None,
        seed: int = 0,
        log: Callable[[LogRecord], None] | None = None,
        epoch: float = 0.0,
        pacing: Pacing = "wire",
        device_bauds: bool = False,
    ) -> None:
        self.models: tuple[DeviceModel, ...] = tuple(models)
        self.baud = baud
        self.device_bauds = bool(device_bauds)
        #: Per model: on the line (``plug``/``unplug``).
        self.connected = [True] * len(self.models)
        self.pacing: Pacing = check_pacing(pacing)
        self._paced = self.pacing == "wire"
        wire_byte_time = byte_time(baud)  # validates the baud in either mode
        self._byte_time = wire_byte_time if self._paced else 0.0
        self.faults = faults if faults is not None else FaultConfig()
        self.seed = seed
        self.epoch = epoch
        self._log = log
        self._rng = random.Random(seed)
        # A separate stream, so that turning faults on does not change turnaround draws.
        self._injector = FaultInjector(self.faults, random.Random(f"motorbus-faults-{seed}"))
        self.stats = SimStats(faults_injected=self._injector.counts)
        self._families = frozenset(m.family for m in self.models)
        self._reassembler = Reassembler(direction=Direction.REQUEST, families=self._families)
        # Host -> device line: when it goes idle, and the chunks still being cut into
        # requests as (global index of first byte, start time, length).
        self._rx_free = -math.inf
        self._rx_chunks: deque[tuple[int, float, int]] = deque()
        self._rx_fed = 0
        self._rx_consumed = 0
        # Device -> host line, and per model its recent transmit intervals (start, end).
        self._tx_free = -math.inf
        self._transmitting: list[deque[tuple[float, float]]] = [deque() for _ in self.models]
        self._pending: list[_Pending] = []
        self._seq = 0
        # Per model: event times at or before this were already polled (see STUCK_...).
        self._polled_to: list[float] = [-math.inf] * len(self.models)
        self._link_up = True
        self._schedule = self.faults.link_schedule()
        self._next_outage: tuple[float, float] | None = next(self._schedule, None)
        self._link_events: list[LinkEvent] = []
        self._ready: list[bytes] = []
        self._caught_up_to = -math.inf

    # -- public API -----------------------------------------------------------------

    @property
    def link_up(self) -> bool:
        """False while a disconnect fault holds the link down."""
        return self._link_up

    def plug(self, index: int, now: float) -> None:
        """Put model ``index`` on the line, powered up afresh (its RAM from flash)."""
        self.models[index].power_cycle(now)
        self.connected[index] = True

    def unplug(self, index: int) -> None:
        """Take model ``index`` off the line: it hears nothing and sends nothing."""
        self.connected[index] = False

    def set_line_rate(self, baud: int) -> None:
        """The host now speaks at ``baud`` (``device_bauds``: who hears, and wire time)."""
        if baud != self.baud:
            self._byte_time = byte_time(baud) if self._paced else 0.0
            self.baud = baud

    def _hears(self, i: int) -> bool:
        if not self.connected[i]:
            return False
        own = getattr(self.models[i], "baud", None) if self.device_bauds else None
        return own is None or own == self.baud

    def receive(self, data: bytes, now: float) -> None:
        """Take ``data`` the host wrote, all of which arrived at ``now`` (s).

        Complete requests are passed to the models of their family (those not busy
        transmitting) at the time their last byte left the emulated wire; replies are
        scheduled for ``due_output``.  Bytes received while the link is down are lost.
        """
        if not data:
            return
        self._catch_up(now)
        self.stats.bytes_in += len(data)
        if not self._link_up:
            self.stats.lost_while_down += len(data)
            return
        start = max(now, self._rx_free)
        self._rx_chunks.append((self._rx_fed, start, len(data)))
        self._rx_fed += len(data)
        self._rx_free = start + len(data) * self._byte_time
        for item in self._reassembler.feed(data):
            size = len(item.raw)
            first = self._rx_consumed
            self._rx_consumed += size
            t_start = self._byte_end(first) - self._byte_time
            t_end = self._byte_end(first + size - 1)
            if type(item) is Frame:
                self._on_request(item, t_start, t_end)
            else:
                # Discarded runs, or an EE DD (a reply marker) that a host has no reason
                # to send: nothing a device would act on.
                self.stats.discarded_bytes += size
                reason = item.reason if type(item) is Discarded else "reply marker"
                self._emit_log(t_end, "rx", item.raw, None, f"discarded: {reason}")
        while self._rx_chunks:
            first, _, length = self._rx_chunks[0]
            if first + length > self._rx_consumed:
                break
            self._rx_chunks.popleft()

    def due_output(self, now: float) -> list[bytes]:
        """Return the chunks due toward the host by ``now`` (s), in wire order.

        Also advances the models (``poll``) and the fault schedule to ``now``.  Write
        these chunks first, then act on ``link_events``: output that was due before a
        disconnect is returned, output that was not is lost with the link.
        """
        self._catch_up(now)
        out, self._ready = self._ready, []
        return out

    def link_events(self, now: float) -> list[LinkEvent]:
        """Return the link changes (disconnect faults) that happened by ``now`` (s).

        Call it after ``due_output`` (see there).
        """
        self._catch_up(now)
        events, self._link_events = self._link_events, []
        return events

    def next_wakeup(self) -> float | None:
        """Return the earliest time (s) at which ``due_output``/``link_events`` has news.

        ``None`` if nothing is scheduled (the driver then waits for host bytes only).
        The value may be in the past: call ``due_output`` at once.
        """
        times: list[float] = []
        if self._pending:
            times.append(self._pending[0].due)
        for i, model in enumerate(self.models):
            t = model.next_event_time()
            if t is not None:
                times.append(self._effective_event_time(i, t))
        if self._ready:
            return self._caught_up_to
        change = self._next_link_change()
        if change < math.inf:
            times.append(change)
        return min(times) if times else None

    # -- requests -------------------------------------------------------------------

    def _byte_end(self, index: int) -> float:
        """When byte ``index`` (global, host -> device) finished on the emulated wire."""
        for first, start, length in self._rx_chunks:
            if index < first + length:
                return start + (index - first + 1) * self._byte_time
        # Not reachable while the reassembler accounts for every byte; be safe anyway.
        return self._rx_free

    def _on_request(self, frame: Frame, t_start: float, t_end: float) -> None:
        self.stats.requests += 1
        self._poll_models(t_end)  # unsolicited output that was due comes first
        hearing: list[int] = []
        missed = 0
        for i, model in enumerate(self.models):
            if model.family is not frame.family or not self._hears(i):
                continue
            if self._is_transmitting(i, t_start, t_end):
                missed += 1
            else:
                hearing.append(i)
        self.stats.ignored_while_transmitting += missed
        self._emit_log(t_end, "rx", frame.raw, frame.family, "half_duplex" if missed else None)
        for i in hearing:
            model = self.models[i]
            replies = model.handle(frame.raw, t_end)
            if replies:
                self.stats.replies += len(replies)
                turnaround = model.turnaround(self._rng) if self._paced else 0.0
                self._send(i, replies, t_end + turnaround)

    def _is_transmitting(self, i: int, start: float, end: float) -> bool:
        intervals = self._transmitting[i]
        if self._paced:
            while intervals and intervals[0][1] <= start:
                intervals.popleft()
            return any(s < end and e > start for s, e in intervals)
        # Prompt: transmissions and requests last an instant; closed intervals meet.
        while intervals and intervals[0][1] < start:
            intervals.popleft()
        return any(s <= end and e >= start for s, e in intervals)

    # -- output ---------------------------------------------------------------------

    def _send(self, i: int, frames: Sequence[bytes], earliest: float) -> None:
        """Put ``frames`` of model ``i`` on the device -> host line from ``earliest``."""
        family = self.models[i].family
        t = earliest
        for frame in frames:
            if not self._link_up:
                self.stats.lost_while_down += len(frame)
                continue
            if self.faults.is_silent(t - self.epoch):
                self.stats.faults_injected["silent"] += 1
                self._emit_log(t, "tx", frame, family, "silent")
                continue
            fate = self._injector.apply(frame) if self.faults.active else None
            data = fate.data if fate is not None else frame
            fault = ",".join(fate.kinds) if fate is not None and fate.kinds else None
            delay = fate.extra_delay_s if fate is not None else 0.0
            copies = fate.copies if fate is not None else 1
            duration = wire_time(len(data), self.baud) if self._paced else 0.0
            late_start = t + delay
            for _ in range(copies):
                if delay:
                    # A late device talks later; it does not hold the line meanwhile.
                    start = late_start
                    late_start += duration
                else:
                    start = max(t, self._tx_free)
                    self._tx_free = t = start + duration
                end = start + duration
                intervals = self._transmitting[i]
                intervals.append((start, end))
                if len(intervals) > MAX_TRACKED_TRANSMISSIONS:
                    intervals.popleft()
                self._seq += 1
                heapq.heappush(self._pending, _Pending(end, self._seq, data, family, fault))

    def _effective_event_time(self, i: int, t: float) -> float:
        floor = self._polled_to[i]
        return t if t > floor else floor + STUCK_MODEL_RETRY_S

    def _poll_models(self, up_to: float) -> None:
        """Run every model's due events up to ``up_to``, in time order across models."""
        for _ in range(MAX_POLLS_PER_ADVANCE):
            best_i = -1
            best_t = math.inf
            for i, model in enumerate(self.models):
                t = model.next_event_time()
                if t is None:
                    continue
                t = self._effective_event_time(i, t)
                if t <= up_to and t < best_t:
                    best_i, best_t = i, t
            if best_i < 0:
                return
            model = self.models[best_i]
            frames = model.poll(best_t)
            self._polled_to[best_i] = best_t
            if frames:
                self.stats.unsolicited += len(frames)
                self._send(best_i, frames, best_t)

    # -- link -----------------------------------------------------------------------

    def _next_link_change(self) -> float:
        if self._next_outage is None:
            return math.inf
        down, up = self._next_outage
        return self.epoch + (down if self._link_up else up)

    def _catch_up(self, now: float) -> None:
        """Advance models, output and link to ``now``, in time order."""
        self._caught_up_to = max(self._caught_up_to, now)
        while True:
            boundary = self._next_link_change()
            step = min(now, boundary)
            self._poll_models(step)
            pending = self._pending
            while pending and pending[0].due <= step:
                item = heapq.heappop(pending)
                if not item.data:
                    continue  # every byte was dropped by the drop fault
                self.stats.bytes_out += len(item.data)
                self._emit_log(item.due, "tx", item.data, item.family, item.fault)
                self._ready.append(item.data)
            if boundary > now:
                return
            if self._link_up:
                self._go_down(boundary)
            else:
                self._link_up = True
                self._link_events.append(LinkEvent.UP)
                self._emit_log(boundary, "link", b"", None, None)
                self._next_outage = next(self._schedule, None)

    def _go_down(self, t: float) -> None:
        self._link_up = False
        self.stats.faults_injected["disconnect"] += 1
        lost = sum(len(p.data) for p in self._pending)
        self.stats.lost_while_down += lost + self._reassembler.buffered
        self._pending.clear()
        # A partial request dies with the link; start the line afresh.
        self._reassembler = Reassembler(direction=Direction.REQUEST, families=self._families)
        self._rx_chunks.clear()
        self._rx_fed = self._rx_consumed = 0
        self._link_events.append(LinkEvent.DOWN)
        self._emit_log(t, "link", b"", None, "disconnect")

    def _emit_log(
        self, t: float, direction: str, raw: bytes, family: Family | None, fault: str | None
    ) -> None:
        if self._log is None:
            return
        self._log(
            {
                "t": t - self.epoch,
                "dir": direction,
                "hex": format_hex(raw),
                "family": family.value if family is not None else None,
                "fault": fault,
            }
        )
