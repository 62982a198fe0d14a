"""``motorbus rig --connect``: the rig as a lease holder on a served bus.

The actuators under test are leased to the rig (owner ``motorbus rig``) before anything
moves: a device another client holds refuses the run with ``LeaseConflictError`` naming
the holder (exit 1), and nothing is sent.  The lease ends with its safe action (pause)
when the run ends, however it ends (the server's deadman covers a killed rig).

The rig watches replies through ``Bus.add_observer``; a served bus is watched here, at
the client: each request's write and reply times are this client's, so the rig's
figures include the round trip to the server (docs/serve.md, Measured).

The tracking test streams through the server (``ServedBus.served_streamer``: the
server ticks), under the rig's lease: the sine goes ahead as a sequence, ``RIG_LEAD_S``
ahead of its ticks.  Its targets are written by the server, out of this client's
sight: the rig takes row ``k`` as written at tick ``k``, ``stream.origin + k * period``
on this client's clock, the clock its status samples are stamped on; both are late by
the way from the server to here, so the amplitude ratio, the phase and the lag compare
like with like (docs/rig.md, On a served bus).  The rows the server says it never wrote
are left out; a gap, or more than a few unwritten, runs the frequency again.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, cast

from motorbus import Bus, Priority
from motorbus.protocol.base import Command

__all__ = ["RIG_LEAD_S", "RIG_OWNER", "ObservedServedBus", "held", "run_served_rig"]

#: The owner of the rig's lease, as other clients see it.
RIG_OWNER = "motorbus rig"
#: How far ahead of its ticks the tracking sine goes to the server (seconds): the rig
#: knows it all, and a row that comes after its tick fails the test.
RIG_LEAD_S = 0.5
_SERVED_PRIORITIES = (Priority.NORMAL, Priority.HIGH, Priority.EMERGENCY)


class ObservedServedBus:
    """A ``ServedBus`` with ``add_observer``: the observers are told at this client, with
    its timer's clock (``on_write`` as the request leaves, ``on_reply`` as its reply
    comes back).  Priorities the server does not take (``BACKGROUND``) go as ``NORMAL``.
    Everything else is the served bus's."""

    def __init__(self, bus: Any) -> None:
        self._bus = bus
        self._observers: list[Any] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._bus, name)

    def served_streamer(self, *, phase: float = 0.0, lead: float | None = None) -> Any:
        """``Streamer(bus)``: the served bus's, its targets ``RIG_LEAD_S`` ahead (or
        ``lead``, if given)."""
        return self._bus.served_streamer(phase=phase, lead=RIG_LEAD_S if lead is None else lead)

    def add_observer(self, observer: Any) -> None:
        if observer not in self._observers:
            self._observers.append(observer)

    def remove_observer(self, observer: Any) -> None:
        if observer in self._observers:
            self._observers.remove(observer)

    def submit(
        self,
        cmd: Command[Any],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
        **options: Any,
    ) -> asyncio.Future[Any]:
        if priority not in _SERVED_PRIORITIES:
            priority = Priority.NORMAL
        timer = self._bus.timer
        future: asyncio.Future[Any] = self._bus.submit(
            cmd, timeout=timeout, retries=retries, priority=priority, **options
        )
        written = timer.now()
        for observer in list(self._observers):
            observer.on_write(cmd, written)

        def replied(done: asyncio.Future[Any]) -> None:
            if done.cancelled() or done.exception() is not None:
                return
            now = timer.now()
            for observer in list(self._observers):
                observer.on_reply(cmd, done.result(), written, now)

        future.add_done_callback(replied)
        return future

    async def request(
        self,
        cmd: Command[Any],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> Any:
        future = self.submit(cmd, timeout=timeout, retries=retries, priority=priority)
        try:
            return await future
        except asyncio.CancelledError:
            future.cancel()
            raise


@contextlib.asynccontextmanager
async def held(bus: Any, keys: list[str]) -> AsyncIterator[Any]:
    """The rig's lease of ``keys`` on the served ``bus`` (bound to this task and the
    tasks it starts), ended with its safe action (pause) on the way out.

    Raises:
        LeaseConflictError: another client holds one of them (names it); nothing sent.
    """
    lease = bus.lease(keys, owner=RIG_OWNER, safe_action="pause")
    try:
        yield lease
    finally:
        await lease.release(hold=False)


async def run_served_rig(
    bus: Any, plan: Any, progress: Any, run_rig: Callable[..., Awaitable[Any]]
) -> tuple[Any, dict[str, Any]]:
    """Run ``plan`` (a ``RigPlan``) with ``run_rig`` (``motorbus.rig.run_rig``) on the
    served ``bus`` holding the lease of its actuators; return the ``RigResult`` and the
    server bus's counters.

    Raises:
        LeaseConflictError: another client holds one of the actuators (names it);
            nothing was sent.
    """
    async with held(bus, [f"la:{i}" for i in plan.ids]):
        result = await run_rig(
            cast(Bus, ObservedServedBus(bus)), plan, progress, raise_on_abort=False
        )
    stats: dict[str, Any] = await bus.fetch_stats()
    return result, stats
