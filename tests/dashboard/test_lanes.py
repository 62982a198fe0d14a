"""The dashboard's two loops behind one address (``dashboard/lanes.py``): each new
connection is routed by its request line, the viewers run on a loop of their own, and
a control is answered while that loop is stuck."""

from __future__ import annotations

import asyncio
import json
import os
import sys
import threading

import pytest

pytest.importorskip("aiohttp")

from motorbus.dashboard import lanes
from motorbus.dashboard.lanes import PEEK_MAX, VIEWER_NICE, route
from motorbus.protocol import la
from tests.dashboard.test_server import WAIT_S, frame, served


@pytest.mark.parametrize(
    ("head", "where"),
    [
        (b"GET /ws HTTP/1.1\r\nHost: x\r\n\r\n", "viewers"),
        (b"GET /ws?token=abc HTTP/1.1\r\n", "viewers"),
        (b"GET /wsx HTTP/1.1\r\n", "control"),
        (b"GET / HTTP/1.1\r\n", "control"),
        (b"POST /ws HTTP/1.1\r\n", "control"),
        (b"POST /api/estop HTTP/1.1\r\n", "control"),
        (b"garbage\n", "control"),
        (b"GET /w", None),
        (b"", None),
        (b"G" * PEEK_MAX, "control"),
    ],
)
def test_a_connection_goes_where_its_request_line_says(head: bytes, where: str | None) -> None:
    assert route(head) == where


async def test_a_control_is_answered_while_the_viewers_loop_is_stuck() -> None:
    async with served(control=True) as rig:
        await rig.rounds(1)
        async with rig.client.ws_connect("/ws") as ws:
            assert json.loads((await ws.receive(timeout=WAIT_S)).data)["type"] == "full"
        lane = rig.lane
        assert lane.loop is not None and lane.loop is not asyncio.get_running_loop()
        stuck, release = threading.Event(), threading.Event()

        def block() -> None:  # the viewers' loop does nothing else until released
            stuck.set()
            release.wait(WAIT_S)

        lane.loop.call_soon_threadsafe(block)
        try:
            assert await asyncio.to_thread(stuck.wait, WAIT_S)
            r = await rig.client.post("/api/estop", json={"bus": "arm", "id": 2})
            assert r.status == 200, await r.text()
            assert not release.is_set()  # answered while the viewers' loop was stuck
            assert frame(2, la.ControlAction.ESTOP) in rig.requests()
            assert (await rig.client.get("/api/state")).status == 200
        finally:
            release.set()
        async with rig.client.ws_connect("/ws") as ws:  # and the viewers carry on
            assert json.loads((await ws.receive(timeout=WAIT_S)).data)["type"] == "full"


async def test_each_http_answer_closes_its_connection() -> None:
    async with served(control=False) as rig:
        r = await rig.client.get("/api/state")
        assert r.status == 200 and r.headers.get("Connection", "").lower() == "close"
        r = await rig.client.post("/api/estop", json={})
        assert r.status == 403 and r.headers.get("Connection", "").lower() == "close"


async def test_a_request_line_sent_in_pieces_is_routed_once_whole() -> None:
    async with served(control=False) as rig:
        reader, writer = await asyncio.open_connection("127.0.0.1", rig.client.port)
        writer.write(b"GE")
        await writer.drain()
        await asyncio.sleep(0.05)  # the server looks, finds no whole line, looks again
        writer.write(b"T /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        await writer.drain()
        status = await asyncio.wait_for(reader.readline(), WAIT_S)
        assert status.startswith(b"HTTP/1.1 200")
        writer.close()
        # A connection that closes before its request line is dropped quietly.
        _, quiet = await asyncio.open_connection("127.0.0.1", rig.client.port)
        quiet.close()
        await quiet.wait_closed()
        assert (await rig.client.get("/api/state")).status == 200


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a nice value per thread")
async def test_the_viewers_thread_runs_at_a_lower_cpu_priority_than_the_controls() -> None:
    async with served(control=False) as rig:
        tid = rig.lane._thread.native_id
        mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        assert os.getpriority(os.PRIO_PROCESS, tid) == min(19, mine + VIEWER_NICE)
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SCHED_FIFO per thread")
def test_the_viewers_thread_leaves_the_real_time_mode_it_inherits() -> None:
    seen: dict[str, int] = {}

    def viewers() -> None:  # started by a real-time thread, as the lane may be
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except PermissionError:
            return
        seen["before"] = os.sched_getscheduler(0)
        lanes._yield_to_the_controls()
        seen["after"] = os.sched_getscheduler(0)

    thread = threading.Thread(target=viewers)
    thread.start()
    thread.join()
    if not seen:
        pytest.skip("SCHED_FIFO is not allowed here")
    assert (seen["before"], seen["after"]) == (os.SCHED_FIFO, os.SCHED_OTHER)


async def test_a_connection_that_never_asks_is_closed_after_the_timeout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(lanes, "PEEK_TIMEOUT_S", 0.2)
    async with served(control=False) as rig:
        reader, writer = await asyncio.open_connection("127.0.0.1", rig.client.port)
        assert await asyncio.wait_for(reader.read(), WAIT_S) == b""  # closed by the server
        writer.close()
        assert (await rig.client.get("/api/state")).status == 200
