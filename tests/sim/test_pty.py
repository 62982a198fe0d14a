"""PtySim and ``motorbus sim`` on real pseudo-terminals, driven with plain pyserial."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import serial

from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim

STATUS_QUERY = bytes.fromhex("55 AA 03 01 04 00 22 2A")  # doc 002 C.3, CMD_MC 0x22 to ID 1
STATUS_SIZE = 22  # doc 002 C.4
READ_TIMEOUT_S = 5.0  # an upper bound for a failing test, never a timing assertion
ROOT = Path(__file__).resolve().parents[2]


def query(dev: int) -> bytes:
    body = bytes([0x03, dev, 0x04, 0x00, 0x22])
    return b"\x55\xaa" + body + bytes([sum(body) & 0xFF])


def open_port(path: str | Path) -> serial.Serial:
    return serial.Serial(str(path), baudrate=921600, timeout=READ_TIMEOUT_S)


@pytest.mark.parametrize("spin", [False, True], ids=["select", "busy-poll"])
def test_la_status_over_a_pty_with_plain_pyserial(spin: bool) -> None:
    with PtySim([LAModel(id=1)], spin=spin) as sim, open_port(sim.path) as port:
        port.write(STATUS_QUERY)
        reply = port.read(STATUS_SIZE)
        assert reply[:4] == bytes.fromhex("AA 55 11 01")
        assert len(reply) == STATUS_SIZE
        assert sum(reply[2:-1]) & 0xFF == reply[-1]
    assert sim.bus.stats.requests == 1
    assert sim.bus.stats.replies == 1
    assert sim.error is None


def test_link_is_created_replaced_and_removed(tmp_path: Path) -> None:
    link = tmp_path / "ttyLA"
    link.symlink_to("/nonexistent")  # a stale link from an earlier run is replaced
    with PtySim([LAModel(id=1)], link=link) as sim:
        assert os.readlink(link) == sim.path
        with open_port(link) as port:
            port.write(STATUS_QUERY)
            assert port.read(STATUS_SIZE)[:4] == bytes.fromhex("AA 55 11 01")
    assert not link.exists() and not link.is_symlink()


def test_a_regular_file_is_never_overwritten(tmp_path: Path) -> None:
    precious = tmp_path / "ttyLA"
    precious.write_text("keep me")
    with pytest.raises(FileExistsError, match="not a symlink"):
        PtySim([LAModel(id=1)], link=precious).start()
    assert precious.read_text() == "keep me"


def test_garbage_fault_is_seen_on_the_wire(tmp_path: Path) -> None:
    sent: list[dict[str, object]] = []
    log_file = tmp_path / "sim.jsonl"
    faults = FaultConfig(garbage_rate=1.0)
    with (
        PtySim([LAModel(id=1)], faults=faults, seed=5, log=sent.append, log_file=log_file) as sim,
        open_port(sim.path) as port,
    ):
        port.write(STATUS_QUERY)
        head = port.read(STATUS_SIZE)  # at least 23 bytes are coming
        (record,) = [r for r in sent if r["dir"] == "tx"]
        wire = bytes.fromhex(str(record["hex"]))
        rest = port.read(len(wire) - STATUS_SIZE)
    assert record["fault"] == "garbage"
    assert head + rest == wire
    extra = len(wire) - STATUS_SIZE
    assert 1 <= extra <= 8
    # Remove the burst somewhere and a valid status frame remains.
    frames = [wire[:i] + wire[i + extra :] for i in range(STATUS_SIZE + 1)]
    assert any(
        f[:4] == bytes.fromhex("AA 55 11 01") and sum(f[2:-1]) & 0xFF == f[-1] for f in frames
    )
    assert sim.bus.stats.faults_injected["garbage"] == 1
    header, *lines = [json.loads(line) for line in log_file.read_text().splitlines()]
    assert (header["format"], header["version"]) == ("motorbus-frame-log", 1)
    assert (header["source"], header["port"], header["families"]) == ("sim", sim.path, ["la"])
    assert [(r["kind"], r["direction"], r.get("fault")) for r in lines] == [
        ("frame", "request", None),
        ("frame", "reply", "garbage"),
    ]


def test_disconnect_fault_closes_the_pty_and_serves_a_new_one(tmp_path: Path) -> None:
    link = tmp_path / "ttyLA"
    faults = FaultConfig(disconnect_after_s=0.5, reconnect_after_s=0.05, disconnect_count=1)
    with PtySim([LAModel(id=1)], faults=faults, link=link) as sim:
        with open_port(link) as port, pytest.raises(serial.SerialException):
            port.read(1)  # blocks until the simulator pulls the plug
        assert sim.wait_open(READ_TIMEOUT_S)
        assert os.readlink(link) == sim.path
        with open_port(link) as port:
            port.write(STATUS_QUERY)
            assert port.read(STATUS_SIZE)[:4] == bytes.fromhex("AA 55 11 01")
    assert sim.bus.stats.faults_injected["disconnect"] == 1


def test_cli_serves_three_actuators_until_sigint(tmp_path: Path) -> None:
    link = tmp_path / "ttyLA"
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus.cli.sim", "--link", str(link), "la:1-3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().split()
        assert line[1:] == [str(link)], line
        assert line[0].startswith("/dev/")
        with open_port(link) as port:
            for dev in (1, 2, 3):
                port.write(query(dev))
                reply = port.read(STATUS_SIZE)
                assert reply[:4] == bytes([0xAA, 0x55, 0x11, dev]), reply.hex(" ")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=READ_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "3 requests, 3 replies" in out
    assert not link.is_symlink()


def test_cli_refuses_a_bad_spec() -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    out = subprocess.run(
        [sys.executable, "-m", "motorbus.cli.sim", "la:0"],
        capture_output=True,
        text=True,
        env=env,
        timeout=30,
    )
    assert out.returncode == 2
    assert "la:0" in out.stderr and "1..254" in out.stderr
