"""``motorbus demo``: the whole library on built-in simulators, no hardware needed.

It starts three simulated buses on real pseudo-terminals - 15 LA actuators at
921600 baud, a project stepper and a quad stepper at 9600 - opens them through the
ordinary serial stack, and then, all at once:

* streams a smooth trajectory to the 15 actuators at 100 Hz through 0xF3 broadcasts,
  polling their status in the slots left free;
* programs a two-step project into the project stepper, reads it back, runs it and
  awaits its ``EE DD``;
* configures and runs a quad stepper motor, awaiting its "done" reply, and blinks an LED.

The stream starts where the actuators are: their status is read first, and the targets
ramp from those positions into the trajectory over the first seconds (no jump at t = 0).

It shows a live table, ends with a summary (frames, timeouts, late replies, jitter as
measured by the simulator), and writes a PNG plot.  With ``--json`` the summary is the
one JSON document on standard output; the live table and every other line go to
standard error.  The LA simulator's frame log (docs/frame-log.md) is kept as
``la-bus-frames.jsonl`` in the output folder: ``motorbus replay`` shows it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO, TypeVar

from motorbus import BusManager, Stream
from motorbus.cli.realtime_option import add_realtime_option
from motorbus.errors import LocalProtocolError, MotorbusError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.families import LA_DEFAULT_BAUD, STEPPER_DEFAULT_BAUD
from motorbus.sim import SimProcess, tick_timing

__all__ = ["register", "run"]

T = TypeVar("T")

N_ACTUATORS = 15
#: Host margin of the demo's LA bus: 2 ms (the default) covers a real adapter, but the
#: demo's devices are simulator processes on the same 2 cores as the bus, whose answers
#: came up to ~2 ms after a 2 ms-margin deadline in 10 runs on a busy machine.
DEMO_HOST_MARGIN_MS = 5.0
PERIOD_S = 0.010  # 100 Hz, the fastest follow rate the manual allows (3.5.3)
LA_BAUD = LA_DEFAULT_BAUD  # the family registry, protocol/families.py
STEPPER_BAUD = STEPPER_DEFAULT_BAUD
PLOTTED_IDS = (1, 2, 3)
#: Longest ramp from the actuators' positions into the trajectory (s).  Smoothstep over
#: 2 s from position 0 to the trajectory's top (1600) needs at most 1200 units/s on top
#: of the sine's own 940 units/s peak; the simulated actuator does 2000 units/s.
RAMP_S = 2.0
#: How a 0xF3 broadcast looks in the simulator's log from byte 2 on: Len, ID FF, F3.
F3_PREFIX = "FF F3"


def register(sub: Any) -> None:
    """Add the ``demo`` command."""
    p = sub.add_parser(
        "demo",
        help="run every device on built-in simulators (no hardware)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--seconds", type=float, default=8.0, help="streaming time (1..3600 s)")
    p.add_argument("--no-plot", action="store_true", help="do not write the PNG plot")
    p.add_argument("--out", default="motorbus-demo", help="folder for the plot and summary")
    p.add_argument("--backend", default="fast", help="serial backend: fast, serialx, ...")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the summary as one JSON document on stdout (everything else on stderr)",
    )
    add_realtime_option(p)
    p.set_defaults(func=run)


@dataclass
class DemoLog:
    """What the demo records while it runs."""

    samples: list[tuple[float, int, int, int]] = field(default_factory=list)  # t, id, tgt, pos
    project: str = "waiting"
    project_time: float = 0.0
    quad: str = "waiting"


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns the exit code."""
    if not 1 <= args.seconds <= 3600:
        raise LocalProtocolError(
            f"--seconds={args.seconds} is out of range: allowed 1..3600", field="seconds"
        )
    try:  # a folder that cannot be made is bad input (exit 2), found before anything runs
        Path(args.out).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise LocalProtocolError(
            f"--out={args.out}: cannot make the folder ({err.strerror})",
            field="--out",
            value=args.out,
        ) from err
    return asyncio.run(_demo(args))


def trajectory(t: float, i: int) -> float:
    """A smooth sine per actuator, phase-shifted along the row, 0.25 Hz, 400..1600."""
    return 1000 + 600 * math.sin(2 * math.pi * 0.25 * t + 2 * math.pi * i / N_ACTUATORS)


def ramp_s(seconds: float) -> float:
    """The ramp's length for a demo of ``seconds``: ``RAMP_S``, or half a short demo."""
    return min(RAMP_S, seconds / 2)


def ramped(t: float, i: int, start: float, ramp: float) -> float:
    """The target of actuator ``i`` (0-based) at ``t``: from ``start`` into the trajectory.

    A smoothstep blend over ``ramp`` seconds: equal to ``start`` at t = 0, to
    ``trajectory`` from ``ramp`` on, with no jump and no step in speed at either end.
    """
    goal = trajectory(t, i)
    if ramp <= 0 or t >= ramp:
        return goal
    u = max(0.0, t / ramp)
    weight = u * u * (3 - 2 * u)
    return start + (goal - start) * weight


async def _demo(args: argparse.Namespace) -> int:
    # With --json, standard output carries the summary document and nothing else.
    human = sys.stderr if args.json else sys.stdout
    log = DemoLog()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sim_log = out / "la-bus-frames.jsonl"
    sim_log.unlink(missing_ok=True)
    # The simulators run in their own processes, like real devices: their timing does
    # not depend on our event loop, and what they log is what "arrived on the wire".
    with (
        SimProcess([f"la:1-{N_ACTUATORS}"], baud=LA_BAUD, log_file=sim_log) as la_sim,
        SimProcess(["project-stepper"], baud=STEPPER_BAUD) as ps_sim,
        SimProcess(["quad-stepper"], baud=STEPPER_BAUD) as q_sim,
    ):
        print(
            f"simulators: LA bus {la_sim.path} (15 actuators, {LA_BAUD} Bd), project stepper "
            f"{ps_sim.path}, quad stepper {q_sim.path} ({STEPPER_BAUD} Bd)",
            file=human,
            flush=True,
        )
        mgr = BusManager()
        mgr.add_bus(
            "la",
            la_sim.path,
            baud=LA_BAUD,
            devices=[f"la:1-{N_ACTUATORS}"],
            backend=args.backend,
            # The simulators are Python processes sharing this machine's cores: their
            # answers come later than a real actuator's 800 us (see the summary).
            host_margin_ms=DEMO_HOST_MARGIN_MS,
        )
        mgr.add_bus(
            "project",
            ps_sim.path,
            baud=STEPPER_BAUD,
            devices=["project-stepper"],
            backend=args.backend,
        )
        mgr.add_bus(
            "quad", q_sim.path, baud=STEPPER_BAUD, devices=["quad-stepper"], backend=args.backend
        )
        started = time.monotonic()
        async with mgr:
            actuators = [mgr.la("la", i) for i in range(1, N_ACTUATORS + 1)]
            # Start where they are: a stream that began at trajectory(0) would ask for a
            # jump of up to 1600 units in the first tick.
            start: list[float] = []
            for a in actuators:
                await _setup(a.enable)
                start.append(float((await _setup(a.status)).position))
            ramp = ramp_s(args.seconds)

            def targets(t: float, statuses: dict[int, la.Status]) -> list[float] | None:
                if t >= args.seconds:
                    return None
                now = [ramped(t, i, start[i], ramp) for i in range(N_ACTUATORS)]
                for ident in PLOTTED_IDS:
                    s = statuses.get(ident)
                    if s is not None:
                        log.samples.append((t, ident, round(now[ident - 1]), s.position))
                return now

            stream = mgr.streamer("la").follow(
                actuators, targets, period=PERIOD_S, poll_status=True, safe_action="pause"
            )
            jobs = [
                asyncio.create_task(_project_job(mgr, log)),
                asyncio.create_task(_quad_job(mgr, log)),
            ]
            live = asyncio.create_task(_live_table(mgr, stream, log, started, human))
            try:
                await stream.wait()
                await asyncio.gather(*jobs)
            finally:
                live.cancel()
                for j in jobs:
                    j.cancel()
                await asyncio.gather(live, *jobs, return_exceptions=True)
            _draw(mgr, stream, log, started, human, final=True)
        la_sim.stop()
        arrivals = [
            r["t"]
            for r in la_sim.log_records()
            if r["direction"] == "request" and r["hex"].startswith(F3_PREFIX, 9)
        ]
        summary = _summary(mgr, stream, log, arrivals)
    (out / "summary.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    if not args.json:
        _print_summary(summary)
    if not args.no_plot:
        print(_plot(log, arrivals, out), file=human)
    print(f"summary written to {out / 'summary.json'}", file=human)
    if args.json:
        print(json.dumps(summary, indent=2), flush=True)
    # Success means every job finished and the stream ran; timeouts, late replies and
    # jitter are reported above, not failures: a loaded machine shows some.
    ran = summary["stream_host"]["ticks"] > 0
    return 0 if ran and summary["project"] == "done" and summary["quad"] == "done" else 1


#: Attempts of each set-up request (enable, first status) before the demo gives up.  The
#: bus's deadlines are tuned for streaming (2 ms host margin); on a loaded machine a
#: reply can miss one, which the summary counts as a timeout, and the demo goes on.
SETUP_ATTEMPTS = 4


async def _setup(call: Callable[[], Awaitable[T]]) -> T:
    for attempt in range(1, SETUP_ATTEMPTS + 1):
        try:
            return await call()
        except ReplyTimeoutError:
            if attempt == SETUP_ATTEMPTS:
                raise
    raise AssertionError("unreachable")


def _simple_project() -> ps.Project:
    step = ps.StepSpec(
        run_distance=2,
        direction=ps.RotationDirection.FORWARD,
        start_hz=100,
        accel_hz=50,
        speed_rpm=300,
        output=ps.StepOutputCode(1),
        delay_ms=200,
    )
    back = ps.StepSpec(
        run_distance=2,
        direction=ps.RotationDirection.REVERSE,
        start_hz=100,
        accel_hz=50,
        speed_rpm=300,
        output=ps.StepOutputCode(5),
        delay_ms=100,
    )
    return ps.Project(1, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(step, back))


async def _project_job(mgr: BusManager, log: DemoLog) -> None:
    stepper = mgr.project_stepper("project")
    try:
        log.project = "uploading"
        await stepper.upload(_simple_project())
        log.project = "running"
        t0 = time.monotonic()
        await stepper.run_project(1, timeout=30)
        log.project = "done"
        log.project_time = time.monotonic() - t0
    except MotorbusError as err:
        log.project = f"failed: {err}"


async def _quad_job(mgr: BusManager, log: DemoLog) -> None:
    quad = mgr.quad_stepper("quad")
    try:
        log.quad = "configuring"
        await quad.configure(
            1,
            subdivision=8,
            step_angle_x100=180,
            pulses=3200,
            start_hz=200,
            accel_hz=20,
            speed_rpm=300,
        )
        for n in range(2):
            log.quad = f"run {n + 1}/2"
            await quad.run(1, timeout=10)
            await quad.led(1, n % 2 == 0)
        log.quad = "done"
    except MotorbusError as err:
        log.quad = f"failed: {err}"


async def _live_table(
    mgr: BusManager, stream: Stream, log: DemoLog, started: float, out: TextIO
) -> None:
    # On a terminal the table redraws in place; elsewhere (a log, a pipe) a line every
    # 2 s says how far it is, and the whole table comes once, at the end.
    brief = not out.isatty()
    while True:
        await asyncio.sleep(2.0 if brief else 0.5)
        _draw(mgr, stream, log, started, out, final=False, brief=brief)


_drawn_lines = 0


def _draw(
    mgr: BusManager,
    stream: Stream,
    log: DemoLog,
    started: float,
    out: TextIO,
    *,
    final: bool,
    brief: bool = False,
) -> None:
    global _drawn_lines
    lines = []
    la_bus = mgr.bus("la")
    st = stream.stats.as_dict()
    lines.append(
        f"t={time.monotonic() - started:5.1f}s  stream: {st['ticks']} ticks, {st['late']} late, "
        f"{st['skipped']} skipped, jitter p99 {st['jitter_p99_us']:.0f} µs (host)  "
        f"LA bus: {la_bus.stats.requests} frames, {la_bus.stats.timeouts} timeouts"
    )
    if brief:  # the first line alone
        out.write(lines[0] + "\n")
        out.flush()
        return
    lines.append("  id  target  position  temp  current  errors")
    for ident in (1, 2, 3, 8, 15):
        s = stream.statuses.get(ident)
        tgt = stream.last_targets.get(ident, 0)
        if s is None:
            lines.append(f"  {ident:2d}  {tgt:6d}  {'-':>8}")
        else:
            flags = ",".join(f.name or "?" for f in la.ErrorFlags if f in s.errors) or "-"
            lines.append(
                f"  {ident:2d}  {tgt:6d}  {s.position:8d}  {s.temperature:3d}C  {s.current:5d}mA  "
                f"{flags}"
            )
    lines.append(f"  project stepper: {log.project:<20} quad stepper: {log.quad}")
    if out.isatty() and _drawn_lines:
        out.write(f"\x1b[{_drawn_lines}F\x1b[J")
    out.write("\n".join(lines) + "\n")
    out.flush()
    _drawn_lines = len(lines) if not final else 0


def _summary(
    mgr: BusManager, stream: Stream, log: DemoLog, arrivals: list[float]
) -> dict[str, Any]:
    timing = tick_timing(arrivals, PERIOD_S).as_dict()
    buses = {name: bus.stats.as_dict() for name, bus in mgr.buses.items()}
    stats = [bus.stats for bus in mgr.buses.values()]
    return {
        "frames": sum(b.requests for b in stats),
        "timeouts": sum(b.timeouts for b in stats),
        # Timeouts decided over 1 ms after their deadline: the host stalled, not the device.
        "timeouts_in_host_stall": sum(b.timeouts_in_host_stall for b in stats),
        "host_stall_max_ms": max((b.host_stall_max for b in stats), default=0.0) * 1e3,
        "late_replies": sum(b.late_replies for b in stats),
        "late_reply_max_ms": max((b.late_reply_max for b in stats), default=0.0) * 1e3,
        "garbage_bytes": sum(b.garbage_bytes for b in stats),
        "stream_host": stream.stats.as_dict(),
        "stream_sim": timing,
        "missed_ticks": int(timing["missed_ticks"]),
        "project": log.project,
        "quad": log.quad,
        "buses": buses,
    }


def _timeout_cause(s: dict[str, Any]) -> str:
    """What the timeouts of a fault-free run were: the host stalling, or slow answers."""
    total, stalled = s["timeouts"], s["timeouts_in_host_stall"]
    if not total:
        return ""
    parts = []
    if stalled:
        parts.append(
            f"{stalled} decided while this host stalled (up to {s['host_stall_max_ms']:.1f} ms)"
        )
    rest = total - stalled
    if rest and s["late_replies"] >= rest:
        parts.append(
            f"{rest} with the host on time, each answered late (up to "
            f"{s['late_reply_max_ms']:.1f} ms after its deadline): the simulator processes "
            "share this machine's cores"
        )
    elif rest:
        parts.append(f"{rest} with the host on time: see the bus stats in summary.json")
    return " (" + "; ".join(parts) + ")"


def _print_summary(s: dict[str, Any]) -> None:
    sim = s["stream_sim"]
    host = s["stream_host"]
    print("summary")
    print(f"  frames sent            {s['frames']}")
    print(f"  timeouts               {s['timeouts']}{_timeout_cause(s)}")
    late = s["late_replies"]
    print(
        f"  late replies           {late}"
        + (" (the answers to those timeouts, counted, never mismatched)" if late else "")
    )
    print(f"  garbage bytes          {s['garbage_bytes']}")
    print(
        f"  stream ticks (host)    {host['ticks']} sent, {host['late']} late, "
        f"{host['skipped']} skipped, {host['slipped']} slipped, {host['polls']} status polls "
        f"({host['polls_skipped']} skipped: no free slot)"
    )
    print(
        f"  tick jitter (sim side) p50 {sim['tick_jitter_p50_us']:.0f} µs, "
        f"p99 {sim['tick_jitter_p99_us']:.0f} µs, max {sim['tick_jitter_max_us']:.0f} µs, "
        f"missed {sim['missed_ticks']}, drift {sim['drift_ppm']:.1f} ppm"
    )
    print(f"  project stepper        {s['project']}")
    print(f"  quad stepper           {s['quad']}")


def _plot(log: DemoLog, arrivals: list[float], out: Path) -> str:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "plot skipped: matplotlib is not installed (pip install 'motorbus[plot]')"
    fig = figure(log, arrivals)
    path = out / "demo.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return f"plot written to {path}"


#: Offsets below this are drawn in the first bin of the log-scale histogram (µs): the
#: earliest arrival is 0 by definition, which a log axis cannot show.
JITTER_FLOOR_US = 1.0


def figure(log: DemoLog, arrivals: list[float]) -> Any:
    """Build the demo's figure (matplotlib must be importable; the caller picks a backend).

    Top: target and reported position of ``PLOTTED_IDS`` against time.  Bottom: the
    histogram of the 0xF3 arrival offsets from the 10 ms grid on a logarithmic axis in
    µs, with p50 and p99 drawn and every offset beyond p99 marked as an outlier.
    """
    import matplotlib.pyplot as plt

    timing = tick_timing(arrivals, PERIOD_S)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 7))
    for ident in PLOTTED_IDS:
        pts = [(t, tgt, pos) for t, i, tgt, pos in log.samples if i == ident]
        if not pts:
            continue
        ts = [p[0] for p in pts]
        (line,) = ax1.plot(ts, [p[1] for p in pts], "--", linewidth=1, label=f"target {ident}")
        ax1.plot(ts, [p[2] for p in pts], "-", color=line.get_color(), label=f"position {ident}")
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("position (0..2000 = full stroke)")
    ax1.set_title("follow-mode stream at 100 Hz, ramped in from the read positions")
    ax1.legend(ncol=3, fontsize="small")

    offsets = [max(o * 1e6, JITTER_FLOOR_US) for o in timing.offsets]
    p50, p99 = timing.jitter_p50 * 1e6, timing.jitter_p99 * 1e6
    if offsets:
        top = max(max(offsets), JITTER_FLOOR_US * 10)
        edges = [JITTER_FLOOR_US * (top / JITTER_FLOOR_US) ** (k / 50) for k in range(51)]
        ax2.hist(offsets, bins=edges, color="tab:blue")
        outliers = [o for o in offsets if o > max(p99, JITTER_FLOOR_US)]
        if outliers:
            # Marked along the top edge (x in data, y in axes units): a single late
            # tick is one count, invisible as a bar beside hundreds.
            ax2.plot(
                outliers,
                [0.97] * len(outliers),
                "v",
                transform=ax2.get_xaxis_transform(),
                color="tab:red",
                markersize=7,
                label=f"{len(outliers)} outlier{'s' if len(outliers) != 1 else ''} beyond p99",
            )
        for value, name, style in ((p50, "p50", ":"), (p99, "p99", "--")):
            if value >= JITTER_FLOOR_US:
                ax2.axvline(value, color="black", linestyle=style, linewidth=1, label=name)
        ax2.legend(fontsize="small")
    ax2.set_xscale("log")
    ax2.set_xlabel("0xF3 arrival offset from the 10 ms grid, at the simulator (µs, log scale)")
    ax2.set_ylabel("ticks")
    ax2.set_title(
        f"tick jitter: p50 {p50:.0f} µs, p99 {p99:.0f} µs,"
        f" max {timing.jitter_max * 1e6:.0f} µs, {timing.missed} missed"
    )
    fig.tight_layout()
    return fig
