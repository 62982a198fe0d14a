"""Compare two rig runs figure by figure: pure (two ``results.json`` values in, rows out).

Each figure has a direction (is a larger value better or worse?) and a default tolerance,
relative (a fraction of the old value, never less than ``at_least`` units) or absolute
(in the figure's own units, for figures that may be near zero).  A figure *regressed*
when it moved in its worse direction by more than its tolerance; moving the other way
is never a regression.  A figure or an actuator the old run has and the new one lacks
regressed too (the new run did not measure it); one only the new run has is listed.
A new run that recorded failures (``read_failures``) fails the comparison.

:func:`read_results` checks a parsed ``results.json`` before anything is compared: its
format and version, and that every figure is a known figure with a finite number (not
null, not a boolean, not a string), naming the field that is not.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from motorbus.errors import LocalProtocolError

__all__ = [
    "FIGURES",
    "FORMAT",
    "VERSIONS",
    "Figure",
    "Row",
    "compare_results",
    "parse_tolerances",
    "read_failures",
    "read_results",
]

#: The ``format`` of a rig's ``results.json``, and the versions this code reads.
FORMAT = "motorbus-rig-results"
VERSIONS = (1,)


@dataclass(frozen=True, slots=True)
class Figure:
    """How to judge one figure: ``worse`` is "higher" or "lower"; the tolerance is
    ``rel`` (fraction of the old value, at least ``at_least`` units) or, when
    ``absolute`` is set, that many units."""

    worse: Literal["higher", "lower"]
    rel: float = 0.10
    absolute: float | None = None
    at_least: float = 0.0


#: Every figure ``rig`` writes per actuator, with its default tolerance.
FIGURES: dict[str, Figure] = {
    "step.dead_time_ms": Figure("higher", rel=0.20),
    "step.rise_time_ms": Figure("higher", rel=0.10),
    "step.speed_units_per_s": Figure("lower", rel=0.10),
    "step.mean_speed_units_per_s": Figure("lower", rel=0.10),
    "step.overshoot_pct": Figure("higher", absolute=2.0),
    "step.settling_time_ms": Figure("higher", rel=0.15),
    "step.steady_state_error": Figure("higher", absolute=5.0),
    "step.peak_current_ma": Figure("higher", rel=0.20, at_least=20.0),
    "step.peak_force_g": Figure("higher", rel=0.20, at_least=100.0),
    "track.rms_error": Figure("higher", rel=0.20),
    "track.max_error": Figure("higher", rel=0.20),
    "track.lag_ms": Figure("higher", rel=0.20),
    "latency.p50_ms": Figure("higher", rel=0.20),
    "latency.p99_ms": Figure("higher", rel=0.30),
    "latency.max_ms": Figure("higher", rel=0.50),
    "repeat.spread": Figure("higher", absolute=3.0),
    "repeat.backlash": Figure("higher", absolute=3.0),
    "repeat.std_below": Figure("higher", absolute=1.0),
    "repeat.std_above": Figure("higher", absolute=1.0),
}


@dataclass(frozen=True, slots=True)
class Row:
    """One figure of one actuator: ``old``/``new`` are NaN where that run lacks it
    (``missing`` says which: ``"old"``, ``"new"`` or None)."""

    device: str
    figure: str
    old: float
    new: float
    allowed: float
    regressed: bool
    missing: Literal["old", "new"] | None = None

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


def _refuse(field: str, value: object, why: str) -> LocalProtocolError:
    shown = json.dumps(value, default=repr)
    return LocalProtocolError(f"{field}={shown}: {why}", field=field, value=value)


def read_results(doc: Any) -> dict[str, dict[str, float]]:
    """The figures of a parsed ``results.json``: ``{"la:1": {"step.rise_time_ms": ...}}``.

    Raises:
        LocalProtocolError: the document is not rig results (``format``), has a version
            this code does not read, or a device or figure that is not a finite number
            of a known figure; ``field`` names it (e.g. ``devices.la:1.step.rise_time_ms``).
    """
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise _refuse("format", got, f"not rig results (a rig writes format {FORMAT!r})")
    version = doc.get("version")
    if isinstance(version, bool) or version not in VERSIONS:
        allowed = ", ".join(str(v) for v in VERSIONS)
        raise _refuse("version", version, f"not a version this motorbus reads ({allowed})")
    devices = doc.get("devices")
    if not isinstance(devices, dict) or not devices:
        raise _refuse("devices", devices, "a rig's results name at least one actuator")
    out: dict[str, dict[str, float]] = {}
    for device, figures in devices.items():
        where = f"devices.{device}"
        if not isinstance(figures, dict):
            raise _refuse(where, figures, "must be an object of figures")
        out[device] = {}
        for name, value in figures.items():
            if name not in FIGURES:
                raise _refuse(f"{where}.{name}", value, "not a figure motorbus rig writes")
            if value is None:
                raise _refuse(
                    f"{where}.{name}", value, "the run could not measure it (see its failures)"
                )
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise _refuse(f"{where}.{name}", value, "must be a number")
            if not math.isfinite(value):
                raise _refuse(f"{where}.{name}", value, "must be a finite number")
            out[device][name] = float(value)
    return out


def read_failures(doc: Mapping[str, Any]) -> list[str]:
    """The failures a results document records (``"la:1 step: why"``; ``[]`` for a
    run that passed, or a results file written before runs recorded them).

    Raises:
        LocalProtocolError: ``failures`` is not a list of objects with ``device``,
            ``test`` and ``why``.
    """
    failures = doc.get("failures", [])
    if not isinstance(failures, list):
        raise _refuse("failures", failures, "must be a list")
    out = []
    for k, f in enumerate(failures):
        if not isinstance(f, dict) or not isinstance(f.get("why"), str):
            raise _refuse(f"failures[{k}]", f, "must be an object with device, test and why")
        where = " ".join(str(x) for x in (f.get("device"), f.get("test")) if x)
        out.append(f"{where}: {f['why']}")
    return out


def _allowed(fig: Figure, old: float) -> float:
    if fig.absolute is not None:
        return fig.absolute
    return max(abs(old) * fig.rel, fig.at_least)


def _order(name: str) -> tuple[int, str]:
    keys = list(FIGURES)
    return (keys.index(name), name) if name in FIGURES else (len(keys), name)


def compare_results(
    old: Mapping[str, Mapping[str, float]],
    new: Mapping[str, Mapping[str, float]],
    tolerances: Mapping[str, Figure] | None = None,
) -> list[Row]:
    """A row for every figure of every actuator in either run (``old``/``new`` map a
    device name such as ``"la:1"`` to its flat figures), devices in name order and
    figures in ``FIGURES`` order.  A figure the old run has and the new one lacks (or
    that became NaN) regressed; one only the new run has did not.

    Raises:
        ValueError: a figure that is not in ``FIGURES`` (its direction is unknown).
    """
    figures = {**FIGURES, **(tolerances or {})}
    rows: list[Row] = []
    for device in sorted(set(old) | set(new)):
        a_figs, b_figs = old.get(device, {}), new.get(device, {})
        for name in sorted(set(a_figs) | set(b_figs), key=_order):
            fig = figures.get(name)
            if fig is None:
                raise ValueError(f"{device} {name}: not a figure motorbus rig writes")
            a = float(a_figs.get(name, math.nan))
            b = float(b_figs.get(name, math.nan))
            missing: Literal["old", "new"] | None = (
                "new" if name not in b_figs else "old" if name not in a_figs else None
            )
            allowed = _allowed(fig, a) if math.isfinite(a) else math.nan
            if math.isnan(a) or math.isnan(b):
                regressed = (math.isnan(b) and not math.isnan(a)) or missing == "new"
            else:
                worse_by = (b - a) if fig.worse == "higher" else (a - b)
                regressed = worse_by > allowed
            rows.append(Row(device, name, a, b, allowed, regressed, missing))
    return rows
