"""The benchmark harness's pure parts: plan, results.json, goals, report.md, plots.

No benchmark runs here (timing belongs in benchmarks/, not in tests): the harness gets
small fake reports shaped like each script's JSON.
"""

from __future__ import annotations

import ast
import json
import math
import sys
from pathlib import Path
from typing import Any

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import bench_cpu  # noqa: E402
import run  # noqa: E402
import run_report  # noqa: E402
import run_results  # noqa: E402

DATE = "2026-01-02T03:04:05+00:00"
MACHINE = {"platform": "Linux-test", "python": "3.11.7", "cpus": 2, "load_avg": [0.5, 0.4, 0.3]}


def bus_report(rtt_us: float, backend: str = "fast", loop: str = "asyncio") -> dict[str, Any]:
    return {
        "rtt_p50_us": rtt_us,
        "rtt_p99_us": 2 * rtt_us,
        "rtt_minimal_client_p50_us": 800.0,
        "rtt_minimal_client_p99_us": 1200.0,
        "rtt_blocking_pyserial_p50_us": 640.0,
        "rtt_blocking_pyserial_p99_us": 1000.0,
        "rtt_ratio_vs_minimal": rtt_us / 800.0,
        "commands_per_s": 950.0,
        "min_gap_us": 1001.0,
        "gaps_under_1000us": 0,
        "timeout_late_p99_us": 200.0,
        "timeout_early_count": 0,
        "rate_kernel_measured": True,
        "rate_kernel_min_gap_us": 1012.0,
        "rate_kernel_gaps_under_1000us": 0,
        "mixed_kernel_measured": True,
        "mixed_kernel_min_gap_us": 998.0,
        "mixed_kernel_gaps_under_1000us": 3,
        "mixed_kernel_ticks_sent_pct": 99.5,
        "mixed_sim_min_gap_us": 87.0,
        "mixed_prompt_pacing": "pending: no pacing option",
        "mixed_prompt_poll_timeouts": None,
        "n": 300,
        "backend": backend,
        "loop": loop,
        "timer": "TimerfdTimer",
    }


def startup_report() -> dict[str, Any]:
    """bench_startup.py --no-before's JSON, cut down: the floor and the "after" tree."""

    def times(median_s: float) -> dict[str, float]:
        return {
            "min_s": median_s - 0.002,
            "median_s": median_s,
            "max_s": median_s + 0.01,
            "median_above_floor_s": median_s - 0.01,
        }

    return {
        "floor": {"command": "python -c pass", **times(0.01)},
        "trees": {
            "after": {
                "motorbus --version": times(0.028),
                "motorbus --help": times(0.029),
                "motorbus la status --help": times(0.087),
                "motorbus la status 1 --port PTY": times(0.35),
            }
        },
        "runs": 3,
        "bytecode": "cached",
        "loadavg_start": [0.1, 0.1, 0.05],
    }


def fake_reports() -> dict[str, Any]:
    return {
        "reassembler": {
            "frames_per_s": 1_200_000,
            "frames_per_s_garbage1": 600_000,
            "decoded_per_s": 500_000,
            "decoded_per_s_garbage1": 300_000,
            "pymodbus_decoded_per_s": 100_000,
            "ratio_vs_pymodbus": 5.0,
            "goals": {"every_undamaged_frame_found": True},
            "pymodbus": {"version": "3.16.1"},
        },
        "startup": startup_report(),
        "bus-fast-asyncio": bus_report(1000.0),
        "bus-serialx-asyncio": bus_report(1200.0, backend="serialx"),
        "bus-fast-uvloop": bus_report(900.0, loop="uvloop"),
        "stream": {
            "tick_jitter_p50_us": 40,
            "tick_jitter_p99_us": 250,
            "tick_jitter_max_us": 2500,
            "missed_ticks": 0,
            "drift_ppm": -150.0,
            "naive_tick_jitter_p99_us": 1000,
            "naive_tick_jitter_max_us": 5000,
            "scaling": {
                "buses": [1, 4, 16],
                "cpu_percent": [3.0, 10.0, float("nan")],
                "tick_jitter_p99_us": [100, 200, 400],
            },
            "scaling_seconds": 4.0,
            "backend": "fast",
            "timer": "timerfd",
            "loop": "asyncio default",
            "kernel_measured": True,
            "kernel_tick_jitter_p50_us": 20.0,
            "kernel_tick_jitter_p99_us": 120.0,
            "kernel_tick_jitter_max_us": 1500.0,
            "naive_kernel_tick_jitter_p99_us": 4000.0,
            "cpu_us_per_tick": 90.0,
            "baseline_sleep_tick_jitter_max_us": 5000,
            "baseline_timerfd_kernel_tick_jitter_p99_us": 60.0,
            "baseline_timerfd_cpu_us_per_tick": 30.0,
            "baseline_timerfd_spin_cpu_us_per_tick": 60.0,
        },
        "load": {
            "plain": {"tick_jitter_p99_us": 4000.0, "missed_ticks": 30, "late_ticks": 100},
            "rt": {
                "tick_jitter_p99_us": 60.0,
                "tick_jitter_max_us": 700.0,
                "missed_ticks": 0,
                "late_ticks": 0,
                "min_gap_us": 1010.0,
                "kernel_measured": False,
                "kernel_why": "perf is not installed",
            },
            "rt_method": "os.sched_setscheduler(SCHED_FIFO, 50)",
            "hogs": 2,
            "seconds": 5.0,
        },
        "cpu": {
            "buses": [1, 16, 32, 64, 128],
            "cpu_percent": [2.0, 20.0, 36.0, 70.0, 99.0],
            "spin_percent": [0.9, 5.0, 9.0, 3.0, 0.0],
            "timer_arms_per_tick": [3.1, 0.55, 0.5, 0.45, 0.4],
            "round_ratios": [[2.0], [1.2, 1.5], [1.2, 1.2], [], [1.0, None]],
            "minimal_cpu_percent": [1.0, 15.0, 30.0, 60.0, 90.0],
            "ratio": [2.0, 1.33, 1.2, 1.17, 1.1],
            "timerfd_cpu_percent": [1.0, 10.0, 20.0, 40.0, 60.0],
            "ratio_timerfd": [2.0, 2.0, 1.8, 1.75, 1.65],
            "round_ratios_timerfd": [[2.0], [1.9, 2.1], [1.8, 1.8], [], [1.6, None]],
            "timerfd_spin_cpu_percent": [1.5, 15.0, 30.0, 55.0, 80.0],
            "ratio_timerfd_spin": [1.33, 1.33, 1.2, 1.27, 1.24],
            "spin_s_timerfd_spin": 0.0005,
            "ratio_per_tick": [2.0, 1.33, 1.2, 1.17, 2.2],
            "ticks": [300, 4800, 9600, 19200, 19200],
            "minimal_ticks": [300, 4800, 9600, 19200, 38400],
            "ticks_sent_pct": [100.0, 100.0, 100.0, 99.94, 50.0],
            "stream_errors": [0, 0, 0, 0, 3],
            "keeps_up": [True, True, True, True, False],
            "max_ratio": 2.0,
            "max_buses_keeping_up": 64,
            "seconds": 3.0,
        },
        "late_ticks": {
            "runs": [
                {
                    "tick_jitter_p50_us": 40.0,
                    "tick_jitter_p99_us": 120.0,
                    "tick_jitter_max_us": 900.0,
                    "late_ticks": 0,
                    "missed_ticks": 0,
                    "gc_collections": 42,
                    "timer_spin_s": 0.1225,
                    "cpu_us_per_tick": 95.5,
                    "kernel_why": None,
                    "origin": 775.28,  # not a figure: left out
                },
                {
                    "tick_jitter_p50_us": 45.0,
                    "tick_jitter_p99_us": 505.7,
                    "tick_jitter_max_us": 3447.1,
                    "late_ticks": 4,
                    "missed_ticks": 1,
                    "gc_collections": 40,
                    "timer_spin_s": 0.0,
                    "cpu_us_per_tick": 101.0,
                    "kernel_why": None,
                },
            ],
            "late_ticks": [{"index": 10, "late_us": 3447.1, "cause": "machine: run queue"}] * 5,
            "causes": {
                "gc": {"ticks": 1, "worst_us": 620.0},
                "machine: run queue": {"ticks": 4, "worst_us": 3447.1},
                "ours: loop busy": {"ticks": 0, "worst_us": 0.0},
                "machine: slow wake-up": {"ticks": 0, "worst_us": 0.0},
                "ours: wake to write": {"ticks": 0, "worst_us": 0.0},
                "unattributed": {"ticks": 0, "worst_us": 0.0},
            },
            "goals": {"kernel_max_le_1000us_every_run": False},
            "seconds": 60.0,
            "realtime": False,
            "hogs": 0,
            "threshold_us": 500.0,
            "machine": {"load_avg_before": [0.07, 0.1, 0.2]},
        },
        "timer": {
            "seconds_per_run": 1.0,
            "timerfd": True,
            "results": [
                {"loop": "asyncio", "period_ms": 1.0, "method": "asyncio.sleep", "p99_us": 900.0},
                {"loop": "asyncio", "period_ms": 1.0, "method": "TimerfdTimer", "p99_us": 90.0},
            ],
        },
    }


RUNS = {
    "bus-pyserial-asyncio-asyncio": {
        "command": ["python", "bench_bus.py"],
        "returncode": 1,
        "seconds": 1.0,
        "load_avg_1min": 0.5,
        "probe": {"loop_ms": 6.25, "wakeup_cpu_us": 21.0},
        "steal_percent": 12.5,
        "log": "logs/bus-pyserial-asyncio-asyncio.log",
    }
}


def build(reports: dict[str, Any] | None = None) -> dict[str, Any]:
    return run_results.build_results(
        fake_reports() if reports is None else reports,
        quick=True,
        date=DATE,
        machine=MACHINE,
        runs=RUNS,
        backends=["fast", "serialx", "pyserial-asyncio"],
        loops=["asyncio", "uvloop"],
        duration_s=12.34,
    )


def test_plan_runs_every_benchmark_once_with_quick() -> None:
    steps = run.plan(True, ["fast", "serialx"], ["asyncio", "uvloop"])
    assert [s.name for s in steps] == [
        "reassembler",
        "bus-fast-asyncio",
        "bus-serialx-asyncio",
        "bus-fast-uvloop",
        "stream",
        "timer",
        "load",
        "cpu",
        "late_ticks",
        "startup",
    ]
    assert all("--quick" in s.args for s in steps if s.script != "bench_timer.py")
    assert steps[-2].command(Path("/x/raw"))[1:] == [
        str(run.HERE / "bench_late_ticks.py"),
        "--quick",
        "--out",
        "/x/raw/late_ticks.json",
    ]
    assert steps[5].args == ("--seconds", "1")
    # The mixed workload runs once, with the headline bus configuration.
    assert "--mixed-seconds" not in steps[1].args
    assert steps[2].args[-2:] == ("--mixed-seconds", "0")
    cmd = steps[3].command(Path("/x/raw"))
    assert cmd[2:] == [
        "--quick",
        "--backend",
        "fast",
        "--loop",
        "uvloop",
        "--mixed-seconds",
        "0",
        "--out",
        "/x/raw/bus-fast-uvloop.json",
        "--samples",
        "/x/raw/bus-fast-uvloop.samples.json",
    ]
    full = {s.name: s for s in run.plan(False, ["fast"], ["asyncio"])}
    assert "--quick" not in full["reassembler"].args
    # The full run: where one core saturates (up to 128 buses); three 60 s late-tick runs.
    assert full["cpu"].args == ("--buses", "1,16,32,64,128")
    assert full["late_ticks"].args == ("--runs", "3", "--seconds", "60")
    assert not full["late_ticks"].samples
    # Its runs, each with its start-up (simulator, perf), fit in a step's time.
    args = full["late_ticks"].args
    assert int(args[1]) * float(args[3]) <= run.STEP_TIMEOUT_S / 2
    # Start-up of this tree only (a report says what is here, not a comparison).
    assert full["startup"].args == ("--runs", "7", "--no-before")
    assert steps[-1].args == ("--quick", "--no-before")


def test_results_have_every_documented_key() -> None:
    r = build()
    for key in (
        "reassembler.frames_per_s",
        "reassembler.decoded_per_s",
        "reassembler.pymodbus_decoded_per_s",
        "bus.rtt_p50_us",
        "bus.rtt_minimal_client_p50_us",
        "bus.rtt_blocking_pyserial_p50_us",
        "bus.commands_per_s",
        "bus.min_gap_us",
        "bus.timeout_late_p99_us",
        "bus.timeout_early_count",
        "stream.tick_jitter_p99_us",
        "stream.tick_jitter_max_us",
        "stream.missed_ticks",
        "stream.naive_tick_jitter_p99_us",
        "scaling.buses",
        "scaling.cpu_percent",
        "scaling.tick_jitter_p99_us",
        "bus.rate_kernel_min_gap_us",
        "bus.mixed_kernel_min_gap_us",
        "stream.kernel_tick_jitter_p99_us",
        "load.rt.tick_jitter_p99_us",
        "load.plain.tick_jitter_p99_us",
        "load.rt_method",
        "cpu.buses",
        "cpu.ratio",
        "cpu.max_ratio",
        "cpu.ratio_per_tick",
        "cpu.spin_percent",
        "cpu.timer_arms_per_tick",
        "cpu.ticks_sent_pct",
        "cpu.keeps_up",
        "cpu.max_ratio_1_16_32",
        "cpu.ratio_timerfd",
        "cpu.ratio_timerfd_spin",
        "cpu.max_ratio_timerfd_1_16_32",
        "cpu.spin_s_timerfd_spin",
        "cpu.max_buses_keeping_up",
        "late_ticks.runs",
        "late_ticks.kernel_max_us",
        "late_ticks.attributed_ticks",
        "late_ticks.causes",
        "late_ticks.seconds",
        "late_ticks.threshold_us",
        "late_ticks.load_avg_before",
        "startup.floor_median_s",
        "startup.commands",
        "startup.version_median_s",
        "startup.la_status_median_s",
        "machine.platform",
        "machine.python",
        "machine.cpus",
    ):
        assert run_results.lookup(r, key) is not None, key
    assert (r["backend"], r["event_loop"], r["timer_source"]) == ("fast", "asyncio", "TimerfdTimer")
    assert r["bus"]["backends"]["serialx"]["rtt_p50_us"] == 1200.0
    assert r["bus"]["backends"]["pyserial-asyncio"]["status"] == "failed"
    assert r["bus"]["loops"]["uvloop"]["rtt_p50_us"] == 900.0
    assert r["scaling"]["cpu_percent"] == [3.0, 10.0, None]  # NaN is not JSON
    assert r["cpu"]["max_ratio_1_16_32"] == 2.0  # 64 and 128 buses are reported only
    assert r["cpu"]["max_ratio_timerfd_1_16_32"] == 2.0
    late = r["late_ticks"]
    assert late["kernel_max_us"] == 3447.1  # the worst run's
    assert late["attributed_ticks"] == 5
    assert [run_["tick_jitter_max_us"] for run_ in late["runs"]] == [900.0, 3447.1]
    assert set(late["runs"][0]) == set(run_results.LATE_RUN_KEYS)  # "origin" left out
    assert late["runs"][0]["timer_wakeups"] is None  # absent: null, not missing
    assert list(late["causes"]) == list(run_results.LATE_CAUSES)
    assert late["causes"]["machine: run queue"] == {"ticks": 4, "worst_us": 3447.1}
    assert r["errors"] == [
        "bus-pyserial-asyncio-asyncio: exit status 1 (timeout if null), "
        "see logs/bus-pyserial-asyncio-asyncio.log"
    ]
    json.dumps(r, allow_nan=False)


def test_missing_reports_give_nulls_not_missing_keys() -> None:
    r = build({})
    assert r["bus"]["rtt_p50_us"] is None
    assert r["scaling"]["buses"] == []
    assert r["cpu"]["buses"] == []
    assert r["cpu"]["keeps_up"] == []
    assert r["cpu"]["max_buses_keeping_up"] is None
    assert r["cpu"]["max_ratio_1_16_32"] is None
    assert r["late_ticks"]["runs"] == []
    assert r["late_ticks"]["kernel_max_us"] is None
    assert r["late_ticks"]["attributed_ticks"] is None
    assert r["startup"]["version_median_s"] is None
    assert r["startup"]["commands"]["motorbus --version"] == {
        "min_s": None,
        "median_s": None,
        "median_above_floor_s": None,
    }
    assert r["late_ticks"]["causes"] == {
        c: {"ticks": None, "worst_us": None} for c in run_results.LATE_CAUSES
    }
    assert r["load"]["rt"]["tick_jitter_p99_us"] is None
    assert r["bus"]["backends"]["fast"]["status"] == "failed"
    assert all(g["met"] is None for g in r["goals"].values())
    text = run_report.render_report(r)
    assert "n/a" in text
    assert "## Late ticks, attributed: 0 run(s) of n/a" in text
    assert "| `gc` | n/a | n/a |" in text
    assert "no stream ended): not measured." in text


@pytest.mark.parametrize(
    ("name", "value", "met"),
    [
        ("reassembler.framing_ge_1M_per_s", 1_200_000, True),
        ("reassembler.decoded_ge_5x_pymodbus", 5.0, True),  # the bound itself is met
        ("reassembler.every_undamaged_frame_found", True, True),
        ("bus.rtt_le_1.3x_minimal_client", 1.25, True),
        ("bus.commands_ge_950_per_s", 950.0, True),
        ("bus.min_gap_ge_1000us", 998.0, False),  # the kernel's figure, not the simulator's
        ("bus.no_gap_under_1ms", 3, False),
        ("bus.rate_min_gap_ge_1000us", 1012.0, True),
        ("bus.mixed_ticks_sent_ge_99pct", 99.5, True),
        ("bus.mixed_prompt_no_poll_timeout", None, None),  # pending: no prompt simulator
        ("stream.kernel_p99_le_150us", 120.0, True),
        ("stream.kernel_max_le_1ms", 1500.0, False),
        ("load.rt_p99_le_100us", 60.0, True),
        ("load.rt_max_le_500us", 700.0, False),
        ("load.rt_no_missed_tick", 0, True),
        ("cpu.ratio_le_1.5x_timerfd", 2.0, False),
        ("cpu.32_buses_lt_35pct", 36.0, False),  # the 32-bus entry of cpu.buses
        ("bus.timeout_late_p99_le_150us", 200.0, False),
        ("bus.timeout_never_early", 0, True),
        ("stream.p99_le_300us", 250, True),
        ("stream.max_le_2ms", 2500, False),
        ("stream.no_drift", -150.0, False),  # |drift| counts, not its sign
        ("scaling.32_buses_cpu_lt_50pct", None, None),  # 32 buses not run in quick mode
        ("late_ticks.kernel_max_le_1000us_every_run", 3447.1, False),  # one run of two
        ("startup.version_le_0.3s", 0.028, True),  # the median, not the best run
        ("startup.la_status_le_0.3s", 0.35, False),
    ],
)
def test_goals(name: str, value: Any, met: bool | None) -> None:
    goal = build()["goals"][name]
    assert (goal["value"], goal["met"]) == (value, met)


def test_scaling_goal_reads_the_32_bus_entry() -> None:
    reports = fake_reports()
    reports["stream"]["scaling"] = {
        "buses": [1, 32],
        "cpu_percent": [2.0, 49.9],
        "tick_jitter_p99_us": [100, 1001],
    }
    goals = build(reports)["goals"]
    assert goals["scaling.32_buses_cpu_lt_50pct"]["met"] is True
    assert goals["scaling.32_buses_p99_le_1ms"]["value"] == 1001
    assert goals["scaling.32_buses_p99_le_1ms"]["met"] is False


def test_cpu_ratio_goal_reads_baseline_b_at_1_16_and_32_buses_only() -> None:
    reports = fake_reports()
    reports["cpu"]["ratio_timerfd"] = [1.4, 1.5, 1.2, 3.0, 4.0]
    reports["cpu"]["ratio"] = [3.0, 3.0, 3.0, 3.0, 3.0]  # the minimal loop: reported only
    r = build(reports)
    goal = r["goals"]["cpu.ratio_le_1.5x_timerfd"]
    assert (goal["figure"], goal["value"], goal["met"]) == (
        "cpu.max_ratio_timerfd_1_16_32",
        1.5,
        True,
    )
    assert r["cpu"]["max_ratio_1_16_32"] == 3.0
    reports["cpu"]["buses"] = [64, 128]
    reports["cpu"]["ratio_timerfd"] = [1.0, 1.0]
    assert build(reports)["goals"]["cpu.ratio_le_1.5x_timerfd"]["met"] is None
    # A report of a bench_cpu.py without the baselines: the goal is not measured.
    del reports["cpu"]["ratio_timerfd"]
    reports["cpu"]["buses"] = [1, 16]
    assert build(reports)["goals"]["cpu.ratio_le_1.5x_timerfd"]["met"] is None


def test_where_one_core_saturates_is_the_first_count_ours_falls_behind_at() -> None:
    buses = [1, 16, 32, 64, 128]
    # A count kept up with after one that was not (noise) does not count.
    assert bench_cpu.max_buses_keeping_up(buses, [True, True, False, True, False]) == 16
    assert bench_cpu.max_buses_keeping_up(buses[::-1], [False, True, True, True, True]) == 64
    assert bench_cpu.max_buses_keeping_up(buses, [False] * 5) == 0
    reports = fake_reports()
    reports["cpu"]["max_buses_keeping_up"] = 0
    assert "ours fell behind already at **1 bus**" in run_report.render_report(build(reports))


def test_late_tick_goal_needs_every_run_measured() -> None:
    reports = fake_reports()
    runs = reports["late_ticks"]["runs"]
    runs[1]["tick_jitter_max_us"] = 999.0
    r = build(reports)
    goal = r["goals"]["late_ticks.kernel_max_le_1000us_every_run"]
    assert (goal["value"], goal["met"]) == (999.0, True)
    runs[1].update(tick_jitter_max_us=None, kernel_why="perf is not installed")
    r = build(reports)
    assert r["late_ticks"]["kernel_max_us"] is None
    assert r["goals"]["late_ticks.kernel_max_le_1000us_every_run"]["met"] is None
    report = run_report.render_report(r)
    assert "- run 2: kernel clock not measured: perf is not installed" in report


def test_report_shows_ratios_goals_and_machine() -> None:
    text = run_report.render_report(build())
    assert text.startswith("# motorbus benchmark report\n")
    assert "Linux-test, 2 CPUs, Python 3.11.7" in text
    assert DATE in text
    # decoded 500k against pymodbus 100k
    assert (
        "| reassembler framing + decode_status | 500,000 frames/s | pymodbus RTU decode: "
        "100,000 frames/s | 5.00 | >= 5 | met |"
    ) in text
    # RTT against the minimal client (1000 / 800) and the blocking one (1000 / 640)
    assert "| minimal asyncio client p50: 800 µs | 1.25 | <= 1.3 | met |" in text
    assert "blocking pyserial p50: 640 µs | 1.56 | - | - |" in text
    assert (
        "| stream tick jitter max | 2,500 µs | absolute-deadline asyncio.sleep loop max: "
        "5,000 µs | 0.50 |"
    ) in text
    # the fair baselines (issue 23): the bare timerfd loop and its busy-wait variant
    assert "| bare timerfd loop p99 (kernel): 60 µs | 2.00 | <= 150 | met |" in text
    assert "| stream CPU per tick, one bus | 90 µs | bare timerfd loop: 30 µs | 3.00 |" in text
    assert "| timerfd + busy-wait loop: 60 µs | 1.50 |" in text
    # the send-then-sleep loop drifts: never a jitter baseline, labelled drift where shown
    main = text.split("| figure |", 1)[1].split("\n\n", 1)[0]
    assert "naive" not in main and "send-then-sleep loop drift" in main
    assert "send-then-sleep loop, DRIFT not jitter: p99 (µs)" in text
    assert (
        "- **NOT MET**: `stream.max_le_2ms`: stream.tick_jitter_max_us = 2,500 (goal <= 2,000)"
    ) in text
    assert "- not measured: `scaling.32_buses_cpu_lt_50pct`" in text
    states = ("- met: ", "- **NOT MET**: ", "- not measured: ")
    goal_lines = [line for line in text.splitlines() if line.startswith(states)]
    assert len(goal_lines) == len(run_results.GOALS)
    # serialx RTT 1200 vs its minimal client 800, and vs fast 1000
    assert "| serialx | ok | TimerfdTimer | 1,200 µs | 2,400 µs | 800 µs | 1.50 | 1.20 |" in text
    assert "| 16 | n/a | n/a | 400 µs | n/a | n/a |" in text
    # kernel and simulator figures side by side; why a kernel figure is missing
    assert "| mixed: smallest start gap (µs) | 998 | 87 |" in text
    assert "- load (real-time): kernel clock not measured: perf is not installed" in text
    assert "- polls against a prompt device: pending: no pacing option" in text
    # CPU: ours, the part of it the timer spent spinning, baseline (b) and the ratio to
    # it, with its spread over the rounds in which the loops took turns; then (c) and
    # the minimal loop, each with its ratio
    assert (
        "| 16 | 20 % | 5 % | 0.55 | 10 % | 2 | 1.90-2.10 | 15 % | 1.33 | 15 % | 1.33 | 1.33 |"
        in text
    )
    # each step's machine probe beside its load average
    assert (
        "| bus-pyserial-asyncio-asyncio | 1 s | 0.50 | 6.25 ms | 21 µs | 12 % | 1 | n/a |" in text
    )
    # start-up: each command against the floor, the goal on the two that have one
    assert "| `python -c pass` (the floor) | 8 ms | 10 ms | - | - |" in text
    assert "| `motorbus --version` | 26 ms | 28 ms | 18 ms | <= 0.3 s: met |" in text
    assert "| `motorbus la status --help` | 85 ms | 87 ms | 77 ms | - |" in text
    assert "| 348 ms | 350 ms | 340 ms | <= 0.3 s: **NOT MET** |" in text
    assert (
        "| 32 | 36 % | 9 % | 0.50 | 20 % | 1.80 | 1.80 | 30 % | 1.20 | 30 % | 1.20 | 1.20" in text
    )
    assert (
        "| 128 | 99 % | 0 % | 0.40 | 60 % | 1.65 | 1.60 | 80 % | 1.24 | 90 % | 1.10 | 2.20" in text
    )
    assert "| 3 | **no: fell behind** |" in text
    assert "| 1.17 | 1.17 | 99.9 % |" in text  # not rounded up to 100 %
    assert "The ratio goal is read against (b), at 1, 16, 32 buses" in text
    assert "(c) the same armed 500 µs early" in text
    assert (
        "Where one core saturates (keeping up: sent >= 99 % of its ticks, no stream "
        "ended): ours kept up with every count up to **64 buses** (measured: 1, 16, 32, "
        "64, 128)."
    ) in text
    # the late-tick attribution: a row per run, a row per cause
    assert "## Late ticks, attributed: 2 run(s) of 60 s" in text
    assert "SCHED_OTHER, 0 CPU hogs, load average before [0.07, 0.1, 0.2]" in text
    assert "| 1 | 40 µs | 120 µs | 900 µs | 0 | 0 | 42 | 122 ms | 96 µs |" in text
    assert "| 2 | 45 µs | 506 µs | 3,447 µs | 4 | 1 | 40 | 0 ms | 101 µs |" in text
    assert "Ticks later than 500 µs after their deadline at the kernel, over all runs (5)" in text
    assert "| `machine: run queue` | 4 | 3,447 µs |" in text
    assert "| `gc` | 1 | 620 µs |" in text
    assert (
        "- **NOT MET**: `late_ticks.kernel_max_le_1000us_every_run`: "
        "late_ticks.kernel_max_us = 3,447 (goal <= 1,000)"
    ) in text


@pytest.mark.parametrize(
    ("value", "unit", "text"),
    [
        (None, "µs", "n/a"),
        (math.nan, "", "n/a"),
        (True, "", "yes"),
        (1234.6, "µs", "1,235 µs"),
        (1.2345, "", "1.23"),
        (3, "", "3"),
    ],
)
def test_fmt(value: Any, unit: str, text: str) -> None:
    assert run_report.fmt(value, unit) == text


def test_plots_are_written(tmp_path: Path) -> None:
    # Here, not at the top: matplotlib was 0.4 s of every worker's collection.
    import report_plots

    results = build()
    samples = {
        "bus-fast-asyncio": {
            "rtt_ours": [0.001, 0.0011, 0.0009],
            "rtt_minimal_client": [0.0008, 0.0009],
            "rtt_blocking_pyserial": [0.0007],
        },
        "stream": {"tick_offsets_motorbus": [0.0, 5e-5, 2e-4], "tick_offsets_naive": [0.0, 0.02]},
        "timer": {
            "runs": [
                {
                    "loop": "asyncio",
                    "period_ms": 1.0,
                    "method": "asyncio.sleep",
                    "lateness": [5e-4],
                },
                {
                    "loop": "uvloop",
                    "period_ms": 10.0,
                    "method": "TimerfdTimer",
                    "lateness": [-1e-5],
                },
            ]
        },
    }
    plots, skipped = report_plots.make_plots(results, samples, tmp_path)
    assert plots == report_plots.PLOT_FILES
    assert skipped == {}
    for name in plots.values():
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Without samples only the plots from results.json are drawn; stale files go.
    plots, skipped = report_plots.make_plots(results, {}, tmp_path)
    assert plots == {"scaling": "scaling.png", "cpu": "cpu.png"}
    assert set(skipped) == {"tick_jitter", "rtt_cdf", "timer_lateness"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cpu.png", "scaling.png"]


def test_every_start_up_goal_of_bench_startup_has_a_results_key() -> None:
    assert set(run_results.STARTUP_GOAL_KEYS) == set(run_results.STARTUP_GOALS)
    goals = {g.figure for g in run_results.GOALS if g.name.startswith("startup.")}
    assert goals == {f"startup.{k}_median_s" for k in run_results.STARTUP_GOAL_KEYS.values()}


def test_machine_probe_measures_a_loop_and_a_wake_up() -> None:
    probe = run.machine_probe()
    assert set(probe) == {"loop_ms", "wakeup_cpu_us"}
    assert probe["loop_ms"] > 0
    assert math.isfinite(probe["wakeup_cpu_us"]) and probe["wakeup_cpu_us"] >= 0


def test_steal_is_a_share_of_the_machines_cpu_time() -> None:
    cpus = run.os.cpu_count() or 1
    assert run.steal_percent(10.0, 10.0 + cpus, 4.0) == 25.0  # a quarter of 4 s x cpus
    assert run.steal_percent(None, 3.0, 4.0) is None  # no /proc/stat: not measured
    assert run.steal_percent(1.0, 2.0, 0.0) is None
    now = run.steal_seconds()
    assert now is None or now >= 0


def test_vcpu_gap_loop_counts_every_step_over_its_threshold() -> None:
    """With a threshold below any clock step every step is a gap: the gaps then add up
    to the loop's wall time, and each is split into what was charged and what was not."""
    import bench_vcpu_gaps

    allowed = run.os.sched_getaffinity(0)
    cpu = min(allowed)
    try:
        loop = bench_vcpu_gaps.busy_loop(cpu, 0.05, 1e-12)
        assert run.os.sched_getaffinity(0) == {cpu}  # pinned, as each loop's process is
        idle = bench_vcpu_gaps.busy_loop(cpu, 0.01, 10.0)
    finally:
        run.os.sched_setaffinity(0, allowed)
    assert loop["cpu"] == cpu and loop["wall_s"] >= 0.05
    assert loop["gaps"] > 100
    assert loop["gap_total_ms"] == pytest.approx(1e3 * loop["wall_s"], rel=0.01)
    total = loop["uncharged_total_ms"] + loop["charged_total_ms"]
    assert total == pytest.approx(loop["gap_total_ms"], abs=0.05)
    assert idle["gaps"] == 0  # no step of 10 s in a 10 ms loop


def test_profile_layers_put_each_file_in_one_place() -> None:
    import profile_cpu

    assert profile_cpu.layer("~") == "C"
    assert profile_cpu.layer("/x/src/motorbus/bus/engine.py") == "shell"
    assert profile_cpu.layer("/x/src/motorbus/transport/serial.py") == "shell"
    assert profile_cpu.layer("/x/src/motorbus/bus/schedule.py") == "core"
    assert profile_cpu.layer("/x/src/motorbus/protocol/la/wire.py") == "core"
    assert profile_cpu.layer("/x/src/motorbus/devices/la.py") == "motorbus, other"
    assert profile_cpu.layer("/usr/lib/python3.11/asyncio/events.py") == "asyncio"
    assert profile_cpu.layer("/usr/lib/python3.11/selectors.py") == "selectors"
    assert profile_cpu.layer("/x/benchmarks/bench_cpu.py") == "benchmark"
    assert profile_cpu.layer("<frozen abc>") == "other"
    assert set(profile_cpu.LAYERS) >= {"shell", "core", "C", "other"}


def test_ab_pairs_alternate_and_are_summarised_pair_by_pair() -> None:
    import ab_cpu

    assert [ab_cpu.order(i) for i in range(3)] == [
        ("before", "after"),
        ("after", "before"),
        ("before", "after"),
    ]
    # Pair 2 is a slow spell on both sides: its ratio, not its level, counts.
    s = ab_cpu.paired_summary([10.0, 10.0, 20.0], [9.0, 11.0, 16.0])
    assert s["ratios"] == [0.9, 1.1, 0.8]
    assert s["median_ratio"] == 0.9
    assert s["after_won"] == 2 and s["pairs"] == 3
    assert s["before_median"] == 10.0 and s["after_median"] == 11.0
    with pytest.raises(ValueError):
        ab_cpu.paired_summary([1.0], [])


def test_ab_counts_the_timers_settime_calls_whatever_the_tree(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """ab_cpu.py counts timerfd_settime through the timer's syscall wrapper, so any tree
    with the timerfd timer compares; the count agrees with ``harness.TimerProbe``'s arms
    (the library keeps no counter of its own)."""
    import asyncio

    import ab_cpu
    from harness import TimerProbe
    from motorbus.bus import timer as timer_module
    from motorbus.bus.timerfd import TimerfdApi as api

    if not timer_module.timerfd_available():
        pytest.skip("no timerfd on this platform")
    monkeypatch.setattr(api, "set_absolute_ns", api.set_absolute_ns)  # restored after
    calls = ab_cpu.count_settime_calls()

    async def main() -> int:
        timer = timer_module.TimerfdTimer(spin_lead=0.0)
        probe = TimerProbe(timer)
        for _ in range(3):
            await timer.sleep_until(timer.now() + 0.001)
        assert probe.wakeups >= 3 and probe.spin_s == 0.0
        timer.close()
        return probe.arms

    arms = asyncio.run(main())
    assert arms >= 3
    assert calls[0] >= arms  # each arming, and the disarms that arms leaves out


def test_ab_exports_a_revision_of_this_checkout(tmp_path: Path) -> None:
    import ab_cpu

    if not (ab_cpu.REPO / ".git").exists():
        pytest.skip("not a git checkout (an sdist)")
    src = ab_cpu.export_rev("HEAD", tmp_path)
    assert (src / "motorbus" / "__init__.py").is_file()


def test_cpu_tick_lateness_is_taken_over_every_stream_at_once() -> None:
    from motorbus.bus.stats import LatencyHistogram

    quick, slow, empty = LatencyHistogram(), LatencyHistogram(), LatencyHistogram()
    for _ in range(99):
        quick.record(10e-6)
    slow.record(5e-3)  # one stream's slow first tick: not the p99 of all 100 ticks
    m = bench_cpu.merged([quick, slow, empty])
    assert m.count == 100 and m.max == 5e-3 and m.min == 10e-6
    assert m.percentile(99) == pytest.approx(10e-6, rel=0.01)
    assert m.percentile(100) == 5e-3
    assert bench_cpu.merged([]).count == 0


def test_the_three_cpu_sides_take_turns_and_ratios_are_taken_pair_by_pair() -> None:
    import bench_cpu_tasks as tasks

    assert [tasks.rotation(k)[0] for k in range(4)] == ["minimal", "tasks", "ours", "minimal"]
    assert all(sorted(tasks.rotation(k)) == sorted(tasks.SIDES) for k in range(3))

    def pair(minimal: float, with_tasks: float, ours: float) -> dict[str, dict[str, Any]]:
        return {
            "minimal": {"cpu_percent": minimal},
            "tasks": {"cpu_percent": with_tasks},
            "ours": {"cpu_percent": ours},
        }

    # The second pair is a slow spell on every side: its ratios, not its levels, count.
    s = tasks.summarise([pair(10, 15, 30), pair(20, 30, 50), pair(10, 12, 24)])
    assert s["ours_over_minimal"] == 2.5 and s["ours_over_minimal_range"] == [2.4, 3.0]
    assert s["tasks_over_minimal"] == 1.5 and s["ours_over_tasks"] == 2.0
    assert s["minimal_cpu_percent"] == 10 and s["ours_cpu_percent"] == 30


def test_the_task_loop_does_the_minimal_loops_work(tmp_path: Path) -> None:
    import asyncio

    import bench_cpu_tasks as tasks

    responder = bench_cpu.Responder(2, tmp_path / "rec.json")
    try:
        # A reply timeout no loaded machine misses: every poll is answered and counted.
        out = asyncio.run(tasks.tasks_loop(responder.paths, 0.2, reply_timeout=10.0))
    finally:
        responder.stop()
    assert out["ticks"] == 2 * 20  # 20 ticks of 10 ms per bus, none skipped
    assert out["replies"] == out["ticks"]  # a poll a tick, each reply counted once
    assert out["cpu_percent"] > 0


def test_ours_polls_on_one_clock_for_every_bus_when_asked(tmp_path: Path) -> None:
    """``--polls shared``: the same work (a tick and a poll per bus and 10 ms), the polls
    of every bus on one clock; an unknown phase is refused before anything runs."""
    import asyncio

    with pytest.raises(ValueError, match="polls must be one of tick, shared"):
        asyncio.run(bench_cpu.ours([], 0.1, polls="sometimes"))
    responder = bench_cpu.Responder(2, tmp_path / "rec.json")
    try:
        out = asyncio.run(bench_cpu.ours(responder.paths, 0.3, polls="shared"))
        apart = asyncio.run(bench_cpu.ours(responder.paths, 0.3, polls="tick"))
    finally:
        responder.stop()
    # Two buses in two tick phases: each poll task on its own bus's clock, or on one.
    assert (apart["tick_phases"], apart["poll_clocks"]) == (2, 2)
    assert (out["tick_phases"], out["poll_clocks"]) == (2, 1)
    assert out["stream_errors"] == 0
    assert out["ticks"] > 0 and out["polls"] > 0
    assert out["replies"] <= out["polls"]


def test_ours_spreads_the_buses_over_the_phase_groups_asked_then_restores_the_librarys(
    tmp_path: Path,
) -> None:
    """``--phase-groups``: the run uses that many tick phases; the library's constant is
    back afterwards, and a count below 1 is refused before anything runs."""
    import asyncio

    from motorbus import manager

    library = manager.PHASE_GROUPS
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="phase_groups must be an integer >= 1"):
            asyncio.run(bench_cpu.ours([], 0.1, phase_groups=bad))  # type: ignore[arg-type]
    responder = bench_cpu.Responder(3, tmp_path / "rec.json")
    try:
        one = asyncio.run(bench_cpu.ours(responder.paths, 0.2, phase_groups=1))
        three = asyncio.run(bench_cpu.ours(responder.paths, 0.2, phase_groups=3))
    finally:
        responder.stop()
    assert library == manager.PHASE_GROUPS
    assert (one["tick_phases"], three["tick_phases"]) == (1, 3)
    out = one
    assert out["stream_errors"] == 0 and out["ticks"] > 0
    assert (
        bench_cpu.combine(
            [
                {**out, "tick_p99_us": 100.0},
                {**out, "tick_p99_us": 300.0},
                {**out, "tick_p99_us": 200.0},
            ]
        )["tick_p99_us"]
        == 200.0
    )


def test_bench_pieces_times_every_piece_it_labels(caplog: pytest.LogCaptureFixture) -> None:
    """Each labelled piece is measured (the timerfd's only where there is one), in
    microseconds above zero, and the bus it used closed without a safe stop owed.
    ``timer_call_at_cancel_us`` is a difference of two timed loops (with and without
    the call), which 20 calls on a loaded machine can make zero or less: a number."""
    import asyncio

    import bench_pieces
    from motorbus.bus.timer import timerfd_available

    figures = asyncio.run(bench_pieces.measure(number=20, repeat=1))
    expected = set(bench_pieces.LABELS)
    if not timerfd_available():
        expected -= {k for k in expected if k.startswith("settime_")}
    assert expected <= set(figures)
    differences = {"timer_call_at_cancel_us"}
    assert all(figures[k] > 0 for k in expected - differences)
    assert all(math.isfinite(figures[k]) for k in expected & differences)
    assert not [r for r in caplog.records if "safe action" in r.getMessage()]


def test_the_timerfd_baselines_do_ours_work_on_ours_phases(tmp_path: Path) -> None:
    """Baselines (b) and (c) of bench_cpu.py: a broadcast a tick and a query a tick for
    every bus, each reply read; buses on the phases ours would put them on."""
    import asyncio

    import baselines

    assert [bench_cpu.turn_order(r)[0] for r in range(4)] == list(bench_cpu.SIDES)
    assert sorted(bench_cpu.turn_order(5)) == sorted(bench_cpu.SIDES)
    with pytest.raises(ValueError, match="side must be one of"):
        bench_cpu.run_side("fastest", [], 0.1, "tick", None)
    responder = bench_cpu.Responder(3, tmp_path / "rec.json")
    try:
        for spin in (0.0, baselines.SPIN_S):
            work = bench_cpu.polled_work(2)
            out = asyncio.run(baselines.polled_timerfd_loop(responder.paths, work, 0.2, spin=spin))
            assert (out["ticks"], out["polls"]) == (3 * 20, 3 * 20), spin
            assert out["replies"] == out["polls"], spin  # every query answered, read once
            assert out["cpu_percent"] > 0
    finally:
        responder.stop()
    # Each bus got its tick's broadcast, then its query, tick after tick, in both runs.
    per_pty = json.loads((tmp_path / "rec.json").read_text())["frames"]
    broadcast, query = bench_cpu.broadcast_bytes(0)[4], bench_cpu.QUERIES[0][4]
    assert [[cmd for _, cmd in frames] for frames in per_pty] == [[broadcast, query] * 40] * 3


def test_polls_none_leaves_the_queries_out_of_every_loop(tmp_path: Path) -> None:
    """``--polls none`` (issue 40's streams-alone goal): ours, the timerfd baseline and
    the minimal loop each write their ticks' broadcasts and not one query."""
    import asyncio

    import baselines

    responder = bench_cpu.Responder(2, tmp_path / "rec.json")
    try:
        work = bench_cpu.polled_work(2, polls=False)
        base = asyncio.run(baselines.polled_timerfd_loop(responder.paths, work, 0.2, spin=0.0))
        minimal = asyncio.run(bench_cpu.minimal(responder.paths, 0.2, polls=False))
        ours = asyncio.run(bench_cpu.ours(responder.paths, 0.2, polls="none"))
    finally:
        responder.stop()
    assert (base["ticks"], base["polls"], base["replies"]) == (2 * 20, 0, 0)
    assert (minimal["polls"], minimal["replies"]) == (0, 0)
    assert 2 * 20 <= minimal["ticks"] <= 2 * 21  # its end is a float compare
    assert (ours["polls"], ours["replies"], ours["stream_errors"]) == (0, 0, 0)
    assert ours["ticks"] > 0  # (a loaded machine skips some: counted, not a failure)
    per_pty = json.loads((tmp_path / "rec.json").read_text())["frames"]
    broadcast, control = bench_cpu.broadcast_bytes(0)[4], bench_cpu.QUERIES[0][4]
    for frames in per_pty:
        # Broadcasts only, then ours's stream end: a pause (CMD_MC, as a query is) to each
        # actuator.  A poll would have come between two broadcasts.
        cmds = [cmd for _, cmd in frames]
        body = cmds[: cmds.index(control)]
        assert body and set(body) == {broadcast}, cmds
        assert set(cmds[len(body) :]) == {control} and len(cmds) - len(body) >= 15, cmds


def record(t: float, hexstr: str, direction: str = "request") -> dict[str, Any]:
    return {"t": t, "kind": "frame", "direction": direction, "hex": hexstr}


def test_a_safe_stops_spread_runs_to_the_last_present_actuators_first_pause() -> None:
    """bench_safe_stop.py's figure, from a simulator's frame log: la:1 is absent (its
    pause retried), la:2 and la:3 are there; a broadcast and a reply do not count."""
    import bench_safe_stop as b

    def pause(ident: int) -> str:
        return b.la.Control(ident, b.la.ControlAction.PAUSE).encode().hex(" ")

    records = [
        record(0.990, "55 AA 2E FF F3 01 E8 03"),
        record(1.000, pause(1)),
        record(1.004, pause(2)),
        record(1.005, "AA 55 11 02 04 00 14 00", direction="reply"),
        record(1.006, pause(3)),
        record(1.030, pause(1)),  # la:1's retry
        record(1.040, pause(2)),  # the close's pause: not the first
    ]
    assert b.spread_ms(records, {2, 3}) == pytest.approx(6.0)
    assert b.spread_ms(records, {2, 3, 4}) is None  # la:4 got no pause
    assert b.spread_ms([], {2}) is None
    s = b.summary([6.0, None, 10.0])
    assert (s["median_ms"], s["max_ms"], s["runs_missing_a_pause"]) == (8.0, 10.0, 1)


def test_the_parts_taken_out_come_back_and_the_stream_still_ticks(tmp_path: Path) -> None:
    """``bench_cpu_parts.py``: each variant replaces its parts of the bus for its run
    only; with all of them out, the workload still sends its ticks (over a pty)."""
    import bench_cpu_parts as parts
    from motorbus.bus.engine import BusEngine
    from motorbus.bus.lease_shell import LeaseKeeper

    claim, queue = LeaseKeeper.__dict__["claim"], BusEngine.__dict__["queue"]
    with parts.without(("no_leases",)):
        assert LeaseKeeper.__dict__["claim"] is parts._nothing
        assert BusEngine.__dict__["queue"] is queue
    with pytest.raises(RuntimeError), parts.without(parts.PARTS):
        assert BusEngine.__dict__["queue"] is not queue
        raise RuntimeError("a run that failed")
    assert (LeaseKeeper.__dict__["claim"], BusEngine.__dict__["queue"]) == (claim, queue)
    responder = bench_cpu.Responder(1, tmp_path / "rec.json")
    try:
        out = parts.run_once("without_all", responder.paths, 0.2, "none")
    finally:
        responder.stop()
    assert out["stream_errors"] == 0 and out["ticks"] >= 15
    assert (LeaseKeeper.__dict__["claim"], BusEngine.__dict__["queue"]) == (claim, queue)


@pytest.mark.parametrize("side", ["bare_write", "bare_tick"])
def test_a_bare_side_writes_every_tick_itself_and_gives_the_streamer_back(
    side: str, tmp_path: Path
) -> None:
    """``bench_cpu_parts.py``'s bare sides write each tick's 0xF3 frame from the
    streamer's callback with ``os.write``; the frames reach the port (the responder
    records them) and the streamer's own methods come back after the run."""
    import bench_cpu_parts as parts
    from motorbus.streams import Streamer

    fire, prepare = Streamer.__dict__["_fire"], Streamer.__dict__["_prepare_tick"]
    responder = bench_cpu.Responder(1, tmp_path / "rec.json")
    try:
        out = parts.run_once(side, responder.paths, 0.2, "none")
    finally:
        responder.stop()
    assert out["stream_errors"] == 0 and out["ticks"] >= 15
    assert (Streamer.__dict__["_fire"], Streamer.__dict__["_prepare_tick"]) == (fire, prepare)
    (frames,) = json.loads((tmp_path / "rec.json").read_text())["frames"]
    assert sum(1 for _t, cmd in frames if cmd == 0xF3) >= out["ticks"]


#: benchmarks/*.py that are not scripts writing a report of their own: the harness, the
#: full run and its parts, and modules or children the scripts use.
NOT_REPORTING = {
    "harness.py",
    "run.py",
    "run_results.py",
    "run_report.py",
    "report_plots.py",
    "pty_recorder.py",
    "sim_many.py",
    "guard_victim.py",
    "baselines.py",
    "kernel_clock.py",
    "late_ticks.py",
}


def test_every_benchmark_script_writes_its_report_with_write_report() -> None:
    """A script's report gets its machine, date and writing from harness.write_report."""
    scripts = sorted(p for p in BENCHMARKS.glob("*.py") if p.name not in NOT_REPORTING)
    assert all((BENCHMARKS / name).is_file() for name in NOT_REPORTING)
    assert len(scripts) > 20
    missing = []
    for path in scripts:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        calls = [
            node.func
            for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name | ast.Attribute)
        ]
        names = {f.id if isinstance(f, ast.Name) else f.attr for f in calls}
        if "write_report" not in names:
            missing.append(path.name)
    assert missing == []


def test_write_report_adds_the_machine_and_date_and_keeps_a_scripts_own_machine_keys(
    tmp_path: Path,
) -> None:
    import harness

    out = tmp_path / "deep" / "r.json"
    harness.write_report(out, {"x": 1, "machine": {"load_avg_before": [0.5, 0.4, 0.3]}})
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["x"] == 1 and report["date"]
    assert report["machine"]["load_avg_before"] == [0.5, 0.4, 0.3]
    assert {"platform", "python", "cpus", "load_avg"} <= set(report["machine"])


def test_instructions_a_tick_are_the_difference_of_two_runs_over_their_ticks() -> None:
    import count_instructions as ci

    # Start-up (1,000) cancels out: 200 ticks more cost 200 * 300 instructions more.
    assert ci.per_tick((1_000 + 100 * 300, 100), (1_000 + 300 * 300, 300)) == 300
    assert ci.per_tick((5, 100), (9, 100)) is None  # no more ticks: no figure
    err = (
        "==12== I   refs:      1,843,299,318\n==12== I1  misses:        6,741,061\n"
        "==12== LLi misses:           21,005\n==12== D   refs:        852,751,394  (558 rd)\n"
        "==12== D1  misses:       12,653,755  (  9,973,806 rd   +   2,679,949 wr)\n"
    )
    assert ci.collected(err) == {
        "instructions": 1_843_299_318,
        "i1_misses": 6_741_061,
        "d1_misses": 12_653_755,
    }
    with pytest.raises(RuntimeError, match="no cachegrind summary"):
        ci.collected("valgrind: command not found")
    assert ci.ratio(120.0, 100.0) == 1.2 and ci.ratio(None, 100.0) is None
    assert ci.collected(err, caches=False) == {"instructions": 1_843_299_318}


def test_a_child_kept_up_with_its_ticks_its_replies_and_on_time() -> None:
    import count_instructions as ci

    assert ci.kept_up({"ticks": 598, "replies": 600, "late_ticks": 8, "polls": "tick"}, 6.0)
    assert ci.kept_up({"ticks": 600, "replies": 0, "late_ticks": None, "polls": "none"}, 6.0)
    # Saturated: the ticks went out, but late, and a poll in seven was skipped.
    late = {"ticks": 595, "replies": 512, "late_ticks": 512, "polls": "tick"}
    assert not ci.kept_up(late, 6.0)
    assert not ci.kept_up({**late, "replies": 600}, 6.0)  # late alone fails it
    assert not ci.kept_up({"ticks": 500, "replies": 0, "late_ticks": 0, "polls": "none"}, 6.0)


@pytest.mark.parametrize("side", ["ours", "without_all"])
def test_the_instruction_counts_child_runs_one_side_and_prints_its_ticks(
    side: str, capsys: pytest.CaptureFixture[str]
) -> None:
    import count_instructions as ci

    ci.child(side, 0.3, "none")
    ticks = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["ticks"]
    assert ticks >= 15
