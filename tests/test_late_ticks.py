"""benchmarks/late_ticks.py: each kind of late tick is put down to its cause.

Synthetic records whose answer is known: a 10 ms grid, one late tick per case, the
rest on time.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import late_ticks as lt

PERIOD = 0.010
LEAD = 200e-6
N = 5


def records(late_tick: int, late: float, **kwargs: object) -> lt.TickRecords:
    """Five ticks on time (written 20 µs after the deadline) but ``late_tick``, written
    ``late`` after; the loop idles in select between ticks unless told otherwise."""
    deadlines = [1.0 + k * PERIOD for k in range(N)]
    writes = [d + (late if k == late_tick else 20e-6) for k, d in enumerate(deadlines)]
    wakeups = [(d - LEAD, d - LEAD + 50e-6, d) for d in deadlines]
    selects = [(d - PERIOD + 0.001, d - LEAD + 50e-6) for d in deadlines]
    base = {
        "deadlines": deadlines,
        "writes": writes,
        "wakeups": wakeups,
        "selects": selects,
        "collections": [],
        "runqueue": [(w, 0.0) for w in writes],
    }
    base.update(kwargs)
    return lt.TickRecords(**base)  # type: ignore[arg-type]


def test_on_time_ticks_are_not_reported() -> None:
    assert lt.attribute(records(2, 100e-6)) == []


def test_a_collection_over_the_tick_is_the_gc() -> None:
    d = 1.0 + 2 * PERIOD
    late = lt.attribute(records(2, 2e-3, collections=[(d - 1e-3, d + 1.9e-3)]))
    assert [(t.index, t.cause) for t in late] == [(2, "gc")]
    assert late[0].late_us == pytest.approx(2000)


def test_run_queue_wait_is_the_machine() -> None:
    r = records(3, 3e-3)
    runqueue = [(w, 0.0 if k < 3 else 2.5e-3) for k, w in enumerate(r.writes)]
    late = lt.attribute(records(3, 3e-3, runqueue=runqueue))
    assert [t.cause for t in late] == ["machine: run queue"]
    assert late[0].runqueue_us == pytest.approx(2500)


def test_a_write_of_another_frame_held_in_the_kernel_is_the_machine() -> None:
    """A poll's write(2) entered before the deadline and returned 1.8 ms later: the loop
    was busy all that time, but inside the kernel, not in our code."""
    r = records(2, 2e-3)
    d = r.deadlines[2]
    selects = list(r.selects)
    selects[2] = (d - 0.008, d - 0.003)
    selects.insert(3, (d + 1.9e-3, d + 1.95e-3))
    late = lt.attribute(
        records(
            2, 2e-3, selects=selects, syscalls=[(d - 0.003, d - 0.0029), (d - LEAD, d + 1.8e-3)]
        )
    )
    assert [t.cause for t in late] == ["machine: write(2) held"]
    assert late[0].write_calls_us == pytest.approx(1800 + LEAD * 1e6)  # from the arming on
    assert late[0].loop_busy_us > 1800  # what it was counted as before the calls were traced


def test_a_callback_running_past_the_arming_is_ours() -> None:
    r = records(1, 1.5e-3)
    d = r.deadlines[1]
    selects = list(r.selects)
    # The loop left select well before the arming and came back 1.4 ms after it.
    selects[1] = (d - 0.008, d - 0.003)
    selects.insert(2, (d - LEAD + 1.4e-3, d + 1.45e-3))
    wakeups = list(r.wakeups)
    wakeups[1] = (d - LEAD, d - LEAD + 1.45e-3, d - LEAD + 1.45e-3)
    late = lt.attribute(records(1, 1.5e-3, selects=selects, wakeups=wakeups))
    assert [t.cause for t in late] == ["ours: loop busy"]
    assert late[0].loop_busy_us == pytest.approx(1450)  # from the arming to the callback


def test_callbacks_that_run_before_the_timers_after_the_look_are_ours() -> None:
    """The select that found the timerfd ready returned on time (it found a reply too),
    and the reply's callbacks ran 1.5 ms before the timer's."""
    r = records(3, 1.7e-3)
    d = r.deadlines[3]
    wakeups = list(r.wakeups)
    wakeups[3] = (d - LEAD, d + 1.5e-3, d + 1.5e-3)
    late = lt.attribute(records(3, 1.7e-3, wakeups=wakeups))
    assert [t.cause for t in late] == ["ours: loop busy"]
    assert late[0].wakeup_us == pytest.approx(50)
    assert late[0].loop_busy_us == pytest.approx(1500 + LEAD * 1e6 - 50)


def test_a_select_that_returns_late_is_a_slow_wake_up() -> None:
    r = records(4, 1.2e-3)
    d = r.deadlines[4]
    selects = list(r.selects)
    selects[4] = (d - 0.005, d - LEAD + 1.3e-3)
    wakeups = list(r.wakeups)
    wakeups[4] = (d - LEAD, d - LEAD + 1.3e-3, d - LEAD + 1.3e-3)
    late = lt.attribute(records(4, 1.2e-3, selects=selects, wakeups=wakeups))
    assert [t.cause for t in late] == ["machine: slow wake-up"]


def test_a_prompt_wake_up_and_a_late_write_is_ours() -> None:
    late = lt.attribute(records(2, 900e-6))
    assert [t.cause for t in late] == ["ours: wake to write"]
    assert late[0].wake_to_write_us == pytest.approx(900)


def test_summary_counts_every_cause() -> None:
    ticks = lt.attribute(records(2, 900e-6)) + lt.attribute(
        records(1, 2e-3, collections=[(1.005, 1.013)])
    )
    summary = lt.summarise(ticks)
    assert set(summary) == set(lt.CAUSES)
    assert summary["gc"] == {"ticks": 1, "worst_us": 2000.0}
    assert summary["ours: wake to write"]["ticks"] == 1
    assert sum(v["ticks"] for v in summary.values()) == 2
