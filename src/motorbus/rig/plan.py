"""A rig test plan: what to run on which actuators, inside which window.  Pure.

Every value is checked when the plan is made (field, value, allowed range), and every
target any test will send is checked against the position window then, so a plan that
would send a target outside it is refused before anything moves.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import check_int
from motorbus.protocol.la import ID_MAX, ID_MIN, POSITION_MAX, POSITION_MIN
from motorbus.streaming.model import PERIOD_MAX_S, PERIOD_MIN_S

__all__ = ["TESTS", "RigPlan", "default_window"]

#: Every test the rig knows, in the order it runs them.
TESTS = ("step", "track", "latency", "repeat")
#: A tracked sine needs at least this many ticks per cycle.
MIN_TICKS_PER_CYCLE = 10
#: Default frequencies of the tracking test, Hz.
DEFAULT_FREQUENCIES = (0.1, 0.5, 1.0, 2.0, 5.0)


def default_window() -> tuple[int, int]:
    """The full stroke less 5 % at each end: 100..1900."""
    margin = round((POSITION_MAX - POSITION_MIN) * 0.05)
    return POSITION_MIN + margin, POSITION_MAX - margin


def _number(name: str, value: object, lo: float, hi: float, unit: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise LocalProtocolError(
            f"{name}={value!r} is not a number: allowed {lo:g}..{hi:g}{unit}",
            field=name,
            value=value,
        )
    if not lo <= value <= hi:
        raise LocalProtocolError(
            f"{name}={value!r} is out of range: allowed {lo:g}..{hi:g}{unit}",
            field=name,
            value=value,
        )
    return float(value)


@dataclass(frozen=True)
class RigPlan:
    """What the rig runs.  Positions in LA units (0..2000), times in seconds.

    Defaults (``None``) are derived from the window: the step goes from 25 % to 75 %
    of it, the sine is centred in it with a quarter of its width as amplitude, the
    repeatability point is its middle.
    """

    ids: tuple[int, ...]
    tests: tuple[str, ...] = TESTS
    window: tuple[int, int] = field(default_factory=default_window)
    step_start: int | None = None
    step_end: int | None = None
    settle_timeout: float = 5.0
    period: float = 0.01
    frequencies: tuple[float, ...] = DEFAULT_FREQUENCIES
    cycles: float = 2.0
    amplitude: int | None = None
    latency_count: int = 50
    latency_step: int = 20
    repeat_count: int = 5
    repeat_point: int | None = None
    repeat_approach: int = 100
    max_current_ma: int = 1500
    max_force_g: int = 30000

    def __post_init__(self) -> None:
        ids = tuple(self.ids)
        if not ids:
            raise LocalProtocolError("ids: give at least one actuator", field="ids", value=ids)
        for ident in ids:
            check_int("ids", ident, ID_MIN, ID_MAX)
        if len(set(ids)) != len(ids):
            raise LocalProtocolError(f"ids={list(ids)} names an actuator twice", field="ids")
        object.__setattr__(self, "ids", ids)
        tests = tuple(self.tests)
        for name in tests:
            if name not in TESTS:
                raise LocalProtocolError(
                    f"tests: {name!r} is not a test: allowed {', '.join(TESTS)} (or all)",
                    field="tests",
                    value=name,
                )
        if not tests:
            raise LocalProtocolError("tests: give at least one test", field="tests")
        object.__setattr__(self, "tests", tuple(t for t in TESTS if t in tests))
        lo, hi = self.window
        check_int("min", lo, POSITION_MIN, POSITION_MAX)
        check_int("max", hi, POSITION_MIN, POSITION_MAX)
        if hi - lo < 4 * self.latency_step or hi <= lo:
            raise LocalProtocolError(
                f"window {lo}..{hi} is too narrow: max must exceed min by at least "
                f"{4 * self.latency_step}",
                field="window",
                value=(lo, hi),
            )
        span = hi - lo
        object.__setattr__(self, "step_start", self._pos("step_start", self.step_start, 0.25))
        object.__setattr__(self, "step_end", self._pos("step_end", self.step_end, 0.75))
        if self.step_start == self.step_end:
            raise LocalProtocolError(
                f"step_start and step_end are both {self.step_start}: a step needs two positions",
                field="step_end",
                value=self.step_end,
            )
        _number("settle_timeout", self.settle_timeout, 0.1, 60.0, " s")
        _number("period", self.period, PERIOD_MIN_S, PERIOD_MAX_S, " s (LA manual 3.5.3)")
        top = 1.0 / (MIN_TICKS_PER_CYCLE * self.period)
        freqs = tuple(self.frequencies)
        if "track" in self.tests and not freqs:
            raise LocalProtocolError("frequencies: give at least one", field="frequencies")
        for f in freqs:
            _number("frequency", f, 0.01, top, f" Hz ({MIN_TICKS_PER_CYCLE} ticks a cycle)")
        object.__setattr__(self, "frequencies", freqs)
        _number("cycles", self.cycles, 0.5, 100.0)
        amp = round(span / 4) if self.amplitude is None else self.amplitude
        check_int("amplitude", amp, 1, span // 2)
        object.__setattr__(self, "amplitude", amp)
        check_int("latency_count", self.latency_count, 1, 10_000)
        check_int("latency_step", self.latency_step, 1, 500)
        check_int("repeat_count", self.repeat_count, 1, 1000)
        point = self._pos("repeat_point", self.repeat_point, 0.5)
        object.__setattr__(self, "repeat_point", point)
        check_int("repeat_approach", self.repeat_approach, 1, span)
        for name, x in (
            ("repeat_point - repeat_approach", point - self.repeat_approach),
            ("repeat_point + repeat_approach", point + self.repeat_approach),
        ):
            if not lo <= x <= hi:
                raise LocalProtocolError(
                    f"{name}={x} is outside the window {lo}..{hi}", field="repeat_approach"
                )
        check_int("max_current_ma", self.max_current_ma, 1, 32767)
        check_int("max_force_g", self.max_force_g, 1, 32767 * 10)

    def _pos(self, name: str, value: int | None, share: float) -> int:
        lo, hi = self.window
        if value is None:
            return round(lo + (hi - lo) * share)
        check_int(name, value, lo, hi)
        return int(value)

    @property
    def center(self) -> int:
        """Middle of the window: where the sine is centred."""
        lo, hi = self.window
        return (lo + hi) // 2

    def targets(self) -> Iterable[int]:
        """The extreme targets the plan can send (each is inside the window)."""
        assert self.step_start is not None and self.step_end is not None
        assert self.amplitude is not None and self.repeat_point is not None
        yield from (self.step_start, self.step_end, self.center)
        yield from (self.center - self.amplitude, self.center + self.amplitude)
        yield from (
            self.repeat_point - self.repeat_approach,
            self.repeat_point + self.repeat_approach,
        )

    def in_window(self, position: float) -> bool:
        lo, hi = self.window
        return lo <= position <= hi

    def track_seconds(self, frequency: float) -> float:
        """How long one frequency of the tracking test streams."""
        return max(self.cycles / frequency, 1.0)

    def estimate_seconds(self) -> float:
        """A rough duration of the whole plan (the progress bar's total)."""
        per = 0.0
        if "step" in self.tests:
            per += 2 * 1.5
        if "track" in self.tests:
            per += sum(self.track_seconds(f) + 0.5 for f in self.frequencies)
        if "latency" in self.tests:
            per += self.latency_count * 0.15
        if "repeat" in self.tests:
            per += self.repeat_count * 2 * 2 * 0.6
        return per * len(self.ids) + 1.0

    def as_dict(self) -> dict[str, object]:
        return {
            "ids": list(self.ids),
            "tests": list(self.tests),
            "window": list(self.window),
            "step_start": self.step_start,
            "step_end": self.step_end,
            "settle_timeout_s": self.settle_timeout,
            "period_s": self.period,
            "frequencies_hz": list(self.frequencies),
            "cycles": self.cycles,
            "amplitude": self.amplitude,
            "latency_count": self.latency_count,
            "latency_step": self.latency_step,
            "repeat_count": self.repeat_count,
            "repeat_point": self.repeat_point,
            "repeat_approach": self.repeat_approach,
            "max_current_ma": self.max_current_ma,
            "max_force_g": self.max_force_g,
        }
