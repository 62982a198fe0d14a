"""Compare two rig runs figure by figure: pure (two ``results.json`` values in, rows out).

Each figure has a direction (is a larger value better or worse?) and a default tolerance,
relative (a fraction of the old value) or absolute (in the figure's own units, for
figures that may be near zero).  A figure *regressed* when it moved in its worse
direction by more than its tolerance; moving the other way is never a regression.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

__all__ = ["FIGURES", "Figure", "Row", "compare_results", "parse_tolerances"]


@dataclass(frozen=True, slots=True)
class Figure:
    """How to judge one figure: ``worse`` is "higher" or "lower"; the tolerance is
    ``rel`` (fraction of the old value) or, when ``absolute`` is set, that many units."""

    worse: Literal["higher", "lower"]
    rel: float = 0.10
    absolute: float | None = None


#: Every figure ``rig`` writes per actuator, with its default tolerance.
FIGURES: dict[str, Figure] = {
    "step.dead_time_ms": Figure("higher", rel=0.20),
    "step.rise_time_ms": Figure("higher", rel=0.10),
    "step.speed_units_per_s": Figure("lower", rel=0.10),
    "step.mean_speed_units_per_s": Figure("lower", rel=0.10),
    "step.overshoot_pct": Figure("higher", absolute=2.0),
    "step.settling_time_ms": Figure("higher", rel=0.15),
    "step.steady_state_error": Figure("higher", absolute=5.0),
    "track.rms_error": Figure("higher", rel=0.20),
    "track.max_error": Figure("higher", rel=0.20),
    "track.lag_ms": Figure("higher", rel=0.20),
    "latency.p50_ms": Figure("higher", rel=0.20),
    "latency.p99_ms": Figure("higher", rel=0.30),
    "repeat.spread": Figure("higher", absolute=3.0),
    "repeat.backlash": Figure("higher", absolute=3.0),
}


@dataclass(frozen=True, slots=True)
class Row:
    """One figure of one actuator in both runs."""

    device: str
    figure: str
    old: float
    new: float
    allowed: float
    regressed: bool

    @property
    def change(self) -> float:
        return self.new - self.old

    @property
    def change_pct(self) -> float:
        return math.nan if self.old == 0 else (self.new - self.old) / abs(self.old) * 100.0


def parse_tolerances(text: str) -> dict[str, Figure]:
    """``"step.rise_time_ms=5%,repeat.backlash=1.5"``: percent means relative, a bare
    number means absolute units.  Raises ValueError naming the figure and value."""
    out: dict[str, Figure] = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in FIGURES:
            raise ValueError(
                f"--tolerance: {item!r} is not FIGURE=VALUE with FIGURE one of "
                + ", ".join(sorted(FIGURES))
            )
        value = value.strip()
        try:
            number = float(value.removesuffix("%"))
        except ValueError:
            raise ValueError(
                f"--tolerance {name}: {value!r} is not a number (e.g. 10% or 2.5)"
            ) from None
        if not math.isfinite(number) or number < 0:
            raise ValueError(f"--tolerance {name}: {value!r} must be 0 or more")
        base = FIGURES[name]
        if value.endswith("%"):
            out[name] = Figure(base.worse, rel=number / 100.0)
        else:
            out[name] = Figure(base.worse, rel=0.0, absolute=number)
    return out


def _allowed(fig: Figure, old: float) -> float:
    return fig.absolute if fig.absolute is not None else abs(old) * fig.rel


def compare_results(
    old: Mapping[str, Mapping[str, float]],
    new: Mapping[str, Mapping[str, float]],
    tolerances: Mapping[str, Figure] | None = None,
) -> list[Row]:
    """Rows for every figure present in both runs for an actuator present in both
    (``old``/``new`` map a device name such as ``"la:1"`` to its flat figures)."""
    figures = {**FIGURES, **(tolerances or {})}
    rows: list[Row] = []
    for device in sorted(set(old) & set(new)):
        for name, fig in figures.items():
            a = old[device].get(name)
            b = new[device].get(name)
            if a is None or b is None:
                continue
            a, b = float(a), float(b)
            allowed = _allowed(fig, a)
            if math.isnan(a) or math.isnan(b):
                regressed = math.isnan(b) and not math.isnan(a)
            else:
                worse_by = (b - a) if fig.worse == "higher" else (a - b)
                regressed = worse_by > allowed
            rows.append(Row(device, name, a, b, allowed, regressed))
    return rows
