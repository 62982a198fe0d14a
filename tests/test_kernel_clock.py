"""benchmarks/kernel_clock.py: the pure parts (gaps, least-squares grid, perf parser).

No perf runs here: the parser gets a captured ``perf script`` sample, the analysis
synthetic times whose answers are known.
"""

from __future__ import annotations

import math
import random
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import kernel_clock as kc  # noqa: E402

#: Captured from ``perf script -F comm,pid,tid,time,event,trace --ns`` on this project's
#: machine (perf 6.1), with a line of another process, a write from a second thread that
#: interleaves, a failed write and a line that is not a write event.
SAMPLE = "\n".join(
    (
        "         python3 14462/14462   728.853835468:"
        " syscalls:sys_enter_write: fd: 0x00000005, buf: 0x7fde2f2cbfe0, count: 0x00000009",
        "         python3 14462/14462   728.853836930:  syscalls:sys_exit_write: 0x9",
        "            bash 11808/11808   728.853900000:"
        " syscalls:sys_enter_write: fd: 0x00000002, buf: 0x55d953a4ac90, count: 0x000000ed",
        "         python3 14462/14462   728.854970201:"
        " syscalls:sys_enter_write: fd: 0x00000005, buf: 0x7fde2f2cbfe0, count: 0x00000009",
        "  python3 worker 14462/14470   728.854971000:"
        " syscalls:sys_enter_write: fd: 0x00000001, buf: 0x7fde2f2cc000, count: 0x00000013",
        "         python3 14462/14462   728.854973997:  syscalls:sys_exit_write: 0x9",
        "  python3 worker 14462/14470   728.854990000:  syscalls:sys_exit_write: 0x13",
        "         python3 14462/14462   728.856427325:"
        " syscalls:sys_enter_write: fd: 0x00000007, buf: 0x7fde2f2cbfe0, count: 0x00000016",
        "         python3 14462/14462   728.856429919:"
        "  syscalls:sys_exit_write: 0xfffffffffffffff5",
        "         python3 14462/14462   728.856500000: sched:sched_switch: prev_comm=python3",
    )
)


def test_parser_pairs_entries_with_exits_per_thread() -> None:
    calls = kc.parse_perf_script(SAMPLE, pid=14462)
    assert [(c.tid, c.fd, c.count) for c in calls] == [
        (14462, 5, 9),
        (14462, 5, 9),
        (14470, 1, 19),
        (14462, 7, 22),
    ]
    first = calls[0]
    assert first.start == pytest.approx(728.853835468)
    assert first.end == pytest.approx(728.853836930)
    assert first.ret == 9
    assert first.duration == pytest.approx(1.462e-6, rel=1e-3)
    assert calls[2].end == pytest.approx(728.854990000)  # its own thread's exit, not 14462's
    assert calls[3].ret == -11  # EAGAIN, printed by perf as an unsigned 64-bit value


def test_parser_without_pid_keeps_other_processes_and_skips_junk() -> None:
    calls = kc.parse_perf_script([*SAMPLE.splitlines(), "garbage", ""])
    assert [c.pid for c in calls].count(11808) == 1
    assert len(calls) == 5
    bash = next(c for c in calls if c.pid == 11808)
    assert bash.end is None and bash.duration is None


#: ``raw_syscalls`` lines as perf 6.1 prints them here (``every_syscall=True``): two
#: threads interleaving, another process, an entry whose exit is missing, and the
#: write(2) event of the same call beside its raw entry.
RAW_SAMPLE = "\n".join(
    (
        "         python3  6236/6236   1731.817461007: raw_syscalls:sys_enter:"
        " NR 232 (3, 7fb1c35dc000, 3, 36, 0, 0)",
        "  python3 worker  6236/6240   1731.817470000: raw_syscalls:sys_enter: NR 202 (0, 0)",
        "            bash  1180/1180   1731.817480000: raw_syscalls:sys_enter: NR 0 (0, 0)",
        "         python3  6236/6236   1731.817601916:  raw_syscalls:sys_exit: NR 232 = 1",
        "         python3  6236/6236   1731.817614114: raw_syscalls:sys_enter:"
        " NR 1 (b, 7fefaa65a090, 33, 0, 0, 0)",
        "         python3  6236/6236   1731.817614200:"
        " syscalls:sys_enter_write: fd: 0x0000000b, buf: 0x7fefaa65a090, count: 0x00000033",
        "         python3  6236/6236   1731.817621400:  syscalls:sys_exit_write: 0x33",
        "         python3  6236/6236   1731.817621495:  raw_syscalls:sys_exit: NR 1 = 51",
        "  python3 worker  6236/6240   1731.819470000:  raw_syscalls:sys_exit: NR 202 = 0",
        "         python3  6236/6236   1731.819500000: raw_syscalls:sys_enter: NR 39 (0)",
    )
)


def test_every_syscall_is_paired_per_thread_and_waits_are_marked() -> None:
    calls = kc.parse_syscalls(RAW_SAMPLE, pid=6236)
    assert [(c.tid, c.nr) for c in calls] == [(6236, 232), (6240, 202), (6236, 1)]
    epoll, futex, write = calls
    assert epoll.waits and not futex.waits and not write.waits
    assert epoll.end - epoll.start == pytest.approx(140.909e-6, rel=1e-4)
    assert futex.end == pytest.approx(1731.81947)  # its own thread's exit
    assert write.end - write.start == pytest.approx(7.381e-6, rel=1e-3)
    # The write events of the same call still parse as before, beside the raw ones.
    assert [(c.fd, c.count, c.ret) for c in kc.parse_perf_script(RAW_SAMPLE)] == [(11, 51, 51)]
    # Without a pid: bash's read never returned and getpid's exit is missing: skipped.
    assert len(kc.parse_syscalls(RAW_SAMPLE)) == 3


def test_a_poll_that_checks_is_not_a_wait() -> None:
    """The bus's poll(0) before a request (drain_input) returns at once: time held in
    it is not the loop's sleep, unlike epoll_wait."""
    lines = [
        "         python3  6236/6236   1731.900000000: raw_syscalls:sys_enter: NR 7 (7ff, 1, 0)",
        "         python3  6236/6236   1731.901200000:  raw_syscalls:sys_exit: NR 7 = 0",
    ]
    (poll,) = kc.parse_syscalls(lines, pid=6236)
    assert poll.nr == 7 and not poll.waits


def test_busiest_fd_prefers_frame_sized_writes_above_stderr() -> None:
    calls = kc.parse_perf_script(SAMPLE)
    assert kc.busiest_fd(calls) == 5
    assert kc.busiest_fd(calls, sizes=[22]) == 7
    assert kc.busiest_fd(calls, sizes=[4]) is None
    assert kc.busiest_fd([]) is None


def test_write_gaps_min_and_count_under_threshold() -> None:
    times = [0.0, 0.0012, 0.0021, 0.0040, 0.00495]  # gaps 1.2, 0.9, 1.9, 0.95 ms
    stats = kc.write_gaps(list(reversed(times)))  # order does not matter
    assert stats.count == 4
    assert stats.min_us == pytest.approx(900.0)
    assert stats.under == 2
    assert stats.as_dict() == {"gaps": 4, "min_gap_us": 900.0, "gaps_under_1000us": 2}


def test_write_gaps_exactly_at_the_threshold_is_not_under() -> None:
    assert kc.write_gaps([0.0, 0.25, 0.5], threshold=0.25).under == 0
    empty = kc.write_gaps([1.0])
    assert empty.count == 0 and math.isnan(empty.min_us)
    assert empty.as_dict()["min_gap_us"] is None


def test_grid_jitter_perfect_grid_with_offset_has_no_jitter() -> None:
    times = [5.0003 + k * 0.010 for k in range(100)]
    j = kc.grid_jitter(times, 0.010)
    assert j.ticks == 100 and j.missed == 0 and j.late == 0 and j.extra == 0
    assert j.max_us == pytest.approx(0.0, abs=1e-3)
    assert j.period_us == pytest.approx(10_000.0)
    assert j.drift_ppm == pytest.approx(0.0, abs=1e-3)


def test_grid_jitter_measures_residuals_and_late_ticks() -> None:
    rng = random.Random(7)
    noise = [rng.uniform(-20e-6, 20e-6) for _ in range(200)]
    times = [1.0 + k * 0.010 + noise[k] for k in range(200)]
    times[50] += 3e-3  # one tick 3 ms late
    j = kc.grid_jitter(times, 0.010)
    assert j.late == 1
    assert j.missed == 0
    assert j.max_us == pytest.approx(3000.0, abs=60.0)
    assert j.p50_us < 25.0
    assert j.p99_us < j.max_us


def test_grid_jitter_counts_missed_and_doubled_slots() -> None:
    ks = [k for k in range(60) if k not in (10, 11, 40)]
    times = [2.0 + k * 0.010 for k in ks] + [2.0 + 20 * 0.010 + 1e-4]
    j = kc.grid_jitter(times, 0.010)
    assert j.missed == 3
    assert j.extra == 1


def test_grid_jitter_absorbs_a_steady_rate_difference_and_reports_it() -> None:
    period = 0.010 * (1 + 50e-6)  # a sender clock 50 ppm slow
    times = [k * period for k in range(1000)]
    j = kc.grid_jitter(times, 0.010)
    assert j.drift_ppm == pytest.approx(50.0, abs=0.1)
    assert j.max_us < 0.01
    assert j.missed == 0


def test_grid_jitter_late_first_tick_does_not_shift_the_grid() -> None:
    times = [0.0025] + [k * 0.010 for k in range(1, 100)]  # first tick 2.5 ms late
    j = kc.grid_jitter(times, 0.010)
    assert j.late == 1
    assert j.missed == 0
    # Least squares leans a little towards the outlier; the grid is not shifted by a slot.
    assert j.max_us == pytest.approx(2500.0, abs=150.0)


def test_grid_jitter_by_index_counts_a_slow_loop_s_drift_as_jitter() -> None:
    times = [k * 0.0101 for k in range(100)]  # a sleep loop 1 % slow
    held = kc.grid_jitter(times, 0.010, by_index=True)
    # The grid's origin is fitted: the drift (99 x 100 us) shows half early, half late.
    assert held.max_us == pytest.approx(4950.0, rel=1e-3)
    assert held.late == 40 and held.missed == 0
    assert held.drift_ppm == pytest.approx(10_000.0, rel=1e-3)


def test_grid_jitter_needs_two_slots() -> None:
    assert math.isnan(kc.grid_jitter([1.0], 0.01).p99_us)
    same = kc.grid_jitter([1.0, 1.0001], 0.01)
    assert math.isnan(same.max_us) and same.extra == 1
    assert kc.grid_jitter([1.0], 0.01).as_dict()["tick_jitter_p99_us"] is None


def test_trace_without_perf_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kc.shutil, "which", lambda name: None)
    with kc.KernelWriteTrace() as trace:
        pass
    assert not trace.measured
    assert "perf is not installed" in trace.why
    assert trace.calls == []


def test_trace_not_root_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kc.shutil, "which", lambda name: "/usr/bin/perf")
    monkeypatch.setattr(kc.os, "geteuid", lambda: 1000)
    monkeypatch.setattr(kc.Path, "read_text", lambda self, *a, **k: "2\n")
    trace = kc.KernelWriteTrace()
    trace.start()
    trace.stop()
    assert not trace.measured
    assert "not root" in trace.why and "perf_event_paranoid=2" in trace.why


def _call(fd: int, count: int, start: float, duration: float = 5e-6) -> kc.WriteCall:
    return kc.WriteCall(1, 1, fd, count, start, start + duration, count)


def test_port_figures_pick_the_port_and_measure_spacing_and_ticks() -> None:
    calls = [_call(2, 100, 0.0)]  # stderr: never the port
    for k in range(100):  # a broadcast every 10 ms, a poll 2 ms after it
        calls.append(_call(7, 51, 1.0 + k * 0.010))
        calls.append(_call(7, 8, 1.0 + k * 0.010 + 0.002, duration=20e-6))
    calls.append(_call(7, 8, 1.0 + 99 * 0.010 + 0.0025))  # 500 µs after the last poll
    calls.append(_call(9, 8, 3.0))  # another fd, fewer writes
    trace = kc.KernelWriteTrace(measured=True, why="", calls=calls)
    k = kc.port_figures(trace, [8, 51], tick_bytes=51, period=0.010, expected_ticks=101)
    assert k["kernel_measured"] is True and k["kernel_fd"] == 7
    assert k["kernel_writes"] == 201
    assert k["kernel_min_gap_us"] == pytest.approx(500.0)
    assert k["kernel_gaps_under_1000us"] == 1
    assert k["kernel_min_gap_after_return_us"] == pytest.approx(480.0)
    assert k["kernel_write_max_us"] == pytest.approx(20.0)
    assert k["kernel_ticks"] == 100 and k["kernel_missed_ticks"] == 0
    assert k["kernel_ticks_sent_pct"] == pytest.approx(100 * 100 / 101)
    assert k["kernel_tick_jitter_max_us"] == pytest.approx(0.0, abs=1e-3)


def test_port_figures_and_worst_bus_say_why_when_not_measured() -> None:
    trace = kc.KernelWriteTrace(measured=False, why="perf is not installed")
    assert kc.port_figures(trace, [8]) == {
        "kernel_measured": False,
        "kernel_why": "perf is not installed",
    }
    assert kc.worst_tick_figures(trace, 51, 0.01)["kernel_why"] == "perf is not installed"
    empty = kc.KernelWriteTrace(measured=True, why="", calls=[_call(2, 8, 0.0)])
    assert kc.port_figures(empty, [8])["kernel_measured"] is False


def test_worst_tick_figures_takes_the_worst_bus() -> None:
    calls = [_call(5, 51, k * 0.010) for k in range(50)]
    calls += [_call(6, 51, k * 0.010 + (0.002 if k == 20 else 0.0)) for k in range(50)]
    trace = kc.KernelWriteTrace(measured=True, why="", calls=calls)
    w = kc.worst_tick_figures(trace, 51, 0.010)
    assert w["kernel_buses"] == 2
    assert w["kernel_late_ticks"] == 1
    assert w["kernel_tick_jitter_max_us"] == pytest.approx(2000.0, abs=100.0)
    assert w["kernel_min_gap_us"] == pytest.approx(8000.0, abs=1.0)
