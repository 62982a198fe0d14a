"""The bus under faults: silence, cancellation, late replies, garbage, port loss.

Every request must resolve (a value or a typed error), and no reply may ever be given to
a request it does not answer: MoveTo targets differ per request, so a stale status would
show the wrong target.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from motorbus.bus.bus import Bus, BusState
from motorbus.bus.events import BusStateChanged
from motorbus.errors import BusClosedError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.sim.bus import LogRecord, Pacing
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from tests.bus.test_bus_memory import DELIVERIES, frames, la_models, logged_sim_bus
from tests.helpers import PACINGS

#: Tight deadlines for the timeout tests (the bus default): what times out here should.
TIGHT_MARGIN_S = 1e-3
#: Upper bound on waiting for a counter the simulator's late output will bump.
EVENTUALLY_S = 2.0
POLL_S = 0.01
#: A late reply in these tests comes this much after it was due: past the deadline
#: (about 2.1 ms for an LA status at 921600 bit/s with the default margin) but inside the
#: bus's default late guard (20 ms).  A device later than the guard can have its stale
#: reply taken for the answer to a newer same-shaped request; see the report on the bus.
LATE_DELAY_S = 0.01


async def eventually(condition: Any, what: str) -> None:
    """Poll ``condition()`` every few ms until true; fail after ``EVENTUALLY_S``."""
    loop = asyncio.get_running_loop()
    give_up = loop.time() + EVENTUALLY_S
    while not condition():
        if loop.time() > give_up:
            pytest.fail(f"timed out waiting for {what}")
        await asyncio.sleep(POLL_S)


def status_query(ident: int) -> la.Control:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


# -- timeouts ----------------------------------------------------------------------------------


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_silent_device_times_out_after_retries(delivery: str, pacing: Pacing) -> None:
    faults = FaultConfig(silent=True)
    async with logged_sim_bus(
        la_models(1), delivery=delivery, faults=faults, host_margin=TIGHT_MARGIN_S, pacing=pacing
    ) as (bus, sim, trace):
        with pytest.raises(ReplyTimeoutError, match=r"la:1 .* after 2 attempts"):
            await bus.request(status_query(1))
        assert frames(trace.records, "rx") == [status_query(1).encode()] * 2
        assert (bus.stats.timeouts, bus.stats.retries, bus.stats.failed) == (2, 1, 1)
        assert bus.stats.device("la:1").retries == 1
        assert sim.bus.stats.faults_injected["silent"] == 2


@pytest.mark.parametrize("pacing", PACINGS)
async def test_missing_id_times_out_with_requested_retries(pacing: Pacing) -> None:
    async with logged_sim_bus(la_models(1), host_margin=TIGHT_MARGIN_S, pacing=pacing) as (
        bus,
        _,
        trace,
    ):
        with pytest.raises(ReplyTimeoutError, match=r"la:9 .* after 3 attempts"):
            await bus.request(status_query(9), retries=2)
        with pytest.raises(ReplyTimeoutError, match="la:9") as info:
            await bus.request(status_query(9), retries=0)
        assert "attempts" not in str(info.value)
        assert len(frames(trace.records, "rx")) == 4
        assert bus.stats.device("la:9").timeouts == 4 and bus.stats.retries == 2
        # Other devices were never held by la:9's trouble.
        assert (await bus.request(status_query(1))).id == 1


@pytest.mark.parametrize(
    "cmd",
    [la.MoveTo(1, 500), la.Follow(1, 500), la.WriteRegister(1, la.Register.TARGET, 500)],
    ids=["move_to", "follow", "write_target"],
)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_motion_is_never_retried(cmd: la.LACommand, pacing: Pacing) -> None:
    faults = FaultConfig(silent=True)
    async with logged_sim_bus(
        la_models(1), faults=faults, host_margin=TIGHT_MARGIN_S, pacing=pacing
    ) as (
        bus,
        _,
        trace,
    ):
        assert cmd.starts_motion
        with pytest.raises(ReplyTimeoutError, match="la:1"):
            await bus.request(cmd, retries=5)
        assert frames(trace.records, "rx") == [cmd.encode()]
        assert (bus.stats.timeouts, bus.stats.retries) == (1, 0)


# -- cancellation ------------------------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
async def test_cancelled_queued_request_is_not_sent(pacing: Pacing) -> None:
    queued: list[asyncio.Future[Any]] = []
    sent_when_cancelled: list[int] = []
    buses: list[Bus] = []

    def cancel_queued(record: LogRecord) -> None:
        # The first request has reached the device: the second is still in the queue.
        if record["dir"] == "rx" and queued and not queued[0].done():
            sent_when_cancelled.append(buses[0].stats.requests)
            queued[0].cancel()

    async with logged_sim_bus(la_models(1), on_record=cancel_queued, pacing=pacing) as (
        bus,
        _,
        trace,
    ):
        buses.append(bus)
        first = asyncio.ensure_future(bus.request(status_query(9), timeout=0.05, retries=0))
        queued.append(asyncio.ensure_future(bus.request(la.MoveTo(1, 1234))))
        with pytest.raises(ReplyTimeoutError, match="la:9"):
            await first
        with pytest.raises(asyncio.CancelledError):
            await queued[0]
        assert sent_when_cancelled == [1]
        after = await bus.request(la.MoveTo(1, 321))
        assert after.target == 321
        sent = frames(trace.records, "rx")
        assert sent == [status_query(9).encode(), la.MoveTo(1, 321).encode()]


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_cancelling_a_sent_request_does_not_break_the_next(
    delivery: str, pacing: Pacing
) -> None:
    model = LAModel(1)
    pending: list[asyncio.Future[Any]] = []

    def cancel_on_arrival(record: LogRecord) -> None:
        if record["dir"] == "rx" and pending and not pending[0].done():
            pending[0].cancel()

    async with logged_sim_bus(
        [model], delivery=delivery, on_record=cancel_on_arrival, pacing=pacing
    ) as (
        bus,
        _,
        trace,
    ):
        pending.append(asyncio.ensure_future(bus.request(la.MoveTo(1, 500))))
        with pytest.raises(asyncio.CancelledError):
            await pending[0]
        status = await bus.request(la.MoveTo(1, 700))
        assert status.target == 700
        status = await bus.request(status_query(1))
        assert status.target == 700
        assert [target for _, _, target in model.received] == [500, 700]
        assert len(frames(trace.records, "tx")) == 3
        assert bus.stats.timeouts == 0 and bus.stats.unexpected_frames == 0


@pytest.mark.parametrize("pacing", PACINGS)
async def test_cancelled_sent_query_is_not_retried(pacing: Pacing) -> None:
    pending: list[asyncio.Future[Any]] = []

    def cancel_on_arrival(record: LogRecord) -> None:
        if record["dir"] == "rx" and pending and not pending[0].done():
            pending[0].cancel()

    faults = FaultConfig(silent_windows=((0.0, 0.2),))
    async with logged_sim_bus(
        la_models(1),
        faults=faults,
        host_margin=TIGHT_MARGIN_S,
        on_record=cancel_on_arrival,
        pacing=pacing,
    ) as (bus, _, trace):
        pending.append(asyncio.ensure_future(bus.request(status_query(1), retries=3)))
        with pytest.raises(asyncio.CancelledError):
            await pending[0]
        # A later request queues behind the cancelled one until its deadline ran out.
        with pytest.raises(ReplyTimeoutError):
            await bus.request(la.ReadRegister(1, la.Register.TARGET), retries=0)
        assert frames(trace.records, "rx") == [
            status_query(1).encode(),
            la.ReadRegister(1, la.Register.TARGET).encode(),
        ]
        assert bus.stats.retries == 0  # nobody is waiting for a retry: none was counted


# -- late replies ------------------------------------------------------------------------------


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_late_reply_is_counted_and_never_given_to_a_later_request(
    delivery: str, pacing: Pacing
) -> None:
    faults = FaultConfig(late_reply_rate=0.3, late_reply_delay_s=LATE_DELAY_S)
    async with logged_sim_bus(
        la_models(1, 2),
        delivery=delivery,
        faults=faults,
        seed=5,
        host_margin=TIGHT_MARGIN_S,
        pacing=pacing,
    ) as (bus, sim, _):
        outcomes: list[str] = []
        for k in range(40):
            target = 100 + 7 * k
            ident = 1 + k % 2
            try:
                status = await bus.request(la.MoveTo(ident, target))
            except ReplyTimeoutError as err:
                assert f"la:{ident}" in str(err)
                outcomes.append("timeout")
                continue
            assert (status.id, status.target) == (ident, target)
            outcomes.append("ok")
        injected = sim.bus.stats.faults_injected["late"]
        assert injected > 0 and "ok" in outcomes
        # A loop that runs late may take a delayed reply as its own request's answer: a
        # deadline is decided when its callback runs (bus/matching.py), and a loaded
        # machine delays that callback.  What may never happen: a reply given to
        # another request (the statuses above), a timeout with no delayed reply behind
        # it, or a timed-out request's reply going uncounted.  (On a prompt machine the
        # timeouts are the delayed replies alone; on a loaded one an on-time reply read
        # over 1 ms late times out too (22 timeouts for 20 delays, seen), and is then
        # counted late all the same: every timeout's reply is counted, and only those.)
        timeouts = outcomes.count("timeout")
        assert timeouts > 0
        await eventually(lambda: bus.stats.late_replies >= timeouts, "the late replies")
        assert bus.stats.late_replies == timeouts
        assert bus.stats.unexpected_frames == 0
        assert bus.stats.retries == 0  # MoveTo starts motion: never retried


# -- garbage and resync ------------------------------------------------------------------------


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_garbage_flips_and_drops_never_mismatch(delivery: str, pacing: Pacing) -> None:
    faults = FaultConfig(
        garbage_rate=0.3, bit_flip_rate=0.004, drop_byte_rate=0.004, duplicate_reply_rate=0.05
    )
    models = la_models(1, 2, 3)
    async with logged_sim_bus(
        models, delivery=delivery, faults=faults, seed=11, host_margin=5e-3, pacing=pacing
    ) as (bus, sim, _):
        resolved = 0
        for k in range(45):
            ident = 1 + k % 3
            target = 10 + 13 * k
            kind = k % 3
            cmd: la.LACommand
            if kind == 0:
                cmd = la.MoveTo(ident, target)
            elif kind == 1:
                cmd = status_query(ident)
            else:
                cmd = la.ReadRegister(ident, la.Register.TARGET)
            try:
                result = await bus.request(cmd)
            except ReplyTimeoutError as err:
                assert f"la:{ident}" in str(err)
                resolved += 1
                continue
            resolved += 1
            if isinstance(cmd, la.ReadRegister):
                assert result == models[ident - 1].target
            else:
                assert result.id == ident
                if isinstance(cmd, la.MoveTo):
                    assert result.target == target
        assert resolved == 45
        assert bus.stats.garbage_bytes > 0 and bus.stats.resyncs > 0
        counts = sim.bus.stats.faults_injected
        assert counts["garbage"] > 0 and counts["flip"] + counts["drop"] > 0


# -- port loss ---------------------------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
async def test_unplug_fails_pending_and_bus_reconnects_after_plug(pacing: Pacing) -> None:
    sims: list[Any] = []

    def unplug_on_arrival(record: LogRecord) -> None:
        if record["dir"] == "rx" and str(record["hex"]).startswith("55 AA 03 09"):
            sims[0].peer.unplug()

    async with logged_sim_bus(la_models(1), on_record=unplug_on_arrival, pacing=pacing) as (
        bus,
        sim,
        _,
    ):
        sims.append(sim)
        with bus.events.subscribe(BusStateChanged) as states:
            with pytest.raises(BusClosedError, match="lost its port"):
                await bus.request(status_query(9), timeout=1.0)
            assert bus.state is BusState.LOST
            with pytest.raises(BusClosedError, match="lost"):
                await bus.request(status_query(1))
            sim.peer.plug()
            await bus.wait_state(BusState.OPEN, timeout=EVENTUALLY_S)
            seen = [e.state for e in states.pending()]
        assert seen[0] == "lost" and seen[-1] == "open" and "reconnecting" in seen
        assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)
        assert (await bus.request(status_query(1))).id == 1


@pytest.mark.parametrize("pacing", PACINGS)
async def test_simulated_disconnect_fault_and_recovery(pacing: Pacing) -> None:
    faults = FaultConfig(disconnect_after_s=0.1, reconnect_after_s=0.05, disconnect_count=1)
    async with logged_sim_bus(la_models(1), faults=faults, pacing=pacing) as (bus, sim, _):
        with bus.events.subscribe(BusStateChanged, lambda e: e.state == "lost") as lost:
            await lost.next(timeout=EVENTUALLY_S)
        await bus.wait_state(BusState.OPEN, timeout=EVENTUALLY_S)
        assert (await bus.request(status_query(1))).id == 1
        assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)
        assert sim.bus.stats.faults_injected["disconnect"] == 1


@pytest.mark.parametrize("pacing", PACINGS)
async def test_lost_done_replies_do_not_pile_up(pacing: Pacing) -> None:
    """Done replies that never come are forgotten past a bound, and counted."""
    from motorbus.bus.matching import MAX_DONE_WATCHES
    from motorbus.protocol import quad_stepper as q
    from motorbus.sim.quad_stepper import QuadStepperModel
    from tests.helpers import sim_bus

    model = QuadStepperModel()
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        await bus.request(q.MotorSetup(1, 8, 180))
        await bus.request(q.RunPulses(1, 1_000_000))  # long enough not to finish
        for _ in range(MAX_DONE_WATCHES + 5):
            await bus.request(q.Run(1))  # acked each time; the done reply never comes
        assert len(bus._core.matcher.done_watches) == MAX_DONE_WATCHES
        assert bus.stats.done_watches_dropped == 5
        await bus.request(q.Stop(1))
