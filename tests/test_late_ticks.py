"""benchmarks/late_ticks.py: each kind of late tick is put down to its cause.

Synthetic records whose answer is known: a 10 ms grid, one late tick per case, the
rest on time.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

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
    assert [t.cause for t in late] == ["machine: system call held"]
    assert late[0].syscalls_us == pytest.approx(1800 + LEAD * 1e6)  # from the arming on
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


def cpu_samples(
    selects: list[tuple[float, float]], stolen: tuple[float, float] | None = None
) -> list[tuple[float, float, float]]:
    """The thread's CPU clock at each select's entry (asleep after) and return (awake
    after): it runs all the time it is awake, but inside ``stolen``."""
    out: list[tuple[float, float, float]] = []
    cpu, last = 0.0, None
    for entered, returned in selects:
        if last is not None:  # awake from the last return to this entry
            cpu += entered - last
            if stolen is not None:
                cpu -= max(0.0, min(entered, stolen[1]) - max(last, stolen[0]))
        out.append((entered, cpu, 0.0))
        out.append((returned, cpu, 1.0))
        last = returned
    return out


def busy_past_the_arming() -> tuple[lt.TickRecords, float]:
    """Tick 1 written 1.5 ms late: the loop left select 0.1 ms before the arming and
    came back 1.4 ms after it, and the timer's callback ran then."""
    r = records(1, 1.5e-3)
    d = r.deadlines[1]
    selects = list(r.selects)
    selects[1] = (d - 0.008, d - LEAD - 0.1e-3)
    selects.insert(2, (d - LEAD + 1.4e-3, d + 1.45e-3))
    wakeups = list(r.wakeups)
    wakeups[1] = (d - LEAD, d - LEAD + 1.45e-3, d - LEAD + 1.45e-3)
    return records(1, 1.5e-3, selects=selects, wakeups=wakeups), d


def test_a_busy_loop_whose_thread_ran_is_ours_with_its_cpu() -> None:
    r, d = busy_past_the_arming()
    callbacks = [
        (d - 0.006, d - 0.0055, "task Streamer._run"),  # before the tick: not named
        (d - LEAD - 0.1e-3, d - LEAD + 0.2e-3, "SerialTransport._read_ready"),
        (d - LEAD + 0.2e-3, d - LEAD + 1.4e-3, "task Poller.run"),
    ]
    late = lt.attribute(
        records(
            1,
            1.5e-3,
            **_fields(r, thread_cpu=cpu_samples(r.selects), slow_callbacks=callbacks),
        )
    )
    assert [t.cause for t in late] == ["ours: loop busy"]
    assert late[0].callback == "task Poller.run (1,200 us)"
    assert late[0].taken_us == pytest.approx(0, abs=1e-6)
    assert late[0].on_cpu_us == pytest.approx(1400)  # awake from the arming to select


def test_an_awake_thread_that_did_not_run_had_its_cpu_taken_away() -> None:
    """The same busy loop, but its thread ran 0.2 ms of the 1.4 ms: not in the run
    queue, not in a system call, not running: the hypervisor had the vCPU."""
    r, d = busy_past_the_arming()
    stolen = (d - LEAD + 0.1e-3, d - LEAD + 1.3e-3)
    late = lt.attribute(records(1, 1.5e-3, **_fields(r, thread_cpu=cpu_samples(r.selects, stolen))))
    assert [t.cause for t in late] == ["machine: CPU taken away"]
    assert late[0].taken_us == pytest.approx(1100)  # 1.2 ms, of which 0.1 may be before
    assert late[0].on_cpu_us == pytest.approx(300)
    assert late[0].loop_busy_us == pytest.approx(1450)  # still reported beside it


def test_cpu_taken_away_leaves_out_the_run_queue_and_sleep() -> None:
    """Off CPU while queued is the run queue's; off CPU asleep in select is no one's."""
    r, d = busy_past_the_arming()
    stolen = (d - LEAD + 0.1e-3, d - LEAD + 1.3e-3)
    queued = [(w, 0.0 if k < 1 else 0.8e-3) for k, w in enumerate(r.writes)]
    late = lt.attribute(
        records(1, 1.5e-3, **_fields(r, runqueue=queued, thread_cpu=cpu_samples(r.selects, stolen)))
    )
    assert [t.cause for t in late] == ["machine: run queue"]
    assert late[0].taken_us == pytest.approx(300)  # 1.1 ms off CPU, 0.8 of it queued
    # A late select return (the thread asleep) is a slow wake-up, however little it ran.
    slow = slow_wake_up()
    late = lt.attribute(records(4, 1.2e-3, **slow, thread_cpu=cpu_samples(slow["selects"])))
    assert [t.cause for t in late] == ["machine: slow wake-up"]
    assert late[0].taken_us == pytest.approx(0, abs=1e-6)


def _fields(r: lt.TickRecords, **changes: object) -> dict[str, object]:
    """``r``'s recorded fields but deadlines and writes (``records`` makes those), with
    ``changes``."""
    out: dict[str, object] = {"selects": r.selects, "wakeups": r.wakeups}
    out.update(changes)
    return out


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


def slow_wake_up() -> dict[str, list[Any]]:
    """Selects and wake-ups of ``records(4, 1.2e-3)`` in which the select that waited
    for tick 4 returned 1.3 ms after the arming."""
    r = records(4, 1.2e-3)
    d = r.deadlines[4]
    selects = list(r.selects)
    selects[4] = (d - 0.005, d - LEAD + 1.3e-3)
    wakeups = list(r.wakeups)
    wakeups[4] = (d - LEAD, d - LEAD + 1.3e-3, d - LEAD + 1.3e-3)
    return {"selects": selects, "wakeups": wakeups}


def test_a_select_that_returns_late_is_a_slow_wake_up() -> None:
    late = lt.attribute(records(4, 1.2e-3, **slow_wake_up()))
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
