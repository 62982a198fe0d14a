"""``motorbus rig --connect``: the rig as a lease holder on a served bus.

The actuators under test are leased to the rig (owner ``motorbus rig``) before anything
moves: a device another client holds refuses the run with ``LeaseConflictError`` naming
the holder (exit 1), and nothing is sent.  The lease ends with its safe action (pause)
when the run ends, however it ends (the server's deadman covers a killed rig).

The rig watches replies through ``Bus.add_observer``; a served bus is watched here, at
the client: each request's write and reply times are this client's, so the rig's
figures include the round trip to the server (docs/serve.md, Measured).  The tracking
test streams, and streams are not served by this version: ``--tests all`` runs the
others on a served bus and says so.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, cast

from motorbus import Bus, Priority
from motorbus.errors import UsageError
from motorbus.protocol.base import Command

__all__ = ["RIG_OWNER", "ObservedServedBus", "held", "run_served_rig", "served_tests"]

#: The owner of the rig's lease, as other clients see it.
RIG_OWNER = "motorbus rig"
#: The tests that stream (not on a served bus yet).
STREAMING_TESTS = ("track",)
_SERVED_PRIORITIES = (Priority.NORMAL, Priority.HIGH, Priority.EMERGENCY)


def served_tests(tests: tuple[str, ...], asked: str) -> tuple[str, ...]:
    """The tests a served rig runs: ``all`` less the streaming ones (said on standard
    error); a streaming test asked by name is refused (exit 2, nothing sent)."""
    streaming = [t for t in tests if t in STREAMING_TESTS]
    if not streaming:
        return tests
    if asked.strip() != "all":
        raise UsageError(
            f"--tests {','.join(streaming)} streams on the bus: not on a served bus "
            "(--connect) yet; choose among step, latency, repeat"
        )
    print(
        f"motorbus rig: --connect: {', '.join(streaming)} not run (it streams; streams are "
        "not served yet)",
        file=sys.stderr,
    )
    return tuple(t for t in tests if t not in STREAMING_TESTS)


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
