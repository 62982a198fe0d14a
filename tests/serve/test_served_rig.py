"""``motorbus rig --connect`` runs the tracking test: its sine streams through the server
(the server ticks) under the rig's lease, and its figures match the local rig's on the
same simulator.  The rig, the server and the simulators are separate processes; the
simulator's own record is the judge of what reached the actuators.  Assertions are on
figures against the local rig's (with tolerances a broken run cannot meet), order and
counts, never on speed."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("zenoh")

from motorbus.protocol import la
from motorbus.sim import SimProcess
from tests.serve.conftest import Child
from tests.zygote import run_motorbus

#: The sine frequencies of these runs (Hz): one the simulated actuator follows (ratio
#: ~1), one it cannot (ratio ~0.45, phase ~-60 degrees): both are told apart from a run
#: whose targets were misplaced in time or never arrived.
FREQUENCIES = "0.5,2"
#: Served against local, per frequency: at most this far apart.  A served run whose
#: targets were stamped when published (the 0.5 s lead early) is 90 degrees off at
#: 0.5 Hz; one whose targets never reached the actuator has a ratio near 0.  (The lag
#: is not compared: on a loaded machine the local run's own skipped ticks move it by
#: tens of ms at 0.5 Hz, where the phase moves by a few degrees.)
RATIO_TOLERANCE = 0.1
#: A loaded run's late-read samples move one run's phase against the other's (12.9
#: degrees at 2 Hz seen with six workers); the early stamping above is 90 off at 0.5 Hz.
PHASE_TOLERANCE_DEG = 20.0


def rig(*args: str) -> subprocess.CompletedProcess[str]:
    return run_motorbus(["rig", *args], timeout=300)


def results(out: Path) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads((out / "results.json").read_text(encoding="utf-8"))
    return doc


def responses(doc: dict[str, Any], device: str) -> dict[float, tuple[float, float, float]]:
    """Per frequency: (amplitude ratio, phase in degrees, lag in ms) of one actuator."""
    out = {}
    for track in doc["details"][device]["tracks"]:
        r = track["response"]
        out[r["frequency_hz"]] = (r["amplitude_ratio"], r["phase_deg"], track["lag_ms"])
    return out


def requests(sim: SimProcess) -> list[Any]:
    """Every frame the simulator received, decoded, in order."""
    return [
        la.decode_request(bytes.fromhex(r["hex"]))
        for r in sim.log_records()
        if r["direction"] == "request" and r["kind"] == "frame"
    ]


def streams_to(sent: list[Any], ident: int) -> list[tuple[list[int], Any]]:
    """Each run of broadcast frames carrying a target for ``ident``: its targets, and
    the next frame addressed to ``ident`` after it (status queries left out)."""
    out: list[tuple[list[int], Any]] = []
    run: list[int] = []
    for frame in sent:
        if isinstance(frame, la.Broadcast):
            run.extend(p for i, p in frame.entries if i == ident)
            continue
        if getattr(frame, "id", None) != ident:
            continue
        if isinstance(frame, la.Control) and frame.action is la.ControlAction.QUERY_STATUS:
            continue
        if run:
            out.append((run, frame))
            run = []
    if run:
        out.append((run, None))
    return out


def assert_the_sines_arrived_and_each_ended_with_a_pause(
    sim: SimProcess, plan: dict[str, Any], ids: tuple[int, ...]
) -> None:
    period = plan["period_s"]
    center = (plan["window"][0] + plan["window"][1]) // 2
    amplitude = plan["amplitude"]
    pause = {i: la.Control(i, la.ControlAction.PAUSE) for i in ids}
    sent = requests(sim)
    for ident in ids:
        runs = streams_to(sent, ident)
        # One stream per frequency (more only if a disturbed one was run again).
        assert len(runs) >= len(plan["frequencies_hz"]), (ident, len(runs))
        for _, after in runs:
            assert after == pause[ident], (ident, after)  # the stream's safe action
        for f in plan["frequencies_hz"]:
            # Its figures came from a run in which at least 95 % of the sine's ticks
            # were written (the rig runs one that lost more again; a skipped tick is
            # not written) and the targets swept the amplitude.
            ticks = round(max(plan["cycles"] / f, 1.0) / period) + 1
            whole = [t for t, _ in runs if 0.95 * ticks <= len(t) <= ticks]
            assert whole, (ident, f, [len(t) for t, _ in runs])
            # The ticks a loaded server skipped may all fall about a peak of the sine
            # (seen once in a fresh-clone CI run): it then reaches the peak's value at the
            # last tick written before them or the first after.
            assert any(
                min(t) <= center - amplitude + _reach(amplitude, f, period, ticks - len(t))
                and max(t) >= center + amplitude - _reach(amplitude, f, period, ticks - len(t))
                for t in whole
            ), (ident, f, [(min(t), max(t), len(t)) for t in whole], center, amplitude)


def _reach(amplitude: float, f: float, period: float, skipped: int) -> float:
    """How far short of a peak a sine of ``amplitude`` and ``f`` Hz on ticks of ``period``
    can stay when ``skipped`` ticks are missing about it (and 2 of rounding)."""
    return amplitude * (1 - math.cos(math.pi * f * (skipped + 1) * period)) + 2


def test_rig_connect_tracks_as_the_local_rig_does_on_the_same_simulator(
    la_sim: SimProcess, la_server: Child, endpoint: str, tmp_path: Path
) -> None:
    # One actuator (the other test tracks the first): each actuator's tracking runs
    # alone, one after the other, so a second one only doubled this test's time.
    served, local = tmp_path / "served", tmp_path / "local"
    common = ("2", "--tests", "track", "--frequencies", FREQUENCIES, "--cycles", "1")
    out = rig(*common, "--connect", endpoint, "--out", str(served))
    assert out.returncode == 0, out.stderr[-3000:]
    with SimProcess(["la:1-2"], baud=921600) as sim:
        ran = rig(*common, "--port", sim.path, "--baud", "921600", "--out", str(local))
    assert ran.returncode == 0, ran.stderr[-3000:]

    served_doc, local_doc = results(served), results(local)
    assert served_doc["passed"] and not served_doc["failures"]
    for device in ("la:2",):
        figures = served_doc["devices"][device]
        assert {"track.rms_error", "track.max_error", "track.lag_ms"} <= set(figures)
        assert all(v is not None for v in figures.values()), figures
        mine, theirs = responses(served_doc, device), responses(local_doc, device)
        assert set(mine) == set(theirs) == {0.5, 2.0}
        for f, (ratio, phase, lag) in mine.items():
            l_ratio, l_phase, _ = theirs[f]
            about = (device, f, mine[f], theirs[f])
            assert abs(ratio - l_ratio) <= RATIO_TOLERANCE, about
            assert abs(phase - l_phase) <= PHASE_TOLERANCE_DEG, about
            # Found inside the search window (0 to 0.5 s); at 0.5 Hz the simulated
            # actuator lags by a few ms, which a loaded run's timing can bring to 0.
            assert 0 <= lag < 500, about
    assert_the_sines_arrived_and_each_ended_with_a_pause(la_sim, served_doc["plan"], (2,))
    # The rig's lease ended with its pause, and nothing after it but status queries (a
    # poll of the rig's written behind it, seen once); nothing moved actuator 1.
    sent = requests(la_sim)
    pause = la.Control(2, la.ControlAction.PAUSE)
    query = la.Control(2, la.ControlAction.QUERY_STATUS)
    last = max(n for n, f in enumerate(sent) if f == pause)
    assert all(f in (pause, query) for f in sent[last + 1 :]), sent[last:]
    to_1 = [f for f in sent if getattr(f, "id", None) == 1 or 1 in dict(getattr(f, "entries", ()))]
    assert not [f for f in to_1 if f.starts_motion], to_1

    # The report renders the served figures: the tracking plot and the Bode table of
    # each actuator, and the targets beside the samples in samples.csv.
    html = (served / "report.html").read_text(encoding="utf-8")
    assert html.count('aria-label="Tracking at 2 Hz (its last stretch)"') == 1
    assert html.count('aria-label="Bode: gain"') == 1
    rows = (served / "samples.csv").read_text(encoding="utf-8").splitlines()
    header = rows[0].split(",")
    ident, target = header.index("id"), header.index("target")
    for n in (2,):
        streamed = [r for r in rows[1:] if r.split(",")[ident] == str(n) and r.split(",")[target]]
        assert len(streamed) >= 0.95 * (201 + 101), (n, len(streamed))


def test_rig_connect_all_runs_track_with_the_others(
    la_sim: SimProcess, la_server: Child, endpoint: str, tmp_path: Path
) -> None:
    out = rig(
        "1", "--connect", endpoint, "--tests", "all", "--frequencies", "2",
        "--latency-count", "3", "--repeat-count", "1", "--out", str(tmp_path),
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    assert "not run" not in out.stderr
    doc = results(tmp_path)
    assert doc["plan"]["tests"] == ["step", "track", "latency", "repeat"]
    figures = doc["devices"]["la:1"]
    for name in ("step.rise_time_ms", "track.lag_ms", "latency.p50_ms", "repeat.spread"):
        assert figures[name] is not None, (name, figures)
    ratio = responses(doc, "la:1")[2.0][0]
    assert 0.2 < ratio < 0.8, ratio  # the simulated actuator's ~0.45 at 2 Hz
    assert_the_sines_arrived_and_each_ended_with_a_pause(la_sim, doc["plan"], (1,))
    assert 'aria-label="Bode: gain"' in (tmp_path / "report.html").read_text(encoding="utf-8")
