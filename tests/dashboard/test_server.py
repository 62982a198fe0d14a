"""The dashboard's server against in-memory simulators, served as the command serves it:
snapshots on the WebSocket, one poller whatever the number of viewers, the controls
refused without control and reaching the simulator with it, the token and the origin."""

from __future__ import annotations

import asyncio
import csv
import json
import re
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("aiohttp")

from aiohttp import WSMsgType

from motorbus import Bus, Family
from motorbus.bus.timer import default_timer
from motorbus.dashboard import BusSetup, Dashboard
from motorbus.dashboard.server import LANE_KEY, make_app
from motorbus.errors import LocalProtocolError
from motorbus.protocol import framelog, la
from motorbus.protocol.base import format_hex
from motorbus.sim.bus import LogRecord
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from tests.dashboard.page import PageClient, page_client
from tests.helpers import LOADED_HOST_MARGIN_MS

IDS = (1, 2, 3)
PERIOD = 0.03
#: Generous bound on waiting for something the dashboard does (not a speed claim).
WAIT_S = 10.0


@dataclass
class Rig:
    client: PageClient
    dash: Dashboard
    bus: Bus
    models: dict[int, LAModel]
    log: list[LogRecord] = field(default_factory=list)
    lane: Any = None  # the viewers' lane (dashboard/lanes.py) of the page being served

    def requests(self) -> list[str]:
        """Hex of every frame the simulator received."""
        return [str(r["hex"]) for r in self.log if r.get("dir") == "rx"]

    async def wait_for(self, what: Callable[[], bool]) -> None:
        async with asyncio.timeout(WAIT_S):
            while not what():
                await asyncio.sleep(0.01)

    async def rounds(self, n: int) -> None:
        """Wait until the poller has completed ``n`` more rounds."""
        target = self.dash.rounds["arm"] + n
        await self.wait_for(lambda: self.dash.rounds["arm"] >= target)


@asynccontextmanager
async def served(
    *,
    control: bool,
    token: str | None = None,
    window: tuple[int, int] = (0, 2000),
    record_dir: Path | None = None,
) -> AsyncIterator[Rig]:
    timer = default_timer()
    models = {i: LAModel(i, position=300.0, stroke_speed=2000.0) for i in IDS}
    log: list[LogRecord] = []
    async with MemorySim.start(list(models.values()), timer=timer, log=log.append) as sim:
        # No test here waits for a timeout: a loaded run's late replies must not make one.
        bus = Bus(
            sim.transport,
            name="arm",
            families=[Family.LA],
            timer=timer,
            host_margin=LOADED_HOST_MARGIN_MS / 1e3,
        )
        async with bus:
            dash = Dashboard([BusSetup(bus, list(IDS))], period=PERIOD, control=control,
                             window=window)  # fmt: skip
            app = make_app(dash, token=token, push_hz=20.0, record_dir=record_dir)
            async with page_client(app) as client:
                await dash.start()
                try:
                    yield Rig(client, dash, bus, models, log, app[LANE_KEY])
                finally:
                    await dash.stop()


def frame(ident: int, action: la.ControlAction) -> str:
    return format_hex(la.Control(ident, action).encode())


QUERIES = {frame(i, la.ControlAction.QUERY_STATUS) for i in IDS}


async def test_a_viewer_gets_a_full_snapshot_then_deltas_with_live_values() -> None:
    async with served(control=False) as rig:
        await rig.rounds(2)
        async with rig.client.ws_connect("/ws") as ws:
            first = json.loads((await ws.receive(timeout=WAIT_S)).data)
            assert first["type"] == "full" and first["control"] is False
            (bus,) = first["buses"]
            assert bus["name"] == "arm" and bus["state"] == "open"
            assert [d["id"] for d in bus["la"]] == list(IDS)
            assert all(d["latest"]["position"] == 300 for d in bus["la"])
            assert len(bus["la"][0]["series"]["t"]) >= 2
            second = json.loads((await ws.receive(timeout=WAIT_S)).data)
            assert second["type"] == "delta" and second["seq"] >= first["seq"]
            assert bus["requests"] > 0 and bus["poll_load"] > 0


async def test_a_viewer_offering_compression_as_browsers_do_gets_none() -> None:
    # Deflating the one snapshot once per viewer took the CPU an e-stop needed: with 50
    # browser-like viewers the served e-stop went from ~6 to ~60 ms (bench_dashboard.py).
    async with served(control=False) as rig, rig.client.ws_connect("/ws", compress=15) as ws:
        first = json.loads((await ws.receive(timeout=WAIT_S)).data)
        assert first["type"] == "full"
        assert ws.compress == 0  # permessage-deflate was not agreed


async def test_five_viewers_make_the_same_bus_traffic_as_one() -> None:
    async with served(control=False) as rig:
        received: list[int] = []

        async def view(n: int) -> None:
            async with rig.client.ws_connect("/ws") as ws:
                async for msg in ws:
                    assert msg.type == WSMsgType.TEXT
                    received[n] += 1

        async def window(viewers: int) -> tuple[int, int, list[str]]:
            received[:] = [0] * viewers
            tasks = [asyncio.create_task(view(n)) for n in range(viewers)]
            await rig.wait_for(lambda: all(received))  # every viewer is connected
            # Over a window of whole poll rounds: the frames of exactly those rounds.
            await rig.rounds(1)
            start, before = rig.dash.rounds["arm"], len(rig.requests())
            requests_before = rig.bus.stats.requests
            await rig.rounds(10)
            frames = rig.requests()[before:]
            rounds = rig.dash.rounds["arm"] - start
            sent = rig.bus.stats.requests - requests_before
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            assert min(received) >= 2, received  # every viewer was fed during the window
            return rounds, sent, frames

        rounds1, sent1, frames1 = await window(1)
        rounds5, sent5, frames5 = await window(5)
        # Within a round's granularity: the counts are read up to a round after its
        # edges (10 ms apart, longer on a loaded run: 33 requests in 10 rounds of 3 seen),
        # never more.  Five viewers' own traffic would be 15 a round.
        assert abs(sent1 - len(IDS) * rounds1) <= len(IDS)
        assert abs(sent5 - len(IDS) * rounds5) <= len(IDS)
        assert abs(sent5 / rounds5 - sent1 / rounds1) <= 2 * len(IDS) / rounds1
        assert set(frames1) == set(frames5) == QUERIES  # viewers send nothing of their own


async def test_without_control_every_write_is_refused_and_nothing_is_sent() -> None:
    async with served(control=False) as rig:
        await rig.rounds(1)
        for path, body in [
            ("/api/estop", {}),
            ("/api/estop", {"bus": "arm", "id": 1}),
            ("/api/pause", {"bus": "arm"}),
            ("/api/work", {"bus": "arm", "id": 2}),
            ("/api/clear_fault", {"bus": "arm", "id": 2}),
            ("/api/move", {"bus": "arm", "id": 1, "position": 900, "confirm": True}),
            ("/api/record", {"on": True}),
        ]:
            r = await rig.client.post(path, json=body)
            assert r.status == 403, path
            assert "--control" in (await r.json())["error"]
        await rig.rounds(2)
        assert set(rig.requests()) == QUERIES
        assert all(m.target == 300 for m in rig.models.values())


async def test_with_control_a_bus_estop_reaches_every_actuator() -> None:
    async with served(control=True) as rig:
        await rig.rounds(1)
        r = await rig.client.post("/api/estop", json={"bus": "arm"})
        assert r.status == 200
        results = (await r.json())["results"]
        assert [x["device"] for x in results] == ["la:1", "la:2", "la:3"]
        assert all(x["ok"] for x in results), results
        sent = rig.requests()
        for i in IDS:
            assert frame(i, la.ControlAction.ESTOP) in sent
        await rig.rounds(1)
        snap = json.loads(rig.dash.message())
        assert [d["mode"] for d in snap["buses"][0]["la"]] == ["estop"] * 3
        assert any("estop arm" in e["text"] for e in snap["buses"][0]["events"])


async def test_move_needs_confirmation_and_a_position_inside_the_window() -> None:
    async with served(control=True, window=(200, 1800)) as rig:
        await rig.rounds(1)
        for body in (
            {"bus": "arm", "id": 1, "position": 900},  # no confirm
            {"bus": "arm", "id": 1, "position": 1900, "confirm": True},
            {"bus": "arm", "id": 9, "position": 900, "confirm": True},
            {"bus": "nope", "id": 1, "position": 900, "confirm": True},
        ):
            r = await rig.client.post("/api/move", json=body)
            assert r.status == 400, body
        assert "allowed 200..1800" in str(
            await (await rig.client.post("/api/move", json={
                "bus": "arm", "id": 1, "position": 1900, "confirm": True})).json()
        )  # fmt: skip
        assert set(rig.requests()) == QUERIES  # nothing was sent for a refused move
        r = await rig.client.post(
            "/api/move", json={"bus": "arm", "id": 1, "position": 900, "confirm": True}
        )
        assert r.status == 200
        assert format_hex(la.MoveTo(1, 900).encode()) in rig.requests()
        await rig.wait_for(lambda: rig.models[1].position == 900)


async def test_exit_pauses_what_the_dashboard_moved_and_nothing_else() -> None:
    async with served(control=True) as rig:
        r = await rig.client.post(
            "/api/move", json={"bus": "arm", "id": 2, "position": 700, "confirm": True}
        )
        assert r.status == 200
        await rig.dash.stop()
        pauses = [h for h in rig.requests() if h not in QUERIES and "MoveTo" not in h]
        assert pauses[-1] == frame(2, la.ControlAction.PAUSE)
        assert frame(1, la.ControlAction.PAUSE) not in pauses
    async with served(control=True) as rig:
        await rig.rounds(2)
        await rig.dash.stop()
        assert set(rig.requests()) == QUERIES  # watching only: nothing sent on exit


async def test_a_fault_in_the_simulator_appears_by_name_on_the_websocket() -> None:
    async with served(control=False) as rig, rig.client.ws_connect("/ws") as ws:
        await ws.receive(timeout=WAIT_S)
        rig.models[2].trigger_fault("stall", rig.bus.timer.now())
        # The status poll that reads the fault and the bus's fault event come one after
        # the other, not always in one snapshot (a loaded machine): wait for both.
        event = {"text": "la:2 faults: STALL"}.items()
        async with asyncio.timeout(WAIT_S):
            while True:
                snap = json.loads((await ws.receive()).data)
                dev = snap["buses"][0]["la"][1]
                events = [e for e in snap["buses"][0]["events"] if event <= e.items()]
                if dev["errors"] and events:
                    break
        assert dev["errors"] == ["STALL"]


async def test_the_token_is_required_everywhere_when_set() -> None:
    async with served(control=True, token="s3cret") as rig:
        assert (await rig.client.get("/")).status == 401
        assert (await rig.client.get("/api/state")).status == 401
        assert (await rig.client.post("/api/estop", json={})).status == 401
        r = await rig.client.get("/ws")
        assert r.status == 401
        assert (await rig.client.get("/?token=wrong")).status == 401
        page = await rig.client.get("/?token=s3cret")
        assert page.status == 200 and "motorbus dashboard" in await page.text()
        async with rig.client.ws_connect("/ws?token=s3cret") as ws:
            assert json.loads((await ws.receive(timeout=WAIT_S)).data)["type"] == "full"
        await rig.rounds(1)  # a whole round since: every ID has been polled
        assert set(rig.requests()) == QUERIES  # the refused e-stop sent nothing


async def test_a_page_of_another_origin_is_refused() -> None:
    async with served(control=True) as rig:
        evil = {"Origin": "http://evil.example"}
        r = await rig.client.post("/api/estop", json={}, headers=evil)
        assert r.status == 403
        r = await rig.client.get("/ws", headers=evil)
        assert r.status == 403
        own = {"Origin": f"http://{rig.client.host}:{rig.client.port}"}
        async with rig.client.ws_connect("/ws", headers=own) as ws:
            assert json.loads((await ws.receive(timeout=WAIT_S)).data)["type"] == "full"
        await rig.rounds(1)  # a whole round since: every ID has been polled
        assert set(rig.requests()) == QUERIES  # the refused e-stop sent nothing


async def test_a_dns_rebinding_request_is_refused_and_sends_nothing() -> None:
    # The attack of issue 39: a page of another site whose name now points at 127.0.0.1
    # sends Host and Origin of its own name; they agree with each other, not with us.
    async with served(control=True) as rig:
        await rig.rounds(1)
        before = len(rig.requests())
        port = rig.client.port
        rebound = {
            "Host": f"rebind.attacker.example:{port}",
            "Origin": f"http://rebind.attacker.example:{port}",
        }
        r = await rig.client.post(
            "/api/move",
            json={"bus": "arm", "id": 1, "position": 1777, "confirm": True},
            headers=rebound,
        )
        assert r.status == 403
        assert "rebind.attacker.example" in (await r.json())["error"]
        for method, path in [("GET", "/api/state"), ("GET", "/"), ("GET", "/ws"),
                             ("POST", "/api/estop")]:  # fmt: skip
            r = await rig.client.request(method, path, headers=rebound)
            assert r.status == 403, path
        r = await rig.client.get("/api/state", headers={"Host": f"localhost:{port}"})
        assert r.status == 200  # a loopback name is one this server answers to
        await rig.rounds(1)  # a whole round since: every ID has been polled
        assert set(rig.requests()[before:]) == QUERIES  # the refused move sent nothing
        assert all(m.target == 300 for m in rig.models.values())


async def test_the_page_is_self_contained() -> None:
    async with served(control=False) as rig:
        r = await rig.client.get("/")
        page = await r.text()
        assert "default-src 'none'" in r.headers["Content-Security-Policy"]
        assert "connect-src 'self'" in r.headers["Content-Security-Policy"]
        assert "http://" not in page and "https://" not in page and "src=" not in page


async def test_recording_writes_a_frame_log_and_the_plotted_values(tmp_path: Path) -> None:
    async with served(control=True, record_dir=tmp_path / "rec") as rig:
        r = await rig.client.post("/api/record", json={"on": True})
        assert r.status == 200
        files = (await r.json())["files"]
        assert json.loads(rig.dash.message())["recording"] == str(tmp_path / "rec")
        await rig.rounds(3)
        r = await rig.client.post("/api/record", json={"on": False})
        assert r.status == 200 and rig.dash.recorder is None
    log_path, csv_path = (Path(f) for f in files)
    log = framelog.read_frame_log(log_path.read_text().splitlines())
    assert log.headers[0]["source"] == "dashboard" and log.headers[0]["families"] == ["la"]
    names = [(r["direction"], r["name"]) for r in log.records]
    assert ("request", "Control") in names and ("reply", "Status") in names
    assert {r["fields"]["id"] for r in log.records} == set(IDS)
    times = [r["t"] for r in log.records]
    assert times == sorted(times) and times[0] >= 0
    rows = list(csv.DictReader(csv_path.open()))
    assert len(rows) >= 2 * len(IDS)  # at least two whole rounds
    assert {int(row["id"]) for row in rows} == set(IDS)
    assert all(row["position"] == "300" and row["bus"] == "arm" for row in rows)


async def test_a_lost_port_shows_and_the_poller_carries_on_after_the_reconnect() -> None:
    async with served(control=False) as rig, rig.client.ws_connect("/ws") as ws:
        await ws.receive(timeout=WAIT_S)
        link = rig.bus.transport
        link.peer.unplug()  # type: ignore[attr-defined]
        states: list[str] = []

        async def state_until(wanted: str) -> dict[str, Any]:
            async with asyncio.timeout(WAIT_S):
                while True:
                    bus = json.loads((await ws.receive()).data)["buses"][0]
                    states.append(bus["state"])
                    if bus["state"] == wanted:
                        return dict(bus)

        await state_until("reconnecting")
        link.peer.plug()  # type: ignore[attr-defined]
        bus = await state_until("open")
        texts = [e["text"] for e in bus["events"]]
        assert any(t.startswith("bus lost") for t in texts)
        assert "bus open (reconnected)" in texts
        await rig.rounds(2)  # polling again


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"period": 0.0}, "period=0.0 s is out of range: allowed 0.001..3600 s"),
        ({"window": (-1, 100)}, "window low=-1 is out of range"),
        ({"window": (900, 100)}, "window high=100 is out of range: allowed 900..2000"),
    ],
)
def test_bad_settings_are_refused_when_the_dashboard_is_built(
    options: dict[str, Any], message: str
) -> None:
    with pytest.raises(LocalProtocolError, match=re.escape(message)):
        Dashboard([], **options)


@pytest.mark.parametrize(
    ("listen", "allowed", "host", "ok"),
    [
        ("127.0.0.1", [], "127.0.0.1:8765", True),
        ("127.0.0.1", [], "LOCALHOST:8765", True),
        ("127.0.0.1", [], "[::1]:8765", True),
        ("127.0.0.1", [], "rebind.attacker.example:8765", False),
        ("127.0.0.1", [], "127.0.0.1.attacker.example", False),
        ("127.0.0.1", [], None, False),
        ("127.0.0.1", ["robot.local"], "robot.local:8765", True),
        ("127.0.0.1", ["robot.local"], "robot.local.:8765", True),
        ("192.0.2.7", [], "192.0.2.7:8765", True),
        ("192.0.2.7", [], "localhost:8765", False),
        ("0.0.0.0", [], "192.0.2.7:8765", True),
        ("0.0.0.0", [], "[2001:db8::1]:8765", True),
        ("0.0.0.0", [], "rebind.attacker.example", False),
    ],
)
def test_the_host_names_a_dashboard_answers_to(
    listen: str, allowed: list[str], host: str | None, ok: bool
) -> None:
    from motorbus.cli.dashboard import host_check

    assert host_check(listen, allowed).allows(host) is ok


def test_an_allowed_host_that_is_not_a_name_is_refused_at_start() -> None:
    from motorbus.cli.dashboard import host_check

    with pytest.raises(LocalProtocolError, match="--allow-host='http://x/'"):
        host_check("127.0.0.1", ["http://x/"])


async def test_viewers_connecting_between_two_pushes_share_one_snapshot_build(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async with served(control=False) as rig:
        await rig.rounds(1)
        builds: list[int | None] = []
        real = rig.dash.state.snapshot

        def counted(since: int | None = None, **kw: Any) -> dict[str, Any]:
            builds.append(since)
            return real(since, **kw)

        monkeypatch.setattr(rig.dash.state, "snapshot", counted)
        rig.dash.pushed()
        first = rig.dash.for_new_viewer()
        assert rig.dash.for_new_viewer() is first  # no push in between
        assert builds.count(None) == 1  # one full build for both viewers
        # A new sample (a round can pass without one: on a loaded run its polls time out).
        await rig.wait_for(lambda: rig.dash.state.seq > json.loads(first)["seq"])
        rig.dash.pushed()
        again = rig.dash.for_new_viewer()
        assert again is not first
        assert json.loads(again)["seq"] > json.loads(first)["seq"]  # fresh after a push
        assert rig.dash.message() is not again  # message() itself is always built anew


async def test_a_push_while_a_viewer_gets_its_snapshot_reaches_it_after_the_snapshot(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The push that goes out between a new viewer's snapshot and its joining the
    # viewers, as a loaded machine made it: held back here until such a push went.
    async with served(control=False) as rig:
        await rig.rounds(2)
        pushed_at: list[int] = []  # the dashboard's seq as each push was built
        real_broadcast, real_snapshot = rig.lane.broadcast, rig.lane._snapshot

        def broadcast(text: str) -> None:
            pushed_at.append(rig.dash.state.seq)
            real_broadcast(text)

        async def snapshot() -> Callable[[], str]:
            render = await real_snapshot()
            taken = rig.dash.state.seq
            # Until a push carried samples newer than the snapshot.
            await rig.wait_for(lambda: any(seq > taken for seq in pushed_at))
            return render

        async with rig.client.ws_connect("/ws") as first:  # the pushes go out for it
            await first.receive(timeout=WAIT_S)
            monkeypatch.setattr(rig.lane, "broadcast", broadcast)
            monkeypatch.setattr(rig.lane, "_snapshot", snapshot)
            async with rig.client.ws_connect("/ws") as ws:
                seen: list[float] = []
                types = []
                for _ in range(4):
                    msg = json.loads((await ws.receive(timeout=WAIT_S)).data)
                    types.append(msg["type"])
                    seen += msg["buses"][0]["la"][0]["series"]["t"]
                state = rig.dash.state
                held = [state._rel(s[1]) for s in state.buses["arm"].la[1].samples]
        assert types[0] == "full" and "full" not in types[1:], types
        span = [t for t in held if min(seen) <= t <= max(seen)]
        assert len(span) >= 4 and set(span) <= set(seen), sorted(set(span) - set(seen))


async def test_a_viewer_gets_every_sample_across_its_snapshot_and_the_pushes() -> None:
    async with served(control=False) as rig:
        await rig.rounds(2)
        async with rig.client.ws_connect("/ws") as ws:
            seen: list[float] = []
            for _ in range(6):
                snap = json.loads((await ws.receive(timeout=WAIT_S)).data)
                (bus,) = snap["buses"]
                seen += bus["la"][0]["series"]["t"]
            # No gap: every sample of la:1 the dashboard holds within the span the viewer
            # saw reached the viewer, in its snapshot or a push.
            state = rig.dash.state
            held = [state._rel(s[1]) for s in state.buses["arm"].la[1].samples]
        span = [t for t in held if min(seen) <= t <= max(seen)]
        assert len(span) >= 6 and set(span) <= set(seen)
