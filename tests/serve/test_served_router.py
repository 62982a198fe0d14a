"""A site layout through Zenoh routers: the server connects to its site's router, a
client to another site's router, the two routers to each other; requests, leases and
the deadman work across them (docs/design.md, "A site of many hosts")."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import InspireLA
from motorbus.protocol import la
from motorbus.sim import SimProcess
from tests.serve.conftest import Child, client, free_endpoint, serve
from tests.serve.test_served_bus import requests_to_sim
from tests.waiting import eventually

ROUTER = """
import json, sys, time, zenoh
config = zenoh.Config()
config.insert_json5("mode", '"router"')
config.insert_json5("scouting/multicast/enabled", "false")
config.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
config.insert_json5("connect/endpoints", json.dumps(sys.argv[2:]))
with zenoh.open(config):
    print("routing", flush=True)
    time.sleep(600)
"""


def router(listen: str, *connect: str) -> Child:
    child = Child([sys.executable, "-c", ROUTER, listen, *connect])
    child.expect("routing")
    return child


@pytest.fixture
def two_sites(la_sim: SimProcess, tmp_path: Path) -> Iterator[str]:
    """Router A (the server's site), router B (the client's) linked to A; the server
    connects to A.  Yields router B's endpoint, the only one a client knows."""
    site_a = free_endpoint()
    site_b = free_endpoint()
    routers = [router(site_a)]
    routers.append(router(site_b, site_a))
    link = tmp_path / "to-router.json5"
    link.write_text(
        json.dumps(
            {"scouting": {"multicast": {"enabled": False}}, "connect": {"endpoints": [site_a]}}
        ),
        encoding="utf-8",
    )
    server = serve(la_sim.path, 921600, "la:1-2", free_endpoint(), "--zenoh-config", str(link))
    try:
        yield site_b
    finally:
        server.finish()
        for r in routers:
            r.finish()


async def test_a_client_at_another_site_drives_the_bus_and_its_deadman_holds(
    la_sim: SimProcess, two_sites: str
) -> None:
    async def reached() -> bool:
        try:
            async with motorbus.connect(two_sites) as site:
                return (await InspireLA(site.bus(), 1).status()).id == 1
        except motorbus.BusClosedError:  # the routes are still being made
            return False

    ok = False
    for _ in range(50):
        if ok := await reached():
            break
        await asyncio.sleep(0.1)
    assert ok, "no server reached through the routers"
    child = client(two_sites, "await InspireLA(bus, 2).move_to(1300)")
    try:
        child.expect("ready")
        async with motorbus.connect(two_sites) as watcher:
            bus = watcher.bus()
            assert [i.key for i in bus.leases] == ["la:2"]
            child.send(signal.SIGKILL)
            await eventually(lambda: bus.leases == (), "the deadman across the routers")
        pause = la.Control(2, la.ControlAction.PAUSE).encode()
        await eventually(lambda: requests_to_sim(la_sim)[-1:] == [pause], "the pause")
        assert la.MoveTo(2, 1300, True).encode() in requests_to_sim(la_sim)
    finally:
        child.finish(signal.SIGKILL)
