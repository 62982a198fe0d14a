"""PtySim's link faults for ``motorbus doctor``: an echoing adapter and a wrong baud rate."""

from __future__ import annotations

import serial

from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim

STATUS_QUERY = bytes.fromhex("55 AA 03 01 04 00 22 2A")  # doc 002 C.3, to ID 1
STATUS_SIZE = 22
READ_TIMEOUT_S = 5.0  # an upper bound for a failing test, never a timing assertion


def test_an_echoing_link_sends_the_request_back_before_the_reply() -> None:
    with (
        PtySim([LAModel(id=1)], echo=True) as sim,
        serial.Serial(sim.path, 921600, timeout=READ_TIMEOUT_S) as port,
    ):
        port.write(STATUS_QUERY)
        got = port.read(len(STATUS_QUERY) + STATUS_SIZE)
    assert got[: len(STATUS_QUERY)] == STATUS_QUERY
    assert got[len(STATUS_QUERY) : len(STATUS_QUERY) + 4] == bytes.fromhex("AA 55 11 01")
    assert sim.echoed_bytes == len(STATUS_QUERY)


def test_without_echo_only_the_reply_comes_back() -> None:
    with (
        PtySim([LAModel(id=1)]) as sim,
        serial.Serial(sim.path, 921600, timeout=READ_TIMEOUT_S) as port,
    ):
        port.write(STATUS_QUERY)
        got = port.read(STATUS_SIZE)
    assert got[:4] == bytes.fromhex("AA 55 11 01")
    assert sim.echoed_bytes == 0


def test_strict_baud_devices_are_deaf_at_another_rate_and_answer_at_theirs() -> None:
    with (
        PtySim([LAModel(id=1)], baud=921600, strict_baud=True) as sim,
        serial.Serial(sim.path, 115200, timeout=0.3) as port,
    ):
        port.write(STATUS_QUERY)
        assert port.read(STATUS_SIZE) == b""
        assert sim.baud_mismatch_bytes == len(STATUS_QUERY)
        port.baudrate = 921600
        port.timeout = READ_TIMEOUT_S
        port.write(STATUS_QUERY)
        assert port.read(STATUS_SIZE)[:4] == bytes.fromhex("AA 55 11 01")
    assert sim.bus.stats.requests == 1
