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
``null``; the others still count.  Numbers are reported as measured, never tuned.  This
file runs the steps; ``run_results.py`` turns their reports into results.json and the
goals, ``run_report.py`` renders report.md.

Usage: ``python benchmarks/run.py [--quick] [--out DIR] [--report-only]``
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_bus import (
    BACKEND_MODULES,
)
from harness import machine_info, steal_seconds
from run_report import fmt, met_text, render_report
from run_results import (
    ALL_BACKENDS,
    ALL_LOOPS,
    MAIN_BACKEND,
    MAIN_LOOP,
    PROBE_LOOP_ITERATIONS,
    PROBE_LOOP_REPEATS,
    PROBE_SLEEP_S,
    PROBE_SLEEPS,
    build_results,
    bus_step_name,
    load_json,
    load_raw,
)

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "results" / "latest"
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
#: Runs of a step that exits with an error (see run_step).
STEP_ATTEMPTS = 2

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
