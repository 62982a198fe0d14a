"""Device events and the hub that delivers them to awaiters and subscriptions.

A subscription is registered *before* the command that triggers its event, so an
event that arrives at once is never missed::

    async with bus.events.subscribe(ProjectFinished) as sub:
        await bus.request(StartProject(1))
        event = await sub.next(timeout=30)
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Generic, TypeVar

from motorbus.errors import ReplyTimeoutError
from motorbus.protocol.base import check_timeout

__all__ = [
    "BusEvent",
    "BusStateChanged",
    "EventHub",
    "FaultChanged",
    "ProjectFinished",
    "QuadDone",
    "Subscription",
]

log = logging.getLogger("motorbus.events")

#: Events kept for a subscriber that does not read them; beyond, the oldest are dropped
#: and counted in ``Subscription.dropped`` (never silently).
SUBSCRIPTION_QUEUE_MAX = 1000


@dataclass(frozen=True, slots=True)
class BusEvent:
    """Base of every event: which bus, and when (monotonic seconds)."""

    bus: str
    time: float


@dataclass(frozen=True, slots=True)
class ProjectFinished(BusEvent):
    """The project stepper sent ``EE DD``: its running project has finished (doc 000, 0x4E)."""


@dataclass(frozen=True, slots=True)
class QuadDone(BusEvent):
    """A quad stepper "done" reply: a run (``kind="run"``) or LED (``"led"``) command finished.

    ``address`` is the reply's b2 (0 for a single-motor run, A1-02), ``led`` the LED
    number for LED commands.
    """

    kind: str
    address: int
    led: int | None
    raw: bytes


@dataclass(frozen=True, slots=True)
class FaultChanged(BusEvent):
    """An LA actuator's error flags changed between two status replies."""

    id: int
    before: int
    after: int
    status: Any


@dataclass(frozen=True, slots=True)
class BusStateChanged(BusEvent):
    """The bus opened, lost its port, is reconnecting, reconnected, or closed."""

    state: str
    detail: str = ""


E = TypeVar("E", bound=BusEvent)


class Subscription(Generic[E]):
    """A queue of matching events: an async iterator, and a (sync or async) context manager.

    It starts queueing when created, so create it before sending the command whose
    event it waits for.
    """

    def __init__(
        self,
        hub: EventHub,
        kind: type[E],
        predicate: Callable[[E], bool] | None,
        maxsize: int,
    ) -> None:
        self._hub = hub
        self.kind = kind
        self.predicate = predicate
        self._queue: collections.deque[E] = collections.deque()
        self._maxsize = maxsize
        self._waiter: asyncio.Future[None] | None = None
        self.dropped = 0
        self.closed = False

    def _offer(self, event: BusEvent) -> None:
        if not isinstance(event, self.kind):
            return
        if self.predicate is not None and not self.predicate(event):
            return
        if len(self._queue) >= self._maxsize:
            self._queue.popleft()
            self.dropped += 1
            log.warning("subscription to %s dropped an event (queue full)", self.kind.__name__)
        self._queue.append(event)
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    async def next(self, timeout: float | None = None) -> E:
        """The next event; raises ``ReplyTimeoutError`` if none comes within ``timeout`` s
        (``LocalProtocolError`` for a timeout that is no number of seconds >= 0)."""
        if timeout is not None:
            check_timeout("timeout", timeout)
        while not self._queue:
            if self.closed:
                raise StopAsyncIteration
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                # asyncio.timeout, not wait_for: on Python 3.11, wait_for loses a
                # cancellation that lands in the same loop turn as close() (the task then
                # ended with an unretrieved StopAsyncIteration instead of being cancelled).
                async with asyncio.timeout(timeout):
                    await self._waiter
            except TimeoutError:
                raise ReplyTimeoutError(
                    f"no {self.kind.__name__} event within {timeout:.3f} s"
                ) from None
            finally:
                self._waiter = None
        return self._queue.popleft()

    def queued(self) -> list[E]:
        """The events queued now, left in the queue."""
        return list(self._queue)

    def pending(self) -> list[E]:
        """Take every event already queued, without waiting."""
        out = list(self._queue)
        self._queue.clear()
        return out

    def close(self) -> None:
        """Stop receiving events; a waiting ``next`` ends the iteration."""
        self.closed = True
        self._hub._remove(self)
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def __aiter__(self) -> Subscription[E]:
        return self

    async def __anext__(self) -> E:
        return await self.next()

    def __enter__(self) -> Subscription[E]:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    async def __aenter__(self) -> Subscription[E]:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class EventHub:
    """Fans events out to subscriptions."""

    def __init__(self) -> None:
        self._subs: list[Subscription[Any]] = []
        self.published = 0

    def publish(self, event: BusEvent) -> None:
        """Deliver ``event`` to every subscription whose kind and predicate match."""
        self.published += 1
        for sub in list(self._subs):
            sub._offer(event)

    def subscribe(
        self,
        kind: type[E],
        predicate: Callable[[E], bool] | None = None,
        *,
        maxsize: int = SUBSCRIPTION_QUEUE_MAX,
    ) -> Subscription[E]:
        """Start queueing events of ``kind`` (and matching ``predicate``) from now on."""
        sub: Subscription[E] = Subscription(self, kind, predicate, maxsize)
        self._subs.append(sub)
        return sub

    def _remove(self, sub: Subscription[Any]) -> None:
        if sub in self._subs:
            self._subs.remove(sub)
