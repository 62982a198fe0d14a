"""How the simulated project stepper moves: move profiles and the plan of a project run.

Kinematic model (simulator assumptions: doc 000 gives no timing, A0-09/A0-14):

* pulses per revolution = subdivision x 36000 / step_angle_x100 (A.3: 8 x 200 = 1600);
* a step moves ``run_distance / distance_per_rev`` revolutions;
* the pulse rate starts at ``min(start_hz, cruise)``, ramps linearly by ``accel_hz``
  every millisecond (``accel_hz`` 0 = no ramp) to the cruise rate
  ``speed_rpm / 60 x pulses per rev``, and ramps down the same way (a triangle if the
  move is too short to reach cruise); speed 0 never moves;
* a step: wait for its start input (level), switch its outputs and move (cut short,
  at once, when its stop input is or becomes active), then wait ``delay_ms``; the next
  step begins :data:`STEP_GAP_S` later (time the controller takes to load a step);
* stops are immediate whatever the stored stop mode (which is only stored).

A move is a :class:`MoveProfile` started at a time in a direction (:class:`Motion`); a
project run (:class:`Run`) is the step order of one pass, unrolled from the step loop
(:func:`step_order`), and where the run stands in it.  The device model that starts
and ends them, on requests, inputs and time, is
``motorbus.sim.project_stepper.ProjectStepperModel``.  Pure: time is passed in.
"""

from __future__ import annotations

import enum
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

from motorbus.protocol.project_stepper import StepSpec

__all__ = [
    "ACCEL_STEP_S",
    "STEP_GAP_S",
    "Motion",
    "MoveProfile",
    "Phase",
    "Run",
    "pulses_per_rev",
    "step_order",
]

#: ``accel_hz`` is read as "Hz per millisecond".  Simulator assumption: the slope unit
#: is unstated (A.3, A0-09).
ACCEL_STEP_S = 1e-3
#: Time between the end of one step and the start of the next.  Simulator assumption
#: (the controller must load the next step); it also keeps a loop of empty steps from
#: spinning at one instant.
STEP_GAP_S = 1e-3
#: Degrees x 100 in one revolution: pulses/rev = subdivision x 36000 / angle x 100 (A.3).
_CENTIDEGREES_PER_REV = 36000


@dataclass(frozen=True, slots=True)
class MoveProfile:
    """A trapezoidal (or triangular) pulse-rate profile; see the module docstring.

    Attributes:
        pulses: pulses to travel (``math.inf`` = continuous, for jogs and homing).
        start_rate: pulse rate at the start and end, Hz.
        peak_rate: highest pulse rate reached, Hz (0 = never moves).
        accel: ramp slope, Hz/s (0 = no ramp).
        ramp_time: duration of each ramp, s.
        cruise_time: time at ``peak_rate``, s (``math.inf`` for continuous moves).
    """

    pulses: float
    start_rate: float
    peak_rate: float
    accel: float
    ramp_time: float
    cruise_time: float

    @classmethod
    def plan(cls, pulses: float, start_hz: float, cruise_hz: float, accel_hz: float) -> MoveProfile:
        """Plan a move of ``pulses`` pulses.

        Args:
            pulses: distance, pulses (``math.inf`` = continuous).
            start_hz: start frequency, Hz (clipped to the cruise rate).
            cruise_hz: cruise pulse rate, Hz.
            accel_hz: accel setting, Hz per :data:`ACCEL_STEP_S` (0 = no ramp).

        Returns:
            The profile; a zero move lasts 0 s, a move at cruise 0 lasts forever.
        """
        if pulses <= 0:
            return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if cruise_hz <= 0:
            return cls(pulses, 0.0, 0.0, 0.0, 0.0, math.inf)
        f0 = min(float(start_hz), cruise_hz)
        accel = accel_hz / ACCEL_STEP_S
        if accel <= 0 or f0 >= cruise_hz:
            return cls(pulses, f0, cruise_hz, 0.0, 0.0, pulses / cruise_hz)
        ramp = (cruise_hz - f0) / accel
        ramp_pulses = (f0 + cruise_hz) / 2 * ramp
        if pulses >= 2 * ramp_pulses:
            return cls(pulses, f0, cruise_hz, accel, ramp, (pulses - 2 * ramp_pulses) / cruise_hz)
        peak = math.sqrt(f0 * f0 + accel * pulses)
        return cls(pulses, f0, peak, accel, (peak - f0) / accel, 0.0)

    @property
    def duration(self) -> float:
        """Total time of the move, s (``math.inf`` if it never ends)."""
        return 2 * self.ramp_time + self.cruise_time

    def pulses_at(self, t: float) -> float:
        """Return the pulses travelled ``t`` seconds after the start (clamped to the move)."""
        if t <= 0 or self.peak_rate <= 0:
            return 0.0
        if t >= self.duration:
            return self.pulses
        a, f0, tr = self.accel, self.start_rate, self.ramp_time
        if t < tr:
            return f0 * t + a * t * t / 2
        ramp_pulses = f0 * tr + a * tr * tr / 2 if tr > 0 else 0.0
        if t < tr + self.cruise_time:
            return ramp_pulses + self.peak_rate * (t - tr)
        td = t - tr - self.cruise_time
        return (
            ramp_pulses + self.peak_rate * self.cruise_time + self.peak_rate * td - a * td * td / 2
        )


@dataclass(slots=True)
class Motion:
    """The motor's current motion: a profile started at ``start`` in direction ``sign``."""

    profile: MoveProfile
    start: float
    sign: int

    @property
    def end(self) -> float:
        return self.start + self.profile.duration

    def travelled(self, now: float) -> float:
        return self.sign * self.profile.pulses_at(now - self.start)


class Phase(enum.Enum):
    """Where a step of a run stands: waiting for its start input, moving, or in its delay."""

    WAIT_START = "wait_start"
    MOVE = "move"
    DELAY = "delay"


@dataclass(slots=True)
class Run:
    """A running project: the step order of one pass and where it stands."""

    project: int
    steps: tuple[StepSpec, ...]
    pulses_per_rev: float
    distance_per_rev: int
    order: tuple[int, ...]  # step numbers of one pass, step loop unrolled (A0-15)
    passes: int | None  # total passes, None = forever (A.4 0x8E 255)
    started: float
    notify: bool  # send EE DD at the end
    pass_index: int = 0
    position: int = 0  # index into ``order``
    phase: Phase = Phase.WAIT_START
    phase_end: float = math.inf

    @property
    def spec(self) -> StepSpec:
        return self.steps[self.order[self.position] - 1]

    def profile(self, spec: StepSpec) -> MoveProfile:
        revs = spec.run_distance / self.distance_per_rev if self.distance_per_rev else 0.0
        cruise = spec.speed_rpm / 60 * self.pulses_per_rev
        return MoveProfile.plan(revs * self.pulses_per_rev, spec.start_hz, cruise, spec.accel_hz)

    def finish_time(self, inputs: Sequence[bool]) -> float | None:
        """When the run's last step ends if no input changes; None if unknowable.

        None if the run goes on forever, waits for a start input now, or has a step
        still to come that waits for an input that is not active.  The sum repeats the
        exact float arithmetic of the model's transitions, so a poll at the time given
        finds the run ended.
        """
        if self.passes is None:
            return None
        if self.phase is Phase.WAIT_START:
            return None
        t = self.phase_end
        if self.phase is Phase.MOVE:
            t = t + self.spec.delay_ms / 1000
        more_passes = self.passes - self.pass_index - 1
        rest = itertools.chain(
            self.order[self.position + 1 :],
            itertools.chain.from_iterable([self.order] * more_passes),
        )
        moves: dict[int, float | None] = {}
        for step in rest:
            if step not in moves:
                moves[step] = self.move_time(step, inputs)
            move = moves[step]
            if move is None:
                return None  # a step still to come waits for an input that is not active
            t = t + STEP_GAP_S  # same operations, same order as the transitions
            if move:
                t = t + move
            t = t + self.steps[step - 1].delay_ms / 1000
        if not t < math.inf:
            return None
        return t

    def move_time(self, step: int, inputs: Sequence[bool]) -> float | None:
        """Duration of the move of ``step`` with these input levels; None if it waits."""
        spec = self.steps[step - 1]
        gate, stop = spec.start_input, spec.stop_input
        if gate and not inputs[gate - 1]:
            return None
        if stop and inputs[stop - 1]:
            return 0.0
        return self.profile(spec).duration


def pulses_per_rev(subdivision: int, step_angle_x100: int) -> float:
    """Motor pulses per revolution (A.3: 8 x 200 = 1600); 0 for a zero step angle."""
    if step_angle_x100 <= 0:
        return 0.0
    return subdivision * _CENTIDEGREES_PER_REV / step_angle_x100


def step_order(n: int, start: int, end: int, count: int) -> tuple[int, ...]:
    """One pass: steps 1..n with ``start..end`` repeated ``count`` times in total (A0-15).

    A disabled (0, 0, 0) or impossible loop (outside 1..n) runs every step once.
    """
    if not (1 <= start <= end <= n and count >= 1):
        return tuple(range(1, n + 1))
    body = tuple(range(start, end + 1))
    return tuple(range(1, start)) + body * count + tuple(range(end + 1, n + 1))
