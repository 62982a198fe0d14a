"""A served bus's events, put back in the server's order against the replies (client side).

An event publication and a query reply travel apart, so an event can reach the client
before the reply of the request that came before it on the wire, or after the reply
of a later one.  The server numbers each bus's events (``seq``: 1, 2, ...) and says in
every reply how many came before it (``events``; docs/serve.md).  :class:`EventOrder`
uses both: while a request is in flight its events are held; once its reply has come,
the client waits (briefly) for the events the reply counts, publishes those before its
caller resumes, and the later ones a few loop turns after, once the request's task
has ended: ``run_project`` takes an ``EE DD`` published before its start's reply is
done for one from before the start, and must never take its own run's for one.  Runs
on the client's event loop; no Zenoh here.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable

from motorbus.bus.events import BusEvent

__all__ = ["EVENT_CATCH_UP_S", "EventOrder"]

#: Longest a reply waits for the events the server published before it (s).
EVENT_CATCH_UP_S = 0.5


class EventOrder:
    """Holds and releases one served bus's events around its requests.

    Args:
        publish: publishes one event to the bus's subscribers (``EventHub.publish``).
    """

    def __init__(self, publish: Callable[[BusEvent], None]) -> None:
        self._publish = publish
        self._seen = 0  # the highest seq delivered
        self._held: list[tuple[int, BusEvent]] = []
        self._in_flight = 0
        self._seen_more: asyncio.Event | None = None

    def deliver(self, seq: int | None, event: BusEvent) -> None:
        """An event publication arrived (on the loop); ``seq`` None: a server that
        numbers no events, published as it comes."""
        if seq is None:
            self._publish(event)
            return
        self._seen = max(self._seen, seq)
        if self._seen_more is not None:
            self._seen_more.set()
        if self._in_flight:
            self._held.append((seq, event))
        else:
            self._publish_held(None)
            self._publish(event)

    def begin(self) -> None:
        """A request is sent: its events are held until it ends."""
        self._in_flight += 1

    async def end(self, before: int | None) -> None:
        """The request's reply came, counting ``before`` events before it (None: not
        counted).  Still in flight while it waits for those, so an event after the
        reply that comes meanwhile is held too, not published as if before it."""
        try:
            if before is not None:
                await self._catch_up(before)
        except BaseException:
            self.fail()
            raise
        self._in_flight -= 1
        self._publish_held(before)

    def fail(self) -> None:
        """The request failed: what it held goes out, in order, all the same."""
        self._in_flight -= 1
        self._release_soon()

    async def _catch_up(self, before: int) -> None:
        deadline = time.monotonic() + EVENT_CATCH_UP_S
        while self._seen < before and (left := deadline - time.monotonic()) > 0:
            self._seen_more = asyncio.Event()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(left):
                    await self._seen_more.wait()
        self._seen_more = None

    def _publish_held(self, before: int | None) -> None:
        """Publish the held events up to ``before`` now, the rest a few turns later."""
        if not self._held:
            return
        self._held.sort(key=lambda item: item[0])
        now = [e for seq, e in self._held if before is None or seq <= before]
        self._held = [(seq, e) for seq, e in self._held if before is not None and seq > before]
        for event in now:
            self._publish(event)
        self._release_soon()

    def _release_soon(self) -> None:
        """Publish the held events three loop turns from now if no request is in flight
        then: the request's task ends, its awaiting caller runs on (one more for a
        caller that wraps it in a task of its own)."""
        if self._held and not self._in_flight:
            loop = asyncio.get_running_loop()
            loop.call_soon(loop.call_soon, loop.call_soon, self._release_held)

    def _release_held(self) -> None:
        if not self._in_flight:
            self._publish_held(None)
