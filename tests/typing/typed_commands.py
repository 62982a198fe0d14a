"""Checked by mypy in tests/test_typed_commands.py (never imported by pytest itself)."""

from __future__ import annotations

import asyncio
from typing import assert_type

from motorbus import Bus
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q


async def typed(bus: Bus) -> None:
    assert_type(await bus.request(la.Control(1, la.ControlAction.PAUSE)), la.Status)
    assert_type(await bus.request(la.ReadTable(1, 0, 2)), la.ReadReply)
    assert_type(await bus.request(la.ReadRegister(1, la.Register.ID)), int)
    assert_type(await bus.request(la.MoveTo(1, 500)), la.Status)
    assert_type(await bus.request(ps.StartProject(1)), ps.Ack)
    assert_type(await bus.request(ps.ManualStop()), ps.Ack)
    assert_type(await bus.request(ps.ReadProject(1)), ps.ProjectDump)
    assert_type(await bus.request(ps.ReadInput(1)), bool)
    assert_type(await bus.request(q.Save()), q.Ack | q.Done)
    assert_type(bus.submit(la.Follow(1, 500)), asyncio.Future[la.Status])
    # A wrong expectation is an error (this line is meant to fail):
    wrong: ps.Ack = await bus.request(la.Control(1, la.ControlAction.PAUSE))  # EXPECT-ERROR
    del wrong
