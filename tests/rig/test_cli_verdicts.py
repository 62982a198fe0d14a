"""``motorbus rig`` keeps its word (issue 41), as a CI gate runs it: against
``motorbus sim`` on a pty, a dead actuator exits 1 naming the actuator, the test and
why (case 1); ``rig compare`` refuses a malformed results file with exit 2 naming the
file and the field (case 2) and covers every figure (case 3).  With ``--json`` a
failure is one JSON object with ``error`` and ``code`` on standard output."""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from motorbus.sim.process import SimProcess
from tests.helpers import cli, loaded_bus_file
from tests.rig.figures import WRITTEN

#: An actuator whose motor does not turn: ``seized`` (the simulator's dead actuator),
#: and one with a near-zero speed (how the issue's reporter modelled it).
DEAD = ["seized=1", "stroke_speed=0.000001"]
#: One small step: the old rig waited out every move of a dead actuator (5 s each).
ONE = ["--latency-count", "1"]
#: A dead actuator fails its first move when this ends: 1 s, not the default 5 s (the
#: simulated actuator's moves here settle well within it).
SOON = ["--settle-timeout", "1"]


@pytest.mark.parametrize("dead", DEAD)
def test_a_dead_actuator_fails_the_rig(tmp_path: Path, dead: str) -> None:
    with SimProcess([f"la:1,{dead}"], baud=921600) as sim:
        buses = str(loaded_bus_file(tmp_path, sim.path, 921600, ["la:1"]))
        r = cli(
            "rig", "1", "--tests", "step,latency", *ONE, *SOON, "--out", str(tmp_path),
            "--bus-file", buses,
        )  # fmt: skip
    assert r.returncode == 1, r.stdout + r.stderr
    assert re.search(r"FAILED la:1 step: did not follow: .*did not move", r.stderr), r.stderr
    assert "limit settle_timeout=1 s" in r.stderr, r.stderr
    assert "not run: latency" in r.stderr
    page = (tmp_path / "report.html").read_text(encoding="utf-8")
    top = page[: page.index("<h2>")]
    assert 'class="verdict failed"' in top and "la:1 step: did not follow" in top
    doc = json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))
    assert doc["passed"] is False
    assert [(f["device"], f["test"]) for f in doc["failures"]] == [("la:1", "step")]


def test_a_dead_actuator_with_json_prints_one_error_object(tmp_path: Path) -> None:
    with SimProcess(["la:1,seized=1"], baud=921600) as sim:
        buses = str(loaded_bus_file(tmp_path, sim.path, 921600, ["la:1"]))
        r = cli(
            "--json", "rig", "1", "--tests", "step", *SOON, "--out", str(tmp_path),
            "--bus-file", buses,
        )  # fmt: skip
    assert r.returncode == 1, r.stderr
    (line,) = r.stdout.splitlines()
    doc = json.loads(line)
    assert doc["code"] == 1 and doc["passed"] is False
    assert doc["error"].startswith("rig failed: la:1 step: did not follow")
    assert doc["failures"][0]["device"] == "la:1" and doc["report"].endswith("report.html")


# -- compare ------------------------------------------------------------------------


def good() -> dict[str, Any]:
    figures = {name: 100.0 + k for k, name in enumerate(WRITTEN)}
    return {"format": "motorbus-rig-results", "version": 1, "devices": {"la:1": figures}}


def edit(change: Callable[[dict[str, Any]], object]) -> dict[str, Any]:
    doc = good()
    change(doc)
    return doc


def figure(name: str, value: object) -> Callable[[dict[str, Any]], object]:
    return lambda d: d["devices"]["la:1"].__setitem__(name, value)


@pytest.fixture
def golden(tmp_path: Path) -> Iterator[Path]:
    path = tmp_path / "golden.json"
    path.write_text(json.dumps(good()), encoding="utf-8")
    yield path


BAD = {
    "null-device": (edit(lambda d: d["devices"].__setitem__("la:1", None)), "devices.la:1"),
    "null-figure": (edit(figure("step.rise_time_ms", None)), "devices.la:1.step.rise_time_ms"),
    "list": (edit(figure("step.rise_time_ms", [1, 2])), "devices.la:1.step.rise_time_ms"),
    "string": (edit(figure("step.rise_time_ms", "fast")), "devices.la:1.step.rise_time_ms"),
    "boolean": (edit(figure("step.rise_time_ms", True)), "devices.la:1.step.rise_time_ms"),
    "version": (edit(lambda d: d.__setitem__("version", 99)), "version"),
    "not-rig": ({"hello": "world"}, "format"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_compare_refuses_a_malformed_file_naming_file_and_field(
    tmp_path: Path, golden: Path, case: str
) -> None:
    doc, field = BAD[case]
    bad = tmp_path / f"{case}.json"
    bad.write_text(json.dumps(doc), encoding="utf-8")
    for old, new in ((golden, bad), (bad, golden)):
        r = cli("rig", "compare", str(old), str(new))
        assert r.returncode == 2, (case, r.returncode, r.stdout, r.stderr)
        assert "Traceback" not in r.stderr
        (line,) = r.stderr.splitlines()
        assert str(bad) in line and field in line, line
    r = cli("--json", "rig", "compare", str(golden), str(bad))
    assert r.returncode == 2
    err = json.loads(r.stdout)
    assert (err["code"], err["file"], err["field"]) == (2, str(bad), field)
    assert str(bad) in err["error"]


def test_compare_prints_every_figure_and_takes_a_tolerance_for_each(golden: Path) -> None:
    tolerances = ",".join(f"{name}=5%" for name in WRITTEN)
    r = cli("rig", "compare", str(golden), str(golden), "--tolerance", tolerances)
    assert r.returncode == 0, r.stderr
    printed = [line.split()[1] for line in r.stdout.splitlines()[1:]]
    assert printed == list(WRITTEN)


def test_compare_fails_a_run_that_lacks_a_figure_of_the_old_one(
    tmp_path: Path, golden: Path
) -> None:
    new = tmp_path / "new.json"
    new.write_text(json.dumps(edit(lambda d: d["devices"]["la:1"].pop("latency.max_ms"))))
    r = cli("rig", "compare", str(golden), str(new))
    assert r.returncode == 1, r.stdout + r.stderr
    assert re.search(r"latency\.max_ms .* REGRESSED \(not in NEW\)", r.stdout), r.stdout


def test_a_bad_plan_with_json_is_one_error_object_and_exit_2() -> None:
    r = cli("--json", "rig", "1", "--tests", "step,spin", "--out", "/nonexistent/x")
    assert r.returncode == 2, r.stderr
    doc = json.loads(r.stdout)
    assert doc["code"] == 2 and doc["field"] == "tests"
    assert "'spin' is not a test" in doc["error"]


@pytest.mark.parametrize("value", ["0.05", "61", "nan"])
def test_a_settle_timeout_out_of_range_is_refused_naming_it(value: str) -> None:
    r = cli("--json", "rig", "1", "--settle-timeout", value, "--out", "/nonexistent/x")
    assert r.returncode == 2, r.stderr
    doc = json.loads(r.stdout)
    assert doc["field"] == "settle_timeout", doc
    assert f"settle_timeout={float(value)!r}" in doc["error"] and "0.1..60 s" in doc["error"]


def test_compare_fails_a_new_run_that_recorded_failures(tmp_path: Path, golden: Path) -> None:
    failed = {"device": "la:1", "test": "latency", "why": "2 of 50 small steps have no dead time"}
    new = tmp_path / "new.json"
    new.write_text(json.dumps({**good(), "passed": False, "failures": [failed]}))
    r = cli("rig", "compare", str(golden), str(new))
    assert r.returncode == 1, r.stdout + r.stderr
    assert "the NEW run failed: la:1 latency: 2 of 50 small steps" in r.stderr
    dead = tmp_path / "dead.json"
    dead.write_text(json.dumps({**good(), "devices": {"la:1": {}}}))
    r = cli("rig", "compare", str(golden), str(dead))
    assert r.returncode == 1, r.stdout + r.stderr
    assert r.stdout.count("REGRESSED (not in NEW)") == len(WRITTEN)


def test_an_aborted_run_exits_1_and_still_writes_its_report(tmp_path: Path) -> None:
    with SimProcess(["la:1,position=300"], baud=921600) as sim:  # it draws 300 mA moving
        buses = str(loaded_bus_file(tmp_path, sim.path, 921600, ["la:1"]))
        r = cli(
            "rig", "1", "--tests", "step", "--max-current", "200", "--out", str(tmp_path),
            "--bus-file", buses,
        )  # fmt: skip
    assert r.returncode == 1, r.stdout + r.stderr
    assert "FAILED la:1 step: la:1 drew 300 mA (ceiling 200 mA)" in r.stderr
    page = (tmp_path / "report.html").read_text(encoding="utf-8")
    top = page[: page.index("<h2>")]
    assert 'class="verdict failed"' in top and "the run was aborted" in top
    doc = json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))
    assert doc["aborted"].startswith("rig aborted in la:1 step: la:1 drew 300 mA")
