"""The simulator's tap (``PtySim(tap=PATH)``, ``motorbus sim --tap PATH``): a listen-only pty
carrying a copy of every byte both ways, so ``capture`` can be tried without hardware."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from motorbus.protocol import la
from motorbus.sim.la import LAModel
from motorbus.sim.process import SimProcess
from motorbus.sim.pty import PtySim

QUERY = la.Control(1, la.ControlAction.QUERY_STATUS).encode()
STATUS_SIZE = 22
READ_TIMEOUT_S = 5.0  # an upper bound for a failing test, never a timing assertion
CLI_TIMEOUT_S = 60
#: The capture's own time limit, only a backstop: the test ends it with SIGINT.
CAPTURE_CAP_S = 120


def wait_for_lines(path: Path, n: int, timeout: float = CLI_TIMEOUT_S) -> None:
    """Return once ``path`` has ``n`` complete lines; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        text = path.read_text(encoding="utf-8") if path.exists() else ""
        if text.count("\n") >= n:
            return
        if time.monotonic() > deadline:
            pytest.fail(f"{path} has {text.count(chr(10))} lines, not {n}, after {timeout} s")
        time.sleep(0.02)


def open_port(path: str | Path, timeout: float = READ_TIMEOUT_S) -> serial.Serial:
    return serial.Serial(str(path), baudrate=921600, timeout=timeout)


def test_tap_copies_both_ways_in_order_and_only_while_someone_listens(tmp_path: Path) -> None:
    tap = tmp_path / "tap"
    with PtySim([LAModel(id=1)], tap=tap) as sim, open_port(sim.path) as host:
        assert tap.is_symlink() and Path(sim.tap_path).samefile(tap)
        # Nobody listens yet: nothing is copied, so nothing stale waits for a listener.
        host.write(QUERY)
        assert len(host.read(STATUS_SIZE)) == STATUS_SIZE
        assert sim.tap_bytes == 0
        with open_port(tap) as listener:
            host.write(QUERY)
            reply = host.read(STATUS_SIZE)
            heard = listener.read(len(QUERY) + STATUS_SIZE)
        assert heard == QUERY + reply
        assert sim.tap_bytes == len(QUERY) + STATUS_SIZE
        # What a listener leaves unread is not served to the next one.
        with open_port(tap) as first:
            host.write(QUERY)
            assert len(host.read(STATUS_SIZE)) == STATUS_SIZE
            assert first.read(len(QUERY)) == QUERY  # the copy arrived; the rest is left
        host.write(QUERY)  # the simulator notices the listener is gone and flushes
        assert len(host.read(STATUS_SIZE)) == STATUS_SIZE
        with open_port(tap, timeout=0.2) as second:
            host.write(QUERY)
            reply = host.read(STATUS_SIZE)
            assert second.read(len(QUERY) + STATUS_SIZE) == QUERY + reply
    assert sim.tap_dropped_bytes == 0
    assert not tap.exists() and not tap.is_symlink()


def test_capture_on_the_tap_records_what_a_bus_and_the_simulator_said(tmp_path: Path) -> None:
    tap = tmp_path / "ttyLA.tap"
    sim_log = tmp_path / "sim.jsonl"
    out = tmp_path / "capture.jsonl"
    with SimProcess(["la:1-3"], baud=921600, log_file=sim_log, tap=tap) as sim:
        capture = subprocess.Popen(
            [sys.executable, "-m", "motorbus", "capture", "--port", str(tap), "--family", "la",
             "--seconds", str(CAPTURE_CAP_S), "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        assert capture.stderr is not None
        ready = capture.stderr.readline()
        assert ready.startswith(f"motorbus capture: listening on {tap}"), ready
        for args in (["la", "status", "1", "2"], ["la", "move", "3", "1500"]):
            r = subprocess.run(
                [sys.executable, "-m", "motorbus", *args, "--port", sim.path],
                capture_output=True,
                text=True,
                timeout=CLI_TIMEOUT_S,
            )
            assert r.returncode == 0, r.stderr
        # Six frames (two queries, a move, their replies) after the header; then Ctrl-C,
        # the ordinary end of a capture.
        wait_for_lines(out, 1 + 6)
        capture.send_signal(signal.SIGINT)
        _, err = capture.communicate(timeout=CLI_TIMEOUT_S)
        assert capture.returncode == 0, err
        wire = [(r["kind"], r["direction"], r["hex"]) for r in sim.log_records()]
    header, *records = [json.loads(line) for line in out.read_text(encoding="utf-8").splitlines()]
    assert header["source"] == "capture" and header["port"] == str(tap)
    heard = [(r["kind"], r["direction"], r["hex"]) for r in records]
    assert heard == wire
    assert [(r["direction"], r["name"]) for r in records] == [
        ("request", "Control"),
        ("reply", "Status"),
        ("request", "Control"),
        ("reply", "Status"),
        ("request", "MoveTo"),
        ("reply", "Status"),
    ]
    assert records[-2]["fields"] == {"id": 3, "position": 1500, "reply": True}


def test_a_regular_file_at_the_tap_path_is_never_overwritten(tmp_path: Path) -> None:
    precious = tmp_path / "tap"
    precious.write_text("keep me")
    with pytest.raises(FileExistsError, match="not a symlink"):
        PtySim([LAModel(id=1)], tap=precious).start()
    assert precious.read_text() == "keep me"
