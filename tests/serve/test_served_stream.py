"""Served streams (issue 39): ``Streamer(served_bus)`` ticks on the server's timer, fed by
the client's targets ahead; the simulator's own record (over a pty) is the judge.
Client and server run in separate processes; assertions are on order and counts,
never on speed."""

from __future__ import annotations

import asyncio
import itertools
import signal
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import InspireLA, LocalProtocolError, StreamEnded, Streamer
from motorbus.protocol import la
from motorbus.serve import keys as k
from motorbus.serve.streams_client import ServedStream, ServedStreamer
from motorbus.sim import SimProcess
from motorbus.streams import StreamGap
from tests.helpers import stream_summary
from tests.serve.conftest import Child, client
from tests.serve.test_served_faults import raw_query
from tests.waiting import eventually
from tests.zygote import run_motorbus

PAUSES = {la.Control(i, la.ControlAction.PAUSE).encode() for i in (1, 2)}


def frames(sim: SimProcess) -> list[Any]:
    """Every request the simulator received, decoded, in order."""
    out = []
    for r in sim.log_records():
        if r["direction"] == "request" and r["kind"] == "frame":
            out.append(la.decode_request(bytes.fromhex(r["hex"])))
    return out


def targets_at_sim(sim: SimProcess) -> list[tuple[int, ...]]:
    """The follow targets of each broadcast, as (la:1, la:2) rows, in order."""
    rows = []
    for f in frames(sim):
        if isinstance(f, la.Broadcast):
            entries = dict(f.entries)
            rows.append(tuple(entries[i] for i in sorted(entries)))
    return rows


def after_last_broadcast(sim: SimProcess) -> list[Any]:
    seen = frames(sim)
    last = max((n for n, f in enumerate(seen) if isinstance(f, la.Broadcast)), default=-1)
    return seen[last + 1 :]


def collapse(rows: list[tuple[int, ...]]) -> list[tuple[int, ...]]:
    """Consecutive repeats (a tick the server held) made one."""
    return [r for n, r in enumerate(rows) if n == 0 or r != rows[n - 1]]


def assert_in_order(
    received: list[tuple[int, ...]],
    sent: list[tuple[int, ...]],
    skipped: int = 0,
    gaps: int = 0,
) -> None:
    """Every row received is one of ``sent``, in ``sent``'s order, none twice apart
    from held repeats; the first and the last are there, unless the stream skipped
    ticks (``skipped``: a server starved on a loaded run skips, never bursts).  After a
    gap (``gaps``: the client starved, rows came late) the server ramps from the last
    row sent to the rows again: targets between those two rows, each coordinate."""
    rows = collapse(received)
    kept = [r for r in rows if r in sent]
    if gaps:
        for n, r in enumerate(rows):
            if r in sent:
                continue
            before = next((x for x in reversed(rows[:n]) if x in sent), sent[0])
            after = next((x for x in rows[n + 1 :] if x in sent), sent[-1])
            between = zip(r, before, after, strict=True)
            assert all(min(a, b) <= v <= max(a, b) for v, a, b in between), (before, r, after)
    else:
        assert kept == rows, [r for r in rows if r not in sent]
    index = [sent.index(r) for r in kept]
    assert index == sorted(set(index)), index
    if not skipped:
        assert index[0] == 0 and index[-1] == len(sent) - 1, index


ROWS = [(100 + 7 * n, 1900 - 7 * n) for n in range(40)]


@pytest.mark.parametrize("kind", ["rows ahead", "a target per tick"])
async def test_targets_reach_the_simulator_in_order_on_the_servers_ticks(
    la_sim: SimProcess, la_server: Child, endpoint: str, kind: str
) -> None:
    def per_tick(t: float, statuses: object) -> tuple[int, int] | None:
        n = round(t / 0.01)
        return ROWS[n] if n < len(ROWS) else None

    source: Any = list(ROWS) if kind == "rows ahead" else per_tick
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        streamer = Streamer(bus)  # the one call of a local bus
        assert isinstance(streamer, ServedStreamer)
        stream = streamer.follow(
            [InspireLA(bus, 1), InspireLA(bus, 2)], source, period=0.01, safe_action="pause"
        )
        assert isinstance(stream, ServedStream)
        await asyncio.wait_for(stream.wait(), 30)
        assert stream.done and stream.error is None
    received = targets_at_sim(la_sim)
    published = [r for r in received if r in ROWS]
    # A starved client (six workers) can publish tick 0's row after the server asked for
    # it: that tick is ``unwritten``, as a skipped one is.
    assert_in_order(published, ROWS, stream.stats.skipped + len(stream.unwritten))
    if len(published) < len(received):
        # Rows of no target: the ramp back to the targets after ticks the server held (a
        # target that came later than its tick: a client starved on a loaded machine) or
        # a gap (a server that fell behind its ticks).  A gap event needs GAP_TICKS held
        # in a row; the ramp follows any held tick (seen: 8 held, no gap, a CPU hog).
        assert stream.stats.gaps >= 1 or stream.stats.held >= 1, received
    # One frame per tick the server served (its own count), and the safe action last.
    assert len(received) == stream.stats.ticks
    assert set(after_last_broadcast(la_sim)) >= {la.decode_request(p) for p in PAUSES}


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP])
async def test_a_client_killed_mid_stream_ends_it_with_the_safe_action_and_nothing_moves(
    la_sim: SimProcess, la_server: Child, endpoint: str, how: int
) -> None:
    # SIGKILL closes its link at once; a frozen client (SIGSTOP) falls silent: its
    # stream holds (on_gap="ramp") until the deadman (--liveness 0.5 s) ends it.
    child = client(
        endpoint,
        """
        def forever():
            n = 0
            while True:
                n += 1
                yield [100 + n % 1000, 1000]
        stream = motorbus.Streamer(bus).follow(
            [InspireLA(bus, 1), InspireLA(bus, 2)], forever(), period=0.01, safe_action="pause"
        )
        """,
    )
    try:
        child.expect("ready")
        await eventually(lambda: len(targets_at_sim(la_sim)) >= 20, "the stream to run")
        child.send(how)
        await eventually(
            lambda: (
                {
                    la.Control(f.id, f.action).encode()
                    for f in after_last_broadcast(la_sim)
                    if isinstance(f, la.Control)
                }
                >= PAUSES
            ),
            "the pauses after the last target",
        )
        count = len(frames(la_sim))
        await asyncio.sleep(0.5)
        # Nothing moves afterwards: no target, no motion of any kind.
        late = frames(la_sim)[count:]
        assert not [f for f in late if getattr(f, "starts_motion", False)], late
        assert not [f for f in after_last_broadcast(la_sim) if getattr(f, "starts_motion", False)]
    finally:
        child.finish(signal.SIGKILL)


async def _stall_then(rows: list[tuple[int, int]], stall: float, after: tuple[int, int]) -> Any:
    async def source() -> AsyncIterator[tuple[int, int]]:
        for r in rows:
            yield r
        await asyncio.sleep(stall)  # the client falls silent
        for _ in range(200):
            yield after

    return source()


async def test_a_silent_client_gets_on_gap_stop_the_safe_action_and_the_end(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        gaps = bus.events.subscribe(StreamGap)
        source = await _stall_then(ROWS[:10], 5.0, (500, 500))
        stream = Streamer(bus).follow(
            [InspireLA(bus, 1), InspireLA(bus, 2)],
            source,
            period=0.01,
            safe_action="pause",
            on_gap="stop",
        )
        with pytest.raises(StreamEnded, match="client silent"):
            await asyncio.wait_for(stream.wait(), 30)
        gap = await gaps.next(5)
        assert (gap.cause, gap.action, gap.missed) == ("client", "stop", 3)
        assert stream.stats.gaps == 1
    received = targets_at_sim(la_sim)
    # The last rows may come after their ticks on a starved client (eight workers): the
    # server holds those ticks (``unwritten``), and the first and last rows are required
    # only when it wrote every row as sent.
    assert_in_order(received, ROWS[:10], stream.stats.skipped + len(stream.unwritten))
    assert (500, 500) not in received
    assert set(after_last_broadcast(la_sim)) >= {la.decode_request(p) for p in PAUSES}


async def test_a_silent_client_gets_on_gap_ramp_back_to_its_targets(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        gaps = bus.events.subscribe(StreamGap)
        source = await _stall_then([(500, 500)] * 10, 0.3, (1500, 1500))
        stream = Streamer(bus).follow(
            [InspireLA(bus, 1), InspireLA(bus, 2)],
            source,
            period=0.01,
            safe_action="pause",
            on_gap="ramp",
            max_speed=2000,  # 20 units a tick
        )
        await asyncio.wait_for(stream.wait(), 30)
        gap = await gaps.next(5)
        while gap.cause == "behind":  # the server's own, starved on a loaded run (seen)
            gap = await gaps.next(5)
        assert (gap.cause, gap.action, gap.ids) == ("client", "ramp", (1, 2))
        assert gap.missed >= 3 and gap.positions == {1: 500, 2: 500}
        # The stall's gap; a worker starved for 30 ms or more (seen) adds one more, each
        # a ramp from where the actuators are, so the path below stays smooth.
        assert stream.stats.gaps >= 1 and stream.stats.held >= gap.missed
    moving = [r[0] for r in collapse(targets_at_sim(la_sim))]
    # From 500 to 1500 in steps of at most 20 (max_speed * period): no jump.
    assert moving[0] == 500 and moving[-1] == 1500
    steps = [b - a for a, b in itertools.pairwise(moving)]
    assert all(0 < s <= 20 for s in steps), steps
    assert len(steps) >= 1000 // 20 - 1


async def test_max_missed_ends_a_served_stream_on_a_silent_actuator(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    # la:9 is not simulated: its feedback replies are missed, two in a row end it.
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        stream = Streamer(bus).follow(
            [InspireLA(bus, 1), InspireLA(bus, 9)],
            ROWS,
            period=0.02,
            feedback=True,
            safe_action="pause",
            max_missed=2,
        )
        with pytest.raises(StreamEnded, match="la:9 missed 2 status replies in a row"):
            await asyncio.wait_for(stream.wait(), 30)
        assert stream.stats.feedback_timeouts == 2


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"period": 0.2}, "period"),
        ({"safe_action": "maybe"}, "safe_action"),
        ({"on_gap": "jump"}, "on_gap"),
        ({"max_speed": 0}, "max_speed"),
        ({"feedback": "yes"}, "feedback"),
        ({"max_missed": 0}, "max_missed"),
    ],
)
async def test_bad_stream_options_are_refused_naming_the_field_and_nothing_is_sent(
    la_sim: SimProcess, la_server: Child, endpoint: str, options: dict[str, Any], field: str
) -> None:
    before = len(la_sim.log_records())
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        with pytest.raises(LocalProtocolError) as refused:
            Streamer(bus).follow(InspireLA(bus, 1), [100, 200], **options)
        assert refused.value.field == field
        # The lead, the client's own option: a server across a slow link gets more.
        assert Streamer(bus, lead=0.3).lead == 0.3
        with pytest.raises(LocalProtocolError) as refused:
            Streamer(bus, lead=6)
        assert refused.value.field == "lead"
    # The server checks them too (a client in another language).
    body = {"client": "x", "op": "open", "ids": [1], **options}
    answer = raw_query(endpoint, k.bus_key("bus", "stream"), k.encode_json(body))
    assert answer["ok"] is False and answer["error"] == "bad_payload"
    assert answer["field"] == field
    await asyncio.sleep(0.2)
    assert len(la_sim.log_records()) == before


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"op": "open", "ids": []}, "ids"),
        ({"op": "open", "ids": [0]}, "ids"),
        ({"op": "open", "ids": [1], "start_in": 60}, "start_in"),
        ({"op": "open", "ids": [1], "period": "fast"}, "period"),
        ({"op": "rewind"}, "op"),
        ({"op": "stop", "stream": 99}, "stream"),
    ],
)
def test_bad_stream_queries_are_refused_naming_the_field(
    la_sim: SimProcess, la_server: Child, endpoint: str, body: dict[str, Any], field: str
) -> None:
    before = len(la_sim.log_records())
    answer = raw_query(endpoint, k.bus_key("bus", "stream"), k.encode_json({"client": "x", **body}))
    assert answer["ok"] is False and answer["field"] == field, answer
    assert len(la_sim.log_records()) == before


def test_motorbus_stream_connect_plays_a_csv_through_the_server(
    la_sim: SimProcess, la_server: Child, endpoint: str, tmp_path: Path
) -> None:
    # A loaded run of the suite skips a tick now and then (2 of 40 at 20 ms a tick, with
    # eight workers on two CPUs): the command then fails, naming the skipped ticks, and
    # what it sent still arrives in order (count, do not time).  A client starved past
    # the server's lead is a gap, after which the server ramps back to the rows.
    csv = tmp_path / "path.csv"
    csv.write_text(
        "t,1,2\n" + "".join(f"{n * 0.02:.2f},{a},{b}\n" for n, (a, b) in enumerate(ROWS))
    )
    done = run_motorbus(
        ["stream", str(csv), "--connect", endpoint, "--ramp", "0", "--period", "0.02", "--json"]
    )
    summary = stream_summary(done)
    assert_in_order(targets_at_sim(la_sim), ROWS, summary["skipped"], summary["gaps"])
    assert set(after_last_broadcast(la_sim)) >= {la.decode_request(p) for p in PAUSES}
    # Again, from where the first left them: out and back to where they start.  No poll
    # fits between the server's ticks (its 250 ms host margin), so the command knows
    # only the final positions, which are the last targets: they followed (it said
    # "did not follow" before).
    again = run_motorbus(
        ["stream", str(csv), "--connect", endpoint, "--ramp", "0", "--period", "0.02", "--json"]
    )
    summary = stream_summary(again)
    assert summary["polls"] == 0 and summary["not_following"] == [], summary


async def test_a_stream_owns_its_actuators_for_its_client_and_a_hold_end_passes_them_back(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint) as site, motorbus.connect(endpoint) as other:
        bus = site.bus()
        await InspireLA(bus, 1).move_to(700)  # this client's own motion: taken over
        stream = Streamer(bus).follow(InspireLA(bus, 1), [700 + n for n in range(200)])
        await eventually(lambda: len(targets_at_sim(la_sim)) >= 5, "the stream to run")
        owners = [(i.key, i.owner) for i in other.bus().leases]
        assert owners == [("la:1", f"stream of client {site.client_id}")]
        with pytest.raises(motorbus.LeaseConflictError) as refused:
            await InspireLA(other.bus(), 1).move_to(100)
        assert refused.value.owner == owners[0][1]
        with pytest.raises(motorbus.LeaseConflictError):
            Streamer(other.bus()).follow(InspireLA(other.bus(), 1), [100, 200])
        await asyncio.wait_for(stream.wait(), 30)
        # Its safe action was "hold": la:1 is this client's again, nothing sent.
        assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "program")]
        assert not [f for f in after_last_broadcast(la_sim) if isinstance(f, la.Control)]
    # The client ended: its end pauses what it held, as a local bus's close does.
    pause = la.decode_request(la.Control(1, la.ControlAction.PAUSE).encode())
    await eventually(lambda: pause in after_last_broadcast(la_sim), "the pause of la:1")
    assert la.MoveTo(1, 100, True) not in frames(la_sim)


def test_motorbus_stream_connect_refuses_the_servers_own_options(tmp_path: Path) -> None:
    csv = tmp_path / "path.csv"
    csv.write_text("t,1\n0,100\n0.01,110\n")
    done = run_motorbus(["stream", str(csv), "--connect", "tcp/127.0.0.1:9", "--guard"])
    assert done.returncode == 2
    assert "--connect" in done.stderr and "--guard" in done.stderr


async def test_a_stream_started_under_the_tasks_lease_runs_under_it_and_ends_with_its_pause(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    pause = la.Control(1, la.ControlAction.PAUSE)
    async with motorbus.connect(endpoint) as site, motorbus.connect(endpoint) as other:
        bus = site.bus()
        lease = bus.lease(["la:1"], owner="jig")  # bound to this task
        mine = [("la:1", f"jig (client {site.client_id})")]
        # A stream of an actuator the lease does not hold would be a second owner.
        with pytest.raises(motorbus.LeaseConflictError):
            Streamer(bus).follow([InspireLA(bus, 1), InspireLA(bus, 2)], [(500, 500)] * 10)
        stream = Streamer(bus).follow(
            InspireLA(bus, 1), [700 + n for n in range(60)], period=0.01, safe_action="pause"
        )
        await eventually(lambda: len(targets_at_sim(la_sim)) >= 5, "the stream to run")
        # One owner: the lease, not a stream's own.
        assert [(i.key, i.owner) for i in other.bus().leases] == mine
        await asyncio.wait_for(stream.wait(), 30)
        assert stream.error is None and stream.origin > 0
        assert pause in after_last_broadcast(la_sim)  # the stream's safe action
        assert [(i.key, i.owner) for i in other.bus().leases] == mine  # still the lease's
        # Releasing the lease stops its running stream first, with its pause.
        second = Streamer(bus).follow(InspireLA(bus, 1), [800] * 3000, safe_action="pause")
        await eventually(lambda: (800,) in targets_at_sim(la_sim), "the second stream to run")
        await lease.release()
        await asyncio.wait_for(second.wait(), 10)
        assert pause in after_last_broadcast(la_sim)
        assert list(other.bus().leases) == []


async def _steady_stream(bus: Any, la_sim: SimProcess) -> Any:
    """A stream holding la:1 and la:2 still ("pause" at its end), five ticks in."""
    stream = Streamer(bus).follow(
        [InspireLA(bus, 1), InspireLA(bus, 2)],
        lambda t, s: (800, 1200),
        period=0.01,
        safe_action="pause",
    )
    await eventually(lambda: len(targets_at_sim(la_sim)) >= 5, "5 ticks at the simulator")
    return stream


async def test_an_estop_from_another_program_ends_the_served_stream(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    """A new user's report: an e-stop from outside left the served stream running (its
    ``wait()`` returned normally, targets went on after the e-stop), and the stream's
    pause at its end lifted the e-stop's latch."""
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        stream = await _steady_stream(bus, la_sim)
        done = run_motorbus(["la", "estop", "1", "--connect", endpoint])
        assert done.returncode == 0, done.stderr
        with pytest.raises(StreamEnded, match=r"la:1 \(ESTOP\) stopped"):
            await asyncio.wait_for(stream.wait(), 30)
    seen = frames(la_sim)
    estop = la.Control(1, la.ControlAction.ESTOP)
    after = seen[min(n for n, f in enumerate(seen) if f == estop) + 1 :]
    assert not any(isinstance(f, la.Broadcast) for f in after), after
    # The stream's own end: its pause, an e-stop for la:1 (a pause would lift the latch).
    assert la.Control(2, la.ControlAction.PAUSE) in after
    assert la.Control(1, la.ControlAction.PAUSE) not in after and estop in after


async def test_a_server_closing_mid_stream_ends_it_with_an_error_the_client_sees(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    """A new user's report: a served stream the server's SIGTERM cut short ended as if
    its targets had run out (``wait()`` returned); now ``wait()`` says why."""
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        stream = await _steady_stream(bus, la_sim)
        la_server.finish(signal.SIGTERM)
        with pytest.raises(StreamEnded, match="the server is closing"):
            await asyncio.wait_for(stream.wait(), 30)
    assert set(after_last_broadcast(la_sim)) >= {la.decode_request(p) for p in PAUSES}
