"""``ServedDashboard`` against a stand-in for a served bus (in memory, no Zenoh): what it
asks of the server, at which priority, and what the page then shows."""

from __future__ import annotations

import asyncio
import json
from typing import Any, cast

from motorbus import Bus, Priority
from motorbus.bus.events import EventHub, FaultChanged
from motorbus.bus.lease_shell import SafeStopper
from motorbus.bus.leases import PROGRAM, LeaseInfo
from motorbus.bus.timer import default_timer
from motorbus.dashboard import BusSetup
from motorbus.dashboard.served import ServedDashboard
from motorbus.protocol import la
from motorbus.protocol.base import Command, Family
from tests.waiting import eventually


class FakeServedBus:
    """The members of ``ServedBus`` the dashboard uses; replies are canned statuses."""

    def __init__(self) -> None:
        self.name = "arm"
        self.families = frozenset({Family.LA})
        self.baudrate = 921600
        self.safe_action = "pause"
        self.events = EventHub()
        self.timer = default_timer()
        self.state = "open"
        self.sent: list[tuple[Command[Any], Priority]] = []
        self.stats_asked = 0
        self.requests = 0
        self.held: tuple[LeaseInfo, ...] = ()
        #: The error flags each actuator's status carries (as a device would keep them).
        self.errors: dict[int, int] = {}
        self.lease_keeper = SafeStopper(self.name, self.families, self.request)

    async def request(
        self,
        cmd: Command[Any],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> Any:
        self.sent.append((cmd, priority))
        await asyncio.sleep(0)
        if isinstance(cmd, la.Control) and cmd.action is la.ControlAction.QUERY_STATUS:
            return la.Status(cmd.id, 800, 700 + cmd.id, 31, 120, 50, self.errors.get(cmd.id, 0))
        return None

    async def fetch_stats(self) -> dict[str, Any]:
        self.stats_asked += 1
        self.requests += 50
        return {"requests": self.requests, "timeouts": 2, "latency": {"p50_us": 900}}

    @property
    def leases(self) -> tuple[LeaseInfo, ...]:
        return self.held


def status_of(sent: list[tuple[Command[Any], Priority]]) -> list[Priority]:
    return [
        p
        for c, p in sent
        if isinstance(c, la.Control) and c.action is la.ControlAction.QUERY_STATUS
    ]


async def test_polls_go_at_background_priority_and_an_estop_at_emergency() -> None:
    bus = FakeServedBus()
    bus.held = (LeaseInfo("la:2", PROGRAM, ()), LeaseInfo("la:1", "app", ()))
    setup = BusSetup(cast(Bus, bus), [1, 2], name="shown")
    dash = ServedDashboard([setup], endpoint="tcp/127.0.0.1:1", period=0.01, control=True)
    await dash.start()
    try:
        await eventually(lambda: dash.rounds["shown"] >= 3, "three poll rounds")
        # The counters asked twice and the rate taken from them (after the leases' read,
        # on a thread: a loaded run's snapshot came between the two, seen).
        await eventually(
            lambda: bus.stats_asked >= 2 and dash.state.frames_per_s("shown") > 0,
            "frames/s from the server's counters, asked twice",
        )
        outcome = await dash.act("estop", "shown", 1, source="test")
        assert outcome == [{"bus": "shown", "device": "la:1", "command": "Control", "ok": True}]
        # The fault as the server sees it: its event, and the statuses after it (each
        # poll shows the flags again; before, a poll could clear them before a look).
        bus.errors[2] = 1
        bus.events.publish(FaultChanged("arm", bus.timer.now(), 2, 0, 1, None))
        shown = dash.state.buses["shown"]
        await eventually(
            lambda: any(e.get("id") == 2 and e["kind"] == "FaultChanged" for e in shown.events),
            "the fault's event, on the shown bus",
        )
        assert shown.la[2].errors == 1
        snap = json.loads(dash.message())
    finally:
        await dash.stop()
    assert set(status_of(bus.sent)) == {Priority.BACKGROUND}
    estops = [p for c, p in bus.sent if c == la.Control(1, la.ControlAction.ESTOP)]
    assert estops == [Priority.EMERGENCY]
    (view,) = snap["buses"]
    assert view["name"] == "shown" and view["served"] == "tcp/127.0.0.1:1"
    assert [d["latest"]["position"] for d in view["la"]] == [701, 702]
    assert view["la"][0]["mode"] == "estop"  # from the frame the dashboard sent
    assert view["timeouts"] == 2 and view["latency"] == {"p50_us": 900}
    assert view["frames_per_s"] > 0  # from the server's counters
    assert view["min_write_gap_ms"] is None  # only the dashboard's own writes are seen
    assert view["leases"] == [
        {"key": "la:2", "owner": "this dashboard"},
        {"key": "la:1", "owner": "app"},
    ]


async def test_exit_sends_the_safe_action_to_what_it_moved_only() -> None:
    bus = FakeServedBus()
    dash = ServedDashboard(
        [BusSetup(cast(Bus, bus), [1, 2], la_safe_action="estop")],
        endpoint="tcp/127.0.0.1:1",
        control=True,
    )
    await dash.start()
    await dash.move_to("arm", 2, 1000, source="test")
    await dash.stop()
    assert (la.MoveTo(2, 1000), Priority.HIGH) in bus.sent
    stops = [(c, p) for c, p in bus.sent if isinstance(c, la.Control) and c.action is not
             la.ControlAction.QUERY_STATUS]  # fmt: skip
    assert stops == [(la.Control(2, la.ControlAction.ESTOP), Priority.EMERGENCY)]


async def test_a_new_viewers_snapshot_waits_for_an_estop_in_flight() -> None:
    from motorbus.dashboard.server import make_app
    from tests.dashboard.page import page_client

    order: list[str] = []
    release = asyncio.Event()

    class SlowEstopBus(FakeServedBus):
        async def request(self, cmd: Command[Any], **kw: Any) -> Any:
            if isinstance(cmd, la.Control) and cmd.action is la.ControlAction.ESTOP:
                self.sent.append((cmd, kw["priority"]))
                await release.wait()
                order.append("e-stop answered")
                return None
            return await super().request(cmd, **kw)

    bus = SlowEstopBus()
    dash = ServedDashboard([BusSetup(cast(Bus, bus), [1])], endpoint="tcp/x:1", control=True)
    async with page_client(make_app(dash)) as http:
        await dash.start()
        try:
            post = asyncio.create_task(http.post("/api/estop", json={"bus": "arm", "id": 1}))
            await eventually(lambda: any(p is Priority.EMERGENCY for _, p in bus.sent), "e-stop")
            async with http.ws_connect("/ws") as ws:
                first = asyncio.create_task(ws.receive())
                await asyncio.sleep(0.2)  # time enough for a snapshot that did not wait
                assert not first.done()
                release.set()
                msg = await asyncio.wait_for(first, 10)
                order.append("snapshot")
                assert json.loads(msg.data)["type"] == "full"
            assert (await post).status == 200
        finally:
            await dash.stop()
    assert order == ["e-stop answered", "snapshot"]
