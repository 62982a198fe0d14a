"""``replay --to`` sends on the bus's own timer: each request at its recorded time divided
by ``--speed``, pass after pass with ``--loop``; checked on the fake clock, exactly."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from motorbus import Priority
from motorbus.cli.replay import _Planned, _schedule, _Sender
from motorbus.protocol import framelog, la
from motorbus.sim.process import SimProcess
from tests.fakeclock import rig
from tests.helpers import CLI_TIMEOUT_S


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


def test_ctrl_c_ends_a_replay_through_the_bus_close(tmp_path: Path) -> None:
    """Interrupted, a replay stops sending at once, closes its bus and exits 130: the
    pending timer handle is cancelled, so nothing is submitted to the closed bus."""
    header = framelog.header("capture", started_utc="2026-01-01T00:00:00.000000Z", families=["la"])
    query = la.Control(1, la.ControlAction.QUERY_STATUS).encode().hex(" ").upper()
    lines = [header] + [
        {"t": round(0.05 * n, 3), "kind": "frame", "family": "la", "direction": "request",
         "hex": query} for n in range(200)
    ]  # fmt: skip
    log = tmp_path / "long.jsonl"
    log.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")
    with SimProcess(["la:1"], baud=921600, log_file=tmp_path / "sim.jsonl") as sim:
        proc = subprocess.Popen(
            [sys.executable, "-m", "motorbus", "replay", str(log), "--to", sim.path],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert proc.stdout is not None
        assert "la request Control id=1" in proc.stdout.readline()  # sending has begun
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=CLI_TIMEOUT_S)
        heard = [x for x in sim.log_records() if x["direction"] == "request"]
    assert proc.returncode == 130, err
    assert err.endswith("motorbus replay: interrupted\n") and "Traceback" not in err, err
    assert 1 <= len(heard) < 200
