"""The dashboard's pure model: observations in, JSON snapshots and deltas out (no asyncio)."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.bus.events import BusStateChanged, FaultChanged, ProjectFinished, QuadDone
from motorbus.dashboard.runtime import json_pieces
from motorbus.dashboard.state import (
    REPLY_EDGES_MS,
    WINDOW_S,
    DashboardState,
    error_names,
    with_columns,
)
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as quad
from motorbus.sim.project_stepper import ProjectStepperModel

QUERY = la.ControlAction.QUERY_STATUS


def status(ident: int, position: int, *, target: int = 1000, errors: int = 0) -> la.Status:
    return la.Status(ident, target, position, temperature=31, current=120, force=-40, errors=errors)


def poll(
    state: DashboardState, t: float, ident: int, position: int, reply_s: float = 0.001, **kw: int
) -> None:
    """One status poll as the bus's observer reports it: the write, then the reply."""
    cmd = la.Control(ident, QUERY)
    state.on_write("arm", cmd, t)
    state.on_reply("arm", cmd, status(ident, position, **kw), t, t + reply_s)


@pytest.fixture
def state() -> DashboardState:
    s = DashboardState(period=0.1)
    s.add_bus("arm", la_ids=[1, 2])
    return s


def test_a_full_snapshot_has_every_sample_of_the_window_and_is_json(state: DashboardState) -> None:
    for k in range(5):
        poll(state, 100.0 + k * 0.1, 1, 10 * k)
    snap = json.loads(json.dumps(state.snapshot()))
    assert snap["type"] == "full"
    (bus,) = snap["buses"]
    one, two = bus["la"]
    assert one["id"] == 1 and two["id"] == 2
    assert one["series"]["position"] == [0, 10, 20, 30, 40]
    assert one["series"]["t"] == pytest.approx([0.001, 0.101, 0.201, 0.301, 0.401])
    assert one["series"]["target"] == [1000] * 5
    assert one["latest"] == {
        "position": 40, "target": 1000, "current": 120, "force": -40, "temperature": 31
    }  # fmt: skip
    assert two["latest"] is None and two["series"]["t"] == []


def test_a_snapshot_taken_as_rows_renders_to_the_same_json_and_keeps_its_moment(
    state: DashboardState,
) -> None:
    # The viewers' snapshot is copied where the state lives and rendered on another
    # thread (runtime.ViewerSnapshot): the same JSON, and blind to later samples.
    for k in range(5):
        poll(state, 100.0 + k * 0.1, 1, 10 * k)
    rows = state.snapshot(columns=False)
    expected = json.dumps(state.snapshot())
    poll(state, 100.5, 1, 50)  # after the copy: not in it
    assert json.dumps(with_columns(rows, state.epoch)) == expected
    state.add_bus("feeder", la_ids=[], project_stepper=True)
    rows = state.snapshot(columns=False)
    state.on_write("feeder", ps.StartProject(2), 101.0)  # the project dict changes
    assert rows["buses"][1]["project"]["running"] is None  # the copy does not
    assert json.loads(expected)["buses"][0]["la"][0]["series"]["position"][-1] == 40


def test_a_delta_carries_only_the_samples_since_the_previous_snapshot(
    state: DashboardState,
) -> None:
    poll(state, 1.0, 1, 5)
    poll(state, 1.1, 2, 6)
    first = state.snapshot()
    poll(state, 1.2, 1, 7)
    delta = state.snapshot(since=first["seq"])
    assert delta["type"] == "delta"
    one, two = delta["buses"][0]["la"]
    assert one["series"]["position"] == [7]
    assert two["series"]["position"] == []
    assert one["latest"]["position"] == 7  # the scalars are always whole


def test_samples_older_than_the_window_are_dropped(state: DashboardState) -> None:
    poll(state, 0.0, 1, 1)
    poll(state, 1.0, 1, 2)
    poll(state, WINDOW_S + 0.5, 1, 3)  # the window now starts at 0.5 s
    assert state.snapshot()["buses"][0]["la"][0]["series"]["position"] == [2, 3]


def test_frames_per_second_and_the_smallest_write_gap(state: DashboardState) -> None:
    for k in range(30):
        state.on_write("arm", la.Control(1, QUERY), 10.0 + k * 0.05)  # 20 frames/s
    bus = state.snapshot()["buses"][0]
    assert bus["frames_per_s"] == 21  # the 21 writes of the last second, both ends in
    assert bus["min_write_gap_ms"] == pytest.approx(50.0)
    state.on_write("arm", la.Control(2, QUERY), 10.0 + 29 * 0.05 + 0.0012)
    assert state.snapshot()["buses"][0]["min_write_gap_ms"] == pytest.approx(1.2)
    state.advance(12.0)  # the bus went silent: the rate falls as its clock moves on
    assert state.snapshot()["buses"][0]["frames_per_s"] == 11  # 11.0 .. 11.45 s
    state.advance(13.0)
    assert state.snapshot()["buses"][0]["frames_per_s"] == 0


def test_reply_times_fall_in_their_buckets(state: DashboardState) -> None:
    for reply_s in (0.0002, 0.0009, 0.001, 0.003, 0.5):
        poll(state, 1.0, 1, 0, reply_s=reply_s)
    hist = state.snapshot()["buses"][0]["reply_hist"]
    assert hist["edges_ms"][-1] is None and len(hist["counts"]) == len(REPLY_EDGES_MS)
    by_edge = dict(zip(hist["edges_ms"], hist["counts"], strict=True))
    assert by_edge[0.25] == 1 and by_edge[1.0] == 2 and by_edge[4.0] == 1 and by_edge[None] == 1
    assert sum(hist["counts"]) == 5


def test_poll_jitter_counts_the_distance_from_the_period(state: DashboardState) -> None:
    poll(state, 1.0, 1, 0, reply_s=0)
    poll(state, 1.1, 1, 0, reply_s=0)  # on time
    poll(state, 1.23, 1, 0, reply_s=0)  # 30 ms late
    hist = state.snapshot()["buses"][0]["la"][0]["jitter_hist"]
    by_edge = dict(zip(hist["edges_ms"], hist["counts"], strict=True))
    assert by_edge[0.1] == 1 and by_edge[50.0] == 1 and sum(hist["counts"]) == 2


def test_the_mode_follows_the_control_frames_the_bus_wrote(state: DashboardState) -> None:
    def mode() -> str:
        return str(state.snapshot()["buses"][0]["la"][0]["mode"])

    assert mode() == "unknown"
    state.on_write("arm", la.Control(1, la.ControlAction.ESTOP), 1.0)
    assert mode() == "estop"
    state.on_write("arm", la.Control(1, la.ControlAction.WORK), 1.1)
    assert mode() == "work"
    state.on_write("arm", la.Control(1, la.ControlAction.PAUSE), 1.2)
    assert mode() == "pause"
    state.on_write("arm", la.MoveTo(1, 500), 1.3)  # a position command resumes a pause
    assert mode() == "work"
    state.on_write("arm", la.Control(1, QUERY), 1.4)  # a status query changes nothing
    assert mode() == "work"


def test_fault_bits_are_named_from_replies_and_events(state: DashboardState) -> None:
    assert error_names(0) == []
    assert error_names(int(la.ErrorFlags.STALL | la.ErrorFlags.OVER_TEMPERATURE)) == [
        "STALL", "OVER_TEMPERATURE"
    ]  # fmt: skip
    assert error_names(0x30) == ["bit4", "bit5"]
    poll(state, 1.0, 2, 0, errors=int(la.ErrorFlags.OVER_CURRENT))
    assert state.snapshot()["buses"][0]["la"][1]["errors"] == ["OVER_CURRENT"]
    state.on_event(FaultChanged("arm", 2.0, 1, 0, int(la.ErrorFlags.STALL), None))
    bus = state.snapshot()["buses"][0]
    assert bus["la"][0]["errors"] == ["STALL"]
    assert bus["events"][-1]["text"] == "la:1 faults: STALL"
    assert bus["events"][-1]["errors"] == ["STALL"]


def test_bus_state_and_stepper_events(state: DashboardState) -> None:
    state.add_bus("feeder", project_stepper=True, quad_stepper=True)
    state.on_event(BusStateChanged("feeder", 1.0, "lost", "port closed"))
    state.on_write("feeder", ps.StartProject(2), 1.5)
    feeder = state.snapshot()["buses"][1]
    assert feeder["state"] == "lost" and feeder["project"]["running"] == 2
    state.on_event(BusStateChanged("feeder", 2.0, "open", "reconnected"))
    state.on_event(ProjectFinished("feeder", 3.0))
    state.on_write("feeder", quad.Run(motor=3), 3.5)
    state.on_event(QuadDone("feeder", 4.0, "run", 0, None, b""))
    feeder = state.snapshot()["buses"][1]
    assert feeder["state"] == "open"
    assert feeder["project"]["running"] is None
    assert feeder["project"]["last_ee_dd"] == pytest.approx(2.0)  # 3.0 - epoch 1.0
    assert feeder["quad"]["axes"]["3"]["last_command"] == "Run"
    assert feeder["quad"]["last_done"]["kind"] == "run"
    texts = [e["text"] for e in feeder["events"]]
    assert texts[0] == "bus lost (port closed)" and "EE DD" in texts[2]


def test_a_project_dump_lists_the_project(state: DashboardState) -> None:
    state.add_bus("feeder", project_stepper=True)
    cmd = ps.ReadProject(3)
    dump = ps.ProjectDump.decode(_cleared_dump(3))
    state.on_reply("feeder", cmd, dump, 1.0, 1.01)
    assert state.snapshot()["buses"][1]["project"]["projects"]["3"]["steps"] == 0


def _cleared_dump(project: int) -> bytes:
    (reply,) = ProjectStepperModel().handle(ps.ReadProject(project).encode(), 0.0)
    return reply


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(), inner, max_size=4),
    max_leaves=30,
)


@given(json_values)
def test_a_snapshot_in_pieces_is_the_same_json(value: object) -> None:
    assert "".join(json_pieces(value)) == json.dumps(value, separators=(",", ":"))
