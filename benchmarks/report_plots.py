"""PNG plots for the benchmark report (``run.py``): jitter, RTT, scaling, timers, CPU.

Every plot is drawn on its own ``matplotlib.figure.Figure`` (no pyplot state) with the
Agg backend, so it works without a display and inside tests.  Each plotting function
takes the samples a benchmark wrote with ``--samples`` (values in seconds) or the
results document, and returns None when its data is missing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

from matplotlib.axes import Axes
from matplotlib.figure import Figure

#: Plot name -> file, in report order.
PLOT_FILES = {
    "tick_jitter": "tick_jitter_hist.png",
    "rtt_cdf": "rtt_cdf.png",
    "scaling": "scaling.png",
    "timer_lateness": "timer_lateness.png",
    "cpu": "cpu.png",
}
DPI = 110
#: Timer lateness axis: linear within +-10 µs, logarithmic beyond (early values are < 0).
SYMLOG_LINTHRESH_US = 10.0


def micro(values: Sequence[float]) -> list[float]:
    """Seconds to microseconds."""
    return [v * 1e6 for v in values]


def cdf(ax: Axes, values_us: Sequence[float], label: str, **style: Any) -> None:
    """Draw the empirical CDF of ``values_us`` on ``ax``."""
    ordered = sorted(values_us)
    n = len(ordered)
    ax.step(ordered, [(i + 1) / n for i in range(n)], where="post", label=label, **style)


def save(fig: Figure, path: Path) -> Path:
    """Write ``fig`` as PNG to ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    return path


def plot_tick_jitter(stream_samples: Mapping[str, Any] | None, path: Path) -> Path | None:
    """Histogram of tick offsets from the 10 ms grid: motorbus Streamer vs naive sleep loop.

    Args:
        stream_samples: bench_stream.py ``--samples`` data (``tick_offsets_motorbus``,
            ``tick_offsets_naive``, seconds).
        path: PNG to write.

    Returns:
        ``path``, or None if there were no samples.
    """
    if not stream_samples or not stream_samples.get("tick_offsets_motorbus"):
        return None
    series = [
        ("motorbus Streamer", micro(stream_samples["tick_offsets_motorbus"])),
        ("naive send + sleep(period)", micro(stream_samples.get("tick_offsets_naive") or [])),
    ]
    # Offsets span 1 µs to (for the drifting naive loop) seconds: log-spaced bins.
    top = max(max(v, default=1.0) for _, v in series)
    lo, hi = 0.0, math.log10(max(top, 10.0) * 1.1)
    bins = [10 ** (lo + (hi - lo) * i / 60) for i in range(61)]
    fig = Figure(figsize=(8, 4.5))
    ax = fig.add_subplot()
    for label, values in series:
        if values:
            clipped = [max(v, 1.0) for v in values]  # the earliest tick is 0 by definition
            ax.hist(clipped, bins=bins, alpha=0.6, label=f"{label} (n={len(values)})")
    ax.set_xscale("log")
    ax.set_xlabel("offset from the ideal grid (µs, earliest tick = 0, shown at 1)")
    ax.set_ylabel("ticks")
    ax.set_title("Follow-mode tick jitter at the simulator, 15 actuators, 10 ms")
    ax.legend()
    return save(fig, path)


def plot_rtt_cdf(
    main_samples: Mapping[str, Any] | None,
    variants: Mapping[str, Mapping[str, Any] | None],
    path: Path,
) -> Path | None:
    """RTT CDFs: ours vs minimal asyncio vs blocking pyserial; ours per backend and loop.

    Args:
        main_samples: bench_bus.py ``--samples`` data of the main run (``rtt_ours``,
            ``rtt_minimal_client``, ``rtt_blocking_pyserial``, seconds).
        variants: label -> ``--samples`` data of every bus run (the right panel).
        path: PNG to write.

    Returns:
        ``path``, or None if the main run has no samples.
    """
    if not main_samples or not main_samples.get("rtt_ours"):
        return None
    fig = Figure(figsize=(11, 4.5))
    left, right = fig.subplots(1, 2, sharey=True)
    for key, label in (
        ("rtt_ours", "motorbus Bus + InspireLA.status"),
        ("rtt_minimal_client", "minimal asyncio client"),
        ("rtt_blocking_pyserial", "blocking pyserial"),
    ):
        if main_samples.get(key):
            cdf(left, micro(main_samples[key]), label)
    left.set_title("LA status round trip, same pty and backend")
    for label, samples in variants.items():
        if samples and samples.get("rtt_ours"):
            cdf(right, micro(samples["rtt_ours"]), label)
    right.set_title("motorbus round trip per backend / event loop")
    for ax in (left, right):
        ax.set_xscale("log")
        ax.set_xlabel("round trip (µs)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    left.set_ylabel("fraction of requests")
    return save(fig, path)


def plot_scaling(scaling: Mapping[str, Any], goals: Mapping[str, Any], path: Path) -> Path | None:
    """CPU % and worst-bus p99 tick jitter against the number of buses.

    Args:
        scaling: the ``scaling`` section of results.json.
        goals: the ``goals`` section (its 32-bus targets are drawn as dashed lines).
        path: PNG to write.

    Returns:
        ``path``, or None if no bus count was measured.
    """
    buses = scaling.get("buses") or []
    if not buses:
        return None
    fig = Figure(figsize=(10, 4))
    cpu_ax, jitter_ax = fig.subplots(1, 2)
    for ax, key, goal_name, ylabel in (
        (
            cpu_ax,
            "cpu_percent",
            "scaling.32_buses_cpu_lt_50pct",
            "CPU of the streaming process (%)",
        ),
        (
            jitter_ax,
            "tick_jitter_p99_us",
            "scaling.32_buses_p99_le_1ms",
            "worst-bus p99 jitter (µs)",
        ),
    ):
        values = scaling.get(key) or []
        points = [(b, v) for b, v in zip(buses, values, strict=False) if v is not None]
        ax.plot([b for b, _ in points], [v for _, v in points], marker="o", label="measured")
        goal = goals.get(goal_name)
        if goal is not None:
            ax.axhline(
                goal["target"],
                linestyle="--",
                color="gray",
                label=f"goal at 32 buses: {goal['goal']}",
            )
        ax.set_xlabel("buses (15 actuators each, 10 ms)")
        ax.set_ylabel(ylabel)
        ax.set_xticks(buses)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    fig.suptitle("Streaming cost and jitter against bus count")
    return save(fig, path)


def plot_timer_lateness(timer_samples: Mapping[str, Any] | None, path: Path) -> Path | None:
    """Lateness CDFs of periodic absolute deadlines per timer source, one panel per loop.

    Args:
        timer_samples: bench_timer.py ``--samples`` data (``runs``: loop, period_ms,
            method, lateness in seconds).
        path: PNG to write.

    Returns:
        ``path``, or None if there were no samples.
    """
    runs = (timer_samples or {}).get("runs") or []
    if not runs:
        return None
    loops = list(dict.fromkeys(r["loop"] for r in runs))
    fig = Figure(figsize=(6 * len(loops), 4.5))
    axes = fig.subplots(1, len(loops), sharey=True, squeeze=False)[0]
    methods = list(dict.fromkeys(r["method"] for r in runs))
    colors = {m: f"C{i}" for i, m in enumerate(methods)}
    for ax, loop in zip(axes, loops, strict=True):
        for r in runs:
            if r["loop"] == loop and r["lateness"]:
                style = "-" if r["period_ms"] < 5 else "--"
                label = f"{r['method']}, {r['period_ms']:g} ms"
                cdf(ax, micro(r["lateness"]), label, color=colors[r["method"]], linestyle=style)
        ax.axvline(0, color="black", linewidth=0.8)
        ax.set_xscale("symlog", linthresh=SYMLOG_LINTHRESH_US)
        ax.set_xlabel("lateness (µs; < 0 = fired early)")
        ax.set_title(f"{loop} loop")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    axes[0].set_ylabel("fraction of wake-ups")
    fig.suptitle("Lateness of periodic absolute deadlines per timer source")
    return save(fig, path)


def plot_cpu(cpu: Mapping[str, Any], path: Path) -> Path | None:
    """CPU % of one core against bus count: motorbus (and its timer's spin), the minimal
    loop, the goal.

    Args:
        cpu: the ``cpu`` section of results.json (bench_cpu.py).
        path: PNG to write.
    """
    buses = cpu.get("buses") or []
    if not buses:
        return None
    fig = Figure(figsize=(6.4, 4.0))
    ax = fig.add_subplot()
    for key, label, style in (
        ("cpu_percent", "motorbus", "o-"),
        ("spin_percent", "motorbus: of which timer spin", "^:"),
        ("timerfd_cpu_percent", "(b) timerfd loop", "s--"),
        ("timerfd_spin_cpu_percent", "(c) timerfd + busy-wait", "d-."),
        ("minimal_cpu_percent", "minimal call_at loop", "x:"),
    ):
        values = cpu.get(key) or []
        pairs = [(b, v) for b, v in zip(buses, values, strict=False) if v is not None]
        if pairs:
            ax.plot([b for b, _ in pairs], [v for _, v in pairs], style, label=label)
    ax.axhline(35, color="red", linewidth=0.8, linestyle=":", label="goal at 32 buses: < 35 %")
    ax.set_xlabel("buses (15 actuators, one 0xF3 broadcast + one status poll per 10 ms)")
    ax.set_ylabel("CPU (% of one core)")
    ax.set_title("CPU per bus-tick, same writes and reads")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    return save(fig, path)


def make_plots(
    results: Mapping[str, Any], samples: Mapping[str, Any], out: Path
) -> tuple[dict[str, str], dict[str, str]]:
    """Draw every plot into ``out``.

    Args:
        results: the results.json document (run.py ``build_results``).
        samples: ``--samples`` data keyed by step name (``bus-<backend>-<loop>``,
            ``stream``, ``timer``).
        out: output directory.

    Returns:
        (plot name -> file name relative to ``out``, plot name -> why it was skipped).
    """
    bus_samples = {
        name.removeprefix("bus-"): data for name, data in samples.items() if name.startswith("bus-")
    }
    main_bus = samples.get(f"bus-{results.get('backend')}-{results.get('event_loop')}")
    drawn = {
        "tick_jitter": plot_tick_jitter(samples.get("stream"), out / PLOT_FILES["tick_jitter"]),
        "rtt_cdf": plot_rtt_cdf(main_bus, bus_samples, out / PLOT_FILES["rtt_cdf"]),
        "scaling": plot_scaling(
            results.get("scaling", {}), results.get("goals", {}), out / PLOT_FILES["scaling"]
        ),
        "timer_lateness": plot_timer_lateness(
            samples.get("timer"), out / PLOT_FILES["timer_lateness"]
        ),
        "cpu": plot_cpu(results.get("cpu", {}), out / PLOT_FILES["cpu"]),
    }
    plots = {name: path.name for name, path in drawn.items() if path is not None}
    skipped = {name: "no data" for name, path in drawn.items() if path is None}
    for name in skipped:  # an earlier run's picture must not pass for this run's
        (out / PLOT_FILES[name]).unlink(missing_ok=True)
    return plots, skipped
