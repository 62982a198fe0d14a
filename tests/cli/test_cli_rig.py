"""``motorbus rig`` and ``rig compare`` as a user runs them, against ``motorbus sim`` on a
pty whose actuators have a configured truth (speed, dead time); the report is opened in
a real headless browser when one is installed (CI installs Debian's chromium)."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from motorbus.sim.process import SimProcess
from tests import packaging
from tests.helpers import cli, loaded_bus_file

#: The dead time is long next to the 17 ms the profile takes to leave the noise band, so
#: that a rig that lost it could not pass for one that measured it.
SPEED, DEAD = 1000.0, 0.030
TRUTH = f"stroke_speed={SPEED:g},accel=10000,dead_time={DEAD},position=300"
SLOW = f"stroke_speed={SPEED * 0.8:g},accel=10000,dead_time={DEAD},position=300"
#: How much later than the simulator a loaded host may read a reply (ms).  The rig stamps
#: a sample when its reply is read (docs/rig.md), so a busy CI worker adds to a measured
#: delay: one such run read a 32 ms dead time as 38.9 ms.
READ_LATE_MS = 10.0
#: How much later than the kernel took a target frame a loaded host may stamp its write
#: (ms).  The rig counts from the completed write, read from the clock after ``write()``
#: returns, so a worker preempted in between shortens a measured delay: one run read a
#: 29.3 ms one as 26.7 ms.  A preemption, like a late read.
WRITE_LATE_MS = READ_LATE_MS
#: How far a loaded host's samples may move the speed and the rise time (relative): with
#: eight workers on two CPUs one run read the 1000 units/s actuator as 1059.  The slower
#: actuator of these runs is 20 % off, and a wrong unit or clock much further.
LOADED_REL = 0.10
QUICK = ["--tests", "step,latency,repeat", "--latency-count", "6", "--repeat-count", "2"]


def rig_run(base: Path, name: str, spec: str) -> None:
    with SimProcess([f"la:1,{spec}"], baud=921600) as sim:
        folder = base / f"{name}-bus"
        folder.mkdir()
        buses = loaded_bus_file(folder, sim.path, 921600, ["la:1"])
        r = cli("rig", "1", *QUICK, "--out", str(base / name), "--bus-file", str(buses))
        assert r.returncode == 0, r.stderr


def rig_runs(base: Path) -> None:
    # The two runs side by side, each with its own simulator process and pty: a run is
    # ten seconds of simulated motion that keeps about a third of a core busy (both took
    # 7.6 s of CPU in 10.5 s here), so together they take the time of one.
    with ThreadPoolExecutor(2) as pool:
        for done in [
            pool.submit(rig_run, base, "golden", TRUTH),
            pool.submit(rig_run, base, "slow", SLOW),
        ]:
            done.result()


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Path]]:
    """One rig run on a nominal actuator, one on an actuator 20 % slower; made once for
    every worker that runs these tests (each takes seconds of simulated motion)."""
    base = packaging.built_once(tmp_path_factory, "rig-runs", rig_runs)
    yield {"golden": base / "golden", "slow": base / "slow"}


def figures(folder: Path) -> dict[str, float]:
    doc = json.loads((folder / "results.json").read_text())
    return doc["devices"]["la:1"]


def test_the_rig_recovers_the_configured_truth_over_a_pty(runs: dict[str, Path]) -> None:
    f = figures(runs["golden"])
    assert f["step.speed_units_per_s"] == pytest.approx(SPEED, rel=LOADED_REL)
    # 10 -> 90 % of the 900-unit default step (550 -> 1450), at cruise: 720 units.
    assert f["step.rise_time_ms"] == pytest.approx(720.0, rel=LOADED_REL)
    # Dead time as docs/rig.md defines it: the model's, plus the time its profile takes
    # to leave the 2-unit noise band from rest.  The simulator reports whole units, so
    # the position reads 2 units on once the profile is 1.5 units on:
    # sqrt(2 * 1.5 / accel) = 17.3 ms.
    moved_ms = DEAD * 1e3 + math.sqrt(2 * 1.5 / 10000) * 1e3
    for key in ("step.dead_time_ms", "latency.p50_ms"):
        low, high = moved_ms - WRITE_LATE_MS, moved_ms + READ_LATE_MS
        assert low <= f[key] <= high, (key, f[key], moved_ms)
    for key in (
        "step.overshoot_pct", "step.settling_time_ms", "step.steady_state_error",
        "latency.p99_ms", "repeat.spread", "repeat.backlash",
    ):  # fmt: skip
        assert key in f
    samples = (runs["golden"] / "samples.csv").read_text().splitlines()
    assert samples[0] == "t_s,id,target,position,current_ma,force_g"
    assert len(samples) > 1000


def test_compare_passes_a_run_against_itself_and_flags_a_slower_actuator(
    runs: dict[str, Path],
) -> None:
    same = cli("rig", "compare", str(runs["golden"]), str(runs["golden"]))
    assert same.returncode == 0, same.stdout + same.stderr
    slow = cli("rig", "compare", str(runs["golden"]), str(runs["slow"] / "results.json"))
    assert slow.returncode == 1, slow.stdout
    assert re.search(r"step\.speed_units_per_s .* REGRESSED", slow.stdout)
    assert "regressed beyond tolerance" in slow.stderr


def test_the_report_is_self_contained_and_has_every_part(runs: dict[str, Path]) -> None:
    page = (runs["golden"] / "report.html").read_text()
    # Nothing to fetch: no scripts, stylesheets, images or links to anywhere.
    assert not re.search(r"<script|<link|<img|src=|href=|url\(", page)
    for title in ("Step response", "Latency (dead time) histogram", "Repeatability", "Plan"):
        assert title in page
    assert page.count("<svg") >= 3


@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium is not installed")
def test_the_report_opens_in_a_browser(runs: dict[str, Path]) -> None:
    # A dead proxy: anything the page tried to fetch would fail (and it fetches nothing).
    browser = ["chromium", "--headless", "--no-sandbox", "--disable-gpu"]
    browser += ["--proxy-server=127.0.0.1:9", "--disable-background-networking"]
    dom = subprocess.run(
        [*browser, "--dump-dom", (runs["golden"] / "report.html").as_uri()],
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout
    assert "<h1>motorbus rig report</h1>" in dom
    assert dom.count("<svg") >= 3 and "<polyline" in dom


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["1", "--tests", "step,spin"], "'spin' is not a test"),
        (["1", "--min", "-5"], "min=-5 is out of range"),
        (["1", "--frequencies", "20"], "frequency=20.0 is out of range: allowed 0.01..10 Hz"),
        (["1", "--start", "50"], "step_start=50 is out of range: allowed 100..1900"),
        (["compare", "only-one"], "give two runs"),
    ],
)
def test_bad_plans_are_refused_before_the_port_opens(args: list[str], message: str) -> None:
    r = cli("rig", *args, "--out", "/nonexistent/x", "--port", "/dev/nonexistent-port")
    assert r.returncode == 2, r.stderr
    assert message in r.stderr


def test_rig_quad_times_runs_against_the_simulator() -> None:
    with SimProcess(["quad-stepper"], baud=9600) as sim:
        config = cli(
            "quad", "config", "2", "--subdivision", "8", "--pulses", "1600", "--start-hz", "50",
            "--accel", "0", "--rpm", "600", "--port", sim.path,
        )  # fmt: skip
        assert config.returncode == 0, config.stderr
        r = cli("rig", "quad", "2", "--runs", "3", "--json", "--port", sim.path)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["what"] == "quad motor 2" and doc["runs"] == 3
    # 1600 pulses at 16,000 pulses/s = 100 ms, plus the frames on a 9600 bit/s wire (about
    # 116 ms in all here).  A loaded run reads the done reply late (over 200 ms seen with
    # six workers), and can stamp the start late too (the start is the bus's clock read
    # just after the write returns): a suite run beside other load read 99 ms once.  A
    # timed-out wait would take seconds; a run not waited for, almost nothing.
    assert all(50.0 < t < 300.0 for t in doc["times_ms"]), doc["times_ms"]


def test_rig_project_needs_one_number() -> None:
    r = cli("rig", "project", "--port", "/dev/nonexistent-port")
    assert r.returncode == 2
    assert "give one project number 1..4" in r.stderr
