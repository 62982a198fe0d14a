"""results.json of a full run: the keys, what each step's report gives them, the goals.

Pure: reports in (each benchmark's JSON, as ``run.py`` collected it), figures out.  The
keys are documented in benchmarks/README.md; ``run_report.py`` renders them.
"""

from __future__ import annotations

import json
import math
import operator
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
from bench_cpu import ROW_KEYS as CPU_KEYS
from bench_late_ticks import GOAL_QUIET_MAX_US as GOAL_LATE_MAX_US
from bench_load import GOAL_RT_MAX_US, GOAL_RT_P99_US
from bench_reassembler import GOAL_DECODED_PER_S, GOAL_FRAMES_PER_S, GOAL_RATIO_VS_PYMODBUS
from bench_startup import COMMANDS as STARTUP_COMMANDS
from bench_startup import GOAL_S as GOAL_STARTUP_S
from bench_startup import GOALS as STARTUP_GOALS
from late_ticks import CAUSES as LATE_CAUSES

#: Bumped whenever a key of results.json changes meaning or disappears.
SCHEMA_VERSION = 2
#: The bus configuration the headline figures come from (the library's defaults).
MAIN_BACKEND = "fast"
MAIN_LOOP = "asyncio"
#: Every backend the bus supports (motorbus.transport.serial.BACKENDS), in report order.
ALL_BACKENDS = tuple(BACKEND_MODULES)
ALL_LOOPS = ("asyncio", "uvloop")
#: The results.json key of each command with a start-up goal (which commands have one is
#: bench_startup.GOALS's to say; a test checks that every one of them has a key here).
STARTUP_GOAL_KEYS = {
    "motorbus --version": "version",
    "motorbus la status 1 --port PTY": "la_status",
}
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
    "timeout_lazy_late_p50_us",
    "timeout_lazy_late_p99_us",
    "timeout_lazy_late_max_us",
    "timeout_lazy_early_count",
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


def bus_step_name(backend: str, loop: str) -> str:
    """The step (and raw file) name of a bus run."""
    return f"bus-{backend}-{loop}"


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


def goal_count_max(buses: Sequence[Any], ratios: Sequence[Any]) -> float | None:
    """The largest of ``ratios`` at the bus counts the CPU ratio goal is read at."""
    at_goal = [
        r
        for b, r in zip(buses, ratios, strict=False)
        if b in CPU_GOAL_RATIO_BUSES and isinstance(r, int | float)
    ]
    return max(at_goal) if at_goal else None


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
    cpu_out["max_ratio_1_16_32"] = goal_count_max(cpu_out["buses"], cpu_out["ratio"])
    cpu_out["max_ratio_timerfd_1_16_32"] = goal_count_max(
        cpu_out["buses"], cpu_out["ratio_timerfd"]
    )
    cpu_out["max_buses_keeping_up"] = (cpu or {}).get("max_buses_keeping_up")
    cpu_out["spin_s_timerfd_spin"] = (cpu or {}).get("spin_s_timerfd_spin")
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
    Goal("cpu.ratio_le_1.5x_timerfd", "cpu.max_ratio_timerfd_1_16_32", "<=", GOAL_CPU_RATIO),
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
