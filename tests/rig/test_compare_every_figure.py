"""``rig compare`` covers every figure the rig writes (issue 41, case 3) and reads only
numbers (case 2): a figure or actuator the new run lacks regressed; a results document
with a null, a non-number, a boolean, an unknown figure or version is refused."""

from __future__ import annotations

import math
import re

import pytest

from motorbus.errors import LocalProtocolError
from motorbus.rig.compare import compare_results, parse_tolerances
from tests.rig.figures import WRITTEN


def results(figures: dict[str, object], **top: object) -> dict[str, object]:
    return {"format": "motorbus-rig-results", "version": 1, "devices": {"la:1": figures}, **top}


def every_figure() -> dict[str, float]:
    return {name: 1000.0 + 10 * k for k, name in enumerate(WRITTEN)}


def test_compare_covers_every_figure_the_rig_writes() -> None:
    figs = every_figure()
    rows = compare_results({"la:1": figs}, {"la:1": figs})
    assert [r.figure for r in rows] == list(WRITTEN)
    assert not any(r.regressed for r in rows)


@pytest.mark.parametrize(
    "name",
    [
        "latency.max_ms",
        "repeat.std_below",
        "repeat.std_above",
        "step.peak_current_ma",
        "step.peak_force_g",
    ],
)
def test_the_five_figures_compare_was_missing_regress_and_take_a_tolerance(name: str) -> None:
    old = every_figure()
    new = {**old, name: old[name] * 3}
    (row,) = [r for r in compare_results({"la:1": old}, {"la:1": new}) if r.figure == name]
    assert row.regressed
    wide = parse_tolerances(f"{name}=300%")
    (row,) = [r for r in compare_results({"la:1": old}, {"la:1": new}, wide) if r.figure == name]
    assert not row.regressed


def test_a_figure_or_actuator_missing_from_new_regressed_and_one_only_in_new_did_not() -> None:
    old = {"la:1": {"step.rise_time_ms": 400.0, "repeat.spread": 2.0}, "la:2": {"repeat.spread": 1}}
    new = {"la:1": {"step.rise_time_ms": 400.0, "latency.p50_ms": 30.0}}
    rows = {(r.device, r.figure): r for r in compare_results(old, new)}
    assert (
        rows["la:1", "repeat.spread"].regressed and rows["la:1", "repeat.spread"].missing == "new"
    )
    assert rows["la:2", "repeat.spread"].regressed
    assert not rows["la:1", "latency.p50_ms"].regressed
    assert rows["la:1", "latency.p50_ms"].missing == "old"
    assert not rows["la:1", "step.rise_time_ms"].regressed


def test_read_results_takes_a_rig_results_document() -> None:
    from motorbus.rig.compare import read_results

    figs = every_figure()
    assert read_results(results(figs)) == {"la:1": figs}


@pytest.mark.parametrize(
    ("doc", "field", "message"),
    [
        ({"devices": {}}, "format", "not rig results"),
        ([1, 2], "format", "not rig results"),
        (results({}, version=99), "version", "version=99: not a version"),
        (results({}, version=True), "version", "not a version"),
        ({**results({}), "devices": {"la:1": None}}, "devices.la:1", "must be an object"),
        (results({"step.rise_time_ms": None}), "devices.la:1.step.rise_time_ms", "null"),
        (results({"step.rise_time_ms": [1, 2]}), "devices.la:1.step.rise_time_ms", "a number"),
        (results({"step.rise_time_ms": "720"}), "devices.la:1.step.rise_time_ms", "a number"),
        (results({"step.rise_time_ms": True}), "devices.la:1.step.rise_time_ms", "true"),
        (results({"step.rise_time_ms": math.inf}), "devices.la:1.step.rise_time_ms", "finite"),
        (results({"step.bogus": 1.0}), "devices.la:1.step.bogus", "not a figure"),
        ({**results({}), "devices": {}}, "devices", "at least one actuator"),
    ],
)
def test_read_results_refuses_what_is_not_a_number_naming_the_field(
    doc: object, field: str, message: str
) -> None:
    from motorbus.rig.compare import read_results

    with pytest.raises(LocalProtocolError, match=re.escape(message)) as err:
        read_results(doc)
    assert err.value.field == field
