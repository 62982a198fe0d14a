"""A client that has ended is gone from the server: a query of its that arrives after the
end (a query and the session's end travel apart) is refused, and nothing reaches the wire.
In one process (the server on a bus over an in-memory simulator), so that the late query
can be put exactly after the end."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import Bus
from motorbus.bus.timer import default_timer
from motorbus.errors import ServedRefusal
from motorbus.protocol import la
from motorbus.serve import BusServer
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from tests.serve.conftest import free_endpoint


async def test_a_query_that_arrives_after_its_clients_session_ended_sends_nothing() -> None:
    # A query and the end of its client's session travel apart (a query in flight when
    # the client was killed, or closed): if the end is handled first, the server used to
    # take the query for a new client's and serve it under a fresh lease, moving the
    # actuator after the deadman's pause.  It is refused, and nothing is sent.
    endpoint, records = free_endpoint(), []  # records: what the simulator received
    async with MemorySim.start(
        [LAModel(1)], baud=921600, timer=default_timer(), log=records.append
    ) as sim:
        bus = Bus(sim.transport, name="arm", host_margin=0.05, reconnect=False)
        async with bus, BusServer({"arm": bus}, listen=endpoint) as server:
            async with motorbus.connect(endpoint) as site:
                await site.bus().request(la.MoveTo(1, 1000, True))
                client = site.client_id
            async with asyncio.timeout(10):  # the session's end reaches the server
                while not server.deadman_ends:
                    await asyncio.sleep(0.01)
            late = la.MoveTo(1, 1500, True)
            with pytest.raises(ServedRefusal, match="session ended"):
                await server._request("arm", {"client": client, "frame": late.encode().hex()})
            read = la.Control(1, la.ControlAction.QUERY_STATUS)  # nor a read: no one awaits it
            with pytest.raises(ServedRefusal, match="session ended"):
                await server._request("arm", {"client": client, "frame": read.encode().hex()})
            await asyncio.sleep(0.05)
    sent = [bytes.fromhex(str(r["hex"])) for r in records if r["dir"] == "rx"]
    pause = la.Control(1, la.ControlAction.PAUSE).encode()
    assert la.MoveTo(1, 1000, True).encode() in sent and pause in sent
    assert late.encode() not in sent
    assert sent[-1] == pause  # the deadman's pause stays the last word
