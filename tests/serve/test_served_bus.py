"""A served bus against simulators over ptys, with client and server in separate
processes: requests, leases, the deadman and the faults of issue 39."""

from __future__ import annotations

import asyncio
import signal
import time

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import BusClosedError, InspireLA, LeaseConflictError
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.sim import SimProcess
from tests.serve.conftest import Child, client, serve
from tests.waiting import eventually

PAUSE_1 = la.Control(1, la.ControlAction.PAUSE).encode()


def requests_to_sim(sim: SimProcess) -> list[bytes]:
    return [
        bytes.fromhex(r["hex"])
        for r in sim.log_records()
        if r["direction"] == "request" and r["kind"] == "frame"
    ]


async def test_served_status_move_and_the_clients_lease(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        assert site.bus("bus") is bus and bus.families == {motorbus.Family.LA}
        actuator = InspireLA(bus, 1)
        status = await actuator.status()
        assert status.id == 1
        moved = await actuator.move_to(1500)
        assert moved is not None and moved.target == 1500
        # The move is this client's: it shows as the program's, as on a local bus.
        assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "program")]
        await actuator.release()  # the safe action now: a pause
        assert bus.leases == ()
    sent = requests_to_sim(la_sim)
    assert la.MoveTo(1, 1500, True).encode() in sent
    assert sent.index(PAUSE_1) > sent.index(la.MoveTo(1, 1500, True).encode())


async def test_a_served_release_refuses_keys_that_name_no_device_here(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    # As a local bus's: a malformed key was passed on, and the server let go of nothing.
    async with motorbus.connect(endpoint) as site:
        bus = site.bus()
        await InspireLA(bus, 1).move_to(1500)
        lease = bus.lease("la:2", owner="arm")
        for keys in (["LA:1"], "bogus", 5, ["project_stepper"]):
            with pytest.raises(LocalProtocolError, match="key"):
                await bus.release(keys)
            with pytest.raises(LocalProtocolError, match="key"):
                await lease.release(keys=keys)
        assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "program"), ("la:2", "arm")]
        await lease.release(hold=True)
        await bus.release(["la:1"])
        assert bus.leases == ()
    assert requests_to_sim(la_sim)[-1] == PAUSE_1


async def test_a_clean_close_ends_the_clients_leases_with_their_safe_action(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint) as site:
        await InspireLA(site.bus(), 1).move_to(800)
    async with motorbus.connect(endpoint) as watcher:
        bus = watcher.bus()
        await eventually(lambda: bus.leases == (), "the closed client's lease to end")
        await eventually(
            lambda: requests_to_sim(la_sim)[-1:] == [PAUSE_1], "the pause at the simulator"
        )


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP])
async def test_the_deadman_pauses_what_a_killed_or_frozen_client_moved(
    la_sim: SimProcess, la_server: Child, endpoint: str, how: int
) -> None:
    child = client(endpoint, "await InspireLA(bus, 1).move_to(1200)")
    try:
        child.expect("ready")
        async with motorbus.connect(endpoint) as watcher:
            bus = watcher.bus()
            owners = [i.owner for i in bus.leases]
            assert len(owners) == 1 and owners[0].startswith("client child-")
            # Another client may not move what the child holds: refused, naming it.
            with pytest.raises(LeaseConflictError) as refused:
                await InspireLA(bus, 1).move_to(100)
            assert refused.value.owner == owners[0] and refused.value.key == "la:1"
            killed = time.monotonic()
            child.send(how)
            # SIGKILL closes its link at once; a frozen client goes silent and its
            # heartbeat runs out (--liveness 0.5 s).
            await eventually(lambda: bus.leases == (), "the deadman to end the lease")
            await eventually(
                lambda: requests_to_sim(la_sim)[-1:] == [PAUSE_1], "the pause at the simulator"
            )
            assert time.monotonic() - killed < 10
            assert la.MoveTo(1, 100, True).encode() not in requests_to_sim(la_sim)
            # Free now: the watcher may move it.
            await InspireLA(bus, 1).move_to(100)
    finally:
        child.finish(signal.SIGKILL)


async def test_explicit_leases_bind_motion_and_end_with_the_client(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    child = client(
        endpoint,
        """
        lease = bus.lease(["la:2"], owner="arm", safe_action="estop")
        await InspireLA(bus, 2).move_to(900)
        """,
    )
    try:
        child.expect("ready")
        async with motorbus.connect(endpoint) as watcher:
            bus = watcher.bus()
            infos = bus.leases
            assert [i.key for i in infos] == ["la:2"]
            assert infos[0].owner.startswith("arm (client child-")
            assert infos[0].safe_frames == (la.Control(2, la.ControlAction.ESTOP).encode(),)
            child.send(signal.SIGKILL)
            await eventually(lambda: bus.leases == (), "the child's lease to end")
            estop = la.Control(2, la.ControlAction.ESTOP).encode()
            await eventually(
                lambda: requests_to_sim(la_sim)[-1:] == [estop], "the e-stop at the simulator"
            )
    finally:
        child.finish(signal.SIGKILL)


async def test_the_server_killed_fails_requests_at_once_and_a_restart_ends_leases(
    la_sim: SimProcess, endpoint: str
) -> None:
    server = serve(la_sim.path, 921600, "la:1-2", endpoint)
    try:
        async with motorbus.connect(endpoint) as site:
            bus = site.bus()
            lease = bus.lease("la:1", owner="arm")
            await InspireLA(bus, 1).move_to(500)
            server.finish(signal.SIGKILL)
            async with asyncio.timeout(10):
                with pytest.raises(BusClosedError):
                    while True:  # until the client learns the server is gone
                        await InspireLA(bus, 1).status()
                        await asyncio.sleep(0.01)
            # The first request to fail may be one no server answered in time (a loaded
            # machine), just before the server's liveliness token is seen gone: then the
            # lease ends as that news arrives.
            await eventually(lambda: not lease.active, "the lease to end with the server")
            assert "went away" in lease.ended
            server = serve(la_sim.path, 921600, "la:1-2", endpoint)
            async with asyncio.timeout(20):
                while site.state != "open":
                    await asyncio.sleep(0.05)
            # Back: requests work again; the old lease is gone and says so.
            assert (await InspireLA(bus, 1).status()).id == 1
            assert bus.leases == ()
            with pytest.raises(BusClosedError, match="ended"):
                async with lease:
                    await InspireLA(bus, 1).move_to(700)
            assert la.MoveTo(1, 700, True).encode() not in requests_to_sim(la_sim)
    finally:
        server.finish()


def test_two_servers_on_one_port_the_second_is_refused_naming_the_holder(
    la_sim: SimProcess, la_server: Child
) -> None:
    from tests.serve.conftest import free_endpoint

    second = Child(
        [
            "python",
            "-m",
            "motorbus",
            "serve",
            "--port",
            la_sim.path,
            "--baud",
            "921600",
            "--devices",
            "la:1-2",
            "--listen",
            free_endpoint(),
        ]
    )
    second.proc.wait(timeout=30)
    err = second.finish()
    assert second.proc.returncode != 0
    assert f"PID {la_server.proc.pid}" in err
