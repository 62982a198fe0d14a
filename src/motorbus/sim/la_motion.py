"""How the simulated LA actuator's motor moves: positioning and follow.

* Positioning drives toward the target with a trapezoidal profile: it accelerates at
  ``accel`` units/s^2 to at most ``vmax`` units/s and brakes to stop at the target.
* Follow tracks the latest streamed target at up to ``vmax``, optionally through a
  first-order lag (``lag_tau`` seconds).
* A move stops ``dead_band / 2`` short of its target along the approach (a simulated
  backlash: approaches from below and above end ``dead_band`` apart).

Motion is integrated in steps of at most :data:`SIM_STEP_S`.  When moves start and
stop (commands, dead time, e-stop, faults) is decided by ``motorbus.sim.la.LAModel``,
which owns an :class:`LAMotion`.  Pure: durations are passed in.
"""

from __future__ import annotations

import math

__all__ = ["SIM_STEP_S", "LAMotion"]

#: Model choice: integration step of the motion profile, seconds.
SIM_STEP_S = 1e-3


class LAMotion:
    """The motor's position and velocity, and the target it drives toward.

    Args:
        position: initial position, units.
        vmax: top speed, units per second.
        accel: acceleration of positioning moves, units per second squared.
        lag_tau: follow-mode lag time constant, seconds (0: none).
        dead_band: units a move stops short of its target (half on each side).
    """

    __slots__ = (
        "accel",
        "aim",
        "chase",
        "dead_band",
        "follow",
        "goal",
        "lag_tau",
        "position",
        "velocity",
        "vmax",
    )

    def __init__(
        self, *, position: float, vmax: float, accel: float, lag_tau: float, dead_band: float
    ) -> None:
        self.vmax = vmax
        self.accel = accel
        self.lag_tau = lag_tau
        self.dead_band = dead_band
        self.position = float(position)
        self.velocity = 0.0
        #: The target being driven toward, or None (stopped).
        self.goal: int | None = None
        self.aim = 0.0  # where the motor is driving: the goal less the dead band
        self.chase = float(position)  # follow mode: the lagged goal
        self.follow = False

    @property
    def moving(self) -> bool:
        """True while the motor is driving toward a target."""
        return self.goal is not None and (self.velocity != 0.0 or self.position != self.aim)

    def stop(self) -> None:
        """Stop at once where the motor is."""
        self.goal = None
        self.velocity = 0.0

    def adopt(self, target: int, follow: bool) -> None:
        """Start driving toward ``target``."""
        if self.goal is None or not self.follow or not follow:
            self.chase = self.position
        self.goal = target
        self.follow = follow
        distance = target - self.position
        half = self.dead_band / 2
        if abs(distance) <= half:
            self.aim = self.position
        else:
            self.aim = target - math.copysign(half, distance)

    def integrate(self, duration: float) -> None:
        """Move toward the aim for ``duration`` seconds in steps of at most SIM_STEP_S."""
        steps = max(1, math.ceil(duration / SIM_STEP_S))
        dt = duration / steps
        for _ in range(steps):
            goal = self.aim
            if self.follow and self.lag_tau:
                self.chase += (goal - self.chase) * min(1.0, dt / self.lag_tau)
                if abs(self.aim - self.chase) < 1e-3:
                    self.chase = self.aim
                goal = self.chase
            distance = goal - self.position
            if self.follow:
                step = max(-self.vmax * dt, min(self.vmax * dt, distance))
                self.position += step
                self.velocity = step / dt
            else:
                # Fastest speed from which we can still brake to a stop at the goal.
                v_wanted = math.copysign(
                    min(self.vmax, math.sqrt(2.0 * self.accel * abs(distance))), distance
                )
                dv = max(-self.accel * dt, min(self.accel * dt, v_wanted - self.velocity))
                self.velocity += dv
                self.position += self.velocity * dt
                if (goal - self.position) * distance <= 0.0:  # reached or passed the goal
                    self.position = goal
            if self.position == goal:
                self.velocity = 0.0
                if goal == self.aim:
                    return
