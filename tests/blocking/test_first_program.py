"""README's first program, written with the blocking API, against a simulator process:
the same frames, the same safe end (the bus's close pauses what it moved)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

import motorbus
import motorbus.blocking as mb
from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.blocking.frames import BAUD, HOST_MARGIN_S, assert_paused_after, pause, query, received


def first_program(port: str) -> tuple[la.Status, la.Status]:
    transport = motorbus.open_transport(port, baudrate=BAUD)
    with mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S) as bus:
        actuator = mb.InspireLA(bus, 1, stroke_mm=30)
        before = actuator.status()
        actuator.enable()
        arrived = actuator.move_to(1500, wait=True)
        assert arrived is not None
        assert actuator.to_mm(arrived.position) == pytest.approx(22.5, abs=0.2)
    assert bus.closed
    return before, arrived


def check_frames(frames: list[bytes]) -> None:
    move = la.MoveTo(1, 1500, True).encode()
    assert frames[0] == query(1)  # status() first
    assert move in frames
    # wait=True polls the status until two in a row are within the tolerance...
    assert frames[frames.index(move) + 1 :].count(query(1)) >= 2
    # ...and the bus's close pauses what the program moved, after the last motion.
    assert frames[-1] == pause(1)
    assert_paused_after(frames, frames.index(move), [1])


def test_the_first_program_runs_blocking(tmp_path: Path) -> None:
    with SimProcess(["la:1"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        before, arrived = first_program(sim.path)
        frames = received(sim)
    assert before.id == 1
    assert abs(arrived.position - 1500) <= 10
    check_frames(frames)


def test_it_runs_where_an_event_loop_already_runs_in_the_calling_thread(tmp_path: Path) -> None:
    # A notebook cell: Jupyter runs an event loop in the thread that runs the cell, so
    # asyncio.run() would refuse; the blocking API does not care.
    async def cell(port: str) -> tuple[la.Status, la.Status]:
        asyncio.get_running_loop()  # there is one, in this very thread
        return first_program(port)

    with SimProcess(["la:1"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        _, arrived = asyncio.run(cell(sim.path))
        frames = received(sim)
    assert abs(arrived.position - 1500) <= 10
    check_frames(frames)


def test_bad_arguments_raise_in_the_calling_thread_and_nothing_is_sent(tmp_path: Path) -> None:
    with SimProcess(["la:1"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        transport = motorbus.open_transport(sim.path, baudrate=BAUD)
        with pytest.raises(motorbus.LocalProtocolError) as bad_option:
            mb.Bus(transport, families=[motorbus.Family.LA], retries=-1)
        assert bad_option.value.field == "retries"
        with mb.Bus(transport, families=[motorbus.Family.LA]) as bus:
            with pytest.raises(motorbus.LocalProtocolError) as bad_id:
                mb.InspireLA(bus, 0)
            assert bad_id.value.field == "id"
            actuator = bus.la(1)
            with pytest.raises(motorbus.LocalProtocolError, match="position=2500"):
                actuator.move_to(2500)
        frames = received(sim)
    assert frames == []  # nothing moved, so the close owed nothing either
