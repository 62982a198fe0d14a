"""The tools on a served bus (``--connect``): ``scan``, ``monitor``, ``capture``,
``doctor``, ``rig``, ``project``, ``quad`` and ``replay``, each a child process beside a
``motorbus serve`` child that owns the simulators' port, while another client holds
leases on the same bus."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import Bus, InspireLA
from motorbus.bus.timer import default_timer
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.serve import BusServer
from motorbus.sim import SimProcess
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from tests.serve.conftest import Child, client, free_endpoint, serve
from tests.zygote import run_motorbus

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: Longest wait for a capture child to say it listens.
LISTEN_TIMEOUT_S = 30.0


def motorbus_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return run_motorbus(args, timeout=timeout)


def requests_of(sim: SimProcess, since: int = 0) -> list[bytes]:
    records = sim.log_records()[since:]
    return [bytes.fromhex(r["hex"]) for r in records if r["direction"] == "request"]


def status_query(ident: int) -> bytes:
    return la.Control(ident, la.ControlAction.QUERY_STATUS).encode()


@pytest.fixture
def holder(la_server: Child, endpoint: str) -> Iterator[Child]:
    """Another client of the served bus, holding la:1 (owner "jig") as an application
    would while the tools run."""
    child = client(endpoint, 'lease = bus.lease(["la:1"], owner="jig")')
    child.expect("ready")
    try:
        yield child
    finally:
        child.finish()


def test_scan_and_monitor_answer_from_what_the_server_knows(
    la_sim: SimProcess, holder: Child, endpoint: str
) -> None:
    start = len(la_sim.log_records())
    # A fixed budget: the default (10 ms from the completed write, on the server's bus)
    # is the machine's promptness, not this test's; the suite's load once held the
    # simulator off the CPU past both passes.
    budget = ("--timeout", "0.25")
    out = motorbus_cli("scan", "--connect", endpoint, *budget)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "1,2"
    assert "declared la:1,2" in out.stderr
    # The declared IDs only, each asked a status through the server: nothing else sent.
    assert sorted(set(requests_of(la_sim, start))) == [status_query(1), status_query(2)]
    out = motorbus_cli(
        "scan", "--connect", endpoint, "--ids", "1-4", "--json", *budget, "--passes", "1"
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == {"ids": [1, 2], "tried": 4, "declared": [1, 2]}
    assert status_query(4) in requests_of(la_sim, start)
    # A --baud the served bus does not run at is refused, not ignored; its own is taken.
    before = len(requests_of(la_sim, start))
    out = motorbus_cli("scan", "--connect", endpoint, "--baud", "115200")
    assert out.returncode == 2, out.stderr
    assert "--baud 115200: the served bus bus runs at 921600 bit/s" in out.stderr
    assert len(requests_of(la_sim, start)) == before  # nothing sent
    out = motorbus_cli("scan", "--connect", endpoint, "--baud", "921600", *budget)
    assert out.returncode == 0, out.stderr
    # monitor needs no --ids: the server's IDs.
    out = motorbus_cli("monitor", "--count", "1", "--connect", endpoint, "--json")
    assert out.returncode == 0, out.stderr
    assert [s["id"] for s in json.loads(out.stdout)["statuses"]] == [1, 2]
    # The holder's lease stood throughout: only status queries went out.
    assert set(requests_of(la_sim, start)) <= {status_query(i) for i in range(1, 5)}


def test_capture_records_what_another_client_does_and_replay_sends_it_again(
    la_sim: SimProcess, holder: Child, endpoint: str, tmp_path: Path
) -> None:
    log = tmp_path / "capture.jsonl"
    capture = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "motorbus",
            "capture",
            "--family",
            "la",
            "--connect",
            endpoint,
            "--seconds",
            "120",
            "--out",
            str(log),
        ],
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert capture.stderr is not None
        listening = capture.stderr.readline()
        assert "listening on bus bus at" in listening, listening + capture.stderr.read()
        start = len(la_sim.log_records())
        for args in (("status", "2"), ("move", "2", "1500")):
            out = motorbus_cli("la", *args, "--connect", endpoint)
            assert out.returncode == 0, out.stderr
        time.sleep(0.5)  # the server publishes every 20 ms
    finally:
        capture.send_signal(signal.SIGINT)
        _, err = capture.communicate(timeout=30)
    assert capture.returncode == 0, err
    lines = log.read_text(encoding="utf-8").splitlines()
    header, records = json.loads(lines[0]), [json.loads(line) for line in lines[1:]]
    assert header["source"] == "capture" and header["baud"] == 921600
    # Every frame the simulator saw and sent since, in the same order, and nothing else.
    sim_frames = [bytes.fromhex(r["hex"]) for r in la_sim.log_records()[start:]]
    captured = [bytes.fromhex(r["hex"]) for r in records if r["kind"] == "frame"]
    assert captured == sim_frames
    assert status_query(2) in captured and la.MoveTo(2, 1500, True).encode() in captured
    assert [r["direction"] for r in records][:2] == ["request", "reply"]
    times = [r["t"] for r in records]
    assert times == sorted(times) and times[0] >= 0

    # Replay the capture through the served bus: the move goes out again.
    out = motorbus_cli("la", "move", "2", "500", "--connect", endpoint)
    assert out.returncode == 0, out.stderr
    before = len(la_sim.log_records())
    out = motorbus_cli("replay", str(log), "--connect", endpoint, "--yes")
    assert out.returncode == 0, out.stderr
    assert "2 requests sent to bus (the only one) at" in out.stderr and "2 replies" in out.stderr
    again = requests_of(la_sim, before)
    assert again[:2] == [status_query(2), la.MoveTo(2, 1500, True).encode()]


def test_doctor_runs_the_read_only_checks_and_names_the_skipped_ones(
    la_sim: SimProcess, holder: Child, endpoint: str
) -> None:
    start = len(la_sim.log_records())
    out = motorbus_cli("doctor", "--connect", endpoint, "--requests", "5", "--json")
    doc = json.loads(out.stdout.splitlines()[0])
    checks = {c["check"]: c for c in doc["checks"]}
    for name in ("port", "latency", "echo"):
        assert checks[name]["level"] == "skip"
        assert "the port belongs to the server" in checks[name]["summary"]
    assert checks["budget"]["level"] == "skip" and checks["host"]["level"] == "skip"
    assert checks["devices"]["level"] == "green", checks["devices"]
    assert checks["devices"]["data"]["found"] == [1, 2]
    for key in ("la:1", "la:2"):  # from the server bus's counters
        assert checks[f"turnaround {key}"]["data"]["requests"] >= 5
    assert checks["line"]["data"]["lost"] == 0
    assert out.returncode == doc["exit_code"], out.stderr
    assert set(requests_of(la_sim, start)) == {status_query(1), status_query(2)}


def test_rig_holds_its_actuators_and_another_clients_lease_refuses_it(
    la_sim: SimProcess, holder: Child, endpoint: str, tmp_path: Path
) -> None:
    start = len(la_sim.log_records())
    out = motorbus_cli("rig", "1", "--connect", endpoint, "--tests", "step", "--out", str(tmp_path))
    assert out.returncode == 1, out.stderr
    assert "leased by 'jig (client child-" in out.stderr and "motorbus rig" in out.stderr
    assert requests_of(la_sim, start) == []  # refused before anything was sent
    # The tracking test streams: refused the same way, before its stream opens.
    track = ("--tests", "track", "--out", str(tmp_path))
    out = motorbus_cli("rig", "1", "--connect", endpoint, *track)
    assert out.returncode == 1, out.stderr
    assert "leased by 'jig (client child-" in out.stderr and "motorbus rig" in out.stderr
    assert requests_of(la_sim, start) == []
    out = motorbus_cli(
        "rig", "2", "--connect", endpoint, "--tests", "latency", "--latency-count", "3",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    results = json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))
    assert results["devices"]["la:2"]["latency.p50_ms"] > 0
    sent = requests_of(la_sim, start)
    moves = [f for f in sent if la.decode_request(f).__class__ is la.MoveTo]
    assert moves and all(la.decode_request(f).id == 2 for f in moves)
    # The rig's lease ended with its safe action: la:2 paused, and nothing after the
    # pause but a status query (a poll of the rig's that the server wrote behind the
    # pause, seen once on a loaded run).
    pause = la.Control(2, la.ControlAction.PAUSE).encode()
    query = la.Control(2, la.ControlAction.QUERY_STATUS).encode()
    last = max(i for i, f in enumerate(sent) if f == pause)
    assert all(f == query for f in sent[last + 1 :]), sent[last:]


def test_tools_on_a_served_bus_refuse_what_needs_the_port(endpoint: str, tmp_path: Path) -> None:
    for args, message in (
        (["capture", "--family", "la", "--port", "/dev/null"], "--connect uses a served bus"),
        (["scan", "--baud", "all"], "--baud all reopens the port"),
        (["doctor", "--fix"], "--fix and --stream"),
        (["replay", "x.jsonl", "--to", "/dev/null"], "--connect uses a served bus"),
        (["project", "stop", "--port", "/dev/null"], "--connect uses a served bus"),
    ):
        out = motorbus_cli(*args, "--connect", endpoint)
        assert out.returncode == 2, (args, out.stderr)
        assert message in out.stderr, (args, out.stderr)


def test_project_and_quad_through_a_served_bus(tmp_path: Path) -> None:
    endpoint = free_endpoint()
    with SimProcess(
        ["project-stepper", "quad-stepper"], baud=9600, log_file=tmp_path / "sim.jsonl"
    ) as sim:
        server = serve(sim.path, 9600, "project-stepper,quad-stepper", endpoint)
        try:
            for args in (
                ("project", "upload", str(EXAMPLES / "project.toml"), "--no-save"),
                ("project", "run", "1", "--timeout", "60"),
                (
                    "quad",
                    "config",
                    "2",
                    "--subdivision",
                    "8",
                    "--pulses",
                    "400",
                    "--start-hz",
                    "50",
                    "--accel",
                    "0",
                    "--rpm",
                    "600",
                ),
                ("quad", "run", "2"),
            ):
                out = motorbus_cli(*args, "--connect", endpoint)
                assert out.returncode == 0, (args, out.stderr)
            out = motorbus_cli("rig", "quad", "2", "--runs", "2", "--json", "--connect", endpoint)
            assert out.returncode == 0, out.stderr
            assert json.loads(out.stdout)["runs"] == 2
        finally:
            server.finish()
        sent = requests_of(sim)
    assert ps.StartProject(1).encode() in sent
    assert sent.count(q.Run(2).encode()) == 3  # quad run, then the rig's two


async def wait_until(condition: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"not {what} within {timeout:g} s"
        await asyncio.sleep(0.01)


async def test_the_server_taps_its_bus_only_while_a_capture_subscribes() -> None:
    endpoint = free_endpoint()
    async with MemorySim.start([LAModel(1)], baud=921600, timer=default_timer()) as sim:
        bus = Bus(sim.transport, name="arm", host_margin=0.05, reconnect=False)
        async with (
            bus,
            BusServer({"arm": bus}, listen=endpoint, devices={"arm": ["la:1", "la:4"]}) as server,
            motorbus.connect(endpoint) as site,
        ):
            served = site.bus()
            feed = server.tools.feeds["arm"]
            devices = await served.fetch_devices()
            assert devices.declared == ("la:1", "la:4") and not devices.frames_tapped
            await InspireLA(served, 1).status()
            assert bus._engine.wire_taps == [] and feed.published == 0  # nobody listened
            assert (await served.fetch_devices()).answered == ("la:1",)
            async with served.frames() as batches:
                await wait_until(lambda: feed.active, "tapped")
                assert bus._engine.wire_taps == [feed.tap]
                await InspireLA(served, 1).status()
                # The request and its reply, in one batch or (a loaded run) in two.
                frames = (await asyncio.wait_for(batches.get(), 10))["frames"]
                if all(direction != "rx" for _, direction, _ in frames):
                    frames += (await asyncio.wait_for(batches.get(), 10))["frames"]
                kinds = [direction for _, direction, _ in frames]
                assert kinds[0] == "tx" and "rx" in kinds
                assert bytes.fromhex(frames[0][2]) == status_query(1)
            await wait_until(lambda: not feed.active, "untapped after the capture")
            assert bus._engine.wire_taps == []
