"""Stepper rigs: how long a stored project or a quad run takes, start to finish, N times.

The start is the completed write of the start command (``Bus.add_observer``); the end
is the bus's time of the frame that says it finished (``EE DD`` for the project
controller, the done reply for the 4-axis controller), as its ``ProjectFinished`` /
``QuadDone`` event carries it.  The runs themselves go through the device classes
(``ProjectStepper.run_project``, ``QuadStepper.run``), so each run that does not
finish in time is stopped, and a cancelled rig stops the motor before it ends.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from motorbus.bus.bus import Bus
from motorbus.bus.events import ProjectFinished, QuadDone
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.devices.quad_stepper import QuadStepper
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Command, check_int
from motorbus.rig.analysis import Distribution, distribution

__all__ = ["RunTimes", "time_project_runs", "time_quad_runs"]

#: Most runs one stepper rig makes.
MAX_RUNS = 10_000


@dataclass(frozen=True, slots=True)
class RunTimes:
    """Start-to-finish times of N runs (ms)."""

    what: str
    times_ms: tuple[float, ...]

    @property
    def stats(self) -> Distribution:
        return distribution(self.times_ms)

    def as_dict(self) -> dict[str, Any]:
        d = self.stats
        return {
            "what": self.what,
            "runs": d.count,
            "p50_ms": d.p50,
            "p99_ms": d.p99,
            "max_ms": d.max,
            "min_ms": d.min,
            "times_ms": list(self.times_ms),
        }


class _Starts:
    """Bus observer: write times of the start commands."""

    def __init__(self, kind: type[Command[Any]]) -> None:
        self.kind = kind
        self.times: list[float] = []

    def on_write(self, cmd: Command[object], at: float) -> None:
        if isinstance(cmd, self.kind):
            self.times.append(at)

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None:
        pass


async def time_project_runs(
    bus: Bus, number: int, runs: int, *, timeout: float | None = None, motor: int | None = None
) -> RunTimes:
    """Run stored project ``number`` ``runs`` times, one after the other; start -> ``EE DD``."""
    check_int("runs", runs, 1, MAX_RUNS)
    ps.StartProject(number)  # validates the number before anything is sent
    device = ProjectStepper(bus) if motor is None else ProjectStepper(bus, motor=motor)
    starts = _Starts(ps.StartProject)
    times: list[float] = []
    bus.add_observer(starts)
    try:
        with bus.events.subscribe(ProjectFinished) as finished:
            for _ in range(runs):
                finished.pending()  # an EE DD from before this run is not its end
                await device.run_project(number, timeout=timeout)
                # run_project returned on the last: one before it was read before the
                # start's acknowledgement, so from before the start.
                ends = finished.pending()
                times.append((ends[-1].time - starts.times[-1]) * 1e3)
    finally:
        bus.remove_observer(starts)
    return RunTimes(f"project {number}", tuple(times))


async def time_quad_runs(
    bus: Bus, motor: int, runs: int, *, timeout: float | None = None
) -> RunTimes:
    """Run quad ``motor`` ``runs`` times with its stored settings; run -> done reply."""
    check_int("runs", runs, 1, MAX_RUNS)
    q.Run(motor)  # validates the motor before anything is sent
    device = QuadStepper(bus)
    starts = _Starts(q.Run)
    times: list[float] = []
    bus.add_observer(starts)
    try:
        with bus.events.subscribe(QuadDone, lambda e: e.kind == "run") as done:
            for _ in range(runs):
                done.pending()
                await device.run(motor, timeout=timeout)
                ends = done.pending()
                times.append((ends[0].time - starts.times[-1]) * 1e3)
    finally:
        bus.remove_observer(starts)
    return RunTimes(f"quad motor {motor}", tuple(times))
