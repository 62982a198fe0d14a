"""How long a frame and its reply hold the bus: the one place for it, worked by hand.

Wire time is 10 bits a byte (start, 8 data, stop).  LA status query 8 bytes, status
reply 22; LA turnaround 800 us (manual 3.4.2); spacing 1 ms; host margin 2 ms.
"""

from __future__ import annotations

import dataclasses

import pytest

from motorbus.bus.bus import Bus
from motorbus.bus.occupancy import (
    BusTiming,
    OccupancyTable,
    answer_window,
    command_occupancy,
    occupancy,
    reply_slack,
)
from motorbus.bus.options import DEFAULT_TURNAROUND
from motorbus.protocol import la
from motorbus.protocol.base import Family


def timing(baud: int) -> BusTiming:
    return BusTiming(baud, 1e-3, 2e-3, DEFAULT_TURNAROUND)


@pytest.mark.parametrize(
    ("baud", "write_ms", "reply_ms", "answered_ms", "budget_ms"),
    [
        # 921600: 8 B = 86.8 us, 22 B = 238.7 us; answered = max(1 ms, 0.0868+0.2387+0.8)
        (921600, 0.086806, 0.238715, 1.125521, 3.125521),
        # 115200: 8 B = 694.4 us, 22 B = 1909.7 us; + 0.8 ms turnaround
        (115200, 0.694444, 1.909722, 3.404167, 5.404167),
        # 19200: 8 B = 4.1667 ms, 22 B = 11.4583 ms
        (19200, 4.166667, 11.458333, 16.425, 18.425),
    ],
)
def test_a_status_query_and_its_reply(
    baud: int, write_ms: float, reply_ms: float, answered_ms: float, budget_ms: float
) -> None:
    occ = command_occupancy(timing(baud), la.Control(1, la.ControlAction.QUERY_STATUS))
    assert occ.write * 1e3 == pytest.approx(write_ms, abs=1e-5)
    assert occ.reply_wire * 1e3 == pytest.approx(reply_ms, abs=1e-5)
    assert occ.answered * 1e3 == pytest.approx(answered_ms, abs=1e-5)
    # The deadline: write + reply on the wire + turnaround + host margin.
    assert occ.budget * 1e3 == pytest.approx(budget_ms, abs=1e-5)
    assert occ.worst == pytest.approx(max(1e-3, occ.budget))
    assert occ.after_write == pytest.approx(max(1e-3, occ.write))


def test_a_frame_without_reply_holds_the_bus_for_the_spacing_or_its_wire_time() -> None:
    full = la.Broadcast(la.BroadcastMode.FOLLOW, tuple((i, 1000) for i in range(1, 16)))
    fast = command_occupancy(timing(921600), full)  # 51 B = 553 us < 1 ms spacing
    assert not fast.expects_reply and fast.budget == 0.0
    assert fast.answered == fast.worst == fast.after_write == pytest.approx(1e-3)
    slow = command_occupancy(timing(19200), full)  # 51 B at 19200 = 26.5625 ms
    assert slow.after_write == slow.answered == pytest.approx(0.0265625)


def test_occupancy_by_size_matches_the_command() -> None:
    t = timing(921600)
    cmd = la.Follow(3, 700, True)
    by_size = occupancy(t, Family.LA, request_bytes=len(cmd.encode()), reply_bytes=22)
    assert command_occupancy(t, cmd) == by_size


def test_reply_slack_is_the_shortest_turnaround_plus_the_margin() -> None:
    t = timing(921600)
    la_only = reply_slack(t, [Family.LA])
    assert la_only == pytest.approx(DEFAULT_TURNAROUND[Family.LA] + 2e-3)
    assert reply_slack(t) == pytest.approx(min(DEFAULT_TURNAROUND.values()) + 2e-3)
    assert reply_slack(t) <= la_only


def test_the_table_answers_as_command_occupancy_for_every_shape() -> None:
    """A bus remembers occupancies per frame shape; every answer is the function's."""
    t = timing(115200)
    table = OccupancyTable(t)
    cmds = [
        la.Control(1, la.ControlAction.QUERY_STATUS),
        la.Control(2, la.ControlAction.QUERY_STATUS),  # same shape: the same answer
        la.Follow(3, 700, True),
        la.Broadcast(la.BroadcastMode.FOLLOW, ((1, 5), (2, 6))),
        la.Broadcast(la.BroadcastMode.FOLLOW, tuple((i, 5) for i in range(1, 16))),
    ]
    for cmd in cmds * 2:
        assert table.of(cmd) == command_occupancy(t, cmd)
        assert table.of(cmd, len(cmd.encode())) == command_occupancy(t, cmd)
    assert len(table._known) == 4


def test_a_bus_config_is_frozen_so_its_costs_cannot_go_stale() -> None:
    from motorbus.transport.memory import memory_pair

    transport, _ = memory_pair(baudrate=115200)
    bus = Bus(transport, families=[Family.LA], host_margin=0.004)
    with pytest.raises(dataclasses.FrozenInstanceError):
        bus.config.host_margin = 0.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        bus.config.turnaround[Family.LA] = 0.0  # type: ignore[index]
    assert bus.timing == BusTiming(115200, 1e-3, 0.004, bus.config.turnaround)
    query = la.Control(1, la.ControlAction.QUERY_STATUS)
    assert bus.occupancy(query) == command_occupancy(bus.timing, query)


def test_answer_window_is_the_longest_turnaround_plus_the_reply_on_the_wire() -> None:
    t = BusTiming(9600, 1e-3, 2e-3, {Family.LA: 800e-6, Family.PROJECT_STEPPER: 5e-3})
    # 24 bytes at 9600 bit/s: 25 ms; the project stepper's 5 ms turnaround is the longest.
    assert answer_window(t, [Family.LA], 24) == pytest.approx(800e-6 + 0.025)
    assert answer_window(t, [Family.LA, Family.PROJECT_STEPPER], 24) == pytest.approx(0.030)
