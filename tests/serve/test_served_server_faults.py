"""The server's own faults: killed with a request in flight (with and without its
guard); requests that name no served key or a wildcard; one client's motion on a device
another client leases."""

from __future__ import annotations

import asyncio
import signal

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import BusClosedError, InspireLA, LeaseConflictError
from motorbus.protocol import la
from motorbus.serve import keys as k
from motorbus.sim import SimProcess
from tests.serve.conftest import Child, serve
from tests.serve.test_served_bus import requests_to_sim
from tests.serve.test_served_faults import raw_query
from tests.waiting import eventually

#: No device answers ID 9: the server waits out the request's whole deadline.
SILENT = la.Control(9, la.ControlAction.QUERY_STATUS)
PAUSE_1 = la.Control(1, la.ControlAction.PAUSE).encode()
ESTOP_2 = la.Control(2, la.ControlAction.ESTOP).encode()


@pytest.mark.parametrize("guard", [False, True], ids=["no-guard", "guard"])
async def test_the_server_killed_with_a_request_in_flight(
    la_sim: SimProcess, endpoint: str, guard: bool
) -> None:
    server = serve(la_sim.path, 921600, "la:1-2", endpoint, *(["--guard"] if guard else []))
    try:
        async with motorbus.connect(endpoint) as site:
            bus = site.bus()
            await InspireLA(bus, 1).move_to(1500)  # the client's implicit lease
            bus.lease("la:2", owner="arm", safe_action="estop")
            await InspireLA(bus, 2).move_to(1700)
            in_flight = asyncio.ensure_future(bus.request(SILENT, timeout=60, retries=0))
            await eventually(
                lambda: SILENT.encode() in requests_to_sim(la_sim), "the request on the wire"
            )
            moved = len(requests_to_sim(la_sim))
            server.finish(signal.SIGKILL)
            # The client learns at once (the server's token and link go), far inside the
            # request's own 60 s: BusClosedError, no hang.
            async with asyncio.timeout(15):
                with pytest.raises(BusClosedError):
                    await in_flight
            # The query's own end may come before the server's token is seen to go.
            await eventually(lambda: site.state == "lost", "the client to see the server gone")
            with pytest.raises(BusClosedError):
                await InspireLA(bus, 1).status()
        if guard:
            # The guard saw its program die and stopped every leased device with the
            # lease's own safe action.
            await eventually(
                lambda: {PAUSE_1, ESTOP_2} <= set(requests_to_sim(la_sim)[moved:]),
                "the guard's pause of la:1 and e-stop of la:2",
            )
        else:
            # Without a guard nothing is left to stop them (docs/guard.md): the devices
            # keep what they were last told.
            await asyncio.sleep(1.0)
            assert requests_to_sim(la_sim)[moved:] == []
    finally:
        server.finish(signal.SIGKILL)


async def test_a_key_no_server_serves_is_a_clear_error_and_sends_nothing(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    move = {"frame": la.MoveTo(1, 300, True).encode().hex()}
    async with motorbus.connect(endpoint) as site:
        before = requests_to_sim(la_sim)
        for key in (k.bus_key("nope", "request"), k.bus_key("bus", "frobnicate")):
            with pytest.raises(BusClosedError, match=f"no motorbus server answered {key}"):
                await site._query(key, move, 5.0)
        assert requests_to_sim(la_sim) == before
        assert (await InspireLA(site.bus(), 1).status()).id == 1


@pytest.mark.parametrize("what", ["request", "lease"])
@pytest.mark.parametrize("key", ["motorbus/v1/bus/*/{what}", "motorbus/v1/bus/**/{what}"])
def test_a_wildcard_request_or_lease_is_refused_and_moves_nothing(
    la_sim: SimProcess, la_server: Child, endpoint: str, what: str, key: str
) -> None:
    # One query to .../bus/*/request would otherwise reach every bus's queryable.
    body = {"client": "x", "frame": la.MoveTo(1, 300, True).encode().hex()}
    if what == "lease":
        body = {"client": "x", "op": "acquire", "keys": ["la:1"], "owner": "x"}
    answer = raw_query(endpoint, key.format(what=what), k.encode_json(body))
    assert answer["ok"] is False and answer["error"] == "bad_payload"
    assert answer["field"] == "key" and "without wildcards" in str(answer["message"])
    assert la.MoveTo(1, 300, True).encode() not in requests_to_sim(la_sim)
    leases = raw_query(endpoint, k.bus_key("bus", "leases"), b"{}")
    assert leases["leases"] == []


async def test_a_client_moving_what_another_client_leases_is_refused_naming_the_holder(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint, name="arm") as holder:
        lease = holder.bus().lease("la:2", owner="gripper", safe_action="estop")
        async with motorbus.connect(endpoint, name="other") as other:
            bus = other.bus()
            before = requests_to_sim(la_sim)
            with pytest.raises(LeaseConflictError) as moved:
                await InspireLA(bus, 2).move_to(900)
            assert moved.value.key == "la:2"
            assert moved.value.owner == f"gripper (client {holder.client_id})"
            with pytest.raises(LeaseConflictError) as leased:
                bus.lease("la:2", owner="thief")
            assert leased.value.owner == moved.value.owner
            assert requests_to_sim(la_sim) == before  # nothing sent
            # Its own devices are its own: la:1 moves.
            await InspireLA(bus, 1).move_to(600)
        await lease.release()
    assert la.MoveTo(2, 900, True).encode() not in requests_to_sim(la_sim)
