"""Blocking events: a bus's ``events`` without ``await``, local or served alike.

``bus.events.subscribe(Kind)`` starts queueing events of ``Kind`` at once (as the
asyncio one does: subscribe before sending the command whose event you wait for);
``sub.next(timeout=...)`` waits for the next one, ``for event in sub:`` takes them
until the subscription is closed, and ``with`` closes it.  The queue and the
predicate live on the bus's thread; only the waiting happens in yours.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

from motorbus.blocking._proxy import Closing, Proxy
from motorbus.bus import events as _events
from motorbus.bus.events import SUBSCRIPTION_QUEUE_MAX, BusEvent

__all__ = ["EventHub", "Subscription"]

E = TypeVar("E", bound=BusEvent)


class EventHub(Proxy[_events.EventHub]):
    """A bus's events: :class:`motorbus.bus.events.EventHub` without ``await``."""

    def subscribe(
        self,
        kind: type[E],
        predicate: Callable[[E], bool] | None = None,
        *,
        maxsize: int = SUBSCRIPTION_QUEUE_MAX,
    ) -> Subscription[E]:
        """Start queueing events of ``kind`` (and matching ``predicate``, which runs on
        the bus's thread and must return at once) from now on."""
        sub = self._runner.call_sync(lambda: self._aio.subscribe(kind, predicate, maxsize=maxsize))
        return Subscription._of(sub, self._runner)

    def publish(self, event: BusEvent) -> None:
        """Deliver ``event`` to every matching subscription (on the bus's thread)."""
        self._runner.call_sync(self._aio.publish, event)


class Subscription(Closing, Proxy["_events.Subscription[E]"], Generic[E]):
    """A queue of matching events: an iterator and a context manager (``close`` on
    exit).  Made by ``bus.events.subscribe``."""

    @property
    def kind(self) -> type[E]:
        """The kind of event queued."""
        return self._aio.kind

    @property
    def dropped(self) -> int:
        """Events dropped because the queue was full (the oldest go first)."""
        return self._aio.dropped

    @property
    def closed(self) -> bool:
        """True once closed."""
        return self._aio.closed

    def next(self, timeout: float | None = None) -> E:
        """The next event; waits for it up to ``timeout`` seconds (None: no limit).

        Raises:
            ReplyTimeoutError: none came within ``timeout``.
            StopIteration: the subscription is closed and its queue is empty.
        """
        try:
            return self._runner.call(self._aio.next(timeout))
        except StopAsyncIteration:
            raise StopIteration from None

    def queued(self) -> list[E]:
        """The events queued now, left in the queue."""
        return self._runner.call_sync(self._aio.queued)

    def pending(self) -> list[E]:
        """Take every event already queued, without waiting."""
        return self._runner.call_sync(self._aio.pending)

    def close(self) -> None:
        """Stop receiving events; a waiting ``next`` ends the iteration."""
        self._runner.call_sync(self._aio.close)

    def __iter__(self) -> Subscription[E]:
        return self

    def __next__(self) -> E:
        return self.next()
