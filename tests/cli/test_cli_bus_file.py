"""``--bus-file F --bus NAME`` opens the bus with every key the table sets, and a port
another program holds is refused by name.

Before, the command line read only ``url``, ``baud`` and ``backend`` from the table:
``remove_echo = true`` on an adapter that echoes left the echo in the reply stream,
``rs485 = true`` was never applied, and the spacing, margin, retries, latency and
sharing keys were ignored (issue 20, "two bus-file readers, and they disagree").
"""

from __future__ import annotations

import fcntl
import os
import select
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli.bus_options import open_bus, resolve_port
from motorbus.cli.dashboard import _manager as dashboard_manager
from motorbus.cli.main import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, build_parser
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, UsageError
from motorbus.protocol.base import Family
from motorbus.sim.bus import SimBus
from motorbus.sim.la import LAModel
from motorbus.sim.process import SimProcess
from motorbus.transport.serial import SerialTransport
from tests import helpers
from tests.helpers import affinities, affinity_kept, cli, json_lines

LA_BAUD = 921600
#: How often the echoing device looks for host bytes, seconds.
POLL_S = 0.005


class EchoingLA:
    """An LA actuator (ID 1) behind a half-duplex adapter that echoes every byte the
    host writes, on a pty: the test's stand-in for an RS-485 adapter without echo
    suppression."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._bus = SimBus([LAModel(1)], baud=LA_BAUD, pacing="prompt")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            readable, _, _ = select.select([self.master], [], [], POLL_S)
            now = time.monotonic()
            if readable:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    continue
                os.write(self.master, data)  # the adapter's echo comes first
                self._bus.receive(data, now)
            for chunk in self._bus.due_output(now):
                os.write(self.master, chunk)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def device() -> Iterator[EchoingLA]:
    d = EchoingLA()
    yield d
    d.close()


def bus_file(tmp_path: Path, url: str, **keys: object) -> Path:
    """A bus file with one bus ``arm`` on ``url`` and the given extra keys."""
    return helpers.bus_file(tmp_path, url, baud=LA_BAUD, **keys)


def status(path: Path, *, debug: bool = True) -> tuple[int, str, str]:
    """``motorbus la status 1 --json`` on bus ``arm`` of ``path`` (with ``--debug``, the
    bus logs every frame it sends and every byte run it discards)."""
    flags = ["--debug"] if debug else []
    r = cli(*flags, "la", "status", "1", "--json", "--bus-file", str(path), "--bus", "arm")
    return r.returncode, r.stdout, r.stderr


def test_remove_echo_from_the_bus_file_drops_the_adapters_echo(
    device: EchoingLA, tmp_path: Path
) -> None:
    code, out, err = status(bus_file(tmp_path, device.path, remove_echo=True))
    assert code == EXIT_OK, err
    assert json_lines(out)[0]["id"] == 1
    assert "TX 55 AA" in err  # the request went out...
    assert "discarded" not in err, err  # ...and its echo never reached the reassembler
    # The same adapter without the key: the echo shows up as discarded garbage.
    code, out, err = status(bus_file(tmp_path, device.path))
    assert code == EXIT_OK, err
    assert "discarded 55 AA 03 01 04 00 22" in err, err


def test_rs485_from_the_bus_file_is_applied(device: EchoingLA, tmp_path: Path) -> None:
    # A pty has no RS-485 mode: applying the key fails, and says so.
    code, _, err = status(bus_file(tmp_path, device.path, rs485=True), debug=False)
    assert code == EXIT_FAILURE
    assert err.startswith(f"motorbus la: cannot open port {device.path}: cannot enable RS-485 mode")


async def test_every_bus_key_reaches_the_transport_and_the_bus(
    device: EchoingLA, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))
    path = bus_file(
        tmp_path,
        device.path,
        backend="serialx",
        remove_echo=True,
        low_latency=False,
        share=True,
        min_spacing_ms=3,
        host_margin_ms=7.5,
        retries=4,
        guard=True,
    )
    args = build_parser().parse_args(["la", "status", "1", "--bus-file", str(path), "--bus", "arm"])
    assert resolve_port(args) == device.path
    assert (args.baud, args.backend) == (LA_BAUD, "serialx")
    assert args.bus_spec.guard is True  # carried for the guard
    async with open_bus(args, [Family.LA]) as bus:
        transport = bus.transport
        assert isinstance(transport, SerialTransport)
        assert (transport.remove_echo, transport.low_latency, transport.share) == (
            True,
            False,
            True,
        )
        assert bus.config.min_spacing == pytest.approx(0.003)
        assert bus.config.host_margin == pytest.approx(0.0075)
        assert bus.config.retries == 4


async def test_a_bus_file_without_timing_keys_keeps_the_cli_margin(
    device: EchoingLA, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))
    path = bus_file(tmp_path, device.path)
    args = build_parser().parse_args(["la", "status", "1", "--bus-file", str(path), "--bus", "arm"])
    resolve_port(args)
    async with open_bus(args, [Family.LA]) as bus:
        assert bus.config.host_margin == pytest.approx(0.050)  # CLI_HOST_MARGIN_S
        assert (bus.config.min_spacing, bus.config.retries) == (pytest.approx(0.001), 1)
        assert bus.transport.share is False  # type: ignore[attr-defined]


@pytest.mark.parametrize(("env_ms", "margin_s"), [("250", 0.25), ("5", 0.05), (None, 0.05)])
def test_the_environments_host_margin_raises_the_cli_margin_never_lowers_it(
    env_ms: str | None, margin_s: float
) -> None:
    """``MOTORBUS_HOST_MARGIN_MS`` raises the deadlines of every bus a program opens
    (docs/hardware.md): the one-shot commands' too, when it asks for more than their
    50 ms; a smaller one leaves them at 50 ms.  (Read at import: a fresh interpreter.)"""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "MOTORBUS_HOST_MARGIN_MS"}
    if env_ms is not None:
        env["MOTORBUS_HOST_MARGIN_MS"] = env_ms
    code = "from motorbus.cli.bus_options import CLI_HOST_MARGIN_S as m; print(repr(m))"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert float(out.stdout) == pytest.approx(margin_s)


@pytest.mark.parametrize(("keys", "margin_ms"), [({}, 50.0), ({"host_margin_ms": 7.5}, 7.5)])
def test_the_dashboard_opens_a_bus_file_with_the_margin_every_command_uses(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, keys: dict[str, Any], margin_ms: float
) -> None:
    # The dashboard opens every bus of the file itself: the same rule as open_bus, the
    # table's margin if it sets one, else the command line's (not the library's 2 ms,
    # which timed out a move on a loaded machine).
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))
    path = bus_file(tmp_path, "/dev/motorbus-never-opened", **keys)
    args = build_parser().parse_args(["dashboard", "--bus-file", str(path)])
    manager, wanted, from_file = dashboard_manager(args)
    assert from_file == path  # its motorbus serve gets the file, and the same margin rule
    assert manager.specs["arm"].host_margin_ms == pytest.approx(margin_ms)
    assert wanted == {"arm": None}  # no devices listed: the dashboard scans for them


# -- a port another program holds ------------------------------------------------------------


@pytest.fixture
def held(device: EchoingLA) -> Iterator[str]:
    """``device``'s port, locked the way pyserial's and serialx's exclusive opens lock it
    (``flock``) by this process, which does not read from it; yields the path."""
    fd = os.open(device.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        yield device.path
    finally:
        os.close(fd)


def test_a_held_port_is_refused_naming_the_holder_unless_the_file_shares(
    held: str, tmp_path: Path
) -> None:
    r = cli("la", "status", "1", "--bus-file", str(bus_file(tmp_path, held)))
    assert r.returncode == EXIT_FAILURE
    assert f"motorbus la: {held} is in use by PID {os.getpid()} (" in r.stderr
    assert "tap" not in r.stderr  # the watch hint is for monitor and capture
    r = cli("la", "status", "1", "--json", "--bus-file", str(bus_file(tmp_path, held, share=True)))
    assert r.returncode == EXIT_OK, r.stderr
    assert json_lines(r.stdout)[0]["id"] == 1


@pytest.mark.parametrize(
    "command",
    [
        ["monitor", "--ids", "1", "--count", "1"],
        ["capture", "--family", "la", "--seconds", "0.1"],
    ],
    ids=["monitor", "capture"],
)
def test_monitor_and_capture_on_a_held_port_point_at_a_tap(held: str, command: list[str]) -> None:
    r = cli(*command, "--port", held)
    assert r.returncode == EXIT_FAILURE
    assert f"is in use by PID {os.getpid()} (" in r.stderr, r.stderr
    assert "tap" in r.stderr and "poll_status=True" in r.stderr, r.stderr


# -- --process: one process group of the bus file, on its CPUs -------------------------------

MISSING = "/dev/motorbus-no-such-port-{}"


def group_file(tmp_path: Path, arm: str, cpu: int) -> Path:
    """Group "arms": bus "arm" on ``arm``; group "legs": buses "hip" and "knee", and a bus
    of no group, all on ports that do not exist (opening one fails the command)."""
    path = tmp_path / "groups.toml"
    path.write_text(
        f"""
[[bus]]
name = "spare"
url = "{MISSING.format(1)}"
baud = {LA_BAUD}

[[bus]]
name = "arm"
url = "{arm}"
baud = {LA_BAUD}
process = "arms"
devices = ["la:1"]

[[bus]]
name = "hip"
url = "{MISSING.format(2)}"
baud = {LA_BAUD}
process = "legs"

[[bus]]
name = "knee"
url = "{MISSING.format(3)}"
baud = {LA_BAUD}
process = "legs"

[process.arms]
cpus = [{cpu}]
""",
        encoding="utf-8",
    )
    return path


def test_bus_file_process_chooses_among_the_groups_buses(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))
    path = group_file(tmp_path, "/dev/motorbus-arm", 0)

    def parse(*extra: str) -> Any:
        return build_parser().parse_args(["stream", "t.csv", "--bus-file", str(path), *extra])

    args = parse("--process", "arms")  # the group's only bus: no --bus needed
    assert resolve_port(args) == "/dev/motorbus-arm"
    assert args.process_group.cpus == frozenset({0})
    args = parse("--process", "legs", "--bus", "knee")
    assert resolve_port(args) == MISSING.format(3)
    with pytest.raises(UsageError) as info:
        resolve_port(parse("--process", "legs"))
    assert str(info.value) == (
        f"process group legs of {path} has 2 buses: choose one with --bus hip|knee"
    )
    with pytest.raises(UsageError) as info:
        resolve_port(parse("--process", "legs", "--bus", "arm"))
    assert str(info.value) == (
        f"--bus arm: process group legs of {path} has no such bus: choose one of hip, knee"
    )
    with pytest.raises(LocalProtocolError) as info:
        resolve_port(parse("--process", "hands"))
    assert str(info.value) == (
        f"{path}: process='hands' is not a process group of this file: choose one of arms, legs"
    )
    args = build_parser().parse_args(["stream", "t.csv", "--port", "/dev/x", "--process", "a"])
    with pytest.raises(UsageError, match="--process a: no bus file: give --bus-file"):
        resolve_port(args)


async def test_bus_file_process_runs_the_command_on_the_groups_cpus(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))
    with affinity_kept() as allowed, SimProcess(["la:1"], baud=LA_BAUD) as sim:
        cpu = max(allowed)
        path = group_file(tmp_path, sim.path, cpu)
        args = build_parser().parse_args(
            ["monitor", "--bus-file", str(path), "--process", "arms", "--ids", "1"]
        )
        async with open_bus(args, [Family.LA]) as bus:
            assert bus.transport.url == sim.path
            assert set(affinities().values()) == {frozenset({cpu})}
            assert (await InspireLA(bus, 1).status()).id == 1
        assert frozenset(os.sched_getaffinity(0)) == allowed


def test_bus_file_process_on_the_command_line(tmp_path: Path) -> None:
    with SimProcess(["la:1"], baud=LA_BAUD) as sim:
        path = group_file(tmp_path, sim.path, 0)
        r = cli("monitor", "--bus-file", str(path), "--process", "arms", "--ids", "1",
                "--count", "1", "--json")  # fmt: skip
        assert r.returncode == EXIT_OK, r.stderr
        assert [s["id"] for s in json_lines(r.stdout)[0]["statuses"]] == [1]
    r = cli("monitor", "--bus-file", str(path), "--process", "hands", "--count", "1")
    assert r.returncode == EXIT_USAGE
    assert r.stderr.strip() == (
        f"motorbus monitor: {path}: process='hands' is not a process group of this file: "
        "choose one of arms, legs"
    )
    r = cli("monitor", "--listen", "--port", "/dev/x", "--process", "arms")
    assert r.returncode == EXIT_USAGE
    assert "--process goes with a monitor that drives its bus, not --listen" in r.stderr
