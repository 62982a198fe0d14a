"""``motorbus rig``: characterise LA actuators (step, tracking, latency, repeatability).

Examples::

    motorbus rig 1 --out rig-run --port /dev/ttyUSB0
    motorbus rig 1-3 --tests step,latency --min 200 --max 1800 --out run2
    motorbus rig compare golden/ run2/ --tolerance step.rise_time_ms=5%
    motorbus rig project 1 --runs 20 --port /dev/ttyUSB1     # start -> EE DD times
    motorbus rig quad 2 --runs 20 --port /dev/ttyUSB2        # run -> done times

Every target stays inside --min..--max (default: the stroke less 5 % at each end);
each test first moves the actuator to its start in positioning mode (the actuator's own
profile, from wherever it is); a status reply over --max-current or --max-force pauses
every actuator under test and ends the run.  However the run ends (Ctrl-C, SIGTERM,
an error), every actuator is paused after its last target.

The run writes results.json, samples.csv and report.html (one self-contained file)
into --out; docs/rig.md defines every figure.  It exits 1, naming the actuator, the
test and why, when an actuator does not follow (a move not half done within 5 s),
a figure cannot be computed or a ceiling aborted the run; the report says so at the
top.  ``rig compare OLD NEW`` prints every figure of two runs side by side and exits
1 if any regressed beyond its tolerance or is missing from NEW, 2 (naming the file
and the field) if a file is not rig results or holds a null or a non-number.
``rig project N`` runs stored project N of a project stepper ``--runs`` times and
reports the start -> ``EE DD`` times (p50/p99/max); ``rig quad MOTOR`` does the same
for a 4-axis run -> its done reply (the motor's stored settings; --baud defaults to
the steppers' rate).  A run that does not finish within --timeout is stopped.

``--connect ENDPOINT`` runs the rig on a bus that ``motorbus serve`` owns, holding the
lease of the devices under test (another client's lease refuses it, naming the holder);
the tracking test streams through the server, under that lease.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from motorbus import Bus
from motorbus.cli.bus_options import LA_BAUD, STEPPER_BAUD, add_bus_options, open_bus
from motorbus.cli.ids import parse_id_args
from motorbus.cli.output import error_doc, fail, print_json
from motorbus.cli.values import check_seconds
from motorbus.errors import LocalProtocolError, UsageError
from motorbus.protocol.base import Family, check_int
from motorbus.rig.plan import DEFAULT_FREQUENCIES, TESTS, RigPlan, default_window

if TYPE_CHECKING:
    from motorbus.rig import Row

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``rig`` command."""
    p = subparsers.add_parser(
        "rig",
        help="characterise LA actuators: step, tracking, latency, repeatability; compare runs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "ids",
        metavar="ID",
        nargs="+",
        help="actuator IDs 1..254 (3, 1,2,3 or 1-3,7); or: compare OLD NEW; project N; quad MOTOR",
    )
    lo, hi = default_window()
    p.add_argument("--tests", default="all", help=f"comma list of {', '.join(TESTS)} or all")
    p.add_argument("--out", metavar="DIR", help="folder for results.json, samples.csv, report.html")
    p.add_argument("--min", type=int, default=lo, help=f"lowest target (default {lo})")
    p.add_argument("--max", type=int, default=hi, help=f"highest target (default {hi})")
    p.add_argument("--start", type=int, help="step start (default 25 %% of the window)")
    p.add_argument("--end", type=int, help="step end (default 75 %% of the window)")
    p.add_argument(
        "--frequencies",
        default=",".join(f"{f:g}" for f in DEFAULT_FREQUENCIES),
        help="tracking sine frequencies, Hz, comma list",
    )
    p.add_argument("--amplitude", type=int, help="sine amplitude (default a quarter window)")
    p.add_argument("--cycles", type=float, default=2.0, help="sine cycles per frequency")
    p.add_argument("--period", type=float, default=0.01, help="stream tick, 0.01..0.05 s")
    p.add_argument("--latency-count", type=int, default=50, help="small steps (default 50)")
    p.add_argument("--repeat-count", type=int, default=5, help="approaches per side (default 5)")
    p.add_argument(
        "--settle-timeout",
        type=float,
        default=5.0,
        help="seconds a move may take to settle before the actuator fails (0.1..60, default 5)",
    )
    p.add_argument("--max-current", type=int, default=1500, help="abort above, mA")
    p.add_argument("--max-force", type=int, default=30000, help="abort above, grams")
    p.add_argument("--runs", type=int, default=10, help="project/quad: runs (default 10)")
    p.add_argument("--timeout", type=float, default=60.0, help="project/quad: seconds a run")
    p.add_argument(
        "--tolerance",
        default="",
        help="compare: FIGURE=N%% (relative) or FIGURE=N (units), comma list",
    )
    add_bus_options(p, default_baud=LA_BAUD, connect=True)
    p.set_defaults(func=run)


def _plan(args: argparse.Namespace) -> RigPlan:
    ids = parse_id_args(args.ids)
    tests = (
        TESTS
        if args.tests.strip() == "all"
        else tuple(t.strip() for t in args.tests.split(",") if t.strip())
    )
    try:
        freqs = tuple(float(f) for f in args.frequencies.split(",") if f.strip())
    except ValueError:
        raise LocalProtocolError(
            f"--frequencies={args.frequencies!r} is not a comma list of numbers (Hz)",
            field="--frequencies",
        ) from None
    return RigPlan(
        ids=tuple(ids),
        tests=tests,
        window=(args.min, args.max),
        step_start=args.start,
        step_end=args.end,
        settle_timeout=args.settle_timeout,
        period=args.period,
        frequencies=freqs,
        cycles=args.cycles,
        amplitude=args.amplitude,
        latency_count=args.latency_count,
        repeat_count=args.repeat_count,
        max_current_ma=args.max_current,
        max_force_g=args.max_force,
    )


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus rig`` (or ``rig compare``).  Errors raised here reach
    ``motorbus.cli.main``, which prints them (one JSON object with ``--json``) and picks
    the exit code."""
    return _dispatch(args)


def _error(args: argparse.Namespace, code: int, message: str, **about: Any) -> int:
    """Report a failure (one line on standard error; with --json also one JSON object on
    standard output) and return its exit code."""
    return fail(args, message, code=code, **_jsonable(about))


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, str | int | float | bool):
        return value
    return repr(value)


def _dispatch(args: argparse.Namespace) -> int:
    if args.ids and args.ids[0] == "compare":
        return _compare(args)
    if args.ids and args.ids[0] in ("project", "quad"):
        return _stepper(args)
    plan = _plan(args)  # every bad value is refused here, before the port opens
    if not args.out:
        raise UsageError("rig: give --out DIR for results.json, samples.csv and report.html")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: exists and is not a folder")
    return asyncio.run(_run(args, plan, out))


class _Bar:
    """One progress line on standard error: what runs, and about how long is left."""

    def __init__(self, total_s: float) -> None:
        self.total = total_s
        self.t0 = time.monotonic()
        self.tty = sys.stderr.isatty()
        self.last = 0.0

    def __call__(self, what: str, done: float) -> None:
        now = time.monotonic()
        if not self.tty and now - self.last < 2.0 and done < 1.0:
            return
        self.last = now
        width = 24
        filled = round(width * done)
        left = max(0.0, self.total - (now - self.t0))
        bar = "#" * filled + "." * (width - filled)
        line = f"[{bar}] {done * 100:3.0f}% {what} (~{left:.0f} s left)"
        if self.tty:
            print(f"\r{line:<79}", end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.tty:
            print(file=sys.stderr)


async def _run(args: argparse.Namespace, plan: RigPlan, out: Path) -> int:
    from motorbus.rig import run_rig, write_report

    bar = _Bar(plan.estimate_seconds())
    async with open_bus(args, [Family.LA]) as bus:
        try:
            if args.connect:
                from motorbus.cli.served_rig import run_served_rig

                result, stats = await run_served_rig(bus, plan, bar, run_rig)
            else:
                result = await run_rig(bus, plan, bar, raise_on_abort=False)
                stats = bus.stats.as_dict()
        finally:
            bar.close()
    paths = write_report(out, result, stats)
    doc = json.loads(paths["results"].read_text(encoding="utf-8"))
    if not result.passed:
        failures = [str(f) for f in result.failures]
        failures += [f"la:{i}: not tested (the run was aborted first)" for i in result.untested]
        for line in failures:
            print(f"motorbus rig: FAILED {line}", file=sys.stderr)
        what = "aborted" if result.aborted else "failed"
        message = f"rig {what}: {'; '.join(failures)} (report: {paths['report']})"
        if args.json:
            print_json(error_doc("rig", message, 1, report=str(paths["report"]), **_jsonable(doc)))
        else:
            print(f"motorbus rig: {what}; report: {paths['report']}", file=sys.stderr)
        return 1
    if args.json:
        print_json(doc)
    else:
        for device, figures in doc["devices"].items():
            print(device)
            for name, value in figures.items():
                print(f"  {name:32} {'n/a' if value is None else f'{value:.4g}'}")
        s = doc["sampling"]
        print(
            f"sampled at {s['rate_hz']:.0f} Hz (interval p99 {s['interval_p99_ms']:.2f} ms); "
            f"report: {paths['report']}"
        )
    return 0


def _load(
    args: argparse.Namespace, path_text: str
) -> tuple[dict[str, dict[str, float]], list[str]] | int:
    """The figures and failures of one results file, or the exit code of its refusal
    (2, the file and the field named)."""
    from motorbus.rig.compare import read_failures, read_results

    path = Path(path_text)
    if path.is_dir():
        path = path / "results.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (FileNotFoundError, IsADirectoryError):
        return _error(args, 2, f"rig compare: {path} does not exist", file=str(path))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        why = f"rig compare: {path} is not a rig results.json ({err})"
        return _error(args, 2, why, file=str(path))
    try:
        return read_results(doc), read_failures(doc)
    except LocalProtocolError as err:
        why = f"rig compare: {path}: {err}"
        return _error(args, 2, why, file=str(path), field=err.field, value=err.value)


def _compare(args: argparse.Namespace) -> int:
    from motorbus.rig import compare_results, parse_tolerances

    rest = args.ids[1:]
    if len(rest) != 2:
        raise UsageError("rig compare: give two runs, OLD and NEW (folders or results.json)")
    try:
        tolerances = parse_tolerances(args.tolerance)
    except ValueError as err:
        return _error(args, 2, str(err), field="--tolerance", value=args.tolerance)
    loaded_old = _load(args, rest[0])
    if isinstance(loaded_old, int):
        return loaded_old
    loaded_new = _load(args, rest[1])
    if isinstance(loaded_new, int):
        return loaded_new
    (old, old_failed), (new, new_failed) = loaded_old, loaded_new
    rows = compare_results(old, new, tolerances)
    if not rows:
        return _error(args, 2, "rig compare: the two runs hold no figure to compare")
    if args.json:
        print_json([_row_dict(r) for r in rows])
    else:
        print(f"{'device':8} {'figure':30} {'old':>10} {'new':>10} {'change':>9}  verdict")
        for r in rows:
            pct = "n/a" if math.isnan(r.change_pct) else f"{r.change_pct:+.1f}%"
            verdict = "REGRESSED" if r.regressed else "ok"
            if r.missing:
                verdict += f" (not in {r.missing.upper()})"
            print(
                f"{r.device:8} {r.figure:30} {_num(r.old):>10} {_num(r.new):>10} {pct:>9}  "
                f"{verdict}"
            )
    for name, failed in (("OLD", old_failed), ("NEW", new_failed)):
        for line in failed:
            print(f"motorbus rig: the {name} run failed: {line}", file=sys.stderr)
    bad = [r for r in rows if r.regressed]
    if bad:
        figures = [f"{r.device} {r.figure}" for r in bad]
        why = f"{len(bad)} figure(s) regressed beyond tolerance or missing from NEW: "
        return _error(args, 1, why + ", ".join(figures), figures=figures)
    if new_failed:
        return _error(args, 1, "the NEW run failed: " + "; ".join(new_failed))
    return 0


def _num(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.4g}"


def _row_dict(r: Row) -> Any:
    return _jsonable(
        {
            "device": r.device,
            "figure": r.figure,
            "old": r.old,
            "new": r.new,
            "change_pct": r.change_pct,
            "allowed": r.allowed,
            "regressed": r.regressed,
            "missing": r.missing,
        }
    )


def _stepper(args: argparse.Namespace) -> int:
    """``rig project N`` / ``rig quad MOTOR``: start -> finish times of N runs."""
    kind, rest = args.ids[0], args.ids[1:]
    if len(rest) != 1 or not rest[0].isdigit():
        what = "project number 1..4" if kind == "project" else "motor 1..4"
        raise UsageError(f"rig {kind}: give one {what}, e.g. rig {kind} 1 --runs 10")
    number = int(rest[0])
    from motorbus.rig.steppers import MAX_RUNS

    check_int("--runs", args.runs, 1, MAX_RUNS)
    check_seconds("--timeout", args.timeout, 0.001)
    args._default_baud = STEPPER_BAUD  # the steppers' rate unless --baud or a bus file says
    family = Family.PROJECT_STEPPER if kind == "project" else Family.QUAD_STEPPER
    return asyncio.run(_time_runs(args, kind, number, family))


async def _time_runs(args: argparse.Namespace, kind: str, number: int, family: Family) -> int:
    from motorbus.rig.steppers import time_project_runs, time_quad_runs

    async with contextlib.AsyncExitStack() as stack:
        bus = await stack.enter_async_context(open_bus(args, [family]))
        if args.connect:  # a lease holder, timed at this client
            from motorbus.cli.served_rig import ObservedServedBus, held

            await stack.enter_async_context(held(bus, [family.value]))
            bus = cast(Bus, ObservedServedBus(bus))
        if kind == "project":
            times = await time_project_runs(bus, number, args.runs, timeout=args.timeout)
        else:
            times = await time_quad_runs(bus, number, args.runs, timeout=args.timeout)
    doc = times.as_dict()
    if args.json:
        print_json(doc)
    else:
        print(
            f"{doc['what']}: {doc['runs']} runs, start -> finish p50 {doc['p50_ms']:.2f} ms, "
            f"p99 {doc['p99_ms']:.2f} ms, max {doc['max_ms']:.2f} ms (min {doc['min_ms']:.2f})"
        )
    return 0
