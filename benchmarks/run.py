"""Run every benchmark, collect their JSON, and write one results.json, report.md and plots.

Each benchmark script runs as its own subprocess, one after the other (running them side
by side would make them compete for this machine's two cores): the reassembler, the bus
once per installed serial backend and once on uvloop, the stream with its scaling run,
the timers, the stream under load (two CPU hogs, plain and real-time), the CPU per
bus-tick against a minimal loop (up to 128 buses: where one core saturates) and the
late-tick attribution (README's stream three times for 60 s, every tick later than
500 µs at the kernel put down to a cause).  Their JSON reports and raw samples land in
``DIR/raw/`` and their output in ``DIR/logs/``; this script then writes to ``DIR``:

* ``results.json``: every figure under a stable key (documented in benchmarks/README.md);
* ``report.md``: machine and date, a line per goal, and tables of each figure with the
  baseline measured in the same run and the ratio to it;
* ``*.png``: tick-jitter histogram, RTT CDFs, scaling curves, timer lateness CDFs.

A benchmark that fails or times out is reported (``errors``, ``runs``) and its figures are
``null``; the others still count.  Numbers are reported as measured, never tuned.

Usage: ``python benchmarks/run.py [--quick] [--out DIR] [--report-only]``
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import math
import operator
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_bus import (
    BACKEND_MODULES,
    GOAL_EARLY,
    GOAL_LATE_P99_US,
    GOAL_MIN_GAP_US,
    GOAL_PROMPT_TIMEOUTS,
    GOAL_RATIO,
    GOAL_TICKS_SENT_PCT,
)
from bench_cpu import GOAL_32_CPU_PERCENT as GOAL_CPU_32_PERCENT
from bench_cpu import GOAL_RATIO as GOAL_CPU_RATIO
from bench_cpu import GOAL_RATIO_BUSES as CPU_GOAL_RATIO_BUSES
from bench_cpu import KEEPS_UP_TICKS_SENT_PCT
from bench_late_ticks import GOAL_QUIET_MAX_US as GOAL_LATE_MAX_US
from bench_load import GOAL_RT_MAX_US, GOAL_RT_P99_US
from bench_reassembler import GOAL_DECODED_PER_S, GOAL_FRAMES_PER_S, GOAL_RATIO_VS_PYMODBUS
from bench_startup import COMMANDS as STARTUP_COMMANDS
from bench_startup import GOAL_S as GOAL_STARTUP_S
from bench_startup import GOALS as STARTUP_GOALS
from kernel_clock import LATE_S
from late_ticks import CAUSES as LATE_CAUSES

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "results" / "latest"
#: Bumped whenever a key of results.json changes meaning or disappears.
SCHEMA_VERSION = 2
#: The bus configuration the headline figures come from (the library's defaults).
MAIN_BACKEND = "fast"
MAIN_LOOP = "asyncio"
#: Every backend the bus supports (motorbus.transport.serial.BACKENDS), in report order.
ALL_BACKENDS = tuple(BACKEND_MODULES)
ALL_LOOPS = ("asyncio", "uvloop")
#: Timer bench run length per (loop, period, method): 1 s gives 1000 wake-ups at 1 ms.
TIMER_SECONDS_QUICK = 1.0
TIMER_SECONDS_FULL = 2.0
#: A step that runs longer than this is killed and reported as failed; far above the
#: longest full runs (the stream: 30 s x 2 + 10 s x 4; the late ticks: 3 x 60 s; each
#: plus start-up).
STEP_TIMEOUT_S = 600.0
#: bench_cpu.py bus counts of the full run: the issue's 1, 16, 32, then 64 and 128 to
#: find where one core saturates (``--quick`` keeps the script's own, smaller set).
CPU_BUSES_FULL = (1, 16, 32, 64, 128)
#: bench_late_ticks.py in the full run: the issue's goal is three 60 s runs.
LATE_TICKS_RUNS_FULL = 3
LATE_TICKS_SECONDS_FULL = 60.0
#: bench_startup.py in the full run: runs per command (``--quick`` keeps the script's 3),
#: on this tree only (``--no-before``): the report says what is here, and a before/after
#: comparison is the script's own job (``--before-ref``).
STARTUP_RUNS_FULL = 7
#: The results.json key of each command with a start-up goal (which commands have one is
#: bench_startup.GOALS's to say; a test checks that every one of them has a key here).
STARTUP_GOAL_KEYS = {
    "motorbus --version": "version",
    "motorbus la status 1 --port PTY": "la_status",
}
#: Runs of a step that exits with an error (see run_step).
STEP_ATTEMPTS = 2
#: The machine probe taken before each step (:func:`machine_probe`).  The load average
#: does not say how fast a shared VM is: two full runs 28 minutes apart (2026-12-03, load
#: average under 0.6 both times, the same code) measured the minimal loop of bench_cpu.py
#: at 13 % and 21 % of a core for the same work at 32 buses, and ours at 36 % and 70 %.
#: The probe did not find that cause: two runs later it was normal (6.4 ms, 24 us) before
#: a CPU step as slow as that.  It rules out the simplest causes (a slow interpreter,
#: costly wake-ups), not every one.
PROBE_LOOP_ITERATIONS = 200_000
PROBE_LOOP_REPEATS = 5
PROBE_SLEEPS = 200
PROBE_SLEEP_S = 0.001
#: The bus's 1 ms minimum spacing between commands: the ceiling of the command rate.
SPACING_US = 1000.0
IDEAL_COMMANDS_PER_S = 1e6 / SPACING_US
#: Goals of bench_stream.py (its GOALS table), restated as numbers for the report.
GOAL_STREAM_P99_US = 300.0
GOAL_STREAM_MAX_US = 2000.0
GOAL_STREAM_DRIFT_PPM = 100.0
GOAL_SCALING_BUSES = 32
GOAL_SCALING_CPU_PERCENT = 50.0
GOAL_SCALING_P99_US = 1000.0
#: Goals on the kernel's clock (kernel_clock.py): what the bus wrote, not when a
#: receiver woke up.
GOAL_RATE = 950.0
GOAL_KERNEL_P99_US = 150.0
GOAL_KERNEL_MAX_US = 1000.0
#: Keys of the kernel-clock figures of one phase of bench_bus (after a prefix).
KERNEL_PHASE_KEYS = (
    "kernel_measured",
    "kernel_why",
    "kernel_min_gap_us",
    "kernel_gaps_under_1000us",
    "kernel_min_gap_after_return_us",
    "kernel_write_p50_us",
    "kernel_write_p99_us",
    "kernel_write_max_us",
    "kernel_writes",
)
KERNEL_TICK_KEYS = (
    "kernel_ticks",
    "kernel_ticks_sent_pct",
    "kernel_tick_jitter_p50_us",
    "kernel_tick_jitter_p99_us",
    "kernel_tick_jitter_max_us",
    "kernel_late_ticks",
    "kernel_missed_ticks",
)
MIXED_KEYS = (
    "mixed_seconds",
    "mixed_stream_stalled",
    "mixed_frames_sim",
    "mixed_requests",
    "mixed_request_failures",
    "mixed_host_ticks",
    "mixed_host_late",
    "mixed_host_skipped",
    "mixed_polls",
    "mixed_poll_timeouts",
    "mixed_bus_requests",
    "mixed_bus_timeouts",
    "mixed_sim_min_gap_us",
    "mixed_sim_gaps_under_1000us",
    "mixed_sim_tick_jitter_p99_us",
    "mixed_sim_tick_jitter_max_us",
    *(f"mixed_{k}" for k in KERNEL_PHASE_KEYS + KERNEL_TICK_KEYS),
    "mixed_prompt_pacing",
    "mixed_prompt_poll_timeouts",
    "mixed_prompt_bus_timeouts",
)
LOAD_KEYS = (
    "kernel_measured",
    "kernel_why",
    "tick_jitter_p50_us",
    "tick_jitter_p99_us",
    "tick_jitter_max_us",
    "late_ticks",
    "missed_ticks",
    "ticks",
    "ticks_sent_pct",
    "min_gap_us",
    "gaps_under_1000us",
    "write_max_us",
    "host_late",
    "host_skipped",
    "polls",
    "poll_timeouts",
)
CPU_KEYS = (
    "buses",
    "cpu_percent",
    "spin_percent",
    "minimal_cpu_percent",
    "ratio",
    "ratio_per_tick",
    "ticks",
    "minimal_ticks",
    "replies",
    "minimal_replies",
    "late_ticks",
    "skipped_ticks",
    "ticks_sent_pct",
    "stream_errors",
    "keeps_up",
    "round_ratios",
)
#: Figures of each run of bench_late_ticks.py (kernel clock unless said).
LATE_RUN_KEYS = (
    "tick_jitter_p50_us",
    "tick_jitter_p99_us",
    "tick_jitter_max_us",
    "late_ticks",
    "missed_ticks",
    "ticks",
    "host_late",
    "host_skipped",
    "cpu_us_per_tick",
    "timer_wakeups",
    "timer_spin_s",
    "gc_collections",
    "rt_method",
    "kernel_why",
)

REASSEMBLER_KEYS = (
    "frames_per_s",
    "frames_per_s_garbage1",
    "decoded_per_s",
    "decoded_per_s_garbage1",
    "pymodbus_decoded_per_s",
    "ratio_vs_pymodbus",
    "frames_per_pass",
    "seconds_per_run",
    "repeats",
)
BUS_KEYS = (
    "rtt_p50_us",
    "rtt_p99_us",
    "rtt_minimal_client_p50_us",
    "rtt_minimal_client_p99_us",
    "rtt_blocking_pyserial_p50_us",
    "rtt_blocking_pyserial_p99_us",
    "rtt_ratio_vs_minimal",
    "commands_per_s",
    "min_gap_us",
    "gaps_under_1000us",
    "min_gap_bus_clock_us",
    "rate_gap_bus_clock_p50_us",
    "rate_timer_fire_late_p50_us",
    "rate_timeouts",
    "timeout_late_p50_us",
    "timeout_late_p99_us",
    "timeout_late_max_us",
    "timeout_early_count",
    "timeout_timer_fire_late_p50_us",
    "timeout_timer_fire_late_p99_us",
    *(f"rate_{k}" for k in KERNEL_PHASE_KEYS),
    *MIXED_KEYS,
    "n",
    "rate_seconds",
)
#: Figures kept for each backend and each event loop (bus.backends.*, bus.loops.*).
BUS_VARIANT_KEYS = (
    "rtt_p50_us",
    "rtt_p99_us",
    "rtt_minimal_client_p50_us",
    "rtt_minimal_client_p99_us",
    "rtt_ratio_vs_minimal",
    "commands_per_s",
    "min_gap_us",
    "gaps_under_1000us",
    "timeout_late_p50_us",
    "timeout_late_p99_us",
    "timeout_early_count",
)
STREAM_KEYS = (
    "tick_jitter_p50_us",
    "tick_jitter_p99_us",
    "tick_jitter_max_us",
    "missed_ticks",
    "drift_ppm",
    "frames",
    "host_late_ticks",
    "host_skipped_ticks",
    "naive_tick_jitter_p99_us",
    "naive_tick_jitter_max_us",
    "naive_drift_ppm",
    "naive_mean_period_us",
    "seconds",
    "kernel_measured",
    "kernel_why",
    "kernel_tick_jitter_p50_us",
    "kernel_tick_jitter_p99_us",
    "kernel_tick_jitter_max_us",
    "kernel_late_ticks",
    "kernel_missed_ticks",
    "kernel_min_gap_us",
    "kernel_gaps_under_1000us",
    "naive_kernel_tick_jitter_p99_us",
    "naive_kernel_tick_jitter_max_us",
    # The hand-written baselines (benchmarks/baselines.py) and motorbus's ratios to them.
    "cpu_us_per_tick",
    *(
        f"baseline_{name}_{key}"
        for name in ("sleep", "timerfd", "timerfd_spin")
        for key in (
            "kernel_tick_jitter_p50_us",
            "kernel_tick_jitter_p99_us",
            "kernel_tick_jitter_max_us",
            "kernel_late_ticks",
            "kernel_missed_ticks",
            "tick_jitter_p99_us",
            "tick_jitter_max_us",
            "cpu_us_per_tick",
            "cpu_percent",
        )
    ),
    *(
        f"ratio_vs_{name}_{key}"
        for name in ("timerfd", "timerfd_spin")
        for key in (
            "kernel_jitter_p50",
            "kernel_jitter_p99",
            "kernel_jitter_max",
            "cpu_per_tick",
        )
    ),
)
SCALING_KEYS = (
    "buses",
    "cpu_percent",
    "cpu_percent_per_bus",
    "tick_jitter_p99_us",
    "tick_jitter_max_us",
    "missed_ticks",
    "kernel_tick_jitter_p99_us",
    "kernel_tick_jitter_max_us",
    "kernel_late_ticks",
    "kernel_missed_ticks",
)
TIMER_ROW_KEYS = (
    "loop",
    "period_ms",
    "method",
    "wakeups",
    "p50_us",
    "p99_us",
    "max_us",
    "early",
    "most_early_us",
    "p99_ratio_to_sleep",
)


# -- the plan ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Step:
    """One benchmark subprocess.

    Attributes:
        name: file stem of its JSON in ``raw/`` and of its log in ``logs/``.
        script: the benchmark script, relative to ``benchmarks/``.
        args: its command-line options, without ``--out`` and ``--samples``.
        samples: whether the script takes ``--samples`` (raw values for the plots).
    """

    name: str
    script: str
    args: tuple[str, ...]
    samples: bool

    def command(self, raw_dir: Path) -> list[str]:
        """The full command line, writing into ``raw_dir``."""
        cmd = [sys.executable, str(HERE / self.script), *self.args]
        cmd += ["--out", str(raw_dir / f"{self.name}.json")]
        if self.samples:
            cmd += ["--samples", str(raw_dir / f"{self.name}.samples.json")]
        return cmd


def bus_step_name(backend: str, loop: str) -> str:
    """The step (and raw file) name of a bus run."""
    return f"bus-{backend}-{loop}"


def installed(module: str) -> bool:
    """Whether ``module`` can be imported (without importing it)."""
    return importlib.util.find_spec(module) is not None


def installed_backends() -> list[str]:
    """The serial backends whose package is installed, in :data:`ALL_BACKENDS` order."""
    return [name for name in ALL_BACKENDS if installed(BACKEND_MODULES[name])]


def installed_loops() -> list[str]:
    """The event loops available here: always the default one, uvloop if installed."""
    return [loop for loop in ALL_LOOPS if loop == "asyncio" or installed(loop)]


def plan(quick: bool, backends: Sequence[str], loops: Sequence[str]) -> list[Step]:
    """The benchmark runs, in order.

    Args:
        quick: pass ``--quick`` (shorter runs) to every script.
        backends: serial backends to measure the bus on, each on the default loop.
        loops: event loops to measure the bus on, each with :data:`MAIN_BACKEND`.

    Returns:
        The steps; the bus run on (MAIN_BACKEND, MAIN_LOOP) comes once, first of the bus
        runs, and serves both comparisons.
    """
    q = ("--quick",) if quick else ()
    steps = [Step("reassembler", "bench_reassembler.py", q, samples=False)]
    pairs = [(MAIN_BACKEND, MAIN_LOOP)]
    pairs += [(b, MAIN_LOOP) for b in backends if b != MAIN_BACKEND]
    pairs += [(MAIN_BACKEND, loop) for loop in loops if loop != MAIN_LOOP]
    for backend, loop in pairs:
        args = (*q, "--backend", backend, "--loop", loop)
        if (backend, loop) != (MAIN_BACKEND, MAIN_LOOP):
            args += ("--mixed-seconds", "0")  # the mixed workload: headline run only
        steps.append(Step(bus_step_name(backend, loop), "bench_bus.py", args, samples=True))
    steps.append(Step("stream", "bench_stream.py", q, samples=True))
    seconds = TIMER_SECONDS_QUICK if quick else TIMER_SECONDS_FULL
    steps.append(Step("timer", "bench_timer.py", ("--seconds", f"{seconds:g}"), samples=True))
    steps.append(Step("load", "bench_load.py", q, samples=False))
    cpu_args = q or ("--buses", ",".join(map(str, CPU_BUSES_FULL)))
    steps.append(Step("cpu", "bench_cpu.py", cpu_args, samples=False))
    late_args = q or (
        "--runs",
        str(LATE_TICKS_RUNS_FULL),
        "--seconds",
        f"{LATE_TICKS_SECONDS_FULL:g}",
    )
    steps.append(Step("late_ticks", "bench_late_ticks.py", late_args, samples=False))
    startup_args = q or ("--runs", str(STARTUP_RUNS_FULL))
    steps.append(Step("startup", "bench_startup.py", (*startup_args, "--no-before"), samples=False))
    return steps


def machine_probe() -> dict[str, float]:
    """How fast this machine is right now, by two fixed workloads (about 0.3 s).

    Returns:
        ``loop_ms``: the best of :data:`PROBE_LOOP_REPEATS` runs of a fixed pure-Python
        loop (the interpreter's speed: other tenants' load on the host, CPU frequency);
        ``wakeup_cpu_us``: this process's CPU time per ``time.sleep`` of 1 ms, over
        :data:`PROBE_SLEEPS` of them (what each timer wake-up costs, the cost a bus pays
        several times a tick).
    """
    best = math.inf
    for _ in range(PROBE_LOOP_REPEATS):
        t0 = time.perf_counter()
        total = 0
        for i in range(PROBE_LOOP_ITERATIONS):
            total += i * i
        best = min(best, time.perf_counter() - t0)
    cpu0 = time.process_time()
    for _ in range(PROBE_SLEEPS):
        time.sleep(PROBE_SLEEP_S)
    wakeup = (time.process_time() - cpu0) / PROBE_SLEEPS
    return {"loop_ms": round(best * 1e3, 2), "wakeup_cpu_us": round(wakeup * 1e6, 1)}


def steal_seconds() -> float | None:
    """CPU time the hypervisor gave to others, all CPUs, since boot (s; ``/proc/stat``'s
    "steal" column); None where not available."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def steal_percent(before: float | None, after: float | None, wall_s: float) -> float | None:
    """Steal over a step as a share of the CPU time the machine's CPUs had in it (%)."""
    if before is None or after is None or wall_s <= 0:
        return None
    return round(100 * (after - before) / (wall_s * (os.cpu_count() or 1)), 2)


def run_step(step: Step, out: Path) -> dict[str, Any]:
    """Run one step, its output going to ``out/logs/<name>.log``.

    A step that exits with an error is run once more (:data:`STEP_ATTEMPTS`): on a shared
    machine one stalled reply can abort a whole benchmark.  Both attempts stay in the log
    and in ``failed_attempts``; a timeout is not retried (it would blow the time budget).

    Returns:
        ``command``, ``returncode`` of the last attempt (None on timeout), ``attempts``,
        ``failed_attempts`` (exit statuses of the attempts before), ``seconds`` (wall
        time, all attempts), ``load_avg_1min`` (just before the first attempt), ``probe``
        (:func:`machine_probe`, just before the first attempt), ``steal_percent`` (the
        hypervisor's steal over the step, :func:`steal_percent`) and ``log`` (path
        relative to ``out``).
    """
    raw_dir, log_dir = out / "raw", out / "logs"
    raw_dir.mkdir(parents=True, exist_ok=True)
    log_dir.mkdir(parents=True, exist_ok=True)
    cmd = step.command(raw_dir)
    log = log_dir / f"{step.name}.log"
    load = os.getloadavg()[0]
    probe = machine_probe()
    steal0 = steal_seconds()
    print(f"-- {step.name}: {' '.join(cmd[1:])}", flush=True)
    t0 = time.monotonic()
    returncode: int | None = None
    failed: list[int] = []
    with log.open("w", encoding="utf-8") as f:
        for attempt in range(1, STEP_ATTEMPTS + 1):
            f.write(f"== attempt {attempt}: {' '.join(cmd)}\n")
            f.flush()
            try:
                returncode = subprocess.run(
                    cmd, stdout=f, stderr=subprocess.STDOUT, timeout=STEP_TIMEOUT_S, check=False
                ).returncode
            except subprocess.TimeoutExpired:
                returncode = None
            if returncode == 0 or returncode is None or attempt == STEP_ATTEMPTS:
                break
            failed.append(returncode)
            print(f"   attempt {attempt} failed ({returncode}), running it again", flush=True)
    seconds = time.monotonic() - t0
    stolen = steal_percent(steal0, steal_seconds(), seconds)
    status = "ok" if returncode == 0 else f"FAILED ({returncode}), see {log}"
    print(f"   {seconds:.1f} s, {status}", flush=True)
    return {
        "command": [Path(cmd[0]).name, *cmd[1:]],
        "returncode": returncode,
        "attempts": len(failed) + 1,
        "failed_attempts": failed,
        "seconds": round(seconds, 1),
        "load_avg_1min": round(load, 2),
        "probe": probe,
        "steal_percent": stolen,
        "log": str(log.relative_to(out)),
    }


def load_json(path: Path) -> Any:
    """Read a JSON file (NaN allowed, as the scripts may write it); None if absent or bad."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def load_raw(raw_dir: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Every report and samples file in ``raw_dir``, keyed by step name."""
    reports: dict[str, Any] = {}
    samples: dict[str, Any] = {}
    for path in sorted(raw_dir.glob("*.json")):
        if path.name.endswith(".samples.json"):
            samples[path.name.removesuffix(".samples.json")] = load_json(path)
        elif path.name != "runs.json":
            reports[path.stem] = load_json(path)
    return reports, samples


# -- results.json ------------------------------------------------------------------------------


def clean(value: Any) -> Any:
    """``value`` with every NaN or infinity replaced by None (strict JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [clean(v) for v in value]
    return value


def pick(source: Mapping[str, Any] | None, keys: Sequence[str]) -> dict[str, Any]:
    """``keys`` of ``source``, None where missing (so every key is always present)."""
    source = source or {}
    return {key: clean(source.get(key)) for key in keys}


def variant(report: Mapping[str, Any] | None, expected: bool) -> dict[str, Any]:
    """One bus run's figures for ``bus.backends``/``bus.loops``, with its status."""
    status = "ok" if report is not None else "failed" if expected else "not installed"
    return {
        "status": status,
        "timer": (report or {}).get("timer"),
        **pick(report, BUS_VARIANT_KEYS),
    }


def late_ticks_results(late: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``late_ticks`` section from bench_late_ticks.py's report (None: all nulls).

    ``kernel_max_us`` is the worst run's kernel max, or None unless every run has one
    (the goal is about every run).
    """
    runs = [pick(r, LATE_RUN_KEYS) for r in (late or {}).get("runs") or []]
    maxes = [r["tick_jitter_max_us"] for r in runs]
    measured = bool(maxes) and all(isinstance(m, int | float) for m in maxes)
    causes = (late or {}).get("causes") or {}
    attributed = (late or {}).get("late_ticks")
    machine = (late or {}).get("machine") or {}
    return {
        "seconds": (late or {}).get("seconds"),
        "threshold_us": (late or {}).get("threshold_us"),
        "realtime": (late or {}).get("realtime"),
        "hogs": (late or {}).get("hogs"),
        "load_avg_before": machine.get("load_avg_before"),
        "runs": runs,
        "kernel_max_us": max(maxes) if measured else None,
        "attributed_ticks": None if attributed is None else len(attributed),
        "causes": {c: pick(causes.get(c), ("ticks", "worst_us")) for c in LATE_CAUSES},
    }


def startup_results(startup: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``startup`` section: each command's wall time (this tree), the floor, and the
    medians the goals read."""
    startup = startup or {}
    after = (startup.get("trees") or {}).get("after") or {}
    floor = startup.get("floor") or {}
    out: dict[str, Any] = {
        "runs": startup.get("runs"),
        "bytecode": startup.get("bytecode"),
        "load_avg_start": startup.get("loadavg_start"),
        "floor_min_s": floor.get("min_s"),
        "floor_median_s": floor.get("median_s"),
        "commands": {
            name: pick(after.get(name), ("min_s", "median_s", "median_above_floor_s"))
            for name in STARTUP_COMMANDS
        },
    }
    for name in STARTUP_GOALS:
        out[f"{STARTUP_GOAL_KEYS[name]}_median_s"] = (after.get(name) or {}).get("median_s")
    return out


def machine_info() -> dict[str, Any]:
    """This machine: platform string, Python version, CPU count, load average now."""
    return {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpus": os.cpu_count(),
        "load_avg": [round(x, 2) for x in os.getloadavg()],
    }


def build_results(
    reports: Mapping[str, Any],
    *,
    quick: bool,
    date: str,
    machine: Mapping[str, Any],
    runs: Mapping[str, Any],
    backends: Sequence[str],
    loops: Sequence[str],
    duration_s: float | None = None,
) -> dict[str, Any]:
    """Gather the scripts' reports into the results.json document (see the README).

    Args:
        reports: each script's JSON report, keyed by step name (``reassembler``,
            ``bus-<backend>-<loop>``, ``stream``, ``timer``, ``load``, ``cpu``,
            ``late_ticks``, ``startup``); a missing one gives nulls.
        quick: whether the scripts ran with ``--quick``.
        date: ISO 8601 UTC time the run started.
        machine: :func:`machine_info` taken at the start.
        runs: :func:`run_step` records keyed by step name.
        backends, loops: the backends and loops that were meant to be measured.
        duration_s: wall time of the whole run (seconds).

    Returns:
        The document, JSON-ready (no NaN), goals evaluated.
    """
    reassembler = reports.get("reassembler")
    main_bus = reports.get(bus_step_name(MAIN_BACKEND, MAIN_LOOP))
    stream = reports.get("stream")
    timer = reports.get("timer")
    load = reports.get("load")
    cpu = reports.get("cpu")
    late = reports.get("late_ticks")

    reassembler_out = pick(reassembler, REASSEMBLER_KEYS)
    reassembler_out["every_undamaged_frame_found"] = (
        None if reassembler is None else reassembler["goals"]["every_undamaged_frame_found"]
    )
    reassembler_out["pymodbus_version"] = (reassembler or {}).get("pymodbus", {}).get("version")

    bus_out = pick(main_bus, BUS_KEYS)
    bus_out["backends"] = {
        name: variant(reports.get(bus_step_name(name, MAIN_LOOP)), name in backends)
        for name in ALL_BACKENDS
    }
    bus_out["loops"] = {
        name: variant(reports.get(bus_step_name(MAIN_BACKEND, name)), name in loops)
        for name in ALL_LOOPS
    }

    stream_out = pick(stream, STREAM_KEYS)
    stream_out["backend"] = (stream or {}).get("backend")
    stream_out["loop"] = (stream or {}).get("loop")
    stream_out["timer_source"] = (stream or {}).get("timer")
    scaling_out = pick((stream or {}).get("scaling"), SCALING_KEYS)
    for key in SCALING_KEYS:
        if scaling_out[key] is None:
            scaling_out[key] = []
    scaling_out["seconds"] = (stream or {}).get("scaling_seconds")

    load_out = {
        "seconds": (load or {}).get("seconds"),
        "hogs": (load or {}).get("hogs"),
        "rt_method": (load or {}).get("rt_method"),
        "plain": pick((load or {}).get("plain"), LOAD_KEYS),
        "rt": pick((load or {}).get("rt"), LOAD_KEYS),
    }
    cpu_out = pick(cpu, CPU_KEYS)
    for key in CPU_KEYS:
        if cpu_out[key] is None:
            cpu_out[key] = []
    cpu_out["max_ratio"] = clean((cpu or {}).get("max_ratio"))
    # Here, not from the script: a report of an older bench_cpu.py has the lists only.
    goal_ratios = [
        r
        for b, r in zip(cpu_out["buses"], cpu_out["ratio"], strict=False)
        if b in CPU_GOAL_RATIO_BUSES and isinstance(r, int | float)
    ]
    cpu_out["max_ratio_1_16_32"] = max(goal_ratios) if goal_ratios else None
    cpu_out["max_buses_keeping_up"] = (cpu or {}).get("max_buses_keeping_up")
    cpu_out["seconds"] = (cpu or {}).get("seconds")

    timer_out = {
        "seconds_per_run": (timer or {}).get("seconds_per_run"),
        "timerfd": (timer or {}).get("timerfd"),
        "rows": [pick(row, TIMER_ROW_KEYS) for row in (timer or {}).get("results", [])],
    }

    errors = [
        f"{name}: exit status {run['returncode']} (timeout if null), see {run['log']}"
        for name, run in runs.items()
        if run.get("returncode") != 0
    ]
    errors += [
        f"{name}: attempt(s) failed with exit status {run['failed_attempts']}, then run again"
        for name, run in runs.items()
        if run.get("failed_attempts")
    ]
    errors += [
        f"{name}: exited 0 but wrote no readable report"
        for name, run in runs.items()
        if run.get("returncode") == 0 and reports.get(name) is None
    ]

    results: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "quick": quick,
        "date": date,
        "duration_s": None if duration_s is None else round(duration_s, 1),
        "machine": dict(machine),
        "backend": MAIN_BACKEND,
        "event_loop": MAIN_LOOP,
        "timer_source": (main_bus or {}).get("timer"),
        "reassembler": reassembler_out,
        "bus": bus_out,
        "stream": stream_out,
        "scaling": scaling_out,
        "timer": timer_out,
        "load": load_out,
        "cpu": cpu_out,
        "late_ticks": late_ticks_results(late),
        "startup": startup_results(reports.get("startup")),
        "goals": {},
        "runs": dict(runs),
        "errors": errors,
        "plots": {},
    }
    results["goals"] = evaluate_goals(results)
    cleaned: dict[str, Any] = clean(results)
    return cleaned


# -- goals -------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Goal:
    """A target for one figure.

    Attributes:
        name: key under ``goals`` in results.json.
        figure: dotted path of the figure in results.json; ``scaling.<key>@N`` (or
            ``cpu.<key>@N``) is the entry of that section's list ``<key>`` for N buses.
        op: one of :data:`OPS`.
        target: the bound.
    """

    name: str
    figure: str
    op: str
    target: float

    def text(self) -> str:
        """The goal as written in the report, e.g. ``<= 1.3``."""
        if isinstance(self.target, bool):
            return f"== {'yes' if self.target else 'no'}"
        target = f"{self.target:,.0f}" if self.target >= 100 else f"{self.target:g}"
        # Not "|x|": a pipe would split the report's Markdown table cell.
        return f"abs <= {target}" if self.op == "abs<=" else f"{self.op} {target}"


OPS: dict[str, Callable[[float, float], bool]] = {
    "<=": operator.le,
    "<": operator.lt,
    ">=": operator.ge,
    "==": operator.eq,
    "abs<=": lambda value, target: abs(value) <= target,
}

GOALS = (
    Goal("reassembler.framing_ge_1M_per_s", "reassembler.frames_per_s", ">=", GOAL_FRAMES_PER_S),
    Goal(
        "reassembler.decoded_ge_400k_per_s", "reassembler.decoded_per_s", ">=", GOAL_DECODED_PER_S
    ),
    Goal(
        "reassembler.decoded_ge_5x_pymodbus",
        "reassembler.ratio_vs_pymodbus",
        ">=",
        GOAL_RATIO_VS_PYMODBUS,
    ),
    Goal(
        "reassembler.every_undamaged_frame_found",
        "reassembler.every_undamaged_frame_found",
        "==",
        True,
    ),
    Goal("bus.rtt_le_1.3x_minimal_client", "bus.rtt_ratio_vs_minimal", "<=", GOAL_RATIO),
    Goal("bus.commands_ge_950_per_s", "bus.commands_per_s", ">=", GOAL_RATE),
    Goal("bus.min_gap_ge_1000us", "bus.mixed_kernel_min_gap_us", ">=", GOAL_MIN_GAP_US),
    Goal("bus.no_gap_under_1ms", "bus.mixed_kernel_gaps_under_1000us", "==", 0),
    Goal("bus.rate_min_gap_ge_1000us", "bus.rate_kernel_min_gap_us", ">=", GOAL_MIN_GAP_US),
    Goal("bus.rate_no_gap_under_1ms", "bus.rate_kernel_gaps_under_1000us", "==", 0),
    Goal(
        "bus.mixed_ticks_sent_ge_99pct",
        "bus.mixed_kernel_ticks_sent_pct",
        ">=",
        GOAL_TICKS_SENT_PCT,
    ),
    Goal(
        "bus.mixed_prompt_no_poll_timeout",
        "bus.mixed_prompt_poll_timeouts",
        "==",
        GOAL_PROMPT_TIMEOUTS,
    ),
    Goal("bus.timeout_never_early", "bus.timeout_early_count", "==", GOAL_EARLY),
    Goal("bus.timeout_late_p99_le_150us", "bus.timeout_late_p99_us", "<=", GOAL_LATE_P99_US),
    Goal(
        "stream.kernel_p99_le_150us",
        "stream.kernel_tick_jitter_p99_us",
        "<=",
        GOAL_KERNEL_P99_US,
    ),
    Goal("stream.kernel_max_le_1ms", "stream.kernel_tick_jitter_max_us", "<=", GOAL_KERNEL_MAX_US),
    Goal("stream.p99_le_300us", "stream.tick_jitter_p99_us", "<=", GOAL_STREAM_P99_US),
    Goal("stream.max_le_2ms", "stream.tick_jitter_max_us", "<=", GOAL_STREAM_MAX_US),
    Goal("stream.no_missed_tick", "stream.missed_ticks", "==", 0),
    Goal("stream.no_drift", "stream.drift_ppm", "abs<=", GOAL_STREAM_DRIFT_PPM),
    Goal(
        "scaling.32_buses_cpu_lt_50pct",
        f"scaling.cpu_percent@{GOAL_SCALING_BUSES}",
        "<",
        GOAL_SCALING_CPU_PERCENT,
    ),
    Goal(
        "scaling.32_buses_p99_le_1ms",
        f"scaling.tick_jitter_p99_us@{GOAL_SCALING_BUSES}",
        "<=",
        GOAL_SCALING_P99_US,
    ),
    Goal("load.rt_p99_le_100us", "load.rt.tick_jitter_p99_us", "<=", GOAL_RT_P99_US),
    Goal("load.rt_max_le_500us", "load.rt.tick_jitter_max_us", "<=", GOAL_RT_MAX_US),
    Goal("load.rt_no_missed_tick", "load.rt.missed_ticks", "==", 0),
    Goal("load.rt_no_late_tick", "load.rt.late_ticks", "==", 0),
    Goal("load.rt_min_gap_ge_1000us", "load.rt.min_gap_us", ">=", GOAL_MIN_GAP_US),
    Goal("cpu.ratio_le_1.5x_minimal", "cpu.max_ratio_1_16_32", "<=", GOAL_CPU_RATIO),
    Goal("cpu.32_buses_lt_35pct", "cpu.cpu_percent@32", "<", GOAL_CPU_32_PERCENT),
    Goal(
        "late_ticks.kernel_max_le_1000us_every_run",
        "late_ticks.kernel_max_us",
        "<=",
        GOAL_LATE_MAX_US,
    ),
    Goal("startup.version_le_0.3s", "startup.version_median_s", "<=", GOAL_STARTUP_S),
    Goal("startup.la_status_le_0.3s", "startup.la_status_median_s", "<=", GOAL_STARTUP_S),
)


def lookup(results: Mapping[str, Any], figure: str) -> Any:
    """The value at ``figure`` (see :class:`Goal`) in ``results``; None if absent."""
    path, _, buses = figure.partition("@")
    value: Any = results
    for part in path.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    if buses:
        section = path.split(".")[0]  # "scaling" or "cpu": each has its own "buses"
        counts = results.get(section, {}).get("buses") or []
        if int(buses) not in counts or not isinstance(value, list):
            return None
        value = value[counts.index(int(buses))]
    return value


def evaluate_goals(results: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Every goal of :data:`GOALS` against ``results``.

    Returns:
        For each goal name: ``figure``, ``value`` (None if not measured), ``goal`` (text),
        ``target`` and ``met`` (None if not measured).
    """
    out: dict[str, dict[str, Any]] = {}
    for g in GOALS:
        value = lookup(results, g.figure)
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        met = None if value is None else bool(OPS[g.op](value, g.target))
        out[g.name] = {
            "figure": g.figure,
            "value": value,
            "goal": g.text(),
            "target": g.target,
            "met": met,
        }
    return out


# -- report.md ---------------------------------------------------------------------------------


def fmt(value: Any, unit: str = "") -> str:
    """A figure for the report: thousands separators, units, ``n/a`` when absent."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float) and abs(value) < 10 and value != int(value):
        text = f"{value:.2f}"
    elif isinstance(value, int | float):
        text = f"{value:,.0f}"
    else:
        text = str(value)
    return f"{text} {unit}".rstrip()


def ratio(value: Any, baseline: Any) -> str:
    """``value / baseline`` to two decimals, or ``-`` if either is absent or zero."""
    if not isinstance(value, int | float) or not isinstance(baseline, int | float):
        return "-"
    if isinstance(value, bool) or baseline == 0:
        return "-"
    return f"{value / baseline:.2f}"


def met_text(met: bool | None) -> str:
    """A goal's state for the report."""
    return {True: "met", False: "**NOT MET**", None: "not measured"}[met]


@dataclass(frozen=True, slots=True)
class Row:
    """A line of the main table: a figure, its baseline (if any) and its goal (if any)."""

    label: str
    figure: str
    unit: str
    baseline_label: str = ""
    baseline_figure: str = ""
    goal: str = ""


#: ``baseline_figure`` "=N" is a constant baseline (N), not a measured figure.
MAIN_ROWS = (
    Row(
        "reassembler framing",
        "reassembler.frames_per_s",
        "frames/s",
        "pymodbus RTU decode",
        "reassembler.pymodbus_decoded_per_s",
        "reassembler.framing_ge_1M_per_s",
    ),
    Row(
        "reassembler framing, 1 % garbage",
        "reassembler.frames_per_s_garbage1",
        "frames/s",
        "pymodbus RTU decode",
        "reassembler.pymodbus_decoded_per_s",
    ),
    Row(
        "reassembler framing + decode_status",
        "reassembler.decoded_per_s",
        "frames/s",
        "pymodbus RTU decode",
        "reassembler.pymodbus_decoded_per_s",
        "reassembler.decoded_ge_5x_pymodbus",
    ),
    Row(
        "reassembler framing + decode_status, 1 % garbage",
        "reassembler.decoded_per_s_garbage1",
        "frames/s",
        "pymodbus RTU decode",
        "reassembler.pymodbus_decoded_per_s",
    ),
    Row(
        "bus RTT p50",
        "bus.rtt_p50_us",
        "µs",
        "minimal asyncio client p50",
        "bus.rtt_minimal_client_p50_us",
        "bus.rtt_le_1.3x_minimal_client",
    ),
    Row(
        "bus RTT p50",
        "bus.rtt_p50_us",
        "µs",
        "blocking pyserial p50",
        "bus.rtt_blocking_pyserial_p50_us",
    ),
    Row(
        "bus RTT p99",
        "bus.rtt_p99_us",
        "µs",
        "minimal asyncio client p99",
        "bus.rtt_minimal_client_p99_us",
    ),
    Row(
        "bus commands/s at 1 ms spacing",
        "bus.commands_per_s",
        "/s",
        "ideal at 1 ms spacing",
        f"={IDEAL_COMMANDS_PER_S:g}",
        "bus.commands_ge_950_per_s",
    ),
    Row(
        "bus smallest write gap, mixed workload (kernel clock)",
        "bus.mixed_kernel_min_gap_us",
        "µs",
        "spacing rule",
        f"={SPACING_US:g}",
        "bus.min_gap_ge_1000us",
    ),
    Row(
        "bus write gaps under 1 ms, mixed workload (kernel clock)",
        "bus.mixed_kernel_gaps_under_1000us",
        "",
        goal="bus.no_gap_under_1ms",
    ),
    Row(
        "bus smallest write gap, rate run (kernel clock)",
        "bus.rate_kernel_min_gap_us",
        "µs",
        "spacing rule",
        f"={SPACING_US:g}",
        "bus.rate_min_gap_ge_1000us",
    ),
    Row(
        "bus ticks sent with 3 request loops (kernel clock)",
        "bus.mixed_kernel_ticks_sent_pct",
        "%",
        goal="bus.mixed_ticks_sent_ge_99pct",
    ),
    Row(
        "bus polls timed out, prompt device",
        "bus.mixed_prompt_poll_timeouts",
        "",
        goal="bus.mixed_prompt_no_poll_timeout",
    ),
    Row(
        "bus smallest start gap (simulator)",
        "bus.min_gap_us",
        "µs",
        "spacing rule",
        f"={SPACING_US:g}",
    ),
    Row(
        "bus 800 µs timeout, lateness p99",
        "bus.timeout_late_p99_us",
        "µs",
        goal="bus.timeout_late_p99_le_150us",
    ),
    Row(
        "bus 800 µs timeout, early firings",
        "bus.timeout_early_count",
        "",
        goal="bus.timeout_never_early",
    ),
    Row(
        "stream tick jitter p50 (kernel clock)",
        "stream.kernel_tick_jitter_p50_us",
        "µs",
        "bare timerfd loop p50 (kernel)",
        "stream.baseline_timerfd_kernel_tick_jitter_p50_us",
    ),
    Row(
        "stream tick jitter p99 (kernel clock)",
        "stream.kernel_tick_jitter_p99_us",
        "µs",
        "bare timerfd loop p99 (kernel)",
        "stream.baseline_timerfd_kernel_tick_jitter_p99_us",
        "stream.kernel_p99_le_150us",
    ),
    Row(
        "stream tick jitter p99 (kernel clock)",
        "stream.kernel_tick_jitter_p99_us",
        "µs",
        "timerfd + busy-wait loop p99 (kernel)",
        "stream.baseline_timerfd_spin_kernel_tick_jitter_p99_us",
    ),
    Row(
        "stream tick jitter max (kernel clock)",
        "stream.kernel_tick_jitter_max_us",
        "µs",
        "bare timerfd loop max (kernel)",
        "stream.baseline_timerfd_kernel_tick_jitter_max_us",
        "stream.kernel_max_le_1ms",
    ),
    Row(
        "stream tick jitter max (kernel clock)",
        "stream.kernel_tick_jitter_max_us",
        "µs",
        "timerfd + busy-wait loop max (kernel)",
        "stream.baseline_timerfd_spin_kernel_tick_jitter_max_us",
    ),
    Row(
        "stream CPU per tick, one bus",
        "stream.cpu_us_per_tick",
        "µs",
        "bare timerfd loop",
        "stream.baseline_timerfd_cpu_us_per_tick",
    ),
    Row(
        "stream CPU per tick, one bus",
        "stream.cpu_us_per_tick",
        "µs",
        "timerfd + busy-wait loop",
        "stream.baseline_timerfd_spin_cpu_us_per_tick",
    ),
    Row(
        "stream tick jitter p99",
        "stream.tick_jitter_p99_us",
        "µs",
        "absolute-deadline asyncio.sleep loop p99",
        "stream.baseline_sleep_tick_jitter_p99_us",
        "stream.p99_le_300us",
    ),
    Row(
        "stream tick jitter max",
        "stream.tick_jitter_max_us",
        "µs",
        "absolute-deadline asyncio.sleep loop max",
        "stream.baseline_sleep_tick_jitter_max_us",
        "stream.max_le_2ms",
    ),
    Row("stream missed ticks", "stream.missed_ticks", "", goal="stream.no_missed_tick"),
    Row(
        "stream drift",
        "stream.drift_ppm",
        "ppm",
        "send-then-sleep loop drift",
        "stream.naive_drift_ppm",
        "stream.no_drift",
    ),
)


def table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def main_table(results: Mapping[str, Any]) -> list[str]:
    """The figures with their baselines and goals."""
    goals = results.get("goals", {})
    rows = []
    for r in MAIN_ROWS:
        value = lookup(results, r.figure)
        if r.baseline_figure.startswith("="):
            baseline: Any = float(r.baseline_figure[1:])
        else:
            baseline = lookup(results, r.baseline_figure) if r.baseline_figure else None
        goal = goals.get(r.goal) if r.goal else None
        rows.append(
            [
                r.label,
                fmt(value, r.unit),
                f"{r.baseline_label}: {fmt(baseline, r.unit)}" if r.baseline_label else "-",
                ratio(value, baseline) if r.baseline_label else "-",
                goal["goal"] if goal else "-",
                met_text(goal["met"]) if goal else "-",
            ]
        )
    return table(("figure", "value", "baseline (same run)", "ratio", "goal", "met"), rows)


def variants_table(results: Mapping[str, Any], kind: str, reference: str) -> list[str]:
    """Bus figures per backend (``kind="backends"``) or per event loop (``"loops"``)."""
    variants = results.get("bus", {}).get(kind, {})
    ref_p50 = variants.get(reference, {}).get("rtt_p50_us")
    rows = []
    for name, v in variants.items():
        rows.append(
            [
                name,
                v.get("status") or "-",
                v.get("timer") or "-",
                fmt(v.get("rtt_p50_us"), "µs"),
                fmt(v.get("rtt_p99_us"), "µs"),
                fmt(v.get("rtt_minimal_client_p50_us"), "µs"),
                ratio(v.get("rtt_p50_us"), v.get("rtt_minimal_client_p50_us")),
                ratio(v.get("rtt_p50_us"), ref_p50),
                fmt(v.get("commands_per_s"), "/s"),
                fmt(v.get("min_gap_us"), "µs"),
                fmt(v.get("timeout_late_p99_us"), "µs"),
                fmt(v.get("timeout_early_count")),
            ]
        )
    header = (
        kind[:-1],
        "status",
        "timer",
        "RTT p50",
        "RTT p99",
        "minimal client p50 (same stack)",
        "ratio to minimal",
        f"ratio to {reference}",
        "commands/s",
        "min gap",
        "timeout late p99",
        "early timeouts",
    )
    return table(header, rows)


#: (label, kernel-clock figure, simulator-clock figure) for the side-by-side table.
KERNEL_VS_SIM = (
    ("rate run: smallest start gap (µs)", "bus.rate_kernel_min_gap_us", "bus.min_gap_us"),
    (
        "rate run: gaps under 1 ms",
        "bus.rate_kernel_gaps_under_1000us",
        "bus.gaps_under_1000us",
    ),
    (
        "rate run: smallest gap from a write's return (µs)",
        "bus.rate_kernel_min_gap_after_return_us",
        "",
    ),
    ("rate run: write(2) duration p50 (µs)", "bus.rate_kernel_write_p50_us", ""),
    ("rate run: write(2) duration p99 (µs)", "bus.rate_kernel_write_p99_us", ""),
    ("rate run: write(2) duration max (µs)", "bus.rate_kernel_write_max_us", ""),
    ("mixed: smallest start gap (µs)", "bus.mixed_kernel_min_gap_us", "bus.mixed_sim_min_gap_us"),
    (
        "mixed: gaps under 1 ms",
        "bus.mixed_kernel_gaps_under_1000us",
        "bus.mixed_sim_gaps_under_1000us",
    ),
    ("mixed: write(2) duration max (µs)", "bus.mixed_kernel_write_max_us", ""),
    (
        "mixed: tick jitter p99 (µs)",
        "bus.mixed_kernel_tick_jitter_p99_us",
        "bus.mixed_sim_tick_jitter_p99_us",
    ),
    (
        "mixed: tick jitter max (µs)",
        "bus.mixed_kernel_tick_jitter_max_us",
        "bus.mixed_sim_tick_jitter_max_us",
    ),
    ("mixed: ticks sent (%)", "bus.mixed_kernel_ticks_sent_pct", ""),
    (
        "stream: tick jitter p50 (µs)",
        "stream.kernel_tick_jitter_p50_us",
        "stream.tick_jitter_p50_us",
    ),
    (
        "stream: tick jitter p99 (µs)",
        "stream.kernel_tick_jitter_p99_us",
        "stream.tick_jitter_p99_us",
    ),
    (
        "stream: tick jitter max (µs)",
        "stream.kernel_tick_jitter_max_us",
        "stream.tick_jitter_max_us",
    ),
    ("stream: missed ticks", "stream.kernel_missed_ticks", "stream.missed_ticks"),
    *(
        (
            f"{label}: tick jitter {q} (µs)",
            f"stream.baseline_{name}_kernel_tick_jitter_{q}_us",
            f"stream.baseline_{name}_tick_jitter_{q}_us",
        )
        for name, label in (
            ("sleep", "absolute-deadline asyncio.sleep loop"),
            ("timerfd", "bare timerfd loop (floor)"),
            ("timerfd_spin", "timerfd + busy-wait loop (precision floor)"),
        )
        for q in ("p99", "max")
    ),
    (
        "send-then-sleep loop, DRIFT not jitter: p99 (µs)",
        "stream.naive_kernel_tick_jitter_p99_us",
        "stream.naive_tick_jitter_p99_us",
    ),
    (
        "send-then-sleep loop, DRIFT not jitter: max (µs)",
        "stream.naive_kernel_tick_jitter_max_us",
        "stream.naive_tick_jitter_max_us",
    ),
)


def kernel_table(results: Mapping[str, Any]) -> list[str]:
    """Kernel-clock figures beside the same figures at the simulator."""
    rows = [
        [
            label,
            fmt(lookup(results, kernel)),
            fmt(lookup(results, sim)) if sim else "-",
        ]
        for label, kernel, sim in KERNEL_VS_SIM
    ]
    return table(("figure", "kernel clock (write(2) entry)", "simulator's clock"), rows)


def kernel_notes(results: Mapping[str, Any]) -> list[str]:
    """Why a phase has no kernel figures, if it has none."""
    notes = []
    for name, flag, why in (
        ("bus rate run", "bus.rate_kernel_measured", "bus.rate_kernel_why"),
        ("bus mixed workload", "bus.mixed_kernel_measured", "bus.mixed_kernel_why"),
        ("stream", "stream.kernel_measured", "stream.kernel_why"),
        ("load (real-time)", "load.rt.kernel_measured", "load.rt.kernel_why"),
    ):
        if lookup(results, flag) is False:
            notes.append(f"- {name}: kernel clock not measured: {lookup(results, why)}")
    pacing = lookup(results, "bus.mixed_prompt_pacing")
    if pacing and pacing != "measured":
        notes.append(f"- polls against a prompt device: {pacing}")
    if lookup(results, "bus.mixed_stream_stalled"):
        notes.append("- mixed workload: the stream STALLED (ended by the benchmark's watchdog)")
    return notes


def load_table(results: Mapping[str, Any]) -> list[str]:
    """The stream under two CPU hogs, plain against real-time."""
    load = results.get("load", {})
    rows = [
        [key, fmt(load.get("plain", {}).get(key)), fmt(load.get("rt", {}).get(key))]
        for key in LOAD_KEYS
        if key not in ("kernel_measured", "kernel_why")
    ]
    return table(("figure (kernel clock; µs)", "plain", "real-time"), rows)


def spread(values: Any) -> str:
    """``min-max`` of a list of figures (``n/a`` when none): the rounds of one case."""
    finite = [v for v in values or [] if isinstance(v, int | float)]
    if not finite:
        return "n/a"
    low, high = min(finite), max(finite)
    return fmt(low) if low == high else f"{fmt(low)}-{fmt(high)}"


def cpu_table(results: Mapping[str, Any]) -> list[str]:
    """CPU per bus count: ours, the minimal loop, the ratio."""
    c = results.get("cpu", {})
    rows = []
    for i, buses in enumerate(c.get("buses") or []):

        def at(key: str, i: int = i) -> Any:
            values = c.get(key) or []
            return values[i] if i < len(values) else None

        kept_up = at("keeps_up")
        rows.append(
            [
                str(buses),
                fmt(at("cpu_percent"), "%"),
                fmt(at("spin_percent"), "%"),
                fmt(at("minimal_cpu_percent"), "%"),
                fmt(at("ratio")),
                spread(at("round_ratios")),
                fmt(at("ratio_per_tick")),
                f"{fmt(at('ticks'))} / {fmt(at('minimal_ticks'))}",
                # One decimal: 99.9 % sent must not read as 100 %.
                "n/a" if at("ticks_sent_pct") is None else f"{at('ticks_sent_pct'):.1f} %",
                f"{fmt(at('replies'))} / {fmt(at('minimal_replies'))}",
                f"{fmt(at('late_ticks'))} / {fmt(at('skipped_ticks'))}",
                fmt(at("stream_errors")),
                "n/a" if kept_up is None else "yes" if kept_up else "**no: fell behind**",
            ]
        )
    header = (
        "buses",
        "ours (one core = 100 %)",
        "of which timer spin",
        "minimal loop",
        "ratio",
        "ratio by round",
        "ratio per tick sent",
        "ticks ours / minimal",
        "ours: ticks sent",
        "replies ours / minimal",
        "ours late / skipped",
        "streams ended",
        "keeps up",
    )
    return table(header, rows)


def cpu_notes(results: Mapping[str, Any]) -> list[str]:
    """What the CPU table says about one core, and what the ratio goal is read from."""
    c = results.get("cpu", {})
    buses = c.get("buses") or []
    kept_up = c.get("max_buses_keeping_up")
    goal_counts = ", ".join(map(str, CPU_GOAL_RATIO_BUSES))
    if kept_up is None or not buses:
        where = "not measured"
    elif kept_up == 0:
        first = min(buses)
        where = f"ours fell behind already at **{first} bus{'es' if first != 1 else ''}**"
    else:
        where = f"ours kept up with every count up to **{fmt(kept_up)} buses**"
    if buses:
        where += f" (measured: {', '.join(map(str, buses))})"
    return [
        f"Where one core saturates (keeping up: sent >= {KEEPS_UP_TICKS_SENT_PCT:g} % of "
        f"its ticks, no stream ended): {where}.",
        "",
        "The bus process has one thread: past one core it does not use more CPU, it sends "
        "fewer ticks, so beyond that count `ratio` understates the cost and `ratio per "
        "tick sent` is the figure; falling behind well under 100 % CPU means the machine "
        "did not give it the core.  The ratio goal is read at "
        f"{goal_counts} buses (`cpu.max_ratio_1_16_32` = {fmt(c.get('max_ratio_1_16_32'))}; "
        f"largest at any count `cpu.max_ratio` = {fmt(c.get('max_ratio'))}).",
    ]


def late_ticks_tables(results: Mapping[str, Any]) -> list[str]:
    """The late-tick runs (kernel clock) and the late ticks by cause."""
    lt = results.get("late_ticks", {})
    rows = [
        [
            str(k),
            fmt(r.get("tick_jitter_p50_us"), "µs"),
            fmt(r.get("tick_jitter_p99_us"), "µs"),
            fmt(r.get("tick_jitter_max_us"), "µs"),
            fmt(r.get("late_ticks")),
            fmt(r.get("missed_ticks")),
            fmt(r.get("gc_collections")),
            fmt(None if r.get("timer_spin_s") is None else 1e3 * r["timer_spin_s"], "ms"),
            fmt(r.get("cpu_us_per_tick"), "µs"),
        ]
        for k, r in enumerate(lt.get("runs") or [], 1)
    ]
    header = (
        "run",
        "tick jitter p50",
        "p99",
        "max",
        f"late (> {LATE_S * 1e3:g} ms)",
        "missed",
        "GC collections",
        "timer spin",
        "CPU per tick",
    )
    lines = table(header, rows)
    notes = [
        f"- run {k}: kernel clock not measured: {r['kernel_why']}"
        for k, r in enumerate(lt.get("runs") or [], 1)
        if r.get("kernel_why")
    ]
    if notes:
        lines += ["", *notes]
    causes = lt.get("causes") or {}
    cause_rows = [
        [
            f"`{cause}`",
            fmt((causes.get(cause) or {}).get("ticks")),
            fmt((causes.get(cause) or {}).get("worst_us"), "µs"),
        ]
        for cause in LATE_CAUSES
    ]
    lines += [
        "",
        f"Ticks later than {fmt(lt.get('threshold_us'), 'µs')} after their deadline at the "
        f"kernel, over all runs ({fmt(lt.get('attributed_ticks'))}), by cause "
        "(`benchmarks/late_ticks.py` says how each is chosen):",
        "",
    ]
    lines += table(("cause", "ticks", "worst"), cause_rows)
    return lines


def scaling_table(results: Mapping[str, Any]) -> list[str]:
    """CPU and jitter per bus count."""
    s = results.get("scaling", {})
    rows = []
    for i, buses in enumerate(s.get("buses") or []):

        def at(key: str, i: int = i) -> Any:
            values = s.get(key) or []
            return values[i] if i < len(values) else None

        rows.append(
            [
                str(buses),
                fmt(at("cpu_percent"), "%"),
                fmt(at("cpu_percent_per_bus"), "%"),
                fmt(at("tick_jitter_p99_us"), "µs"),
                fmt(at("tick_jitter_max_us"), "µs"),
                fmt(at("missed_ticks")),
                fmt(at("kernel_tick_jitter_p99_us"), "µs"),
                fmt(at("kernel_tick_jitter_max_us"), "µs"),
                fmt(at("kernel_late_ticks")),
            ]
        )
    header = (
        "buses",
        "CPU (one core = 100 %)",
        "CPU per bus",
        "worst-bus p99",
        "max",
        "missed",
        "kernel: worst p99",
        "kernel: max",
        "kernel: late",
    )
    return table(header, rows)


def timer_table(results: Mapping[str, Any]) -> list[str]:
    """Lateness of periodic deadlines per loop, period and timer source."""
    rows = [
        [
            str(r["loop"]),
            fmt(r["period_ms"], "ms"),
            str(r["method"]),
            fmt(r["p50_us"], "µs"),
            fmt(r["p99_us"], "µs"),
            fmt(r["max_us"], "µs"),
            f"{fmt(r['early'])} (up to {fmt(r['most_early_us'], 'µs')})",
            fmt(r["p99_ratio_to_sleep"]),
        ]
        for r in results.get("timer", {}).get("rows", [])
    ]
    header = ("loop", "period", "timer", "p50 late", "p99 late", "max late", "early", "p99 ratio")
    return table(header, rows)


def startup_table(results: Mapping[str, Any]) -> list[str]:
    """bench_startup.py's figures: min and median per command, against the floor."""
    s = results.get("startup", {})

    def ms(seconds: Any) -> Any:
        return None if seconds is None else 1000 * seconds

    rows = [
        [
            "`python -c pass` (the floor)",
            fmt(ms(s.get("floor_min_s")), "ms"),
            fmt(ms(s.get("floor_median_s")), "ms"),
            "-",
            "-",
        ]
    ]
    for name, c in (s.get("commands") or {}).items():
        median = c.get("median_s")
        goal = f"<= {GOAL_STARTUP_S:g} s" if name in STARTUP_GOALS else "-"
        if name in STARTUP_GOALS and median is not None:
            goal += f": {met_text(median <= GOAL_STARTUP_S)}"
        rows.append(
            [
                f"`{name}`",
                fmt(ms(c.get("min_s")), "ms"),
                fmt(ms(median), "ms"),
                fmt(ms(c.get("median_above_floor_s")), "ms"),
                goal,
            ]
        )
    return [
        *table(("command", "min", "median", "median above the floor", "goal"), rows),
        "",
        f"`bench_startup.py`, this tree, {fmt(s.get('runs'))} runs a command, bytecode "
        f"{s.get('bytecode')}, load average at start {s.get('load_avg_start')}; "
        "`la status` asks a simulator on a pty.",
    ]


def render_report(results: Mapping[str, Any]) -> str:
    """report.md for ``results`` (a :func:`build_results` document)."""
    m = results.get("machine", {})
    goals = results.get("goals", {})
    counts = [g["met"] for g in goals.values()]
    mode = "quick (--quick)" if results.get("quick") else "full"
    duration = results.get("duration_s")
    lines = [
        "# motorbus benchmark report",
        "",
        f"- Machine: {m.get('platform')}, {m.get('cpus')} CPUs, Python {m.get('python')}, "
        f"load average at start {m.get('load_avg')}",
        f"- Date: {results.get('date')} ({mode} run"
        + (f", {duration:.0f} s" if duration is not None else "")
        + ")",
        f"- Bus: backend `{results.get('backend')}`, event loop `{results.get('event_loop')}`, "
        f"timer source `{results.get('timer_source')}`",
        "- The machine is shared and noisy: absolute figures are indicative; the baselines "
        "were measured in the same run, so the ratios are the comparison.",
        "",
        f"## Goals: {counts.count(True)} met, {counts.count(False)} not met, "
        f"{counts.count(None)} not measured",
        "",
    ]
    for name, g in goals.items():
        lines.append(
            f"- {met_text(g['met'])}: `{name}`: {g['figure']} = {fmt(g['value'])} "
            f"(goal {g['goal']})"
        )
    lines += ["", "## Figures against their baselines", ""]
    lines += main_table(results)
    lines += [
        "",
        "Ratio = value / baseline: below 1 is better for times, above 1 for rates.",
        "",
        "## Bus per serial backend (default event loop)",
        "",
    ]
    lines += variants_table(results, "backends", MAIN_BACKEND)
    lines += ["", f"## Bus per event loop (backend `{MAIN_BACKEND}`)", ""]
    lines += variants_table(results, "loops", MAIN_LOOP)
    lines += [
        "",
        "## Kernel clock beside the simulator's",
        "",
        "The kernel's timestamps of this process's write(2) calls to the port (perf,",
        "CLOCK_MONOTONIC) against the simulator's timestamps of the same frames, which",
        "carry the simulator's own wake-up lateness.",
        "",
    ]
    lines += kernel_table(results)
    notes = kernel_notes(results)
    if notes:
        lines += ["", *notes]
    lines += ["", "## Streaming: scaling with bus count (15 actuators a bus, 10 ms)", ""]
    lines += scaling_table(results)
    load = results.get("load", {})
    lines += [
        "",
        f"## Stream under load: {load.get('hogs')} CPU hogs, {fmt(load.get('seconds'), 's')} "
        "a mode",
        "",
        f"Real-time mode: {load.get('rt_method')}.",
        "",
    ]
    lines += load_table(results)
    late = results.get("late_ticks", {})
    mode = "real-time" if late.get("realtime") else "SCHED_OTHER"
    lines += [
        "",
        f"## Late ticks, attributed: {len(late.get('runs') or [])} run(s) of "
        f"{fmt(late.get('seconds'), 's')}",
        "",
        f"README's stream (15 actuators, 10 ms, status polls), {mode}, "
        f"{fmt(late.get('hogs'))} CPU hogs, load average before "
        f"{late.get('load_avg_before')}; the writes' jitter on the kernel's clock against "
        "a least-squares 10 ms grid, as in the stream's figures.",
        "",
    ]
    lines += late_ticks_tables(results)
    lines += ["", "## CPU per bus-tick against a minimal asyncio loop (same writes)", ""]
    lines += cpu_table(results)
    lines += ["", *cpu_notes(results)]
    lines += ["", "## Command-line start-up: wall time of a fresh process", ""]
    lines += startup_table(results)
    lines += ["", "## Timer sources: lateness of periodic absolute deadlines", ""]
    lines += timer_table(results)
    lines += ["", "p99 ratio: the timer's p99 over `asyncio.sleep`'s p99, same loop and period."]
    plots = results.get("plots", {})
    if plots:
        lines += ["", "## Plots", ""]
        lines += [f"![{name}]({file})" for name, file in plots.items()]
    lines += ["", "## Runs", ""]
    run_rows = [
        [
            name,
            fmt(run.get("seconds"), "s"),
            fmt(run.get("load_avg_1min")),
            fmt((run.get("probe") or {}).get("loop_ms"), "ms"),
            fmt((run.get("probe") or {}).get("wakeup_cpu_us"), "µs"),
            fmt(run.get("steal_percent"), "%"),
            "timeout" if run.get("returncode") is None else str(run.get("returncode")),
            fmt(run.get("attempts")),
        ]
        for name, run in results.get("runs", {}).items()
    ]
    header = (
        "step",
        "wall time",
        "load avg before",
        "probe: fixed loop",
        "probe: CPU per wake-up",
        "steal during the step",
        "exit status",
        "attempts",
    )
    lines += table(header, run_rows)
    lines += [
        "",
        "The probe runs just before each step (`machine_probe`): the best of "
        f"{PROBE_LOOP_REPEATS} runs of a fixed Python loop, and this process's CPU per "
        f"`time.sleep({PROBE_SLEEP_S:g})`.  Steal is the CPU time the hypervisor gave to "
        "other guests during the step (`/proc/stat`), as a share of all this machine's "
        "CPU time in it.  Two runs of the same code on a shared VM can differ by far more "
        "than their load averages suggest: compare these between runs before comparing "
        "their figures.",
    ]
    errors = results.get("errors") or []
    if errors:
        lines += ["", "## Errors and retries", ""] + [f"- {e}" for e in errors]
    return "\n".join(lines) + "\n"


# -- driver ------------------------------------------------------------------------------------


def write_outputs(
    out: Path, reports: Mapping[str, Any], samples: Mapping[str, Any], meta: Mapping[str, Any]
) -> dict[str, Any]:
    """Build results.json, the plots and report.md in ``out``; return the results."""
    results = build_results(reports, **meta)
    # Imported here: matplotlib takes a second to load, and nothing else needs it.
    from report_plots import make_plots

    plots, skipped = make_plots(results, samples, out)
    results["plots"] = plots
    results["errors"] += [f"plot {name} skipped: {why}" for name, why in skipped.items()]
    (out / "results.json").write_text(
        json.dumps(results, indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    (out / "report.md").write_text(render_report(results), encoding="utf-8")
    return results


def main(argv: list[str] | None = None) -> int:
    """Run every benchmark and write the results; return 0, or 1 if a benchmark failed."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="every script's --quick (< 3 min)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory")
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="do not run anything: rebuild results.json, report.md and plots from DIR/raw",
    )
    args = parser.parse_args(argv)
    out: Path = args.out.resolve()
    raw_dir = out / "raw"
    runs_file = raw_dir / "runs.json"

    if args.report_only:
        meta = load_json(runs_file)
        if meta is None:
            parser.error(f"--report-only needs {runs_file} from an earlier run")
    else:
        backends, loops = installed_backends(), installed_loops()
        meta = {
            "quick": args.quick,
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(),
            "runs": {},
            "backends": backends,
            "loops": loops,
        }
        out.mkdir(parents=True, exist_ok=True)
        # Files of an earlier run must not pass for this run's.
        for old in raw_dir.glob("*.json"):
            old.unlink()
        t0 = time.monotonic()
        for step in plan(args.quick, backends, loops):
            meta["runs"][step.name] = run_step(step, out)
        meta["duration_s"] = time.monotonic() - t0
        runs_file.write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")

    reports, samples = load_raw(raw_dir)
    results = write_outputs(out, reports, samples, meta)
    print(f"\nwrote {out / 'results.json'}, {out / 'report.md'} and {len(results['plots'])} plots")
    for name, g in results["goals"].items():
        state = met_text(g["met"]).strip("*")  # no Markdown on the terminal
        print(f"  {state:>12}  {name}: {fmt(g['value'])} (goal {g['goal']})")
    failed = [name for name, run in meta["runs"].items() if run["returncode"] != 0]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
