"""The rig's eyes: every status reply and every target the bus wrote, with the bus's times.

A :class:`Sampler` is a bus observer (``Bus.add_observer``): it sees each status reply
with the time its bytes were read (not when a coroutine resumed) and each target frame
with the time its write completed.  It also polls: one status query at a time, round
robin over the actuators under test, as fast as the bus's spacing allows, at background
priority (so stream ticks and commands go first).  A reply over the current or force
ceiling trips it: it pauses every actuator under test at once, from the callback, and
the test in progress ends with :class:`RigAborted`.
"""

from __future__ import annotations

import asyncio
import bisect
from collections.abc import Sequence
from typing import Any

from motorbus.bus.bus import Bus, Priority
from motorbus.errors import MotorbusError, ReplyTimeoutError, RigAborted
from motorbus.protocol import la
from motorbus.protocol.base import Command
from motorbus.rig.analysis import Sample

__all__ = ["RigAborted", "Sampler"]

#: Faults that stop the motor (motor-abnormal is only a notice, manual 3.8).
_STOPPING_FAULTS = la.ErrorFlags.STALL | la.ErrorFlags.OVER_TEMPERATURE | la.ErrorFlags.OVER_CURRENT


class Sampler:
    """Status samples and written targets of the actuators under test (see module)."""

    def __init__(
        self, bus: Bus, ids: Sequence[int], *, max_current_ma: int, max_force_g: int
    ) -> None:
        self.bus = bus
        self.ids = tuple(ids)
        self.max_current_ma = max_current_ma
        self.max_force_g = max_force_g
        self.samples: dict[int, list[Sample]] = {i: [] for i in self.ids}
        #: (written_at, target) per actuator, for every target frame the bus wrote.
        self.targets: dict[int, list[tuple[float, int]]] = {i: [] for i in self.ids}
        self.tripped: str | None = None
        #: The stream the running test drives, if any (stopped at once on a trip).
        self.stream: Any = None
        self.polls = 0
        self.poll_timeouts = 0
        self._poll_ids: tuple[int, ...] = ()
        self._task: asyncio.Task[None] | None = None
        self._pausing: asyncio.Task[list[object]] | None = None

    # -- BusObserver ------------------------------------------------------------

    def on_write(self, cmd: Command[object], at: float) -> None:
        if isinstance(cmd, la.MoveTo | la.Follow) and cmd.id in self.targets:
            self.targets[cmd.id].append((at, cmd.position))
        elif isinstance(cmd, la.Broadcast):
            for ident, position in cmd.entries:
                if ident in self.targets:
                    self.targets[ident].append((at, position))

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None:
        if not isinstance(value, la.Status) or value.id not in self.samples:
            return
        self.samples[value.id].append(
            Sample(replied_at, float(value.position), float(value.current), float(value.force))
        )
        if self.tripped is None:
            if value.current > self.max_current_ma:
                self._trip(
                    f"la:{value.id} drew {value.current} mA (ceiling {self.max_current_ma} mA)"
                )
            elif abs(value.force) > self.max_force_g:
                self._trip(f"la:{value.id} felt {value.force} g (ceiling {self.max_force_g} g)")
            elif value.errors & _STOPPING_FAULTS:
                self._trip(f"la:{value.id} reported a fault: {value.errors!r}")

    def _trip(self, why: str) -> None:
        self.tripped = why
        if self.stream is not None:
            # No follow target may come after the pause (one would power the LA again).
            self.stream.stopping = True
        # Pause now, ahead of everything queued: the bus's lease table sends it.
        keys = [f"la:{ident}" for ident in self.ids]
        self._pausing = self.bus.lease_keeper.stop_soon(keys, "pause", who="rig: tripped")
        self._pausing.add_done_callback(_ignore_result)

    def check(self) -> None:
        """Raise :class:`RigAborted` if a ceiling tripped."""
        if self.tripped is not None:
            raise RigAborted(f"rig aborted: {self.tripped}; every actuator under test is paused")

    # -- polling --------------------------------------------------------------

    def __enter__(self) -> Sampler:
        self.bus.add_observer(self)
        self._task = asyncio.get_running_loop().create_task(self._poll_loop())
        return self

    def __exit__(self, *exc: object) -> None:
        self.bus.remove_observer(self)
        if self._task is not None:
            self._task.cancel()

    def poll(self, ids: Sequence[int]) -> None:
        """Poll these actuators (round robin) from now on; ``()`` stops polling."""
        self._poll_ids = tuple(ids)

    async def _poll_loop(self) -> None:
        k = 0
        while True:
            ids = self._poll_ids
            if not ids or self.tripped is not None:
                await self._nap(0.002)
                continue
            ident = ids[k % len(ids)]
            k += 1
            self.polls += 1
            try:
                await self.bus.request(
                    la.Control(ident, la.ControlAction.QUERY_STATUS),
                    priority=Priority.BACKGROUND,
                    retries=0,
                )
            except ReplyTimeoutError:
                self.poll_timeouts += 1
            except MotorbusError:
                # The port is lost (or closing): wait, then poll again when it is back.
                self.poll_timeouts += 1
                await asyncio.sleep(0.05)

    async def _nap(self, seconds: float) -> None:
        timer = self.bus.timer
        await timer.sleep_until(timer.now() + seconds)

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` on the bus's clock, or raise :class:`RigAborted` within
        10 ms of a ceiling tripping."""
        timer = self.bus.timer
        end = timer.now() + seconds
        while True:
            self.check()
            now = timer.now()
            if now >= end:
                return
            await timer.sleep_until(min(end, now + 0.01))

    def since(self, ident: int, t: float) -> list[Sample]:
        """The samples of ``ident`` whose replies arrived at or after ``t``.

        Found by bisection: the samples are in arrival order (the bus takes replies one
        at a time, on a monotonic clock), and the settle loop asks every 10 ms, so a
        scan of the whole run grew with its length."""
        samples = self.samples[ident]
        return samples[bisect.bisect_left(samples, t, key=_arrival) :]

    def last_write(self, ident: int) -> float:
        """When the last target frame to ``ident`` was written."""
        return self.targets[ident][-1][0]


def _arrival(sample: Sample) -> float:
    return sample.t


def _ignore_result(fut: asyncio.Future[Any]) -> None:
    if not fut.cancelled():
        fut.exception()
