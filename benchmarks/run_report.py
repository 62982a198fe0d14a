"""report.md of a full run: a line per goal and a table per benchmark, each figure set
against the baseline measured in the same run.  Pure: results.json in, Markdown out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from bench_cpu import GOAL_RATIO_BUSES as CPU_GOAL_RATIO_BUSES
from bench_cpu import KEEPS_UP_TICKS_SENT_PCT
from bench_startup import GOAL_S as GOAL_STARTUP_S
from bench_startup import GOALS as STARTUP_GOALS
from kernel_clock import LATE_S
from late_ticks import CAUSES as LATE_CAUSES
from run_results import (
    IDEAL_COMMANDS_PER_S,
    LOAD_KEYS,
    MAIN_BACKEND,
    MAIN_LOOP,
    PROBE_LOOP_REPEATS,
    PROBE_SLEEP_S,
    SPACING_US,
    lookup,
)

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
    """CPU per bus count: ours, the three baselines, the ratios."""
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
                fmt(at("timer_arms_per_tick")),
                fmt(at("timerfd_cpu_percent"), "%"),
                fmt(at("ratio_timerfd")),
                spread(at("round_ratios_timerfd")),
                fmt(at("timerfd_spin_cpu_percent"), "%"),
                fmt(at("ratio_timerfd_spin")),
                fmt(at("minimal_cpu_percent"), "%"),
                fmt(at("ratio")),
                fmt(at("ratio_per_tick")),
                # One decimal: 99.9 % sent must not read as 100 %.
                "n/a" if at("ticks_sent_pct") is None else f"{at('ticks_sent_pct'):.1f} %",
                f"{fmt(at('replies'))} / {fmt(at('timerfd_replies'))}",
                f"{fmt(at('late_ticks'))} / {fmt(at('skipped_ticks'))}",
                fmt(at("stream_errors")),
                "n/a" if kept_up is None else "yes" if kept_up else "**no: fell behind**",
            ]
        )
    header = (
        "buses",
        "ours (one core = 100 %)",
        "of which timer spin",
        "timer arms a tick",
        "(b) timerfd loop",
        "ratio to (b)",
        "ratio to (b) by round",
        "(c) timerfd + busy-wait",
        "ratio to (c)",
        "minimal call_at loop",
        "ratio to minimal",
        "ratio to minimal per tick sent",
        "ours: ticks sent",
        "replies ours / (b)",
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
    spin = c.get("spin_s_timerfd_spin")
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
        "The baselines do the same writes and read the same replies by hand: (b) one "
        "timerfd per tick phase (ours's phases, so the same wake-ups), (c) the same armed "
        f"{fmt(None if spin is None else spin * 1e6, 'µs')} early with a busy-wait to "
        "each tick (the precision floor), and the minimal loop one `loop.call_at` per bus "
        "and tick (a phase per bus).  The ratio goal is read against (b), at "
        f"{goal_counts} buses (`cpu.max_ratio_timerfd_1_16_32` = "
        f"{fmt(c.get('max_ratio_timerfd_1_16_32'))}; against the minimal loop "
        f"`cpu.max_ratio_1_16_32` = {fmt(c.get('max_ratio_1_16_32'))}).",
        "",
        "The bus process has one thread: past one core it does not use more CPU, it sends "
        "fewer ticks, so beyond that count the ratios understate the cost and `ratio to "
        "minimal per tick sent` is the figure; falling behind well under 100 % CPU means "
        "the machine did not give it the core.",
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
    lines += ["", "## CPU per bus-tick against hand-written loops (same writes and reads)", ""]
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
