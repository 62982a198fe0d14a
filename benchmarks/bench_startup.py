"""Start-up time of the command line, before and after lazy command imports (issue 23).

Wall time of a fresh ``python -m motorbus ...`` process, measured from this process
(``time.perf_counter`` around ``subprocess.run``), for:

* ``python -c pass``: the interpreter alone, the floor every command pays;
* ``motorbus --version``, ``motorbus --help``, ``motorbus la status --help``;
* ``motorbus serve --help``: the served stack's imports (the manager, the bus file);
* ``import motorbus.blocking`` and the names of an LA program (``Bus``, ``InspireLA``,
  ``Streamer``): what the first line of a blocking script costs;
* ``motorbus la status 1 --port PTY``: a real status query to ``motorbus sim``
  (one LA actuator on a pseudo-terminal, started once and shared by every run).

Each command runs ``--runs`` times for each source tree, interleaved (floor, then
each command under "before" and "after", round after round) so that a busy moment of
a shared machine hits both alike.  "after" is this checkout's ``src``; "before" is the
``src`` of git ref ``--before-ref`` (default ``main``), unpacked with ``git archive``
into a temporary directory, or the directory ``--before-src``.  Both run with
``PYTHONPATH`` pointing at their tree, the same interpreter, no ``MOTORBUS_*``
variables and no user bus file.

Bytecode: an installed package has its ``.pyc`` files (pip compiles them), so by
default each tree gets its own ``PYTHONPYCACHEPREFIX`` and one warm-up run per command
before the clock starts (``PYTHONDONTWRITEBYTECODE`` is dropped for the children).
``--bytecode none`` keeps ``PYTHONDONTWRITEBYTECODE=1`` and no cache: every run compiles
every module from source, as a checkout run with that variable set does (on this
machine, where it is set for every session, that alone costs ~0.2 s per command).

Reported per command and tree: min and median seconds, and the median above the
floor.  Goal (issue 23): ``--version`` and ``la status`` within 0.3 s.  The load
average is printed and recorded: on a shared machine the medians move with it; the
minimum is the better estimate of the cost.

``python -X importtime -m motorbus --version`` shows where the time goes.

Prints a table and writes ``benchmarks/results/startup.json``.

Usage: ``python benchmarks/bench_startup.py [--runs 7] [--before-ref main |
--before-src DIR | --no-before] [--bytecode cached|none] [--out PATH]``
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

from harness import write_report

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "startup.json"
GOAL_S = 0.3
#: Commands measured: the interpreter's arguments (the port is filled in once the
#: simulator runs).
COMMANDS: dict[str, list[str]] = {
    "motorbus --version": ["-m", "motorbus", "--version"],
    "motorbus --help": ["-m", "motorbus", "--help"],
    "motorbus la status --help": ["-m", "motorbus", "la", "status", "--help"],
    "motorbus la status 1 --port PTY": ["-m", "motorbus", "la", "status", "1", "--port", "{port}"],
    # The served stack's imports (the manager, the bus file, the server and client):
    "motorbus serve --help": ["-m", "motorbus", "serve", "--help"],
    # A blocking LA program's first line and the names it uses:
    "import motorbus.blocking (LA)": [
        "-c",
        "import motorbus.blocking as mb; mb.Bus, mb.InspireLA, mb.Streamer",
    ],
}
#: Commands with a start-up goal.
GOALS = ("motorbus --version", "motorbus la status 1 --port PTY")


def clean_env(src: Path | None, pycache: Path | None) -> dict[str, str]:
    """The environment of a measured process: ``src`` first on the path; bytecode cached
    under ``pycache``, or (``None``) never written nor read from a cache."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MOTORBUS_")}
    env["XDG_CONFIG_HOME"] = "/nonexistent/motorbus-bench-config"  # no user bus file
    env.pop("PYTHONPATH", None)
    env.pop("PYTHONPYCACHEPREFIX", None)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    if pycache is None:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    else:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(pycache)
    return env


def wall(argv: list[str], env: dict[str, str]) -> float:
    """Seconds one process takes, start to exit; it must succeed."""
    start = time.perf_counter()
    run = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60)
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({run.returncode}): {run.stderr.strip()}")
    return seconds


def unpack_ref(ref: str, into: Path) -> Path:
    """``git archive REF src`` unpacked under ``into``; the path of its ``src``."""
    archive = into / "src.tar"
    with archive.open("wb") as f:
        subprocess.run(["git", "-C", str(ROOT), "archive", ref, "src"], stdout=f, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    return into / "src"


def summary(samples: list[float], floor: float) -> dict[str, float]:
    median = statistics.median(samples)
    return {
        "min_s": min(samples),
        "median_s": median,
        "max_s": max(samples),
        "median_above_floor_s": median - floor,
    }


def measure(trees: dict[str, Path], port: str, runs: int, pycache: Path | None) -> dict[str, Any]:
    floor: list[float] = []
    samples: dict[str, dict[str, list[float]]] = {t: {c: [] for c in COMMANDS} for t in trees}
    envs = {t: clean_env(src, None if pycache is None else pycache / t) for t, src in trees.items()}
    floor_env = clean_env(None, None if pycache is None else pycache / "floor")
    argvs = {
        command: [sys.executable, *(a.format(port=port) for a in args)]
        for command, args in COMMANDS.items()
    }
    wall([sys.executable, "-c", "pass"], floor_env)  # warm-up: fill the bytecode caches
    for tree in trees:
        for argv in argvs.values():
            wall(argv, envs[tree])
    for _ in range(runs):
        floor.append(wall([sys.executable, "-c", "pass"], floor_env))
        for command, argv in argvs.items():
            for tree in trees:
                samples[tree][command].append(wall(argv, envs[tree]))
    floor_median = statistics.median(floor)
    return {
        "floor": {"command": "python -c pass", **summary(floor, floor_median)},
        "trees": {
            tree: {c: summary(s, floor_median) for c, s in by_command.items()}
            for tree, by_command in samples.items()
        },
        "samples": {"floor": floor, **samples},
    }


def print_table(result: dict[str, Any]) -> None:
    floor = result["floor"]
    print(f"bytecode: {result['bytecode']}")
    print(f"load average at start: {result['loadavg_start']}, at end: {result['loadavg_end']}")
    print(
        f"{'command':34} {'tree':7} {'min s':>7} {'median s':>9} {'- floor':>8}  goal"
        f"\n{'python -c pass (floor)':34} {'':7} {floor['min_s']:7.3f} {floor['median_s']:9.3f}"
    )
    for command in COMMANDS:
        for tree, by_command in result["trees"].items():
            row = by_command[command]
            goal = ""
            if command in GOALS:
                goal = f"<= {GOAL_S} s: {'met' if row['median_s'] <= GOAL_S else 'missed'}"
            print(
                f"{command:34} {tree:7} {row['min_s']:7.3f} {row['median_s']:9.3f} "
                f"{row['median_above_floor_s']:8.3f}  {goal}"
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=7, help="runs per command and tree")
    parser.add_argument("--before-ref", default="main", help="git ref of the 'before' tree")
    parser.add_argument("--before-src", type=Path, help="a 'before' src directory instead")
    parser.add_argument("--no-before", action="store_true", help="measure this tree only")
    parser.add_argument("--quick", action="store_true", help="3 runs (a smoke test)")
    parser.add_argument(
        "--bytecode",
        choices=("cached", "none"),
        default="cached",
        help="cached: .pyc files as installed (default); none: compile every run",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    runs = 3 if args.quick else args.runs

    from motorbus.sim.process import SimProcess

    with tempfile.TemporaryDirectory() as tmp, SimProcess(["la:1"]) as sim:
        trees: dict[str, Path] = {}
        before = "none"
        if not args.no_before:
            if args.before_src is not None:
                trees["before"] = args.before_src.resolve()
                before = str(trees["before"])
            else:
                trees["before"] = unpack_ref(args.before_ref, Path(tmp))
                before = f"git ref {args.before_ref}"
        trees["after"] = ROOT / "src"
        loadavg_start = os.getloadavg()
        pycache = Path(tmp) / "pycache" if args.bytecode == "cached" else None
        result = measure(trees, sim.path, runs, pycache)
        result["loadavg_start"] = [round(x, 2) for x in loadavg_start]
        result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    result.update(
        {
            "command": "python benchmarks/bench_startup.py " + " ".join(argv or sys.argv[1:]),
            "runs": runs,
            "before": before,
            "bytecode": args.bytecode,
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "goal_s": GOAL_S,
            "goals_met": {c: result["trees"]["after"][c]["median_s"] <= GOAL_S for c in GOALS},
        }
    )
    print_table(result)
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
