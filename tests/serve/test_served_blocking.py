"""A blocking program on a served bus (``motorbus.blocking.connect``): the server and
its simulators in processes of their own, the blocking clients in this process or in
children a test ends or kills.  The simulator's own record is the judge (what reached
the wire, in what order); nothing here asserts speed."""

from __future__ import annotations

import inspect
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable

import pytest

pytest.importorskip("zenoh")

import motorbus
import motorbus.blocking as mb
import motorbus.serve
from motorbus import LeaseConflictError, LocalProtocolError
from motorbus.bus.events import ProjectFinished, QuadDone
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.sim import SimProcess
from tests.serve.conftest import Child
from tests.serve.test_served_bus import requests_to_sim
from tests.serve.test_served_stream import after_last_broadcast, targets_at_sim
from tests.waiting import EVENTUALLY_TIMEOUT_S

PAUSE_1 = la.Control(1, la.ControlAction.PAUSE).encode()
PAUSE_2 = la.Control(2, la.ControlAction.PAUSE).encode()


def until(condition: Callable[[], object], what: str) -> None:
    """Wait (bounded) until ``condition()`` is true; fail naming ``what`` otherwise."""
    deadline = time.monotonic() + EVENTUALLY_TIMEOUT_S
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {EVENTUALLY_TIMEOUT_S:g} s for {what}")
        time.sleep(0.005)


#: Members of the asyncio ServedBus a blocking program reaches otherwise: ``submit``
#: gives an asyncio future (a blocking call is ``request``), ``served_streamer`` is
#: what ``mb.Streamer(bus)`` uses, ``hand_over``, ``lease_keeper`` and ``timer`` are
#: the device classes' and streams' own (a local blocking bus has none of them either).
INTERNAL = {"submit", "served_streamer", "hand_over", "lease_keeper", "timer"}


def test_the_blocking_served_bus_has_every_member_of_the_blocking_bus_and_the_served_one() -> None:
    local = {n for n in dir(mb.Bus) if not n.startswith("_")}
    served = {n for n in dir(mb.ServedBus) if not n.startswith("_")}
    assert local - served == set()
    aio = {n for n in dir(motorbus.serve.ServedBus) if not n.startswith("_")}
    aio |= {"name", "families", "baudrate", "safe_action", "events", "site"}  # attributes
    assert aio - INTERNAL - served == set()
    for name, member in inspect.getmembers(motorbus.serve.ServedBus):
        if inspect.iscoroutinefunction(member) and not name.startswith("_"):
            assert not inspect.iscoroutinefunction(getattr(mb.ServedBus, name)), name
    # The one thing a served bus does not have, and why: at the call, nothing sent.
    assert "fetch_stats" in (mb.ServedBus.stats.__doc__ or "")


def blocking_client(endpoint: str, body: str) -> Child:
    """A blocking program in its own process: ``body`` runs inside ``with
    mb.connect(endpoint, name="blocking") as site:`` with ``bus = site.bus()``; it
    prints "ready" and waits (in ``time.sleep``, not in a motorbus call) to be ended."""
    code = textwrap.dedent(
        """
        import sys, time
        import motorbus.blocking as mb

        with mb.connect(sys.argv[1], name="blocking") as site:
            bus = site.bus()
        {body}
            print("ready", flush=True)
            time.sleep(120)
        """
    ).format(body=textwrap.indent(textwrap.dedent(body), " " * 4))
    return Child([sys.executable, "-c", code, endpoint])


def test_status_move_group_read_and_the_lease_picture_through_a_served_bus(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    with mb.connect(endpoint, name="blocking") as site:
        bus = site.bus()
        assert site.bus("bus") is bus and site.buses == ("bus",)
        assert bus.families == {motorbus.Family.LA} and bus.state is motorbus.BusState.OPEN
        actuator = mb.InspireLA(bus, 1)
        assert actuator.status().id == 1
        moved = actuator.move_to(1500)
        assert moved is not None and moved.target == 1500
        assert sorted(bus.read_statuses([2, 1])) == [1, 2]
        # The move is this client's: it shows as the program's, as on a local bus.
        assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "program")]
        assert bus.fetch_stats()["requests"] >= 4  # the server bus's counters
        with pytest.raises(AttributeError, match="fetch_stats"):
            bus.stats  # noqa: B018
    assert site.closed and bus.state is motorbus.BusState.CLOSED
    sent = requests_to_sim(la_sim)
    move = la.MoveTo(1, 1500, True).encode()
    assert move in sent
    assert la.Control(1, la.ControlAction.QUERY_STATUS).encode() in sent[: sent.index(move)]


def test_closing_the_with_block_ends_the_lease_with_its_safe_action(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    with mb.connect(endpoint).bus() as bus:  # the served twin of `with mb.Bus(...) as bus:`
        lease = bus.lease(["la:2"], owner="arm", safe_action="pause")
        assert lease.active and lease.keys == {"la:2"}
        mb.InspireLA(bus, 2).move_to(900)
        assert [(i.key, i.owner) for i in bus.leases] == [("la:2", "arm")]
        moved = requests_to_sim(la_sim)
        assert PAUSE_2 not in moved  # nothing paused it while the program held it
    with mb.connect(endpoint, name="watcher") as watcher:
        until(lambda: watcher.bus().leases == (), "the closed client's lease to end")
        until(lambda: PAUSE_2 in requests_to_sim(la_sim), "the pause at the simulator")
    sent = requests_to_sim(la_sim)
    assert sent.index(PAUSE_2) > sent.index(la.MoveTo(2, 900, True).encode())


def test_a_lease_of_the_thread_and_its_release_with_the_with_block(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    with mb.connect(endpoint) as site:
        bus = site.bus()
        with bus.lease("la:1", owner="rig", safe_action="estop") as lease:
            bus.la(1).move_to(300)  # this thread holds the lease: its motion
            assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "rig")]
        assert not lease.active and bus.leases == ()
    sent = requests_to_sim(la_sim)
    estop = la.Control(1, la.ControlAction.ESTOP).encode()
    assert sent[sent.index(la.MoveTo(1, 300, True).encode()) + 1 :] == [estop]


def test_another_clients_command_is_refused_naming_the_blocking_holder_and_sigkill_gets_the_deadman(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    child = blocking_client(
        endpoint,
        """
        bus.lease(["la:2"], owner="arm", safe_action="pause")
        mb.InspireLA(bus, 2).move_to(900)
        """,
    )
    try:
        child.expect("ready")
        with mb.connect(endpoint, name="other") as site:
            bus = site.bus()
            infos = bus.leases
            assert [i.key for i in infos] == ["la:2"]
            holder = infos[0].owner
            assert holder.startswith("arm (client blocking-")
            with pytest.raises(LeaseConflictError) as refused:
                mb.InspireLA(bus, 2).move_to(100)
            assert refused.value.key == "la:2" and refused.value.owner == holder
            assert la.MoveTo(2, 100, True).encode() not in requests_to_sim(la_sim)
            child.send(signal.SIGKILL)  # nothing of the child runs: the server's deadman
            until(lambda: bus.leases == (), "the deadman to end the killed client's lease")
            until(lambda: requests_to_sim(la_sim)[-1:] == [PAUSE_2], "the pause at the sim")
            mb.InspireLA(bus, 2).move_to(100)  # free now
        sent = requests_to_sim(la_sim)
        assert sent.index(la.MoveTo(2, 900, True).encode()) < sent.index(PAUSE_2)
        assert sent.index(PAUSE_2) < sent.index(la.MoveTo(2, 100, True).encode())
    finally:
        child.finish(signal.SIGKILL)


@pytest.mark.parametrize("how", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_or_ctrl_c_closes_the_blocking_client_which_ends_its_lease(
    la_sim: SimProcess, la_server: Child, endpoint: str, how: int
) -> None:
    child = blocking_client(
        endpoint,
        """
        bus.lease(["la:1"], owner="arm", safe_action="pause")
        mb.InspireLA(bus, 1).move_to(700)
        """,
    )
    try:
        child.expect("ready")
        child.send(how)
        child.proc.wait(timeout=30)
        err = child.finish()
        # SIGTERM: the blocking runner's handler closed the connection first; Ctrl-C:
        # the KeyboardInterrupt left the `with` block, which closed it.
        if how == signal.SIGTERM:
            assert "SIGTERM: stopping the motion safely" in err, err
            assert child.proc.returncode == -signal.SIGTERM
        else:
            assert "KeyboardInterrupt" in err, err
        with mb.connect(endpoint, name="watcher") as watcher:
            until(lambda: watcher.bus().leases == (), "the child's lease to end")
        until(lambda: requests_to_sim(la_sim)[-1:] == [PAUSE_1], "the pause at the simulator")
        sent = requests_to_sim(la_sim)
        assert sent.index(la.MoveTo(1, 700, True).encode()) < sent.index(PAUSE_1)
    finally:
        child.finish(signal.SIGKILL)


def test_a_setpoint_streams_its_targets_to_the_simulator_in_order_then_pauses(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    rows = [(500 + 20 * n, 1500 - 20 * n) for n in range(15)]
    with mb.connect(endpoint) as site:
        bus = site.bus()
        arm = [bus.la(1), bus.la(2)]
        setpoint = mb.Setpoint(list(rows[0]))
        with mb.Streamer(bus).follow(arm, setpoint, period=0.02, safe_action="pause") as stream:
            for row in rows[1:]:
                setpoint.set(list(row))
                time.sleep(0.02)
            with pytest.raises(LocalProtocolError) as bad:
                setpoint.set([0, 2500])  # checked in this thread: the stream keeps its row
            assert str(bad.value.field).startswith("targets")
            until(lambda: targets_at_sim(la_sim)[-1:] == [rows[-1]], "the last row at the sim")
            assert not stream.done
        assert stream.done
    received = targets_at_sim(la_sim)
    index = [rows.index(r) for r in received]  # every row received is one that was set
    assert index == sorted(index) and index[-1] == len(rows) - 1
    assert {PAUSE_1, PAUSE_2} <= {f.encode() for f in after_last_broadcast(la_sim)}


def test_the_steppers_run_to_their_end_and_the_servers_events_reach_a_subscription(
    stepper_server: str,
) -> None:
    step = ps.StepSpec(run_distance=20, start_hz=2000, speed_rpm=600)
    project = ps.Project(
        number=1, subdivision=1, step_angle_x100=180, distance_per_rev=200, steps=(step,)
    )
    with mb.connect(stepper_server).bus() as bus:
        stepper = mb.ProjectStepper(bus)
        dump = stepper.upload(project, save=False)
        assert dump is not None and dump.to_project() == project
        with bus.events.subscribe(ProjectFinished) as finished:
            stepper.run_project(1, timeout=10)  # returns on the served EE DD
            # The server's bus saw the EE DD and published it; it came here, in order.
            assert finished.next(timeout=5).bus == bus.name
        quad = mb.QuadStepper(bus)
        quad.configure(
            2, subdivision=8, step_angle_x100=180, pulses=400, start_hz=50, accel_hz=0,
            speed_rpm=600,
        )  # fmt: skip
        with bus.events.subscribe(QuadDone, lambda e: e.kind == "run") as done:
            quad.run(2, timeout=10)  # returns on the served done reply
            assert done.next(timeout=5).bus == bus.name
            with pytest.raises(motorbus.ReplyTimeoutError):
                done.next(timeout=0.05)  # one run, one done
        assert done.closed
        with pytest.raises(StopIteration):
            done.next()


def test_bad_input_is_refused_at_the_call_naming_the_field_nothing_sent(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    with pytest.raises(LocalProtocolError) as bad:
        mb.connect("127.0.0.1:7447")
    assert bad.value.field == "endpoint" and "tcp/127.0.0.1:7447" in str(bad.value)
    with pytest.raises(LocalProtocolError) as bad:
        mb.connect(endpoint, name="x" * 65)
    assert bad.value.field == "name" and "64" in str(bad.value)
    with pytest.raises(LocalProtocolError) as bad:
        mb.connect(endpoint, config_file="/nonexistent/zenoh.json5")
    assert bad.value.field == "config_file"
    before = len(requests_to_sim(la_sim))
    with mb.connect(endpoint) as site:
        bus = site.bus()
        with pytest.raises(LocalProtocolError) as bad:
            bus.lease(["la:300"], owner="arm")
        assert bad.value.field == "key" and "1..254" in str(bad.value)
        with pytest.raises(LocalProtocolError) as bad:
            bus.lease(["quad_stepper"], owner="arm")
        assert bad.value.field == "keys" and "carries la" in str(bad.value)
        with pytest.raises(LocalProtocolError) as bad:
            bus.lease(["la:1"], owner="arm", safe_action="dance")
        assert bad.value.field == "safe_action"
        with pytest.raises(LocalProtocolError) as bad:
            mb.InspireLA(bus, 1).move_to(2500)
        assert "2000" in str(bad.value)
        with pytest.raises(LocalProtocolError) as bad:
            site.bus("arm")
        assert bad.value.field == "bus" and "serves bus" in str(bad.value)
        assert bus.leases == ()
    assert len(requests_to_sim(la_sim)) == before


def test_without_zenoh_connect_names_the_serve_extra() -> None:
    code = (
        "import sys; sys.modules['zenoh'] = None\n"
        "import motorbus.blocking as mb\n"
        "try:\n"
        "    mb.connect('tcp/127.0.0.1:7447')\n"
        "except motorbus.errors.ServeUnavailable as err:\n"
        "    print(err)\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", "import motorbus\n" + code],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "motorbus[serve]" in r.stdout, r.stderr
