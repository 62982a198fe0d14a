"""The lease table, without an event loop: owners, take-overs, what is owed, what a
release returns (``motorbus.bus.leases``, ``motorbus.protocol.safety``)."""

from __future__ import annotations

import gc
import sys
from collections.abc import Callable

import pytest

from motorbus.bus.leases import PROGRAM, LeaseInfo, LeaseTable
from motorbus.errors import LeaseConflictError, LocalProtocolError
from motorbus.protocol import la, safety
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Command


def pause_for(key: str) -> tuple[Command[object], ...]:
    return safety.safe_stop_commands(key, "pause")


def estop_for(key: str) -> tuple[Command[object], ...]:
    return safety.safe_stop_commands(key, "estop")


def program(table: LeaseTable) -> object:
    return table.implicit(pause_for, "pause")


def test_a_second_owner_is_refused_and_nothing_changes() -> None:
    table = LeaseTable()
    first = table.acquire("stream", ["la:1", "la:2"], pause_for)
    with pytest.raises(LeaseConflictError) as info:
        table.acquire("rig", ["la:3", "la:2"], pause_for)
    err = info.value
    assert (err.key, err.owner, err.refused) == ("la:2", "stream", "rig")
    assert "la:2" in str(err) and "'stream'" in str(err) and "'rig'" in str(err)
    assert table.owner_of("la:3") is None  # the refused lease took nothing
    assert first.keys == {"la:1", "la:2"}


def test_motion_outside_any_lease_is_refused_on_a_leased_device() -> None:
    table = LeaseTable()
    table.acquire("stream", ["la:1"], pause_for)
    implicit = table.implicit(pause_for, "pause")
    with pytest.raises(LeaseConflictError) as info:
        table.claim(["la:4", "la:1"], implicit)
    assert (info.value.owner, info.value.refused) == ("stream", PROGRAM)
    assert table.owner_of("la:4") is None


def test_motion_outside_any_lease_gets_the_implicit_lease() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    assert table.claim(["la:3"], implicit) is True
    assert table.claim(["la:3"], implicit) is False  # already held: no change
    assert table.owner_of("la:3") == PROGRAM
    assert table.snapshot() == (
        LeaseInfo("la:3", PROGRAM, (la.Control(3, la.ControlAction.PAUSE).encode(),)),
    )


def test_an_explicit_lease_takes_devices_over_from_the_implicit_one() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    table.claim(["la:1", "la:2"], implicit)
    lease = table.acquire("stream", ["la:1"], estop_for, safe_action="estop")
    assert table.owner_of("la:1") == "stream"
    assert table.owner_of("la:2") == PROGRAM
    # Still owed (it moved), now with the new owner's action.
    assert table.owed("la:1") == (la.Control(1, la.ControlAction.ESTOP),)
    assert table.release(lease, hold=False) == [la.Control(1, la.ControlAction.ESTOP)]
    assert table.owner_of("la:1") is None


def calls_in(fn: Callable[[], object]) -> int:
    """Python and C function calls made while running ``fn()``."""
    count = [0]

    def profile(frame: object, event: str, arg: object) -> None:
        if event in ("call", "c_call"):
            count[0] += 1

    collecting = gc.isenabled()
    gc.disable()
    sys.setprofile(profile)
    try:
        fn()
    finally:
        sys.setprofile(None)
        if collecting:
            gc.enable()
    return count[0]


def test_a_status_read_between_ticks_leaves_the_next_tick_a_no_op() -> None:
    """A status read pays nothing owed, so it changes nothing: the next tick's motion
    is still the remembered one (before, every read made each tick redo the work for
    each of its devices: a stream with a status poll a tick, as a rig or a dashboard
    runs, paid for it every tick)."""
    table = LeaseTable()
    ids = range(1, 16)
    lease = table.acquire("stream", [f"la:{i}" for i in ids], pause_for)
    frame = la.Broadcast(la.BroadcastMode.FOLLOW, tuple((i, 500) for i in ids))
    table.moved(frame)
    # The fewest of a few tries: the suite's other threads and collector can add calls.
    quiet = min(calls_in(lambda: table.moved(frame)) for _ in range(5))  # nothing between
    owed = table.owed("la:3")
    after_read = []
    for _ in range(5):
        table.sent(la.Control(3, la.ControlAction.QUERY_STATUS))
        assert table.owed("la:3") is owed  # not even a copy
        after_read.append(calls_in(lambda: table.moved(frame)))
    assert min(after_read) == quiet, (after_read, quiet)
    table.sent(la.Control(3, la.ControlAction.PAUSE))  # a stop does pay: owed again next
    assert table.owed("la:3") == ()
    table.moved(frame)
    assert table.owed("la:3") == (la.Control(3, la.ControlAction.PAUSE),)
    assert table.release(lease, hold=True) == []


def test_release_with_hold_returns_nothing_and_frees_the_devices() -> None:
    table = LeaseTable()
    lease = table.acquire("rig", ["la:1", "quad_stepper"], pause_for)
    assert table.release(lease, hold=True) == []
    assert not lease.active
    assert table.snapshot() == ()
    again = table.acquire("other", ["la:1"], pause_for)  # free for the next owner
    assert again.keys == {"la:1"}


def test_a_safe_action_sent_since_the_last_motion_is_not_owed_again() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    table.claim(["la:1", "la:2"], implicit)
    table.moved(la.Broadcast(la.BroadcastMode.POSITION, ((1, 500), (2, 600))))
    table.sent(la.Control(1, la.ControlAction.PAUSE))
    assert table.owed("la:1") == ()
    table.sent(la.Control(2, la.ControlAction.QUERY_STATUS))  # not a stop
    assert table.owed("la:2") == (la.Control(2, la.ControlAction.PAUSE),)
    assert table.release(implicit, hold=False) == [la.Control(2, la.ControlAction.PAUSE)]


def test_motion_after_the_safe_action_owes_it_again() -> None:
    table = LeaseTable()
    lease = table.acquire("rig", ["la:1"], pause_for)
    table.sent(la.Control(1, la.ControlAction.PAUSE))
    table.moved(la.MoveTo(1, 500))
    assert table.release(lease, hold=False) == [la.Control(1, la.ControlAction.PAUSE)]


def test_an_estop_covers_a_pause_but_a_pause_never_covers_an_estop() -> None:
    table = LeaseTable()
    paused = table.acquire("a", ["la:1"], pause_for)
    stopped = table.acquire("b", ["la:2"], estop_for, safe_action="estop")
    table.sent(la.Control(1, la.ControlAction.ESTOP))
    table.sent(la.Control(2, la.ControlAction.PAUSE))
    assert table.release(paused, hold=False) == []
    assert table.release(stopped, hold=False) == [la.Control(2, la.ControlAction.ESTOP)]


def test_a_control_frame_to_every_actuator_covers_each() -> None:
    table = LeaseTable()
    lease = table.acquire("a", ["la:1", "la:2"], pause_for)
    table.sent(la.Control(la.BROADCAST_ID, la.ControlAction.PAUSE))
    assert table.release(lease, hold=False) == []


def test_steppers_owe_every_stop_command_until_each_was_sent() -> None:
    table = LeaseTable()
    lease = table.acquire("rig", ["project_stepper", "quad_stepper"], pause_for)
    table.sent(ps.StopProject())
    table.sent(q.Stop(1))  # one motor: not stop all
    assert table.release(lease, hold=False) == [
        q.StopAll(),  # device by device, shorter keys first (la:2 before la:10)
        ps.ManualStop(motor=ps.DEFAULT_MOTOR),
    ]


def test_broadcast_motion_names_each_actuator() -> None:
    frame = la.Broadcast(la.BroadcastMode.FOLLOW, ((4, 100), (7, 200)))
    assert safety.motion_keys(frame) == ("la:4", "la:7")
    table = LeaseTable()
    table.acquire("stream", ["la:7"], pause_for)
    with pytest.raises(LeaseConflictError) as info:
        table.claim(safety.motion_keys(frame), program(table))  # type: ignore[arg-type]
    assert info.value.key == "la:7"


def test_id_255_stands_for_every_actuator_the_bus_addressed() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    assert table.expand(["la:255"]) == ("la:255",)  # none addressed yet: itself
    table.claim(safety.motion_keys(la.MoveTo(255, 500, False)), implicit)
    table.moved(la.MoveTo(255, 500, False))
    assert table.release(implicit, hold=False) == [la.Control(255, la.ControlAction.PAUSE)]
    for key in ("la:2", "la:10", "la:1"):
        table.note(key)
    assert table.expand(["la:255"]) == ("la:1", "la:2", "la:10")
    table.acquire("stream", ["la:10"], pause_for)
    with pytest.raises(LeaseConflictError):
        table.claim(["la:255"], table.implicit(pause_for, "pause"))


def test_release_keys_ends_the_implicit_lease_on_those_keys_only() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    table.claim(["la:1", "la:2"], implicit)
    assert table.release_keys(["la:1"], hold=True) == []
    assert table.owner_of("la:1") is None and table.owner_of("la:2") == PROGRAM
    table.acquire("stream", ["la:3"], pause_for)
    with pytest.raises(LeaseConflictError):
        table.release_keys(["la:3"], hold=False)


def test_listeners_see_every_change_and_no_non_change() -> None:
    table = LeaseTable()
    seen: list[tuple[LeaseInfo, ...]] = []
    table.add_listener(seen.append)
    lease = table.acquire("rig", ["quad_stepper"], pause_for)
    table.claim(["quad_stepper"], lease)  # already its own: nothing new
    table.release(lease, hold=False)
    assert seen == [
        (LeaseInfo("quad_stepper", "rig", (q.StopAll().encode(),)),),
        (),
    ]
    table.remove_listener(seen.append)
    table.acquire("rig", ["quad_stepper"], pause_for)
    assert len(seen) == 2


def test_the_project_steppers_motor_comes_from_its_motion() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    table.claim(["project_stepper"], implicit)
    table.moved(ps.JogForward(motor=5))
    table.set_safe("project_stepper", safety.safe_stop_commands("project_stepper", motor=5))
    assert table.snapshot()[0].safe_frames == (
        ps.StopProject().encode(),
        ps.ManualStop(motor=5).encode(),
    )
    assert table.release(implicit, hold=False) == [ps.ManualStop(motor=5)]


def test_motion_outside_a_lease_owes_what_ends_that_motion_only() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    table.claim(["la:1"], implicit)
    assert table.owed("la:1") == ()  # claimed, not yet written: nothing moved
    table.claim(["project_stepper", "quad_stepper"], implicit)
    table.moved(ps.StartProject(1))
    table.moved(q.Run(2))
    table.moved(q.Run(3))
    assert table.owed("project_stepper") == (ps.StopProject(),)
    assert table.owed("quad_stepper") == (q.Stop(2), q.Stop(3))
    table.sent(q.Stop(2))
    assert table.owed("quad_stepper") == (q.Stop(3),)
    table.sent(q.StopAll())  # covers every motor's stop
    table.sent(safety.AT_REST_AFTER_PROJECT_END)  # the project's EE DD
    assert table.release(implicit, hold=False) == []


def test_a_quad_runs_done_reply_pays_its_stop() -> None:
    table = LeaseTable()
    implicit = table.implicit(pause_for, "pause")
    table.claim(["quad_stepper"], implicit)
    table.moved(q.Run(1))
    rest = safety.at_rest_after_done(q.Run(1))
    assert rest == q.Stop(1)
    table.sent(rest)
    assert table.release(implicit, hold=False) == []
    assert safety.at_rest_after_done(q.RunAll()) is None


@pytest.mark.parametrize(
    ("owner", "keys", "field"),
    [
        ("", ["la:1"], "owner"),
        (PROGRAM, ["la:1"], "owner"),
        (3, ["la:1"], "owner"),
        ("rig", [], "keys"),
        ("rig", ["la:0"], "key"),
        ("rig", ["la:256"], "key"),
        ("rig", ["la:x"], "key"),
        ("rig", ["stepper"], "key"),
        ("rig", [3], "key"),
    ],
)
def test_bad_owners_and_keys_are_refused_by_name(
    owner: object, keys: list[object], field: str
) -> None:
    table = LeaseTable()
    with pytest.raises(LocalProtocolError) as info:
        table.acquire(owner, keys, pause_for)  # type: ignore[arg-type]
    assert info.value.field == field
    assert table.snapshot() == ()


def test_safe_actions_are_checked_by_name() -> None:
    with pytest.raises(LocalProtocolError, match="choose pause, estop, hold") as info:
        safety.safe_stop_commands("la:1", "stop")
    assert info.value.field == "action"
    assert safety.safe_stop_commands("la:1", "hold") == ()
    assert safety.safe_stop_commands("quad_stepper", "estop") == (q.StopAll(),)


def test_a_lease_grows_and_lets_devices_go_one_group_at_a_time() -> None:
    # A streamer's one lease: each new stream adds its actuators, each ended stream
    # lets its own go, with its safe action or with hold.
    table = LeaseTable()
    lease = table.acquire("streams", ["la:1"], pause_for)
    table.add(lease, ["la:2", "la:3"])
    table.acquire("rig", ["la:9"], pause_for)
    with pytest.raises(LeaseConflictError):
        table.add(lease, ["la:4", "la:9"])
    assert table.owner_of("la:4") is None
    assert table.release(lease, hold=False, keys=["la:2"]) == [
        la.Control(2, la.ControlAction.PAUSE)
    ]
    assert table.release(lease, hold=True, keys=["la:3"]) == []
    assert lease.active and lease.keys == {"la:1"}
    assert table.release(lease, hold=False) == [la.Control(1, la.ControlAction.PAUSE)]
    assert not lease.active
    with pytest.raises(LocalProtocolError):
        table.add(lease, ["la:5"])


def test_own_safe_commands_replace_the_action_for_their_device_only() -> None:
    """A project upload's lease: the clear of its project, owed from the start, paid
    when the clear is written and answered, shown to a guard; the other devices keep
    the lease's safe action."""
    table = LeaseTable()
    clear = ps.ClearProject(2)
    lease = table.acquire(
        "upload project 2", ["project_stepper", "la:1"], pause_for, safe_commands=[clear]
    )
    assert lease.own_safe == {"project_stepper"}
    assert table.snapshot() == (
        LeaseInfo("la:1", "upload project 2", (la.Control(1, la.ControlAction.PAUSE).encode(),)),
        LeaseInfo("project_stepper", "upload project 2", (clear.encode(),)),
    )
    assert table.owed("project_stepper") == (clear,)
    table.sent(ps.SelectProject(2, 1))  # an upload frame pays nothing
    table.sent(ps.ClearProject(3))  # nor does another project's clear
    assert table.owed("project_stepper") == (clear,)
    table.sent(clear)
    assert table.owed("project_stepper") == ()
    assert table.release(lease, hold=False) == [la.Control(1, la.ControlAction.PAUSE)]


def test_own_safe_commands_are_owed_until_the_lease_ends_and_hold_drops_them() -> None:
    table = LeaseTable()
    clear = ps.ClearProject(1)
    lease = table.acquire("upload project 1", ["project_stepper"], pause_for, safe_commands=[clear])
    assert table.release(lease, hold=False) == [clear]
    lease = table.acquire("upload project 1", ["project_stepper"], pause_for, safe_commands=[clear])
    assert table.release(lease, hold=True) == []
    assert table.snapshot() == ()


@pytest.mark.parametrize(
    ("commands", "message"),
    [
        (["FF AA 1E"], "is not a motorbus Command"),
        ([ps.StartProject(1)], "StartProject starts motion"),
        ([la.Control(2, la.ControlAction.PAUSE)], "addresses la:2, which the lease does not hold"),
        ([la.Control(255, la.ControlAction.PAUSE)], "addresses la:255 .every device"),
    ],
)
def test_bad_own_safe_commands_are_refused_and_nothing_is_held(
    commands: list[object], message: str
) -> None:
    table = LeaseTable()
    with pytest.raises(LocalProtocolError, match=message) as info:
        table.acquire("rig", ["la:1"], pause_for, safe_commands=commands)  # type: ignore[arg-type]
    assert info.value.field == "safe_commands"
    assert table.snapshot() == ()


def test_the_same_motion_every_tick_owes_again_whatever_changed_in_between() -> None:
    """The table remembers a claim and a motion that changed nothing, so a stream's
    ticks skip the per-device work (issue 40); anything in between still counts."""
    table = LeaseTable()
    lease = table.acquire("stream", ["la:1", "la:2"], pause_for)
    keys = ("la:1", "la:2")
    frame = la.Broadcast(la.BroadcastMode.FOLLOW, ((1, 500), (2, 600)))
    pause1, pause2 = (la.Control(i, la.ControlAction.PAUSE) for i in (1, 2))
    for _ in range(3):  # ticks: claimed and moved, owing both pauses
        assert table.claim(keys, lease) is False
        table.moved(frame)
    assert table.owed("la:1") == (pause1,) and table.owed("la:2") == (pause2,)
    table.sent(pause1)  # paid between two ticks ...
    assert table.owed("la:1") == ()
    table.moved(frame)  # ... and owed again by the next
    assert table.owed("la:1") == (pause1,)
    assert table.release(lease, hold=False, keys=["la:2"]) == [pause2]
    # la:2 is free now: the remembered claim no longer holds, the lease takes it again.
    assert table.claim(keys, lease) is True
    other = table.acquire("rig", ["la:3"], pause_for)
    with pytest.raises(LeaseConflictError):
        table.claim(("la:1", "la:3"), lease)
    table.moved(frame)
    assert table.owed("la:2") == (pause2,)
    assert table.release(other, hold=True) == []
    lease_keys_released = table.release(lease, hold=False)
    assert sorted(map(repr, lease_keys_released)) == sorted(map(repr, [pause1, pause2]))


def test_the_latch_is_set_by_an_estop_and_cleared_only_by_an_answered_work() -> None:
    """``LeaseTable.latched``: an e-stop written (answered, or its answer overdue: it may
    have arrived) sets it; a "work" clears it only once answered, since one that did
    not arrive leaves the device latched; a pause after it is no "work"."""
    table = LeaseTable()
    estop, work = la.Control(1, la.ControlAction.ESTOP), la.Control(1, la.ControlAction.WORK)
    table.unanswered(estop, "la:1")
    assert table.latched == {"la:1"}
    table.unanswered(work, "la:1")
    table.sent(la.Control(1, la.ControlAction.PAUSE), "la:1")
    assert table.latched == {"la:1"}
    assert safety.escalated(la.Control(1, la.ControlAction.PAUSE), table.latched) == estop
    assert safety.escalated(la.Control(2, la.ControlAction.PAUSE), table.latched) == (
        la.Control(2, la.ControlAction.PAUSE)
    )
    table.sent(work, "la:1")
    assert table.latched == set()
    table.sent(la.Control(la.BROADCAST_ID, la.ControlAction.ESTOP), "la:255")
    assert table.latched == {"la:255"}  # nothing seen yet: the wildcard stands for them
    assert safety.escalated(la.Control(2, la.ControlAction.PAUSE), table.latched) == (
        la.Control(2, la.ControlAction.ESTOP)
    )
