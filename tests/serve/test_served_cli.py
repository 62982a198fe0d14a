"""``--connect``: the command-line tools on a served bus, the server owning the port."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from motorbus.protocol import la
from motorbus.sim import SimProcess
from tests.serve.conftest import Child
from tests.zygote import run_motorbus


def motorbus_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return run_motorbus(args)


def test_la_status_and_move_through_a_served_bus(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    # The port is the server's: a second opener is refused; --connect goes through it.
    out = motorbus_cli("la", "status", "1-2", "--connect", endpoint, "--json")
    assert out.returncode == 0, out.stderr
    assert [json.loads(line)["id"] for line in out.stdout.splitlines()] == [1, 2]
    out = motorbus_cli("la", "move", "2", "1234", "--connect", endpoint)
    assert out.returncode == 0, out.stderr
    sent = [bytes.fromhex(r["hex"]) for r in la_sim.log_records() if r["direction"] == "request"]
    assert la.MoveTo(2, 1234, True).encode() in sent
    # A one-shot move is kept on purpose (released with hold): no pause after it.
    assert sent[-1] == la.MoveTo(2, 1234, True).encode()


def test_connect_with_a_port_is_a_usage_error(endpoint: str) -> None:
    out = motorbus_cli("la", "status", "1", "--connect", endpoint, "--port", "/dev/null")
    assert out.returncode == 2 and "--connect" in out.stderr


def test_monitor_through_a_served_bus(la_sim: SimProcess, la_server: Child, endpoint: str) -> None:
    out = motorbus_cli("monitor", "--ids", "1-2", "--count", "2", "--connect", endpoint, "--json")
    assert out.returncode == 0, out.stderr
    refreshes = [json.loads(line) for line in out.stdout.splitlines()]
    assert [r["refresh"] for r in refreshes] == [1, 2]
    assert [s["id"] for s in refreshes[-1]["statuses"]] == [1, 2]


def test_serve_takes_realtime_and_refuses_a_bad_priority(la_sim: SimProcess, endpoint: str) -> None:
    # The server is where the timing is kept: real-time mode is asked there.
    server = Child(
        [sys.executable, "-m", "motorbus", "--debug", "serve", "--port", la_sim.path,
         "--baud", "921600", "--devices", "la:1", "--listen", endpoint, "--realtime=20"]
    )  # fmt: skip
    server.expect("serving")
    err = server.finish()
    (line,) = [ln for ln in err.splitlines() if "real-time mode:" in ln]
    assert "SCHED_FIFO 20" in line or "refused sched_fifo" in line  # applied, or said why not
    out = motorbus_cli("serve", "--port", la_sim.path, "--realtime=0", "--listen", endpoint)
    assert out.returncode == 2 and "--realtime='0' is out of range" in out.stderr


def test_serve_on_port_0_prints_the_port_it_was_given(la_sim: SimProcess) -> None:
    server = Child(
        [sys.executable, "-m", "motorbus", "serve", "--port", la_sim.path, "--baud", "921600",
         "--devices", "la:1", "--listen", "tcp/127.0.0.1:0", "--host-margin-ms", "50"]
    )  # fmt: skip
    try:
        line = server.expect("serving")
        endpoint = line.rsplit(" on ", 1)[1]
        host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
        assert host == "127.0.0.1" and 0 < int(port) < 65536, line
        out = motorbus_cli("la", "status", "1", "--connect", endpoint, "--json")
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout)["id"] == 1
    finally:
        server.finish()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--liveness", "0"], "liveness=0.0 is out of range: allowed 0.1..60 s"),
        (["--liveness", "100"], "liveness=100.0 is out of range"),
        (["--zenoh-config", "/nonexistent/server.json5"], "--zenoh-config /nonexistent"),
        (["--zenoh-config", "BROKEN"], "--zenoh-config "),
    ],
)
def test_a_bad_server_option_is_refused_before_the_port_opens(
    la_sim: SimProcess, endpoint: str, tmp_path: Path, option: list[str], message: str
) -> None:
    """A new user's report: these were found only after the buses opened, so the
    manager's close paused every device on the way out, and a bad Zenoh configuration
    file ended in a 37-line traceback from Zenoh's Rust source."""
    if option[-1] == "BROKEN":
        broken = tmp_path / "broken.json5"
        broken.write_text("{ mode: 'peer', listen: ")
        option = [option[0], str(broken)]
    out = motorbus_cli(
        "serve", "--port", la_sim.path, "--baud", "921600", "--devices", "la:1-2",
        "--listen", endpoint, *option,
    )  # fmt: skip
    assert out.returncode == 2, (out.returncode, out.stderr)
    assert message in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and ".rs:" not in out.stderr, out.stderr
    assert not [r for r in la_sim.log_records() if r["direction"] == "request"]
