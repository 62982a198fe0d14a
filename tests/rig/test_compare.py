"""``rig compare``'s judgement: direction, tolerance, missing figures."""

from __future__ import annotations

import math

import pytest

from motorbus.rig.compare import FIGURES, compare_results, parse_tolerances

GOLDEN = {
    "la:1": {
        "step.dead_time_ms": 12.0,
        "step.rise_time_ms": 400.0,
        "step.speed_units_per_s": 2000.0,
        "repeat.backlash": 1.0,
    }
}


def slowed(by: float) -> dict[str, dict[str, float]]:
    f = GOLDEN["la:1"]
    return {
        "la:1": {
            **f,
            "step.rise_time_ms": f["step.rise_time_ms"] * (1 + by),
            "step.speed_units_per_s": f["step.speed_units_per_s"] / (1 + by),
        }
    }


def test_the_same_actuator_passes_against_itself() -> None:
    rows = compare_results(GOLDEN, GOLDEN)
    assert len(rows) == 4
    assert not any(r.regressed for r in rows)


def test_a_20_percent_slower_actuator_is_flagged() -> None:
    rows = {r.figure: r for r in compare_results(GOLDEN, slowed(0.20))}
    assert rows["step.rise_time_ms"].regressed
    assert rows["step.speed_units_per_s"].regressed
    assert not rows["step.dead_time_ms"].regressed
    assert rows["step.rise_time_ms"].change_pct == pytest.approx(20.0)


def test_getting_better_is_never_a_regression() -> None:
    rows = compare_results(GOLDEN, slowed(-0.5))
    assert not any(r.regressed for r in rows)


def test_tolerances_can_be_widened() -> None:
    wide = parse_tolerances("step.rise_time_ms=25%, step.speed_units_per_s=500")
    rows = compare_results(GOLDEN, slowed(0.20), wide)
    assert not any(r.regressed for r in rows)


def test_a_figure_that_became_nan_regressed() -> None:
    new = {"la:1": {**GOLDEN["la:1"], "step.rise_time_ms": math.nan}}
    rows = {r.figure: r for r in compare_results(GOLDEN, new)}
    assert rows["step.rise_time_ms"].regressed


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("step.bogus=5%", "FIGURE one of"),
        ("step.rise_time_ms", "FIGURE=VALUE"),
        ("step.rise_time_ms=fast", "'fast' is not a number"),
        ("step.rise_time_ms=-3", "must be 0 or more"),
    ],
)
def test_bad_tolerances_name_the_figure(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_tolerances(text)


def test_every_required_figure_has_a_tolerance() -> None:
    required = {
        "step.dead_time_ms", "step.rise_time_ms", "step.speed_units_per_s",
        "step.overshoot_pct", "step.settling_time_ms", "step.steady_state_error",
        "track.rms_error", "track.lag_ms", "latency.p50_ms", "latency.p99_ms",
        "repeat.spread", "repeat.backlash",
    }  # fmt: skip
    assert required <= set(FIGURES)
