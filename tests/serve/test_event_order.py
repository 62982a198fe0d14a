"""Events and replies of a served bus travel apart (a Zenoh publication and a query
reply), so an event can reach the client before the reply of the request that came
before it.  The client puts them back in the server's order: ``run_project`` must see
the EE DD of its own run (after the start's reply), never take it as stale.

No Zenoh here: a fake site answers the queries, and the events arrive in the order a
loaded machine can deliver them.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from motorbus.bus.events import ProjectFinished
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.protocol import project_stepper as ps
from motorbus.serve.client import ServedBus

PROJECT = {"families": ["project_stepper"], "baud": 9600}


class FakeSite:
    """Answers each request with the reply and the count of events before it; calls
    ``before_reply`` first (where a test delivers events that overtake the reply)."""

    endpoint = "fake"
    state = "open"

    def __init__(self) -> None:
        self.before_reply: list[Any] = []
        self.events_before = 0
        self.frames: list[str] = []

    def _check_open(self, bus: str) -> None:
        pass

    async def _query(
        self, key: str, body: dict[str, Any], timeout: float, *, urgent: bool = False
    ) -> dict[str, Any]:
        self.frames.append(body["frame"])
        for deliver in self.before_reply:
            deliver()
        self.before_reply.clear()
        return {"reply": None, "events": self.events_before}


def finished(seq: int) -> tuple[int, ProjectFinished]:
    return seq, ProjectFinished("b", 0.0)


async def test_an_event_that_overtakes_its_requests_reply_still_ends_the_run() -> None:
    site = FakeSite()
    bus = ServedBus(site, "b", PROJECT)  # type: ignore[arg-type]
    stepper = ProjectStepper(bus)  # type: ignore[arg-type]
    # The start's reply says no event came before it; its run's EE DD (event 1) arrives
    # first.
    site.events_before = 0
    site.before_reply.append(lambda: bus._order.deliver(*finished(1)))
    await asyncio.wait_for(stepper.run_project(1, timeout=2), 5)


async def test_an_event_from_before_the_reply_is_stale_even_when_it_arrives_late() -> None:
    site = FakeSite()
    bus = ServedBus(site, "b", PROJECT)  # type: ignore[arg-type]
    with bus.events.subscribe(ProjectFinished) as sub:
        # The reply says one event came before it; that event arrives after the reply.
        site.events_before = 1
        loop = asyncio.get_running_loop()
        loop.call_later(0.05, bus._order.deliver, *finished(1))
        await bus.request(ps.StartProject(1))
        # Published before request returned: a caller taking pending() as stale does.
        assert len(sub.pending()) == 1


async def test_events_with_no_request_in_flight_are_published_at_once() -> None:
    bus = ServedBus(FakeSite(), "b", PROJECT)  # type: ignore[arg-type]
    with bus.events.subscribe(ProjectFinished) as sub:
        bus._order.deliver(*finished(1))
        assert len(sub.pending()) == 1


async def test_an_event_after_the_reply_that_comes_while_the_client_catches_up_is_not_stale() -> (
    None
):
    """The start's reply counts one event before it; that event and the run's own EE DD
    (event 2) come together, after the reply, while the client waits for the first.  The
    second belongs after the reply: it must end the run, not be taken as stale (a loaded
    run with eight workers lost it and timed out after 10 s)."""
    site = FakeSite()
    bus = ServedBus(site, "b", PROJECT)  # type: ignore[arg-type]
    stepper = ProjectStepper(bus)  # type: ignore[arg-type]
    site.events_before = 1
    loop = asyncio.get_running_loop()

    def both() -> None:
        bus._order.deliver(*finished(1))
        bus._order.deliver(*finished(2))

    site.before_reply.append(lambda: loop.call_later(0.05, both))
    await asyncio.wait_for(stepper.run_project(1, timeout=2), 5)


class FailingSite(FakeSite):
    """Delivers the events of ``before_reply``, then fails the request."""

    async def _query(
        self, key: str, body: dict[str, Any], timeout: float, *, urgent: bool = False
    ) -> dict[str, Any]:
        await super()._query(key, body, timeout, urgent=urgent)
        raise ConnectionError("the server went away")


async def test_an_event_held_by_a_request_that_fails_is_still_published() -> None:
    site = FailingSite()
    bus = ServedBus(site, "b", PROJECT)  # type: ignore[arg-type]
    with bus.events.subscribe(ProjectFinished) as sub:
        site.before_reply.append(lambda: bus._order.deliver(*finished(1)))
        with pytest.raises(ConnectionError):
            await bus.request(ps.StartProject(1))
        event = await asyncio.wait_for(sub.next(1), 2)
        assert isinstance(event, ProjectFinished)
