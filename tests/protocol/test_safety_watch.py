"""``safety.watch_allowed``: what a watch-only client of ``motorbus serve`` may send -
reads and stops, never motion or a setting."""

from __future__ import annotations

import pytest

from motorbus.protocol import la, safety
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Command


@pytest.mark.parametrize(
    "cmd",
    [
        la.Control(1, la.ControlAction.QUERY_STATUS),
        la.Control(1, la.ControlAction.PAUSE),
        la.Control(255, la.ControlAction.ESTOP),
        la.ReadTable(1, 0, 10),
        la.ReadRegister(1, la.Register.POSITION),
        ps.StopProject(),
        ps.ManualStop(),
        ps.ReadProject(1),
        ps.ReadInput(1),
        q.Stop(1),
        q.StopAll(),
    ],
)
def test_reads_and_stops_are_allowed(cmd: Command[object]) -> None:
    assert safety.watch_allowed(cmd)


@pytest.mark.parametrize(
    "cmd",
    [
        la.MoveTo(1, 1000, True),
        la.Follow(1, 1000, False),
        la.Broadcast(la.BroadcastMode.FOLLOW, ((1, 1000),)),
        la.Control(1, la.ControlAction.WORK),
        la.Control(1, la.ControlAction.SAVE),
        la.Control(1, la.ControlAction.CLEAR_FAULT),
        la.WriteRegister(1, la.Register.OVER_CURRENT_LIMIT, 600),
        la.WriteRegister(1, la.Register.ID, 7),
        la.WriteTable(1, la.Register.TARGET.index, b"\x00\x04"),
        ps.StartProject(1),
        ps.ClearProject(1),
        ps.JogForward(),
        q.Run(1),
        q.SetLed(1, True),
        q.Save(),
    ],
)
def test_motion_and_settings_are_not(cmd: Command[object]) -> None:
    assert not safety.watch_allowed(cmd)
