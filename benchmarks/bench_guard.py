"""SIGKILL to the last safe frame: how fast the guard stops a killed program's devices.

``guard_victim.py`` streams follow-mode targets at 100 Hz to three LA actuators on each
of ``--buses`` simulated buses (``motorbus sim`` children, each on its own pty, wire
pacing at 921600 baud), under ``motorbus.run(..., guard=True)``.  Once it streams, this
script waits a random 100..300 ms and sends it SIGKILL.  The simulators' frame logs
say when each frame arrived (``time.monotonic`` of the simulator, mapped to this
process's clock through the log header's wall-clock start).  Reported per run:

* ``kill_to_last_safe_ms``: from the SIGKILL to the last pause frame any simulator got
  (every device on every bus is then paused);
* ``kill_to_first_safe_ms``: from the SIGKILL to the first;
* ``all_safe_after_motion``: on every bus, the frames after the last target are
  exactly the three pauses, and the simulated devices heard each (none came while a
  device was answering: ``unheard_safe_frames`` counts those);
* ``kill_to_guard_wake_ms``: from the SIGKILL to the guard's pidfd waking it (its
  ``MOTORBUS_GUARD_REPORT`` file);
* ``guard_wake_to_last_write_ms``: the guard's own figure (its stderr line), from the
  pidfd waking it to its last write.

The same runs without the guard are the baseline: no pause ever follows (reported as
the number of runs whose last frame was a target).

Mapping the clocks costs some accuracy: the simulator stamps its log's start with
``datetime.now()`` and its clock with ``time.monotonic()`` a few tens of microseconds
apart; figures are given to 0.1 ms.

Prints a table and writes ``benchmarks/results/guard.json``.

The simulators' stamps are taken when their loop reads the pty: on a loaded machine
that lags the guard's own drained writes by milliseconds, so both figures are given.

Usage: ``python benchmarks/bench_guard.py [--runs 10] [--buses 1 2 4] [--spin] [--out PATH]``
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import random
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from harness import write_report
from motorbus.protocol import la
from motorbus.runtime import guard as guard_process
from motorbus.runtime.guard import REPORT_ENV
from motorbus.sim.process import SimProcess

HERE = Path(__file__).resolve().parent
VICTIM = HERE / "guard_victim.py"
DEFAULT_OUT = HERE / "results" / "guard.json"
IDS = (1, 2, 3)
PAUSES = {la.Control(i, la.ControlAction.PAUSE).encode().hex(" ").upper() for i in IDS}
START_TIMEOUT_S = 60.0
SETTLE_S = 1.0
#: The guard's stderr line per port: "... (3 frames, the last 2.1 ms after it ended)".
GUARD_SAYS = re.compile(r"the last ([0-9.]+) ms after it ended")


def is_motion(hex_: str) -> bool:
    return hex_.startswith("55 AA") and hex_.split()[4] in ("F3", "F2", "21")


def sim_clock_offset(log: Path) -> float:
    """Seconds to add to a record's ``t`` to get this process's ``time.monotonic()``."""
    with log.open(encoding="utf-8") as fh:
        header = json.loads(fh.readline())
    started = datetime.datetime.fromisoformat(header["started_utc"].replace("Z", "+00:00"))
    return started.timestamp() - (time.time() - time.monotonic())


def requests(log: Path) -> list[tuple[float, str, bool]]:
    """(time, hex, heard) of every request: not heard if it came while a device was
    answering (the simulator's ``half_duplex`` fault)."""
    out = []
    with log.open(encoding="utf-8") as fh:
        for line in fh:
            if not line.endswith("\n"):
                continue
            rec = json.loads(line)
            if rec.get("direction") == "request" and "t" in rec:
                heard = rec.get("fault") != "half_duplex"
                out.append((float(rec["t"]), str(rec["hex"]), heard))
    return out


def one_run(
    n_buses: int, guard: bool, tmp: Path, rng: random.Random, *, spin: bool = False
) -> dict[str, Any]:
    logs = [tmp / f"bus{n}-{time.monotonic_ns()}.jsonl" for n in range(n_buses)]
    sims = [SimProcess(["la:1-3"], baud=921600, log_file=log, spin=spin).start() for log in logs]
    try:
        cmd = [sys.executable, str(VICTIM), "--ids", "1-3"]
        cmd += [a for s in sims for a in ("--port", s.path)]
        if guard:
            cmd += ["--guard"]
        report = tmp / f"guard-{time.monotonic_ns()}.json"
        env = {**os.environ, REPORT_ENV: str(report)}
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if line != "streaming\n":
            proc.kill()
            raise RuntimeError(f"the victim did not stream: {proc.communicate()[1][-2000:]}")
        time.sleep(rng.uniform(0.1, 0.3))
        killed = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        # The guard shares the victim's stderr: this returns once both are gone.
        _, err = proc.communicate(timeout=START_TIMEOUT_S)
        time.sleep(SETTLE_S)  # the guard has milliseconds to act; give it a second
    finally:
        for s in sims:
            s.stop()
    safe_times: list[float] = []
    all_safe = True
    last_is_motion = 0
    unheard = 0
    for log in logs:
        offset = sim_clock_offset(log)
        frames = [(t + offset, h, heard) for t, h, heard in requests(log)]
        last_motion = max(n for n, (_, h, _) in enumerate(frames) if is_motion(h))
        after = frames[last_motion + 1 :]
        unheard += sum(not heard for _, _, heard in after)
        if sorted(h for _, h, _ in after) != sorted(PAUSES) or unheard:
            all_safe = False
        safe_times += [t for t, h, _ in after if h in PAUSES]
        last_is_motion += int(not after)
    result: dict[str, Any] = {
        "buses": n_buses,
        "guard": guard,
        "all_safe_after_motion": all_safe,
        "unheard_safe_frames": unheard,
        "buses_left_moving": last_is_motion,
    }
    guard_ms = [float(m) for m in GUARD_SAYS.findall(err)]
    if guard_ms:
        result["guard_wake_to_last_write_ms"] = max(guard_ms)
    if report.exists():
        woke = json.loads(report.read_text(encoding="utf-8"))["died"]
        result["kill_to_guard_wake_ms"] = (woke - killed) * 1e3
    if safe_times:
        result["kill_to_first_safe_ms"] = (min(safe_times) - killed) * 1e3
        result["kill_to_last_safe_ms"] = (max(safe_times) - killed) * 1e3
    return result


def summarize(runs: list[dict[str, Any]], key: str) -> dict[str, float] | None:
    values = [r[key] for r in runs if key in r]
    if not values:
        return None
    values.sort()
    return {
        "median": statistics.median(values),
        "p90": values[min(len(values) - 1, int(0.9 * len(values)))],
        "min": values[0],
        "max": values[-1],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=10, help="kills per configuration")
    parser.add_argument("--buses", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--spin", action="store_true", help="simulators busy-poll (precise stamps, more CPU)"
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.buses:
            for guard in (True, False):
                runs = [one_run(n, guard, Path(tmp), rng, spin=args.spin) for _ in range(args.runs)]
                rows.append(
                    {
                        "buses": n,
                        "devices": n * len(IDS),
                        "guard": guard,
                        "runs": len(runs),
                        "all_safe_runs": sum(r["all_safe_after_motion"] for r in runs),
                        "unheard_safe_frames": sum(r["unheard_safe_frames"] for r in runs),
                        "runs_left_moving": sum(r["buses_left_moving"] > 0 for r in runs),
                        "kill_to_first_safe_ms": summarize(runs, "kill_to_first_safe_ms"),
                        "kill_to_last_safe_ms": summarize(runs, "kill_to_last_safe_ms"),
                        "kill_to_guard_wake_ms": summarize(runs, "kill_to_guard_wake_ms"),
                        "guard_wake_to_last_write_ms": summarize(
                            runs, "guard_wake_to_last_write_ms"
                        ),
                        "raw": runs,
                    }
                )
    header = (
        f"{'buses':>5} {'devs':>4} {'guard':>5} {'runs':>4} {'all safe':>8} {'unheard':>7} "
        f"{'moving':>6} {'kill->last safe ms: median':>27} {'p90':>6} {'max':>6}"
    )
    print(header)
    for row in rows:
        last = row["kill_to_last_safe_ms"]
        cells = (
            f"{last['median']:27.1f} {last['p90']:6.1f} {last['max']:6.1f}"
            if last
            else f"{'never':>27} {'-':>6} {'-':>6}"
        )
        print(
            f"{row['buses']:>5} {row['devices']:>4} {'yes' if row['guard'] else 'no':>5} "
            f"{row['runs']:>4} {row['all_safe_runs']:>8} {row['unheard_safe_frames']:>7} "
            f"{row['runs_left_moving']:>6} {cells}"
        )
    report = {
        "benchmark": "guard",
        "frame_spacing_ms": guard_process.FRAME_SPACING_S * 1e3,
        "gap_after_reply_ms": guard_process.GAP_AFTER_REPLY_S * 1e3,
        "host_share_ms": guard_process.HOST_SHARE_S * 1e3,
        "spin": args.spin,
        "rows": rows,
    }
    write_report(args.out, report)


if __name__ == "__main__":
    main()
