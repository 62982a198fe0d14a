"""The tapped command a server submits: its raw reply, and a mark taken as that reply came
off the wire (no Zenoh needed: a bus on an in-memory link)."""

from __future__ import annotations

import pytest

from motorbus import Bus, Family
from motorbus.bus.events import FaultChanged, ProjectFinished
from motorbus.protocol import project_stepper as ps
from motorbus.serve.tap import raw_reply, reply_mark, tapped
from motorbus.transport.memory import memory_pair

ACK = bytes.fromhex("ffaa4e010000")  # the controller's acknowledgement of StartProject(1)
EE_DD = b"\xee\xdd"  # and, a short project later, the end of the run


async def test_the_mark_is_taken_as_the_reply_comes_off_the_wire() -> None:
    # The acknowledgement and the EE DD arrive in one read (a server starved of its CPU
    # for the project's length): the EE DD is after the reply on the wire, and the
    # bus has published it before the request's awaiter runs again.  The mark (what a
    # served reply says came before it) must not count it: the client would take it
    # for a stale EE DD and wait for another.
    host, peer = memory_pair(delivery="whole")
    start = ps.StartProject(1)
    peer.set_receiver(lambda data: peer.send(ACK + EE_DD) if data == start.encode() else None)
    async with Bus(host, families=[Family.PROJECT_STEPPER]) as bus:
        with bus.events.subscribe(ProjectFinished) as finished:
            sent = tapped(start, marker=lambda: len(finished.queued()))
            assert sent == start and isinstance(sent, ps.StartProject)  # the same command
            await bus.request(sent)
            assert raw_reply(sent) == ACK
            assert reply_mark(sent) == 0  # taken before the EE DD behind it
            assert len(finished.queued()) == 1  # which the bus published meanwhile
    assert reply_mark(tapped(start)) is None  # no marker, no mark


async def test_a_replys_own_fault_event_comes_before_it_on_a_served_bus_as_on_a_local_one() -> None:
    # The bus publishes a fault change as it takes the status that shows it, before the
    # caller has the status: a served reply counts that event as before it too, so the
    # client has it queued when the status returns (a later one would come after).
    pytest.importorskip("zenoh")
    import motorbus
    from motorbus import InspireLA
    from motorbus.bus.timer import default_timer
    from motorbus.serve import BusServer
    from motorbus.sim.la import LAModel
    from motorbus.sim.memory import MemorySim
    from tests.serve.conftest import free_endpoint

    endpoint = free_endpoint()
    model, timer = LAModel(1), default_timer()
    async with MemorySim.start([model], baud=921600, timer=timer) as sim:
        bus = Bus(sim.transport, name="arm", host_margin=0.05, reconnect=False)
        async with (
            bus,
            BusServer({"arm": bus}, listen=endpoint),
            motorbus.connect(endpoint) as site,
        ):
            served = site.bus()
            actuator = InspireLA(served, 1)
            assert not (await actuator.status()).errors
            model.trigger_fault("stall", timer.now())
            with served.events.subscribe(FaultChanged) as faults:
                status = await actuator.status()
                assert status.errors
                (event,) = faults.pending()  # here when the status returned
                assert event.id == 1 and event.after == int(status.errors)
