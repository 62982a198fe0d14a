"""The bus against simulated devices over the in-memory link: replies, order, priority, events.

Timing is never asserted as speed.  Order ("no request while a reply is owed") is
checked on the simulator's log, which records what the device side saw in the order it
saw it.  Spacing is checked on the bus's own transmit clock: the clock value the bus read
just before each write (its ``timer=`` wrapped to remember the last reading, its
transport's ``write`` wrapped to take it).  Neither the simulator's arrival times nor the
bus's DEBUG "TX" log times hold a 50 us tolerance on a loaded two-core machine: both
include a hop in which the process can be preempted.
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.events import FaultChanged, ProjectFinished, QuadDone
from motorbus.bus.timer import Timer, TimerHandle, default_timer
from motorbus.devices.la import InspireLA
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Family, wire_time
from motorbus.sim.bus import LogRecord, Pacing
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from motorbus.sim.model import DeviceModel
from motorbus.sim.project_stepper import ProjectStepperModel
from motorbus.sim.quad_stepper import QuadStepperModel
from tests.helpers import PACINGS

DELIVERIES = ["whole", "bytewise", "random"]
#: Tolerance on start-to-start gaps measured by the simulator: the in-memory hop
#: (``call_soon``) adds a small, variable delay to each arrival.
GAP_EPSILON_S = 50e-6
LA_BAUD = 921600
#: Host margin for tests whose point is behaviour, not deadlines: on a loaded shared
#: machine the default 1 ms margin produces spurious timeouts.
RELAXED_HOST_MARGIN_S = 0.05


class RecordingClock:
    """Wraps the bus's timer and remembers the last clock reading it handed out."""

    def __init__(self, inner: Timer) -> None:
        self.inner = inner
        self.last = 0.0

    def now(self) -> float:
        """Read the inner clock and remember the value."""
        self.last = self.inner.now()
        return self.last

    def call_at(
        self, deadline: float, callback: Callable[[], None], *, precise: bool = True
    ) -> TimerHandle:
        """Delegate to the inner timer."""
        return self.inner.call_at(deadline, callback, precise=precise)

    def call_at_lazily(
        self, deadline: float, callback: Callable[[], None], now: float | None = None
    ) -> TimerHandle:
        """Delegate to the inner timer."""
        return self.inner.call_at_lazily(deadline, callback, now)

    async def sleep_until(self, deadline: float, *, precise: bool = True) -> None:
        """Delegate to the inner timer."""
        await self.inner.sleep_until(deadline, precise=precise)

    def hold_arming(self) -> None:
        """Delegate to the inner timer."""
        self.inner.hold_arming()

    def release_arming(self) -> None:
        """Delegate to the inner timer."""
        self.inner.release_arming()


@dataclass
class Trace:
    """What a test can look at after the fact.

    Attributes:
        records: the simulator's log records, in the order it emitted them.
        tx_times: the bus clock reading behind each frame it wrote (its tx time).
    """

    records: list[LogRecord] = field(default_factory=list)
    tx_times: list[float] = field(default_factory=list)


@asynccontextmanager
async def logged_sim_bus(
    models: Sequence[DeviceModel],
    *,
    baud: int | None = None,
    delivery: str = "whole",
    faults: FaultConfig | None = None,
    seed: int = 0,
    on_record: Callable[[LogRecord], None] | None = None,
    pacing: Pacing = "wire",
    **bus_options: Any,
) -> AsyncIterator[tuple[Bus, MemorySim, Trace]]:
    """Like ``tests.conftest.sim_bus``, plus the simulator's log and the bus's tx times.

    ``pacing`` is the simulator's: ``"wire"`` or ``"prompt"`` (``tests.conftest.PACINGS``).

    ``on_record`` is called synchronously for every log record, i.e. at the moment
    the simulator takes a request or puts out a reply.
    """
    timer = default_timer()
    trace = Trace()

    def log(record: LogRecord) -> None:
        trace.records.append(record)
        if on_record is not None:
            on_record(record)

    bus_options.setdefault("host_margin", RELAXED_HOST_MARGIN_S)
    before = set(asyncio.all_tasks())
    async with MemorySim.start(
        models,
        baud=baud,
        delivery=delivery,  # type: ignore[arg-type]
        faults=faults,
        seed=seed,
        timer=timer,
        log=log,
        pacing=pacing,
    ) as sim:
        clock = RecordingClock(timer)
        transport = sim.transport
        write = transport.write

        def timed_write(data: bytes) -> None:
            # The bus reads its clock in _transmit and writes with no reading between.
            trace.tx_times.append(clock.last)
            write(data)

        transport.write = timed_write  # type: ignore[method-assign]
        families = {m.family for m in models}
        bus = Bus(transport, name="sim", families=families, timer=clock, **bus_options)  # type: ignore[arg-type]
        async with bus:
            yield bus, sim, trace
    await asyncio.sleep(0)
    leaked = [t for t in asyncio.all_tasks() - before if not t.done()]
    assert not leaked, f"the bus leaked tasks: {leaked}"


def frames(records: list[LogRecord], direction: str) -> list[bytes]:
    """The frames of one direction ("rx": host to device, "tx": device to host), in order."""
    return [bytes.fromhex(str(r["hex"])) for r in records if r["dir"] == direction]


def la_models(*ids: int, **options: Any) -> list[LAModel]:
    """LA models that always answer at their typical turnaround (reproducible order)."""
    return [LAModel(i, **options) for i in ids]


# -- request / reply -------------------------------------------------------------------------


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_la_request_reply(delivery: str, pacing: Pacing) -> None:
    models = la_models(1, 2, 3)
    async with logged_sim_bus(models, delivery=delivery, pacing=pacing) as (bus, _, trace):
        for i in (1, 2, 3):
            status = await bus.request(la.Control(i, la.ControlAction.QUERY_STATUS))
            assert isinstance(status, la.Status)
            assert (status.id, status.cmd_echo) == (i, la.CMD_CONTROL)
        moved = await bus.request(la.MoveTo(2, 1300))
        assert isinstance(moved, la.Status) and (moved.id, moved.target) == (2, 1300)
        assert await bus.request(la.ReadRegister(2, la.Register.TARGET)) == 1300
        written = await bus.request(la.WriteRegister(3, la.Register.OVER_CURRENT_LIMIT, 1000))
        assert isinstance(written, la.Status) and written.id == 3
        assert await bus.request(la.ReadRegister(3, la.Register.OVER_CURRENT_LIMIT)) == 1000
        raw = await bus.request(la.ReadTable(1, la.Register.ID.index, 1))
        assert raw == la.ReadReply(id=1, index=la.Register.ID.index, data=b"\x01")
        # No-reply commands resolve to None as soon as they are written.
        assert await bus.request(la.MoveTo(1, 700, reply=False)) is None
        assert await bus.request(la.Follow(3, 900, reply=False)) is None
        await bus.send(la.Control(la.BROADCAST_ID, la.ControlAction.WORK))
        # A reply-expecting command after them proves the simulator took them in order.
        await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
        assert models[0].received[-1][1:] == (la.CMD_MOVE_NO_REPLY, 700)
        assert models[2].received[-1][1:] == (la.CMD_FOLLOW_NO_REPLY, 900)
        assert bus.stats.timeouts == 0 and bus.stats.garbage_bytes == 0
        assert bus.stats.no_reply_frames == 3
        assert bus.stats.unexpected_frames == 0 and bus.stats.late_replies == 0
        assert len(frames(trace.records, "rx")) == bus.stats.requests


@pytest.mark.parametrize("write_reply", ["status", "ack"])
@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_write_reply_status_or_short_ack(
    write_reply: str, delivery: str, pacing: Pacing
) -> None:
    async with logged_sim_bus(
        la_models(1, write_reply=write_reply), delivery=delivery, pacing=pacing
    ) as (
        bus,
        _,
        _,
    ):
        reply = await bus.request(la.WriteRegister(1, la.Register.OVER_CURRENT_LIMIT, 800))
        if write_reply == "ack":
            assert reply == la.WriteAck(
                id=1, index=la.Register.OVER_CURRENT_LIMIT.index, reserved=0
            )
        else:
            assert isinstance(reply, la.Status) and reply.id == 1
        assert await InspireLA(bus, 1).over_current_limit() == 800


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_status_echo_of_request_cmd(delivery: str, pacing: Pacing) -> None:
    model = LAModel(1, status_cmd_echo="request")
    async with logged_sim_bus([model], delivery=delivery, pacing=pacing) as (bus, _, _):
        moved = await bus.request(la.MoveTo(1, 400))
        assert (moved.cmd_echo, moved.target) == (la.CMD_MOVE, 400)
        followed = await bus.request(la.Follow(1, 450))
        assert (followed.cmd_echo, followed.target) == (la.CMD_FOLLOW, 450)
        status = await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
        assert status.cmd_echo == la.CMD_CONTROL
        written = await bus.request(la.WriteRegister(1, la.Register.OVER_CURRENT_LIMIT, 900))
        assert isinstance(written, la.Status) and written.cmd_echo == la.CMD_WRITE
        assert bus.stats.timeouts == 0 and bus.stats.unexpected_frames == 0


@pytest.mark.parametrize("id_change_reply", ["old", "new"])
@pytest.mark.parametrize("pacing", PACINGS)
async def test_change_id_reply_from_old_or_new_id(id_change_reply: str, pacing: Pacing) -> None:
    model = LAModel(3, id_change_reply=id_change_reply)
    async with logged_sim_bus([model], pacing=pacing) as (bus, _, _):
        reply = await bus.request(la.WriteRegister(3, la.Register.ID, 2))
        assert isinstance(reply, la.Status)
        assert reply.id == (3 if id_change_reply == "old" else 2)
        assert model.id == 2
        status = await bus.request(la.Control(2, la.ControlAction.QUERY_STATUS))
        assert status.id == 2
        assert bus.stats.timeouts == 0 and bus.stats.unexpected_frames == 0


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_broadcasts_reach_every_model(delivery: str, pacing: Pacing) -> None:
    ids = list(range(1, 18))  # 17 actuators: two broadcast frames (15 + 2 entries, C.8)
    models = la_models(*ids)
    async with logged_sim_bus(models, delivery=delivery, pacing=pacing) as (bus, _, trace):
        targets = {i: 100 * i for i in ids}
        position_frames = la.split_broadcast(la.BroadcastMode.POSITION, targets)
        assert len(position_frames) == 2
        for frame in position_frames:
            await bus.send(frame)
        follow = {i: 50 + i for i in ids}
        for frame in la.split_broadcast(la.BroadcastMode.FOLLOW, follow):
            await bus.send(frame)
        # A reply-expecting request queues behind the broadcasts: once it is answered the
        # simulator has taken every broadcast frame.
        await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
        for model in models:
            got = [(cmd, target) for _, cmd, target in model.received]
            assert got == [
                (la.CMD_BROADCAST_MOVE, targets[model.id]),
                (la.CMD_BROADCAST_FOLLOW, follow[model.id]),
            ]
        assert len(frames(trace.records, "tx")) == 1  # only the status query was answered
        assert bus.stats.no_reply_frames == 4


# -- ordering and spacing ---------------------------------------------------------------------


def _la_request(raw: bytes) -> la.LACommand:
    cmd = la.decode_request(raw)
    assert isinstance(cmd, la.LACommand)
    return cmd


def check_order(records: list[LogRecord], baud: int, pacing: Pacing = "wire") -> int:
    """Assert that the simulator never got a request while a reply was owed.

    A request's log time is its end; under ``"wire"`` pacing it started its wire time
    earlier, under ``"prompt"`` it arrived whole at that instant.

    Returns the number of requests checked.
    """
    owed = False  # the last request expects a reply not yet put on the wire
    last_reply_end = -1.0
    n = 0
    for record in records:
        raw = bytes.fromhex(str(record["hex"]))
        t = float(record["t"])  # type: ignore[arg-type]
        if record["dir"] == "tx":
            assert owed, f"a reply nobody asked for: {record}"
            owed = False
            last_reply_end = t
        elif record["dir"] == "rx":
            assert record["fault"] is None, record
            assert not owed, f"request {record['hex']} sent while a reply was owed"
            start = t - wire_time(len(raw), baud) if pacing == "wire" else t
            assert start >= last_reply_end, "request started before the owed reply ended"
            owed = _la_request(raw).expects_reply
            n += 1
    assert not owed
    return n


@pytest.mark.parametrize("min_spacing", [1e-3, 2.5e-3])
@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_requests_never_overlap_an_owed_reply(
    delivery: str, min_spacing: float, pacing: Pacing
) -> None:
    models = la_models(1, 2, 3, slow_turnaround_probability=0.5)
    commands: list[la.LACommand] = []
    for k in range(10):
        i = 1 + k % 3
        commands += [
            la.Control(i, la.ControlAction.QUERY_STATUS),
            la.MoveTo(i, 10 * k + i, reply=k % 2 == 0),
            la.ReadRegister(i, la.Register.TARGET),
            la.Follow(i, 20 * k, reply=False),
        ]
    buses: list[Bus] = []
    burst: list[asyncio.Future[Any]] = []

    def queue_burst(record: LogRecord) -> None:
        # Queue everything while the first request is on the wire: every command then
        # goes through the queue, and none is written amid a burst of task start-ups
        # (which would delay its in-memory hop and blur the simulator's timestamps).
        if record["dir"] == "rx" and not burst:
            burst.extend(asyncio.ensure_future(buses[0].request(c)) for c in commands)

    async with logged_sim_bus(
        models,
        delivery=delivery,
        min_spacing=min_spacing,
        seed=3,
        on_record=queue_burst,
        pacing=pacing,
    ) as (bus, _, trace):
        buses.append(bus)
        await bus.request(la.Control(2, la.ControlAction.QUERY_STATUS))
        results = await asyncio.gather(*burst)
        for cmd, result in zip(commands, results, strict=True):
            if not cmd.expects_reply:
                assert result is None
            elif isinstance(cmd, la.ReadRegister):
                assert isinstance(result, int)
            else:
                assert isinstance(cmd, la.Control | la.MoveTo)
                assert isinstance(result, la.Status) and result.id == cmd.id
                if isinstance(cmd, la.MoveTo):
                    assert result.target == cmd.position
        # Wait for the last no-reply frame to reach the simulator before checking the log.
        await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
        assert check_order(trace.records, LA_BAUD, pacing) == len(commands) + 2
        sent = trace.tx_times
        assert len(sent) == len(commands) + 2
        gaps = [b - a for a, b in itertools.pairwise(sent)]
        assert min(gaps) >= min_spacing - GAP_EPSILON_S, f"{min(gaps) * 1e6:.0f} us"
        assert bus.stats.timeouts == 0


@pytest.mark.parametrize("delivery", DELIVERIES)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_emergency_jumps_the_queue(delivery: str, pacing: Pacing) -> None:
    model = LAModel(1)
    async with logged_sim_bus([model], delivery=delivery, pacing=pacing) as (bus, _, trace):
        started_before_estop: list[int] = []

        async def estop() -> la.Status:
            started_before_estop.append(bus.stats.requests)
            status: la.Status = await bus.request(
                la.Control(1, la.ControlAction.ESTOP), priority=Priority.EMERGENCY
            )
            return status

        # Tasks run in creation order: the 20 queries are queued before the e-stop.
        queries = [
            asyncio.ensure_future(bus.request(la.Control(1, la.ControlAction.QUERY_STATUS)))
            for _ in range(20)
        ]
        stop = asyncio.ensure_future(estop())
        await asyncio.gather(*queries, stop)
        order = [la.decode_request(raw) for raw in frames(trace.records, "rx")]
        actions = [c.action for c in order if isinstance(c, la.Control)]
        assert len(actions) == 21
        position = actions.index(la.ControlAction.ESTOP)
        assert started_before_estop == [position]
        assert position <= 1  # only a query already on the wire may precede it
        assert all(a is la.ControlAction.QUERY_STATUS for a in actions[position + 1 :])


@pytest.mark.parametrize("pacing", PACINGS)
async def test_priority_order_of_queued_requests(pacing: Pacing) -> None:
    async with logged_sim_bus(la_models(1), pacing=pacing) as (bus, _, trace):
        first = asyncio.ensure_future(bus.request(la.MoveTo(1, 1)))
        order = [
            (Priority.BACKGROUND, 2),
            (Priority.NORMAL, 3),
            (Priority.HIGH, 4),
            (Priority.NORMAL, 5),
            (Priority.EMERGENCY, 6),
        ]
        rest = [
            asyncio.ensure_future(bus.request(la.MoveTo(1, target), priority=p))
            for p, target in order
        ]
        await asyncio.gather(first, *rest)
        targets = [_la_request(raw) for raw in frames(trace.records, "rx")]
        assert [t.position for t in targets if isinstance(t, la.MoveTo)] == [1, 6, 4, 3, 5, 2]


# -- events -----------------------------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
async def test_project_finished_event(pacing: Pacing) -> None:
    model = ProjectStepperModel()
    # 20 pulses at 2000 pulses/s (200 pulses/rev at 600 rpm): a 10 ms move.
    project = ps.Project(
        number=1,
        subdivision=1,
        step_angle_x100=180,
        distance_per_rev=200,
        steps=(ps.StepSpec(run_distance=20, start_hz=2000, speed_rpm=600),),
    )
    async with logged_sim_bus([model], baud=115200, pacing=pacing) as (bus, _, _):
        for cmd in ps.project_commands(project):
            assert isinstance(await bus.request(cmd), ps.Ack)
        with bus.events.subscribe(ProjectFinished) as sub:
            ack = await bus.request(ps.StartProject(1))
            assert isinstance(ack, ps.Ack)
            event = await sub.next(timeout=5)
        assert event.bus == "sim"
        assert model.position == pytest.approx(20)
        assert not model.running
        assert bus.stats.events == 1 and bus.stats.timeouts == 0


@pytest.mark.parametrize("pacing", PACINGS)
async def test_quad_done_events(pacing: Pacing) -> None:
    model = QuadStepperModel()
    async with logged_sim_bus([model], baud=115200, pacing=pacing) as (bus, _, _):
        for cmd in (
            q.MotorSetup(2, 8, 180),
            q.RunPulses(2, 100),
            q.DirectionAndStartFrequency(2, q.RotationDirection.FORWARD, 1000),
            q.AccelAndSpeed(2, 0, 600),
        ):
            await bus.request(cmd)
        with bus.events.subscribe(QuadDone) as sub:
            await bus.request(q.Run(2))
            run_done = await sub.next(timeout=5)
            await bus.request(q.SetLed(3, True))
            led_done = await sub.next(timeout=5)
        assert (run_done.kind, run_done.address, run_done.led) == ("run", 0, None)
        assert run_done.raw == bytes.fromhex("FF AA 00 09 01 00")
        assert (led_done.kind, led_done.led) == ("led", 3)
        # The model's position may read 99 here: it floors the pulses at (start + d) - start,
        # a float hair under d.  That is the simulator's rounding, not the bus.
        assert not model.motors[2].running
        assert bus.stats.events == 2 and bus.stats.unexpected_frames == 0


@pytest.mark.parametrize("pacing", PACINGS)
async def test_la_fault_changed_event(pacing: Pacing) -> None:
    model = LAModel(2)
    async with logged_sim_bus([model], pacing=pacing) as (bus, _, _):
        actuator = InspireLA(bus, 2)
        with bus.events.subscribe(FaultChanged) as sub:
            await actuator.status()
            assert sub.pending() == []  # no fault yet: nothing changed
            model.trigger_fault("stall", time.monotonic())  # the simulator's clock
            status = await actuator.status()
            assert status.errors == la.ErrorFlags.STALL
            event = await sub.next(timeout=1)
            assert (event.id, event.before, event.after) == (2, 0, int(la.ErrorFlags.STALL))
            assert event.status == status
            await actuator.clear_fault()
            cleared = await sub.next(timeout=1)
            assert (cleared.before, cleared.after) == (int(la.ErrorFlags.STALL), 0)


@pytest.mark.parametrize("pacing", PACINGS)
async def test_unknown_family_is_refused_before_sending(pacing: Pacing) -> None:
    async with logged_sim_bus(la_models(1), pacing=pacing) as (bus, _, trace):
        assert bus.families == frozenset({Family.LA})
        with pytest.raises(ValueError, match="quad_stepper"):
            await bus.request(q.StopAll())
        assert bus.stats.requests == 0 and trace.records == []


async def test_open_checks_the_usb_adapter_latency_timer() -> None:
    """A transport that knows its adapter's latency timer is asked about the deadline slack."""
    from motorbus.bus.bus import Bus
    from motorbus.transport.memory import memory_pair

    host, _peer = memory_pair(baudrate=921600)
    asked: list[float] = []
    host.warn_if_latency_exceeds = asked.append  # type: ignore[attr-defined]
    bus = Bus(host, families=[Family.LA], host_margin=0.002)
    async with bus:
        pass
    assert asked == [pytest.approx(800e-6 + 0.002)]
