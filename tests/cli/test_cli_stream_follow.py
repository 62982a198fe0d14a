"""``motorbus stream`` checks that the actuators follow: it enables them (or, with
``--no-enable``, finds out that they did not move), reports which did not follow with
exit code 1, and pauses them at the end."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.helpers import cli, json_lines, rx_frames


def write_csv(path: Path, rows: int) -> Path:
    """la:1 and la:2 from 1000 out to 1000 + 3 * rows (10 ms rows)."""
    lines = ["t,1,2"] + [f"{k * 0.01:.2f},{1000 + 3 * k},{1000 + 3 * k}" for k in range(rows)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def last_frame_to(sim: SimProcess, ident: int) -> bytes:
    """The last frame that addressed la:``ident`` (0xF3 entries included), status
    queries aside."""
    last = b""
    query = la.Control(ident, la.ControlAction.QUERY_STATUS).encode()
    for h in rx_frames(sim):
        raw = bytes.fromhex(h)
        if raw == query:
            continue
        if raw[3] == ident or (raw[3] == 0xFF and ident in raw[5:-1:3]):
            last = raw
    return last


def positions(sim: SimProcess) -> list[int]:
    r = cli("la", "status", "1-2", "--json", "--port", sim.path)
    assert r.returncode == 0, r.stderr
    return [d["position"] for d in json_lines(r.stdout)]


def wait_until_at(sim: SimProcess, position: int) -> None:
    """Poll until both actuators report ``position`` (``la move`` returns as the motion
    starts, and the simulated actuators take a while to get there)."""
    deadline = time.monotonic() + 30.0  # a hang guard, not a timing assertion
    while (now := positions(sim)) != [position, position]:
        assert time.monotonic() < deadline, now
        time.sleep(0.05)


def test_stream_enables_estopped_actuators_follows_and_pauses_at_the_end(tmp_path: Path) -> None:
    with SimProcess(["la:1-2"], baud=921600, log_file=tmp_path / "frames.jsonl") as sim:
        assert cli("la", "move", "1", "1000", "--port", sim.path).returncode == 0
        assert cli("la", "move", "2", "1000", "--port", sim.path).returncode == 0
        # E-stopped where the rows start (--ramp 0): a stream that enables them must
        # take both out along the rows.  E-stopped on the way, la:2 could be too far
        # from the rows to get past 1010 in their 0.4 s, enabled or not.
        wait_until_at(sim, 1000)
        assert cli("la", "estop", "1-2", "--port", sim.path).returncode == 0
        csv_file = write_csv(tmp_path / "out.csv", 40)
        r = cli("stream", str(csv_file), "--ramp", "0", "--json", "--port", sim.path)
        summary, *failed = json_lines(r.stdout)
        # The e-stopped actuators were enabled: they moved out along the rows.
        assert all(p > 1000 + 10 for p in positions(sim)), positions(sim)
        assert r.returncode == (0 if summary["skipped"] == 0 else 1), r.stderr
        # Ticks a loaded machine skipped fail the stream: one error object after the summary.
        assert [f["skipped"] for f in failed] == ([summary["skipped"]] if failed else []), r.stdout
        assert bool(failed) == bool(summary["skipped"]), r.stdout
        assert (summary["enabled"], summary["not_following"]) == (True, [])
        for ident in (1, 2):
            assert last_frame_to(sim, ident) == la.Control(ident, la.ControlAction.PAUSE).encode()


def test_stream_no_enable_reports_the_actuator_that_did_not_follow(tmp_path: Path) -> None:
    with SimProcess(["la:1-2"], baud=921600, log_file=tmp_path / "frames.jsonl") as sim:
        assert cli("la", "estop", "2", "--port", sim.path).returncode == 0
        csv_file = write_csv(tmp_path / "out.csv", 300)  # 3 s of rows
        r = cli(
            "stream", str(csv_file), "--ramp", "0.2", "--no-enable", "--json", "--port", sim.path
        )
        assert r.returncode == 1
        summary, error = json_lines(r.stdout)  # the summary, then the failure's object
        assert (summary["enabled"], summary["not_following"]) == (False, [2])
        assert (error["code"], error["command"], error["not_following"]) == (1, "stream", [2])
        assert "did not follow" in error["error"]
        (line,) = [ln for ln in r.stderr.splitlines() if "did not follow" in ln]
        assert line.startswith("motorbus stream: failed: 1 actuator of 2 did not follow (la:2 ")
        assert "paused or e-stopped" in line
        # Stopped once a status showed la:2 still, not after the whole 3 s: la:1 did not
        # go on alone to the end of the rows.
        assert "; stopped at tick " in line
        assert summary["ticks"] < 250
        assert last_frame_to(sim, 1) == la.Control(1, la.ControlAction.PAUSE).encode()
        sent = rx_frames(sim)
        assert len(sent) > 40  # the log is read
        assert not any(h[12:14] == "04" and h[18:20] == "04" for h in sent)  # no "work"


async def test_a_faulted_actuator_is_refused_before_anything_is_sent() -> None:
    from motorbus.cli.main import CommandFailed
    from motorbus.cli.stream import check_actuators
    from motorbus.sim.la import LAModel
    from tests.helpers import sim_bus

    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models) as (bus, _):
        models[1].trigger_fault("stall", bus.timer.now())
        with pytest.raises(CommandFailed, match=r"1 actuator of 2 report a fault \(la:2 stall\)"):
            await check_actuators(bus, [1, 2], 921600)
        assert models[0].received == models[1].received == []  # status queries only


def test_follow_check_names_only_actuators_asked_to_move_that_did_not() -> None:
    from motorbus.cli.stream import FollowCheck

    rows = [(100, 500, 900), (200, 505, 900)]
    check = FollowCheck([1, 2, 3], (100, 500, 900), rows)
    targets = check.source(0.01)
    assert targets(0.0, {}) == rows[0] and targets(0.01, {}) == rows[1]
    assert targets(0.02, {}) is None
    assert check.asked == {1: 100, 2: 5, 3: 0}  # as far as the rows sent asked
    # la:1 was asked to move 100 and did not; la:2 (5) and la:3 (0) were not asked to.
    assert check.not_following({1: 103, 2: 500, 3: 900}) == [1]
    assert check.not_following({1: 150}) == []


def test_follow_check_stops_the_stream_when_a_fresh_status_shows_no_motion() -> None:
    from motorbus.cli.stream import FOLLOW_GRACE_S, FollowCheck
    from motorbus.errors import CommandFailed

    period = 0.01
    rows = [(100 + 5 * k, 500 + 5 * k) for k in range(200)]
    check = FollowCheck([1, 2], (100, 500), rows)
    targets = check.source(period)
    grace = round(FOLLOW_GRACE_S / period)
    still = la.Status(2, target=500, position=500)
    for k in range(grace + 3):  # la:2 asked to move from tick 3; only its status of tick 0
        moving = la.Status(1, target=rows[k][0], position=rows[k][0])
        assert targets(k * period, {1: moving, 2: still}) == rows[k]
    with pytest.raises(CommandFailed, match=r"la:2 did not move 0.5 s after"):
        targets((grace + 3) * period, {2: la.Status(2, target=600, position=500)})
    assert check.stopped_at == grace + 3


def test_without_a_status_in_the_stream_an_actuator_at_its_last_target_followed() -> None:
    from motorbus.cli.stream import FollowCheck

    def play(check: FollowCheck, statuses: dict[int, la.Status]) -> None:
        source, k = check.source(0.02), 0
        while source(k * 0.02, statuses) is not None:
            k += 1

    # A path out and back (368 -> 100 -> 373), no status read during the stream (no
    # poll fitted between the ticks): its end at its last target says nothing against it.
    rows = [(368 - 12 * k,) for k in range(23)] + [(100 + 12 * k,) for k in range(24)]
    check = FollowCheck([1], (368,), rows)
    play(check, {})
    assert check.not_following({1: 375}) == []
    # Ended where it started, far from its last target: it did not follow.
    check = FollowCheck([1], (0,), [(10 * k,) for k in range(40)])
    play(check, {})
    assert check.not_following({1: 0}) == [1]
    # With a status read during the stream, it is judged on what it reported.
    check = FollowCheck([1], (368,), rows[:10])
    play(check, {1: la.Status(1, target=368, position=368)})
    assert check.not_following({1: 368}) == [1]
