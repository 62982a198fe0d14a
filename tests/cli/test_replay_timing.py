"""``replay --to`` sends on the bus's own timer: each request at its recorded time divided
by ``--speed``, pass after pass with ``--loop``; checked on the fake clock, exactly."""

from __future__ import annotations

import pytest

from motorbus import Priority
from motorbus.cli.replay import _Planned, _schedule, _Sender
from motorbus.protocol import la
from tests.fakeclock import rig


def plan(*times: float) -> list[_Planned]:
    return [
        _Planned(t, la.Control(1 + n % 3, la.ControlAction.QUERY_STATUS), Priority.NORMAL, n + 2)
        for n, t in enumerate(times)
    ]


def test_schedule_applies_speed_and_keeps_the_rhythm_across_passes() -> None:
    deadlines = [d for d, _ in _schedule(plan(0.0, 0.01, 0.02), 100.0, 2.0, 2)]
    assert deadlines == pytest.approx([100.0, 100.005, 100.01, 100.015, 100.02, 100.025])
    # One request: passes back to back (the bus paces them).
    assert [d for d, _ in _schedule(plan(5.0), 0.0, 1.0, 3)] == [0.0, 0.0, 0.0]
    # Times are relative to the first request; an earlier one is due at once.
    assert [d for d, _ in _schedule(plan(1.0, 0.5, 2.0), 0.0, 1.0, 1)] == [0.0, 0.0, 1.0]


@pytest.mark.parametrize(("speed", "loops"), [(1.0, 1), (2.0, 2), (0.5, 3)])
async def test_requests_leave_at_their_deadlines_on_the_bus_timer(speed: float, loops: int) -> None:
    recorded = plan(0.0, 0.01, 0.025)
    async with rig(range(1, 4)) as r:
        start = r.timer.now()
        sender = _Sender(r.bus, _schedule(recorded, start, speed, loops))
        await sender.run()
        sent_at = [w.before - start for w in r.wire.writes]
    period = 0.025 + 0.0125  # span plus the mean gap
    expected = [(k * period + t) / speed for k in range(loops) for t in (0.0, 0.01, 0.025)]
    assert sent_at == pytest.approx(expected, abs=1e-9)
    assert (sender.sent, sender.failed) == (3 * loops, 0)
    queried = [la.decode_request(w.data) for w in r.wire.writes]
    assert [c.id for c in queried] == [1, 2, 3] * loops  # type: ignore[attr-defined]


async def test_a_request_due_while_a_reply_is_owed_waits_for_the_bus() -> None:
    """Two requests recorded at one instant: the second goes once the first is answered."""
    async with rig(range(1, 4)) as r:
        start = r.timer.now()
        sender = _Sender(r.bus, _schedule(plan(0.0, 0.0), start, 1.0, 1))
        await sender.run()
        first, second = r.wire.writes
    assert first.before == start
    assert second.before > first.after  # never both at once
    assert sender.failed == 0
