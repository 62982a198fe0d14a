"""Follow-mode streaming: tick jitter at the simulator, drift, and scaling with bus count.

Measured where the frames land: every simulator runs in its own process (``motorbus
sim`` on a pty, like a real device) and logs the time each frame finished arriving
on its emulated wire.  Jitter is each 0xF3 broadcast's offset from the ideal 10 ms
grid (``motorbus.sim.analysis.tick_timing``), so a constant latency is not counted
but every wobble and any drift is.

Part 1: 15 actuators at 10 ms on one bus (one broadcast frame a tick), motorbus's
Streamer against, in the same run and on the same simulator:

* the hand-written baselines of ``baselines.py`` (no bus, raw ``os.write`` of the same
  frame on an absolute 10 ms grid): (a) ``sleep``, ``asyncio.sleep`` to each absolute
  deadline, the loop a careful user writes; (b) ``timerfd``, a bare timerfd read by
  ``add_reader``, the floor; (c) ``timerfd_spin``, the same plus a busy-wait for the
  last 0.5 ms, the precision floor at full CPU cost.  motorbus's kernel-clock tick
  jitter (p50/p99/max) and CPU per tick are reported as ratios to (b) and (c);
* the old "naive" loop, ``await bus.send(frame); await asyncio.sleep(period)``, which
  drifts: its "jitter" against a fixed grid is its accumulated drift, so it is
  labelled drift and is not a baseline for the ratios.

Goals: p99 <= 300 us, max <= 2 ms, no missed tick, no drift.

Part 2: 1, 4, 16 and 32 buses of 15 actuators each in one process: our process's CPU
time (per bus and in all) and the worst bus's p99 jitter.  Goal: 32 buses under 50 %
of one core with p99 <= 1 ms.  Here the receiving end is ``pty_recorder.py``, one
process that only timestamps arrivals on all the ptys: 32 full simulators would need
more than this machine's 2 cores by themselves.

Kernel clock (``kernel_clock.py``): both parts also run under ``perf record`` of this
process's write(2) calls (CLOCK_MONOTONIC).  The 0xF3 broadcasts written to each port
are fitted to a least-squares 10 ms grid there, beside the simulator's figures: the
simulator's timestamps carry its own wake-up lateness, the kernel's do not.  Where perf
cannot run the kernel figures are ``null`` and ``kernel_why`` says why.

    python benchmarks/bench_stream.py [--quick] [--seconds 30] [--scaling-seconds 10]
        [--out PATH] [--samples PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from baselines import BASELINES, run_baseline
from harness import TimerProbe, write_report
from kernel_clock import KernelWriteTrace, port_figures, worst_tick_figures
from motorbus.bus.timer import default_timer
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.sim.analysis import tick_timing
from motorbus.sim.process import SimProcess

PERIOD_S = 0.010
N_ACTUATORS = 15
BAUD = 921600
RESULTS = Path(__file__).resolve().parent / "results" / "stream.json"
#: Bytes of a 15-entry 0xF3 broadcast, the frame of every tick here.
BROADCAST_BYTES = len(
    la.split_broadcast(la.BroadcastMode.FOLLOW, dict.fromkeys(range(1, N_ACTUATORS + 1), 1000))[
        0
    ].encode()
)
GOALS = {
    "one_bus_p99_le_300us": lambda r: r["tick_jitter_p99_us"] <= 300,
    "one_bus_max_le_2ms": lambda r: r["tick_jitter_max_us"] <= 2000,
    "one_bus_no_missed_tick": lambda r: r["missed_ticks"] == 0,
    "one_bus_no_drift": lambda r: abs(r["drift_ppm"]) <= 100,
    "32_buses_cpu_lt_50pct": lambda r: _at(r, 32, "cpu_percent") < 50,
    "32_buses_p99_le_1ms": lambda r: _at(r, 32, "tick_jitter_p99_us") <= 1000,
}


def _at(result: dict[str, Any], buses: int, key: str) -> float:
    scaling = result["scaling"]
    if buses not in scaling["buses"]:
        return math.nan
    return float(scaling[key][scaling["buses"].index(buses)])


def f3_arrivals(sim: SimProcess) -> list[float]:
    """Times (s) at which the simulator finished receiving each 0xF3 broadcast."""
    records = sim.log_records()
    return [r["t"] for r in records if r["direction"] == "request" and r["hex"][9:14] == "FF F3"]


def trajectory(t: float) -> list[float]:
    return [
        1000 + 600 * math.sin(2 * math.pi * 0.5 * t + 2 * math.pi * i / N_ACTUATORS)
        for i in range(N_ACTUATORS)
    ]


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def stream_buses(paths: list[str], seconds: float, backend: str) -> dict[str, Any]:
    """Stream to every bus for ``seconds``; return host-side stats and our CPU use."""
    mgr = BusManager(safe_stop=False)
    for i, path in enumerate(paths):
        mgr.add_bus(f"bus{i}", path, baud=BAUD, devices=[f"la:1-{N_ACTUATORS}"], backend=backend)
    async with mgr:
        streams = []
        for name in mgr.buses:
            actuators = [mgr.la(name, i) for i in range(1, N_ACTUATORS + 1)]
            streams.append(
                mgr.streamer(name).follow(
                    actuators,
                    lambda t, s: None if t >= seconds else trajectory(t),
                    period=PERIOD_S,
                )
            )
        probe = TimerProbe(default_timer())
        wall0, cpu0 = time.monotonic(), cpu_seconds()
        await asyncio.gather(*(s.wait() for s in streams))
        wall, cpu = time.monotonic() - wall0, cpu_seconds() - cpu0
        wakeups, spin = probe.wakeups, probe.spin_s
        late = sum(s.stats.late for s in streams)
        skipped = sum(s.stats.skipped for s in streams)
        host_p99 = max(s.stats.jitter.percentile(99) for s in streams)
    ticks = max(1, sum(s.stats.ticks for s in streams))
    return {
        "cpu_percent": 100 * cpu / wall,
        # What the CPU figure depends on besides our code: how often the timer woke the
        # loop and how long it spun (the spin follows the machine's wake-up lateness).
        "timer_wakeups_per_tick": wakeups / ticks,
        "timer_spin_us_per_tick": 1e6 * spin / ticks,
        "host_late": late,
        "host_skipped": skipped,
        "host_jitter_p99_us": host_p99 * 1e6,
    }


async def naive_loop(path: str, seconds: float, backend: str) -> None:
    """The baseline: send, then ``asyncio.sleep(period)``, on the same bus stack."""
    mgr = BusManager(safe_stop=False)
    mgr.add_bus("naive", path, baud=BAUD, devices=[f"la:1-{N_ACTUATORS}"], backend=backend)
    async with mgr:
        bus = mgr.bus("naive")
        t0 = time.monotonic()
        while (t := time.monotonic() - t0) < seconds:
            targets = {i + 1: round(v) for i, v in enumerate(trajectory(t))}
            for frame in la.split_broadcast(la.BroadcastMode.FOLLOW, targets):
                await bus.send(frame)
            await asyncio.sleep(PERIOD_S)


def tick_frame(k: int) -> bytes:
    """Tick ``k``'s 0xF3 follow broadcast, built as the Streamer builds it (one frame)."""
    targets = {i + 1: round(v) for i, v in enumerate(trajectory(k * PERIOD_S))}
    return la.split_broadcast(la.BroadcastMode.FOLLOW, targets)[0].encode()


def baselines_one_bus(seconds: float, tmp: Path) -> dict[str, Any]:
    """Each baseline of ``baselines.py`` on its own simulator, under the kernel clock."""
    out: dict[str, Any] = {}
    for name in BASELINES:
        log = tmp / f"one-baseline-{name}.jsonl"
        with SimProcess([f"la:1-{N_ACTUATORS}"], baud=BAUD, log_file=log) as sim:
            with KernelWriteTrace() as trace:
                cost = run_baseline(name, [sim.path], tick_frame, PERIOD_S, seconds)
            sim.stop()
            arrivals = f3_arrivals(sim)
        timing = tick_timing(arrivals, PERIOD_S)
        kernel = port_figures(
            trace,
            [BROADCAST_BYTES],
            tick_bytes=BROADCAST_BYTES,
            period=PERIOD_S,
            expected_ticks=round(seconds / PERIOD_S),
        )
        out[name] = {**timing.as_dict(), **cost.as_dict(), "kernel": kernel}
    return out


def one_bus(seconds: float, backend: str, tmp: Path) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for label, runner in (("motorbus", "streamer"), ("naive", "naive")):
        log = tmp / f"one-{label}.jsonl"
        # Not busy-polling (spin=True): on 2 cores a spinning simulator takes the core
        # the streams need; measured, it made the jitter worse, not better.
        with SimProcess([f"la:1-{N_ACTUATORS}"], baud=BAUD, log_file=log) as sim:
            with KernelWriteTrace() as trace:
                if runner == "streamer":
                    host = asyncio.run(stream_buses([sim.path], seconds, backend))
                else:
                    asyncio.run(naive_loop(sim.path, seconds, backend))
                    host = {}
            sim.stop()
            arrivals = f3_arrivals(sim)
        timing = tick_timing(arrivals, PERIOD_S, by_index=(runner == "naive"))
        kernel = port_figures(
            trace,
            [BROADCAST_BYTES],
            tick_bytes=BROADCAST_BYTES,
            period=PERIOD_S,
            expected_ticks=round(seconds / PERIOD_S),
            by_index=(runner == "naive"),  # as on the simulator side: k-th frame, slot k
        )
        out[label] = {**timing.as_dict(), **host, "kernel": kernel}
        # Kept for --samples only; main() picks its report keys by name.
        out[label]["offsets_s"] = list(timing.offsets)
        if runner == "naive":
            span = arrivals[-1] - arrivals[0] if len(arrivals) > 1 else 0.0
            out[label]["mean_period_us"] = 1e6 * span / max(1, len(arrivals) - 1)
    return out


class Recorder:
    """``benchmarks/pty_recorder.py`` in a child process: N ptys that timestamp arrivals."""

    def __init__(self, count: int, out: Path) -> None:
        self.out = out
        script = Path(__file__).resolve().parent / "pty_recorder.py"
        self.proc = subprocess.Popen(
            # --answer: the streams end with their safe pause, which expects a reply;
            # no other request is sent, so answering costs the recorder nothing meanwhile.
            [sys.executable, str(script), str(count), str(out), "--answer"],
            stdout=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        assert self.proc.stdout is not None
        self.paths = self.proc.stdout.readline().split()

    def stop(self) -> list[list[float]]:
        """Stop recording; the 0xF3 arrival times per pty."""
        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(30)
        data = json.loads(self.out.read_text(encoding="utf-8"))
        return [
            [t for t, cmd in frames if cmd == la.CMD_BROADCAST_FOLLOW] for frames in data["frames"]
        ]


def _num(value: Any) -> Any:
    """A figure for the JSON report: rounded, None for NaN or absent."""
    if isinstance(value, float):
        return round(value) if math.isfinite(value) else None
    return value


def scaling(counts: list[int], seconds: float, backend: str, tmp: Path) -> dict[str, Any]:
    rows: dict[str, list[Any]] = {
        k: []
        for k in (
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
            "timer_wakeups_per_tick",
            "timer_spin_us_per_tick",
            "load_avg_1min",
        )
    }
    for n in counts:
        rows["load_avg_1min"].append(round(os.getloadavg()[0], 2))
        recorder = Recorder(n, tmp / f"scale{n}.json")
        try:
            with KernelWriteTrace() as trace:
                host = asyncio.run(stream_buses(recorder.paths, seconds, backend))
        finally:
            arrivals = recorder.stop()
        kernel = worst_tick_figures(trace, BROADCAST_BYTES, PERIOD_S)
        timings = [tick_timing(a, PERIOD_S) for a in arrivals]
        rows["buses"].append(n)
        rows["cpu_percent"].append(round(host["cpu_percent"], 1))
        rows["cpu_percent_per_bus"].append(round(host["cpu_percent"] / n, 2))
        rows["tick_jitter_p99_us"].append(round(max(t.jitter_p99 for t in timings) * 1e6))
        rows["tick_jitter_max_us"].append(round(max(t.jitter_max for t in timings) * 1e6))
        rows["missed_ticks"].append(sum(t.missed for t in timings))
        rows["timer_wakeups_per_tick"].append(round(host["timer_wakeups_per_tick"], 2))
        rows["timer_spin_us_per_tick"].append(round(host["timer_spin_us_per_tick"], 1))
        for key in (
            "kernel_tick_jitter_p99_us",
            "kernel_tick_jitter_max_us",
            "kernel_late_ticks",
            "kernel_missed_ticks",
        ):
            rows[key].append(_num(kernel.get(key)))
        print(
            f"  {n:3d} buses: CPU {host['cpu_percent']:5.1f} % "
            f"({host['cpu_percent'] / n:.2f} %/bus), worst-bus p99 "
            f"{rows['tick_jitter_p99_us'][-1]} us, max {rows['tick_jitter_max_us'][-1]} us, "
            f"missed {rows['missed_ticks'][-1]}; spin {rows['timer_spin_us_per_tick'][-1]} "
            f"us/tick, load {rows['load_avg_1min'][-1]}; kernel clock: "
            + (
                f"p99 {rows['kernel_tick_jitter_p99_us'][-1]} us, "
                f"max {rows['kernel_tick_jitter_max_us'][-1]} us"
                if kernel["kernel_measured"]
                else f"not measured ({kernel['kernel_why']})"
            ),
            flush=True,
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="one-bus run length")
    parser.add_argument("--scaling-seconds", type=float, default=10.0)
    parser.add_argument("--buses", default="1,4,16,32", help="bus counts for the scaling run")
    parser.add_argument("--backend", default="fast")
    parser.add_argument("--quick", action="store_true", help="5 s runs, buses 1,4,16")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--samples",
        type=Path,
        default=None,
        help="also write the one-bus tick offsets from the grid (seconds) to this JSON file",
    )
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.scaling_seconds, args.buses = 5.0, 4.0, "1,4,16"
    counts = [int(x) for x in args.buses.split(",") if x]
    with tempfile.TemporaryDirectory(prefix="motorbus-bench-") as tmp_name:
        tmp = Path(tmp_name)
        print(
            f"one bus, {N_ACTUATORS} actuators, {PERIOD_S * 1e3:.0f} ms, {args.seconds:.0f} s",
            flush=True,
        )
        one = one_bus(args.seconds, args.backend, tmp)
        print("baselines (no bus): sleep, timerfd, timerfd_spin", flush=True)
        base = baselines_one_bus(args.seconds, tmp)
        print(f"scaling, {args.scaling_seconds:.0f} s per step", flush=True)
        scale = scaling(counts, args.scaling_seconds, args.backend, tmp)
    ours, naive = one["motorbus"], one["naive"]
    result: dict[str, Any] = {
        "tick_jitter_p50_us": round(ours["tick_jitter_p50_us"]),
        "tick_jitter_p99_us": round(ours["tick_jitter_p99_us"]),
        "tick_jitter_max_us": round(ours["tick_jitter_max_us"]),
        "missed_ticks": ours["missed_ticks"],
        "drift_ppm": round(ours["drift_ppm"], 1),
        "frames": ours["frames"],
        "host_late_ticks": ours["host_late"],
        "host_skipped_ticks": ours["host_skipped"],
        "host_tick_lateness_p99_us": round(ours["host_jitter_p99_us"]),
        "naive_tick_jitter_p99_us": round(naive["tick_jitter_p99_us"]),
        "naive_tick_jitter_max_us": round(naive["tick_jitter_max_us"]),
        "naive_drift_ppm": round(naive["drift_ppm"], 1),
        "naive_mean_period_us": round(naive["mean_period_us"], 1),
        "naive_note": "send then sleep(period): drifts; its jitter is its accumulated drift",
        "cpu_us_per_tick": round(ours["cpu_percent"] / 100 * PERIOD_S * 1e6, 1),
        **kernel_keys(ours["kernel"], ""),
        **kernel_keys(naive["kernel"], "naive_"),
        **baseline_keys(base),
        **ratio_keys(ours, base),
        "scaling": scale,
        "seconds": args.seconds,
        "scaling_seconds": args.scaling_seconds,
        "backend": args.backend,
        "timer": default_timer_name(),
        "loop": "asyncio default",
        "note": "one-bus: the LA simulator in its own process; scaling: pty_recorder.py; "
        "both share the 2 cores with the streams",
    }
    result["goals"] = {name: bool(check(result)) for name, check in GOALS.items()}
    print()
    print(f"{'':34}{'motorbus':>12}{'naive sleep':>14}")
    for label, key in (
        ("tick jitter p99 (us)", "tick_jitter_p99_us"),
        ("tick jitter max (us)", "tick_jitter_max_us"),
        ("drift (ppm)", "drift_ppm"),
    ):
        print(f"{label:34}{ours[key]:12.0f}{naive[key]:14.0f}")
    print(f"{'missed ticks':34}{ours['missed_ticks']:12d}{'-':>14}")
    for label, key in (
        ("kernel clock: tick jitter p50 (us)", "kernel_tick_jitter_p50_us"),
        ("kernel clock: tick jitter p99 (us)", "kernel_tick_jitter_p99_us"),
        ("kernel clock: tick jitter max (us)", "kernel_tick_jitter_max_us"),
        ("kernel clock: late ticks (> 1 ms)", "kernel_late_ticks"),
        ("kernel clock: missed ticks", "kernel_missed_ticks"),
    ):
        a, b = result[key], result[f"naive_{key}"]
        print(f"{label:34}{'n/a' if a is None else a:>12}{'n/a' if b is None else b:>14}")
    if not result["kernel_measured"]:
        print(f"kernel clock not measured: {result['kernel_why']}")
    print(f"{'mean period (us)':34}{PERIOD_S * 1e6:12.0f}{naive['mean_period_us']:14.0f}")
    print("(naive sleep = send, then sleep(period): it drifts, its jitter is its drift)")
    print()
    print_baselines(result)
    print()
    for name, ok in result["goals"].items():
        print(f"goal {name:28} {'met' if ok else 'NOT met'}")
    write_report(args.out, result)
    if args.samples is not None:
        samples = {
            "unit": "s",
            "tick_offsets_motorbus": ours["offsets_s"],
            "tick_offsets_naive": naive["offsets_s"],
        }
        args.samples.parent.mkdir(parents=True, exist_ok=True)
        args.samples.write_text(json.dumps(samples) + "\n", encoding="utf-8")
        print(f"wrote {args.samples}")
    return 0


def kernel_keys(k: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The one-bus kernel-clock figures under ``<prefix>kernel_*`` keys (README)."""
    keys = (
        "tick_jitter_p50_us",
        "tick_jitter_p99_us",
        "tick_jitter_max_us",
        "late_ticks",
        "missed_ticks",
        "ticks",
        "ticks_sent_pct",
        "min_gap_us",
        "gaps_under_1000us",
        "write_p50_us",
        "write_max_us",
    )
    out: dict[str, Any] = {
        f"{prefix}kernel_measured": bool(k.get("kernel_measured")),
        f"{prefix}kernel_why": k.get("kernel_why") or None,
    }
    for key in keys:
        value = k.get(f"kernel_{key}")
        if isinstance(value, float):
            value = round(value, 1) if math.isfinite(value) else None
        out[f"{prefix}kernel_{key}"] = value
    return out


#: Figures of a baseline kept in the report, from its kernel-clock figures.
_BASELINE_KERNEL = (
    "tick_jitter_p50_us",
    "tick_jitter_p99_us",
    "tick_jitter_max_us",
    "late_ticks",
    "missed_ticks",
)


def baseline_keys(base: dict[str, Any]) -> dict[str, Any]:
    """``baseline_<name>_*`` keys: kernel-clock jitter, late/missed ticks, CPU per tick."""
    out: dict[str, Any] = {}
    for name, figures in base.items():
        prefix = f"baseline_{name}_"
        for key in _BASELINE_KERNEL:
            value = figures["kernel"].get(f"kernel_{key}")
            if isinstance(value, float):
                value = round(value, 1) if math.isfinite(value) else None
            out[f"{prefix}kernel_{key}"] = value
        out[f"{prefix}tick_jitter_p99_us"] = round(figures["tick_jitter_p99_us"])
        out[f"{prefix}tick_jitter_max_us"] = round(figures["tick_jitter_max_us"])
        out[f"{prefix}cpu_us_per_tick"] = figures["cpu_us_per_bus_tick"]
        out[f"{prefix}cpu_percent"] = figures["cpu_percent"]
    return out


def _ratio(value: Any, baseline: Any) -> float | None:
    if not isinstance(value, int | float) or not isinstance(baseline, int | float):
        return None
    if not (math.isfinite(value) and math.isfinite(baseline)) or baseline <= 0:
        return None
    return round(value / baseline, 2)


def ratio_keys(ours: dict[str, Any], base: dict[str, Any]) -> dict[str, Any]:
    """motorbus's kernel-clock jitter and CPU per tick over baselines (b) and (c)."""
    cpu = ours["cpu_percent"] / 100 * PERIOD_S * 1e6
    out: dict[str, Any] = {}
    for name in ("timerfd", "timerfd_spin"):
        if name not in base:
            continue
        for q in ("p50", "p99", "max"):
            key = f"kernel_tick_jitter_{q}_us"
            out[f"ratio_vs_{name}_kernel_jitter_{q}"] = _ratio(
                ours["kernel"].get(key), base[name]["kernel"].get(key)
            )
        out[f"ratio_vs_{name}_cpu_per_tick"] = _ratio(cpu, base[name]["cpu_us_per_bus_tick"])
    return out


def print_baselines(result: dict[str, Any]) -> None:
    """The motorbus-against-baselines table (kernel clock, CPU per tick, ratios)."""
    cols = [("motorbus", "")] + [(n, f"baseline_{n}_") for n in BASELINES]
    print(f"{'one bus, same frames':34}" + "".join(f"{c:>14}" for c, _ in cols))
    rows = [(f"kernel tick jitter {q} (us)", f"kernel_tick_jitter_{q}_us") for q in _QS]
    rows += [("kernel late ticks (> 1 ms)", "kernel_late_ticks")]
    rows += [("kernel missed ticks", "kernel_missed_ticks")]
    rows += [("CPU per tick (us)", "cpu_us_per_tick")]
    for label, key in rows:
        cells = [result.get(f"{prefix}{key}") for _, prefix in cols]
        print(f"{label:34}" + "".join(f"{'n/a' if v is None else v:>14}" for v in cells))
    for name in ("timerfd", "timerfd_spin"):
        ratios = [result.get(f"ratio_vs_{name}_kernel_jitter_{q}") for q in _QS]
        cpu = result.get(f"ratio_vs_{name}_cpu_per_tick")
        print(
            f"motorbus / {name}: jitter p50 {ratios[0]}x, p99 {ratios[1]}x, "
            f"max {ratios[2]}x; CPU per tick {cpu}x"
        )


_QS = ("p50", "p99", "max")


def default_timer_name() -> str:
    async def name() -> str:
        return default_timer().name

    return asyncio.run(name())


if __name__ == "__main__":
    raise SystemExit(main())
