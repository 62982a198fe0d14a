"""``Bus.prepare``: a submission checked and built ahead of its deadline, sent later.

What is checked ahead must still hold when it is sent: a lease that changed in between
is checked again, a bus that closed refuses it, and the frame's ``refresh`` still
decides at the moment of the write; nothing is written before ``send()``, and a
prepared submission is sent once.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

from motorbus.bus.bus import Bus, Priority
from motorbus.errors import (
    BusClosedError,
    LeaseConflictError,
    LocalProtocolError,
    ReplyTimeoutError,
    WrongLoopError,
)
from motorbus.protocol import la
from motorbus.protocol.base import Command
from motorbus.protocol.safety import motion_keys
from motorbus.sim.la import LAModel
from tests.helpers import sim_bus


class Written:
    """A bus observer that keeps what the bus wrote."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def on_write(self, cmd: Command[object], at: float) -> None:
        self.frames.append(cmd.encode())

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None:
        pass


def follow(*ids: int) -> la.Broadcast:
    return la.Broadcast(la.BroadcastMode.FOLLOW, tuple((i, 500 + i) for i in ids))


def watch(bus: Bus) -> Written:
    written = Written()
    bus.add_observer(written)
    return written


async def test_nothing_is_written_before_send_and_a_send_happens_once() -> None:
    async with sim_bus([LAModel(1), LAModel(2)]) as (bus, _):
        written = watch(bus)
        lease = bus.lease(["la:1", "la:2"], owner="stream", bind=False)
        frame = follow(1, 2)
        ready = bus.prepare(frame, priority=Priority.HIGH, reserved=True, lease=lease)
        assert written.frames == []
        await bus.send_prepared(ready)  # a broadcast: no reply
        assert written.frames == [frame.encode()]
        with pytest.raises(LocalProtocolError, match="sent once"):
            bus.send_prepared(ready)
        assert written.frames == [frame.encode()]
        await lease.release(hold=True)


async def test_a_lease_taken_over_before_send_refuses_it_with_nothing_written() -> None:
    async with sim_bus([LAModel(1), LAModel(2)]) as (bus, _):
        written = watch(bus)
        stream = bus.lease(["la:1", "la:2"], owner="stream", bind=False)
        ready = bus.prepare(follow(1, 2), reserved=True, lease=stream)
        # Before the deadline: the stream lets go, and another owner takes la:2.
        await stream.release(hold=True)
        rig = bus.lease(["la:2"], owner="rig", bind=False)
        with pytest.raises(LeaseConflictError, match="la:2 is leased by 'rig'"):
            bus.send_prepared(ready)
        assert written.frames == []
        await rig.release(hold=True)


async def test_the_lease_rule_is_checked_again_for_the_frame_as_refreshed() -> None:
    async with sim_bus([LAModel(1), LAModel(2)]) as (bus, _):
        written = watch(bus)
        stream = bus.lease(["la:1", "la:2"], owner="stream", bind=False)
        wanted: list[la.Broadcast | None] = [follow(1, 2)]
        ready = bus.prepare(follow(1, 2), reserved=True, lease=stream, refresh=lambda: wanted[0])
        # la:2 leaves the stream (its entry is no longer wanted) and gets another owner:
        # the frame as it is now names only la:1, which the stream still holds.
        await stream.release(hold=True, keys=["la:2"])
        rig = bus.lease(["la:2"], owner="rig", bind=False)
        wanted[0] = follow(1)
        await bus.send_prepared(ready)
        assert written.frames == [follow(1).encode()]
        await rig.release(hold=True)
        await stream.release(hold=True)


async def test_its_write_owes_the_stops_of_the_frame_as_written_not_as_claimed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The claim works out the devices of the frame as prepared and the job keeps them
    for its write; a refresh that changes the frame drops them, so the write owes stops
    on the devices the frame it wrote moves, no more and no fewer."""
    async with sim_bus([LAModel(1), LAModel(2), LAModel(3)]) as (bus, _):
        stream = bus.lease(["la:1", "la:2", "la:3"], owner="stream", bind=False)
        table = bus.lease_keeper.table
        owing: list[tuple[bytes, tuple[str, ...]]] = []
        real = table.moved

        def moved(cmd: Command[object], keys: tuple[str, ...] | None = None) -> None:
            owing.append((cmd.encode(), keys if keys is not None else motion_keys(cmd)))
            real(cmd, keys)

        monkeypatch.setattr(table, "moved", moved)
        wanted: list[la.Broadcast | None] = [follow(1, 2)]
        ready = bus.prepare(follow(1, 2), reserved=True, lease=stream, refresh=lambda: wanted[0])
        assert ready.job.motion_keys == ("la:1", "la:2")
        wanted[0] = follow(1, 3)  # what the frame moves changed since its claim
        await bus.send_prepared(ready)
        assert owing == [(follow(1, 3).encode(), ("la:1", "la:3"))]
        plain = bus.prepare(follow(2), reserved=True, lease=stream)
        await bus.send_prepared(plain)  # unchanged: the claim's devices are the write's
        assert owing[1:] == [(follow(2).encode(), ("la:2",))]
        assert plain.job.motion_keys == ("la:2",)
        await stream.release(hold=True)


async def test_a_refresh_that_no_longer_wants_the_frame_drops_it_unsent() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        written = watch(bus)
        ready = bus.prepare(follow(1), reserved=True, refresh=lambda: None)
        await bus.send_prepared(ready)  # resolves, with nothing written
        assert written.frames == []
        assert bus.stats.dropped_by_refresh == 1


async def test_a_bus_closed_before_send_refuses_it() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        written = watch(bus)
        ready = bus.prepare(follow(1), reserved=True)
    with pytest.raises(BusClosedError):
        bus.send_prepared(ready)
    assert follow(1).encode() not in written.frames


async def test_a_prepared_submission_is_sent_once_and_by_its_own_bus() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _), sim_bus([LAModel(1)]) as (other, _):
        written, elsewhere = watch(bus), watch(other)
        ready = bus.prepare(follow(1), reserved=True)
        with pytest.raises(LocalProtocolError, match="by the bus that prepared it"):
            other.send_prepared(ready)
        assert elsewhere.frames == [] and written.frames == []
        await bus.send_prepared(ready)
        with pytest.raises(LocalProtocolError, match="sent once"):
            bus.send_prepared(ready)
        assert written.frames == [follow(1).encode()]


async def test_prepare_refuses_what_submit_refuses() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        with pytest.raises(LocalProtocolError, match="cmd must be a motorbus Command"):
            bus.prepare(b"\x55\xaa")  # type: ignore[arg-type]
        with pytest.raises(LocalProtocolError, match="retries"):
            bus.prepare(follow(1), retries=-1)
        rig = bus.lease(["la:1"], owner="rig", bind=False)
        other = bus.lease(["la:2"], owner="other", bind=False)
        with pytest.raises(LeaseConflictError):
            bus.prepare(follow(1), lease=other)
        await rig.release(hold=True)
        await other.release(hold=True)


async def test_a_send_from_another_event_loop_is_refused_with_nothing_written() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        written = watch(bus)
        ready = bus.prepare(follow(1), reserved=True)
        raised: list[BaseException] = []

        async def elsewhere() -> None:
            try:
                bus.send_prepared(ready)
            except BaseException as err:
                raised.append(err)

        thread = threading.Thread(target=asyncio.run, args=(elsewhere(),))
        thread.start()
        await asyncio.get_running_loop().run_in_executor(None, thread.join)
        assert [type(e) for e in raised] == [WrongLoopError]
        assert written.frames == []


class Timed(Written):
    """Also keeps when each write returned (the bus clock)."""

    def __init__(self) -> None:
        super().__init__()
        self.at: list[float] = []

    def on_write(self, cmd: Command[object], at: float) -> None:
        super().on_write(cmd, at)
        self.at.append(at)


async def test_a_prepared_frame_keeps_the_spacing_and_waits_for_an_owed_reply() -> None:
    async with sim_bus([LAModel(1), LAModel(2)]) as (bus, _):
        written = Timed()
        bus.add_observer(written)
        # Right after a write: the spacing from it still runs.
        await bus.submit(follow(1))
        spaced = bus.prepare(follow(1, 2), reserved=True)
        await bus.send_prepared(spaced)
        assert written.at[1] - written.at[0] >= bus.config.min_spacing
        # A reply owed (from la:3, which is silent) after the spacing has run: the
        # prepared frame waits until the reply's deadline, never written while it is owed.
        silent = la.Control(3, la.ControlAction.QUERY_STATUS)
        asked = bus.submit(silent, retries=0)
        await asyncio.sleep(2 * bus.config.min_spacing)
        owed = bus.prepare(follow(2), reserved=True)
        sent = bus.send_prepared(owed)
        assert not sent.done()
        await sent
        assert asked.done() and isinstance(asked.exception(), ReplyTimeoutError)
        assert written.frames[-2:] == [silent.encode(), follow(2).encode()]
