"""How long a safe stop takes to reach every actuator when some of them do not answer.

Fifteen actuators are streamed at 10 ms to ``motorbus sim``, a child process that logs
every frame it receives on its own clock.  IDs 1..k are absent (``--silent`` k), so
their pauses go unanswered, time out and are retried.  The stop comes two ways:

* ``stream``: ``stream.stop()`` with ``safe_action="pause"`` (the stream's safe action);
* ``close``: a stream that holds its targets, then the bus's close (its leases' pauses).

Per run, on the simulator's clock: ``spread_ms``, from the first pause it received to
the first pause of the last actuator that is there.  That is the time the last working
actuator went on moving after the first was told to stop.  With none silent it is 14
round trips (about 14-20 ms at 921600 baud).  Until 2026-12-03 each silent actuator
ahead of the others added its attempts and late guards, because the stop's commands
were sent one after another and a retry waiting out its guard held the whole queue.

    python benchmarks/bench_safe_stop.py [--silent 0,1,3] [--runs 5] [--quick]
        [--before-rev REV] [--out PATH]

``--before-rev REV`` also measures git revision REV of this checkout (its ``src``,
exported as ``ab_cpu.py`` does), the two trees taking turns run by run, each run a fresh
process; the simulator is the same for both (this checkout's).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "safe_stop.json"
sys.path.insert(0, str(HERE))

from harness import write_report  # noqa: E402
from motorbus.protocol import la  # noqa: E402  (this checkout's: the simulator's log)

BAUD = 921600
N_ACTUATORS = 15
PERIOD_S = 0.010
#: How long the stream runs before it is stopped.
STREAM_S = 0.1
PATHS = ("stream", "close")
#: Each ID's pause frame, as the protocol layer encodes it, and the ID it pauses.
PAUSES = {la.Control(i, la.ControlAction.PAUSE).encode(): i for i in range(1, 255)}


def spread_ms(records: list[dict[str, Any]], present: set[int]) -> float | None:
    """Milliseconds from the first pause the simulator received to the first pause of
    the last actuator in ``present``; None if one of them got none."""
    first: dict[int, float] = {}
    start: float | None = None
    for record in records:
        if record.get("direction") != "request":
            continue
        frame = bytes.fromhex(str(record["hex"]))
        if frame in PAUSES:
            t = float(record["t"])
            start = t if start is None else start
            first.setdefault(PAUSES[frame], t)
    if start is None or not present <= first.keys():
        return None
    return 1e3 * (max(first[i] for i in present) - start)


async def one_stop(silent: int, path: str, workdir: Path) -> float | None:
    """One stream and stop with IDs 1..``silent`` absent; its ``spread_ms``."""
    from motorbus.bus.bus import Bus
    from motorbus.devices.la import InspireLA
    from motorbus.protocol.base import Family
    from motorbus.sim.process import SimProcess
    from motorbus.streams import Streamer
    from motorbus.transport.serial import open_transport

    log = workdir / f"sim-{silent}-{path}.jsonl"
    log.unlink(missing_ok=True)
    with SimProcess((f"la:{silent + 1}-{N_ACTUATORS}",), baud=BAUD, log_file=log) as sim:
        bus = Bus(open_transport(sim.path, baudrate=BAUD), families=[Family.LA])
        async with bus:
            streamer = Streamer(bus)
            stream = streamer.follow(
                [InspireLA(bus, i) for i in range(1, N_ACTUATORS + 1)],
                lambda t, statuses: [1000] * N_ACTUATORS,
                period=PERIOD_S,
                safe_action="pause" if path == "stream" else "hold",
            )
            await asyncio.sleep(STREAM_S)
            await stream.stop()
            await streamer.close()
            if path == "close":
                await bus.close()
        records = sim.log_records()
    return spread_ms(records, set(range(silent + 1, N_ACTUATORS + 1)))


def child(silent: int, path: str) -> None:
    """One run in this process (motorbus from ``PYTHONPATH``); prints its JSON."""
    import motorbus

    with tempfile.TemporaryDirectory(prefix="motorbus-stop-") as tmp:
        spread = asyncio.run(one_stop(silent, path, Path(tmp)))
    where = str(Path(motorbus.__file__).resolve().parent)
    print(json.dumps({"spread_ms": spread, "motorbus": where}))


def run_child(tree: Path, silent: int, path: str) -> float | None:
    """One run in a fresh process importing motorbus from ``tree``."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    args = [sys.executable, __file__, "--child", str(silent), path]
    proc = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    if proc.returncode:
        raise SystemExit(f"a run from {tree} failed:\n{proc.stderr[-2000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    if Path(result["motorbus"]) != (tree / "motorbus").resolve():
        raise SystemExit(f"the run imported motorbus from {result['motorbus']}, not {tree}")
    spread: float | None = result["spread_ms"]
    return spread


def summary(spreads: list[float | None]) -> dict[str, Any]:
    """Median and worst of the runs' spreads (ms), and how many runs missed a pause."""
    got = [s for s in spreads if s is not None]
    return {
        "median_ms": round(statistics.median(got), 2) if got else None,
        "max_ms": round(max(got), 2) if got else None,
        "runs": len(spreads),
        "runs_missing_a_pause": len(spreads) - len(got),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--silent", default="0,1,3", help="absent IDs ahead of the others")
    parser.add_argument("--runs", type=int, default=5, help="runs per case and tree")
    parser.add_argument("--before-rev", help="also measure this git revision's src")
    parser.add_argument("--quick", action="store_true", help="silent 0,1 and 2 runs")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(int(args.child[0]), args.child[1])
        return 0
    if args.quick:
        args.silent, args.runs = "0,1", 2
    try:
        silents = [int(x) for x in args.silent.split(",") if x]
    except ValueError:
        parser.error(f"--silent must be comma-separated integers, got {args.silent!r}")
    if not silents or min(silents) < 0 or max(silents) >= N_ACTUATORS or args.runs < 1:
        parser.error(f"--silent counts 0..{N_ACTUATORS - 1} and --runs >= 1")
    with tempfile.TemporaryDirectory(prefix="motorbus-stop-tree-") as tmp:
        trees = {"after": REPO / "src"}
        if args.before_rev:
            from ab_cpu import export_rev

            trees = {"before": export_rev(args.before_rev, Path(tmp)), **trees}
        print(
            f"safe stop of {N_ACTUATORS} streamed actuators, IDs 1..k absent, "
            f"{args.runs} runs a case; spread = first pause to the last present "
            "actuator's, on the simulator's clock"
        )
        cases = []
        for silent in silents:
            for path in PATHS:
                spreads: dict[str, list[float | None]] = {name: [] for name in trees}
                for r in range(args.runs):
                    names = list(trees) if r % 2 == 0 else list(reversed(trees))
                    for name in names:
                        spreads[name].append(run_child(trees[name], silent, path))
                case = {
                    "silent": silent,
                    "path": path,
                    **{name: summary(s) for name, s in spreads.items()},
                    "spreads_ms": spreads,
                }
                cases.append(case)
                line = "; ".join(
                    f"{name} median {case[name]['median_ms']} ms, max {case[name]['max_ms']} ms"
                    for name in trees
                )
                print(f"  {silent} silent, {path:6s}: {line}", flush=True)
    write_report(
        args.out,
        {"before_rev": args.before_rev, "runs": args.runs, "baud": BAUD, "cases": cases},
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
