"""``MemorySim``: serve a ``SimBus`` over an in-memory link, on the asyncio loop.

The host side is a ``MemoryTransport`` (hand it to the bus under test); the device side
is its ``MemoryPeer``.  Each chunk the host writes goes to ``SimBus.receive`` with the
current time; output is written when ``SimBus.next_wakeup`` comes due.

Timer precision: by default wake-ups go through ``loop.call_later``, which the default
event loop rounds UP to a whole millisecond (docs/platform.md section 1), so replies arrive
up to ~1 ms later than the emulated wire says (never earlier).  Pass ``timer=`` an
object with ``now()`` and ``call_at(deadline, callback) -> handle`` (``handle.cancel()``)
- ``motorbus.bus.timer.default_timer()`` has exactly that API and holds ~0.1 ms - for
wire-accurate timing.

Pacing: ``pacing="wire"`` (default) delivers each reply when its last byte would have
arrived at the baud; ``pacing="prompt"`` delivers it the moment the request is complete
(turnaround 0, no wire time), like a USB-CDC device or a TCP bridge: in that mode a
reply is written from inside the host's write delivery, with no timer in between, and
only late faults and unsolicited output wait for a timer.  See ``motorbus.sim.bus``.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Protocol

from motorbus.sim.bus import LinkEvent, LogRecord, Pacing, SimBus
from motorbus.sim.faults import FaultConfig
from motorbus.sim.model import DeviceModel
from motorbus.sim.spec import default_baud
from motorbus.transport.memory import Delivery, MemoryPeer, MemoryTransport, memory_pair

__all__ = ["CancelHandle", "MemorySim", "SimTimer"]


class CancelHandle(Protocol):
    """A scheduled call that can be cancelled."""

    def cancel(self) -> None:
        """Cancel the call if it has not run yet."""


class SimTimer(Protocol):
    """A clock with absolute-deadline callbacks (``motorbus.bus.timer.Timer`` fits)."""

    def now(self) -> float:
        """Return the current time in seconds (``time.monotonic`` clock)."""

    def call_at(self, deadline: float, callback: Callable[[], None]) -> CancelHandle:
        """Call ``callback`` at ``deadline`` (s, same clock as ``now``), not before."""


class _LoopTimer:
    """Fallback timer on ``loop.call_later`` (rounds up to 1 ms on the default loop)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    def now(self) -> float:
        return time.monotonic()

    def call_at(self, deadline: float, callback: Callable[[], None]) -> CancelHandle:
        # call_later with a delta: the loop's own clock need not be time.monotonic().
        return self._loop.call_later(max(0.0, deadline - time.monotonic()), callback)


class MemorySim:
    """Drives a ``SimBus`` from a ``MemoryPeer`` on the running event loop.

    Args:
        bus: the simulation core.
        peer: the device side of an in-memory link.
        transport: the host side of that link, kept for ``sim.transport`` (optional).
        timer: the clock and timer to use (see the module docstring); default: the loop.

    Use ``MemorySim.start(...)`` for the common case.  Disconnect faults unplug the
    peer (the host's transport reports the loss) and plug it back when they end.
    """

    def __init__(
        self,
        bus: SimBus,
        peer: MemoryPeer,
        *,
        transport: MemoryTransport | None = None,
        timer: SimTimer | None = None,
    ) -> None:
        self.bus = bus
        self.peer = peer
        self._transport = transport
        self._timer = timer
        self._handle: CancelHandle | None = None
        self._wakeup: float | None = None
        self._serving = False

    @property
    def transport(self) -> MemoryTransport:
        """The host-side transport to hand to the bus under test."""
        return self._transport if self._transport is not None else self.peer.host

    @property
    def models(self) -> tuple[DeviceModel, ...]:
        """The simulated devices, for inspection."""
        return self.bus.models

    def serve(self) -> None:
        """Start serving: take host bytes, send due output.  Must run inside the loop."""
        if self._serving:
            return
        if self._timer is None:
            self._timer = _LoopTimer(asyncio.get_running_loop())
        self._serving = True
        self.bus.epoch = self._timer.now()
        self.peer.set_receiver(self._on_chunk)
        self._pump()

    def stop(self) -> None:
        """Stop serving; pending output is not sent.  Idempotent."""
        self._serving = False
        self.peer.set_receiver(_ignore)
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
            self._wakeup = None

    @classmethod
    @contextlib.asynccontextmanager
    async def start(
        cls,
        models: Sequence[DeviceModel],
        *,
        baud: int | None = None,
        delivery: Delivery = "whole",
        faults: FaultConfig | None = None,
        seed: int = 0,
        timer: SimTimer | None = None,
        log: Callable[[LogRecord], None] | None = None,
        pacing: Pacing = "wire",
    ) -> AsyncIterator[MemorySim]:
        """Serve ``models`` on a new in-memory link for the duration of the block.

        Args:
            models: the simulated devices.
            baud: wire rate in bit/s; default 921600 for LA-only buses, else 9600.
            delivery: how device -> host bytes are cut ("whole", "bytewise", "random").
            faults: faults to inject (``None``: none).
            seed: seeds the simulator and the "random" delivery cuts.
            timer: high-resolution timer (see the module docstring).
            log: per-frame log callback (see ``SimBus``).
            pacing: ``"wire"`` emulates wire time and turnarounds at ``baud``; ``"prompt"``
                answers the moment a request is complete (see the module docstring).

        Raises:
            LocalProtocolError: ``pacing`` or ``baud`` is not allowed (before serving).

        Yields:
            The serving ``MemorySim``: ``sim.transport``, ``sim.bus``, ``sim.models``.
        """
        rate = baud if baud is not None else default_baud(models)
        bus = SimBus(models, baud=rate, faults=faults, seed=seed, log=log, pacing=pacing)
        host, peer = memory_pair(delivery=delivery, seed=seed, baudrate=rate)
        sim = cls(bus, peer, transport=host, timer=timer)
        sim.serve()
        try:
            yield sim
        finally:
            sim.stop()

    # -- internals --------------------------------------------------------------------

    def _on_chunk(self, data: bytes) -> None:
        if not self._serving or self._timer is None:
            return
        self.bus.receive(data, self._timer.now())
        self._pump()

    def _pump(self) -> None:
        if not self._serving or self._timer is None:
            return
        now = self._timer.now()
        for chunk in self.bus.due_output(now):
            self.peer.send(chunk)
        for event in self.bus.link_events(now):
            if event is LinkEvent.DOWN:
                self.peer.unplug()
            else:
                self.peer.plug()
        self._arm()

    def _on_timer(self) -> None:
        self._handle = None
        self._wakeup = None
        self._pump()

    def _arm(self) -> None:
        timer = self._timer
        if timer is None:
            return
        wakeup = self.bus.next_wakeup()
        if wakeup == self._wakeup and self._handle is not None:
            return
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self._wakeup = wakeup
        if wakeup is not None:
            self._handle = timer.call_at(wakeup, self._on_timer)


def _ignore(data: bytes) -> None:
    """Receiver installed after ``stop``: the simulator no longer listens."""
