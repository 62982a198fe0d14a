"""Tests of the simulated project stepper controller (doc 000)."""

from __future__ import annotations

import random
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family, parse_hex
from motorbus.protocol.project_stepper import (
    DUMP_SIZE,
    PROJECT_FINISHED,
    AccelAndSpeed,
    ClearProject,
    GatingInput,
    Home,
    JogForward,
    JogReverse,
    ManualStop,
    OutputLevel,
    OutputPort,
    Project,
    ProjectDump,
    ProjectStepperCommand,
    ReadInput,
    ReadProject,
    RepeatCount,
    RotationDirection,
    RunDistance,
    SaveProject,
    SelectProject,
    SetMode4,
    SetOutput,
    SetPowerOnHoming,
    SingleRun,
    StartProject,
    StepLoop,
    StepOutputCode,
    StepSpec,
    StopBehavior,
    StopMode,
    StopProject,
    build_request,
    project_commands,
)
from motorbus.sim.project_stepper import (
    DEFAULT_TURNAROUND_S,
    STEP_GAP_S,
    MoveProfile,
    ProjectStepperModel,
)
from tests.vectors import load_vectors

PPR = 1600  # subdivision 8 x 1.8 degrees (A.3)


def vectors() -> list[dict[str, Any]]:
    """The project stepper vectors (tests/data/vectors.json; a missing file is an error)."""
    return [v for v in load_vectors() if v["device_kind"] == "ffaa11_project_stepper"]


def send(model: ProjectStepperModel, cmd: ProjectStepperCommand, now: float) -> bytes:
    """Send ``cmd``; require exactly one reply that matches it."""
    replies = model.handle(cmd.encode(), now)
    assert len(replies) == 1, (cmd, replies)
    assert cmd.matches_reply(replies[0]), (cmd, replies[0].hex(" "))
    return replies[0]


def program(model: ProjectStepperModel, project: Project, now: float = 0.0) -> None:
    for cmd in project_commands(project, model.motor):
        send(model, cmd, now)


def make_project(
    n: int = 1,
    *,
    number: int = 1,
    distance: int = PPR,
    speed_rpm: int = 60,
    delay_ms: int = 0,
    loop: tuple[int, int, int] = (0, 0, 0),
    repeat: int = 0,
    **step_fields: Any,
) -> Project:
    """``n`` identical steps in pulses (distance per rev = 1600), no ramp by default."""
    spec = StepSpec(run_distance=distance, speed_rpm=speed_rpm, delay_ms=delay_ms, **step_fields)
    return Project(number, 8, 180, PPR, (spec,) * n, *loop, repeat_count=repeat)


# -- the document vectors ------------------------------------------------------------


def test_the_document_session_gets_every_expected_reply() -> None:
    model = ProjectStepperModel()
    synthesized = [v for v in vectors() if v["synthesized"]]
    dump = parse_hex(synthesized[0]["expected_reply_hex"])
    assert len(dump) == DUMP_SIZE
    checked = 0
    for t, v in enumerate(v for v in vectors() if not v["synthesized"]):
        replies = model.handle(parse_hex(v["request_hex"]), float(t))
        assert len(replies) == 1, v["description"]
        reply = replies[0]
        if v["expected_reply_hex"] is not None:
            expected = parse_hex(v["expected_reply_hex"])
            assert reply[: len(expected)] == expected, v["description"]
            checked += 1
        if reply[2] == 0x3E:
            # The document programs project 1 exactly as the synthesized dump describes.
            assert reply == dump
        if reply[2] in (0x7E, 0x8E):
            assert reply[3:] == b"\x01\x00\x00"  # project 1 is selected (A0-03)
        if reply[2:4] == b"\x00\x0b":
            assert reply == parse_hex("FF AA 00 0B 01 00")
    assert checked == 24


def test_start_then_ee_dd_once_the_project_ends() -> None:
    vs = {v["request_hex"]: v for v in vectors() if not v["synthesized"]}
    model = ProjectStepperModel()
    programming = [h for h in vs if parse_hex(h)[2] not in (0x7E, 0x8E, 0x4E, 0x5E, 0x1E)]
    for h in programming[:10]:
        model.handle(parse_hex(h), 0.0)
    start = parse_hex("FF AA 4E 01 00 00 00 00 00 00 F8")
    assert vs[start.hex(" ").upper()]["completion_event_hex"] == "EE DD"
    assert model.handle(start, 1.0) == [parse_hex("FF AA 4E 01 00 00")]
    assert model.running
    # 1 revolution at 100 RPM from 50 Hz, 30 Hz/ms ramp, then 1000 ms delay (doc example).
    move = MoveProfile.plan(PPR, 50, 100 / 60 * PPR, 30)
    finish = model.next_event_time()
    assert finish is not None
    assert finish == pytest.approx(1.0 + move.duration + 1.0)
    assert model.poll(1.5) == []
    assert model.position == pytest.approx(-move.pulses_at(0.5))  # direction 1 = reverse
    assert model.poll(finish - 1e-6) == []
    assert model.poll(finish) == [PROJECT_FINISHED]
    assert model.poll(finish + 10) == []
    assert not model.running
    assert model.position == pytest.approx(-PPR)
    assert model.next_event_time() is None


# -- memory: RAM, flash, dump -----------------------------------------------------------


@settings(max_examples=30)
@given(st.integers(1, 4), st.integers(1, 10), st.integers(0, 255), st.data())
def test_dump_round_trips_what_was_programmed(
    number: int, n: int, repeat: int, data: st.DataObject
) -> None:
    specs = data.draw(
        st.lists(
            st.builds(
                StepSpec,
                run_distance=st.integers(0, 0xFFFFFF),
                direction=st.sampled_from(list(RotationDirection)),
                start_hz=st.integers(0, 0xFFFF),
                speed_rpm=st.integers(0, 0xFFFF),
                output=st.sampled_from(list(StepOutputCode)),
                delay_ms=st.integers(0, 0xFFFFFF),
                start_input=st.sampled_from(list(GatingInput)),
            ),
            min_size=n,
            max_size=n,
        )
    )
    project = Project(number, 16, 90, 3200, tuple(specs), 1, n, 2, repeat)
    model = ProjectStepperModel()
    program(model, project)
    send(model, StopMode(StopBehavior.IMMEDIATE), 0.0)
    send(model, SetMode4(2), 0.0)
    send(model, SetPowerOnHoming(True), 0.0)
    raw = send(model, ReadProject(number), 0.0)
    dump = ProjectDump.decode(raw)
    assert dump.to_project() == project
    assert (dump.stop_mode, dump.mode4, dump.power_on_homing) == (1, 2, 1)
    assert raw == ProjectDump.from_project(project, 1, 2, True).encode()


def test_save_persists_power_cycle_reloads_clear_zeroes() -> None:
    model = ProjectStepperModel()
    p1, p2 = make_project(3, number=1), make_project(2, number=2, distance=5)
    program(model, p1)
    send(model, SaveProject(1), 0.0)
    program(model, p2)  # not saved
    assert ProjectDump.decode(send(model, ReadProject(2), 0.0)).to_project() == p2
    model.power_cycle(1.0)
    assert model.current_project == 1
    assert ProjectDump.decode(send(model, ReadProject(1), 1.0)).to_project() == p1
    cleared = ProjectDump.decode(send(model, ReadProject(2), 1.0))
    assert (cleared.stored_number, cleared.number_of_steps, cleared.steps) == (2, 0, ())
    send(model, ClearProject(1), 2.0)
    raw = send(model, ReadProject(1), 2.0)
    assert raw == parse_hex("FF AA 3E 01 00 00 01") + bytes(DUMP_SIZE - 7)
    model.power_cycle(3.0)
    assert send(model, ReadProject(1), 3.0) == raw  # clearing reached flash too


def test_step_commands_act_on_the_selected_project_a0_03() -> None:
    model = ProjectStepperModel()
    program(model, make_project(2, number=1))
    send(model, SelectProject(3, 2), 1.0)
    assert model.current_project == 3
    send(model, RunDistance(2, 777), 1.0)
    assert send(model, StepLoop(1, 2, 3), 1.0) == parse_hex("FF AA 7E 03 00 00")
    assert send(model, RepeatCount(4), 1.0) == parse_hex("FF AA 8E 03 00 00")
    p3 = ProjectDump.decode(send(model, ReadProject(3), 1.0))
    assert p3.steps[1].run_distance == 777
    assert (p3.loop_start, p3.loop_end, p3.loop_count, p3.repeat_count) == (1, 2, 3, 4)
    p1 = ProjectDump.decode(send(model, ReadProject(1), 1.0))
    assert p1.to_project() == make_project(2, number=1)


# -- running projects ---------------------------------------------------------------------


def test_step_loop_order_is_traced_a0_15() -> None:
    model = ProjectStepperModel()
    program(model, make_project(8, loop=(3, 5, 2), delay_ms=10))
    send(model, StartProject(1), 0.0)
    finish = model.next_event_time()
    assert finish is not None
    assert model.poll(finish) == [PROJECT_FINISHED]
    assert [e.step for e in model.trace] == [1, 2, 3, 4, 5, 3, 4, 5, 6, 7, 8]
    assert {e.project for e in model.trace} == {1}
    assert model.position == pytest.approx(11 * PPR)
    # No ramp: each step is 1 s at 60 RPM, + 10 ms delay, + the gap before the next.
    times = [e.time for e in model.trace]
    assert times[1] - times[0] == pytest.approx(1.0 + 0.010 + STEP_GAP_S)
    assert finish == pytest.approx(11 * 1.010 + 10 * STEP_GAP_S)


@pytest.mark.parametrize(("repeat", "passes"), [(0, 1), (1, 1), (3, 3)])
def test_repeat_count_is_total_passes(repeat: int, passes: int) -> None:
    model = ProjectStepperModel()
    program(model, make_project(2, repeat=repeat, distance=16))
    send(model, StartProject(1), 0.0)
    finish = model.next_event_time()
    assert finish is not None
    assert model.poll(finish) == [PROJECT_FINISHED]
    assert [e.step for e in model.trace] == [1, 2] * passes


def test_repeat_255_never_ends() -> None:
    model = ProjectStepperModel()
    program(model, make_project(2, repeat=255, distance=160))
    send(model, StartProject(1), 0.0)
    assert model.next_event_time() is None
    assert model.poll(100.0) == []
    assert model.running
    assert len(model.trace) > 100
    assert send(model, StopProject(), 100.0) == parse_hex("FF AA 5E 00 00 00")
    assert not model.running
    assert model.poll(1e4) == [] and model.next_event_time() is None


def test_stop_project_suppresses_ee_dd() -> None:
    model = ProjectStepperModel()
    program(model, make_project(3))
    send(model, StartProject(1), 0.0)
    assert model.next_event_time() is not None
    model.poll(1.5)
    send(model, StopProject(), 1.5)
    assert not model.running
    assert model.next_event_time() is None
    assert model.poll(100.0) == []
    assert model.position == pytest.approx(1.5 * PPR - STEP_GAP_S * PPR)
    assert [e.step for e in model.trace] == [1, 2]


def test_start_input_gates_a_step() -> None:
    model = ProjectStepperModel()
    gated = StepSpec(run_distance=PPR, speed_rpm=60, start_input=GatingInput.IN1)
    free = StepSpec(run_distance=PPR, speed_rpm=60)
    program(model, Project(1, 8, 180, PPR, (free, gated)))
    send(model, StartProject(1), 0.0)
    assert model.next_event_time() is None  # step 2 will wait for IN1
    assert model.poll(50.0) == []
    assert model.position == pytest.approx(PPR)
    assert model.running
    model.set_input(1, True, 60.0)
    assert model.next_event_time() == pytest.approx(61.0)
    assert model.poll(61.0) == [PROJECT_FINISHED]


def test_stop_input_cuts_a_step_short() -> None:
    model = ProjectStepperModel()
    stoppable = StepSpec(run_distance=10 * PPR, speed_rpm=60, stop_input=GatingInput.IN2)
    program(model, Project(1, 8, 180, PPR, (stoppable, StepSpec(run_distance=PPR, speed_rpm=60))))
    send(model, StartProject(1), 0.0)
    model.set_input(2, True, 2.5)
    assert model.position == pytest.approx(2.5 * PPR)
    finish = model.next_event_time()
    assert finish is not None
    assert finish == pytest.approx(2.5 + STEP_GAP_S + 1.0)
    assert model.poll(finish) == [PROJECT_FINISHED]
    assert model.position == pytest.approx(3.5 * PPR)


def test_step_outputs_switch_with_the_motion() -> None:
    model = ProjectStepperModel()
    codes = [StepOutputCode.ALL_ON, StepOutputCode.OUT2_OFF, StepOutputCode.OUT3_ON]
    specs = tuple(StepSpec(run_distance=PPR, speed_rpm=60, output=c) for c in codes)
    program(model, Project(1, 8, 180, PPR, specs))
    send(model, StartProject(1), 0.0)
    on = {"OUT1": True, "OUT2": True, "OUT3": True, "LED1": False, "LED2": False}
    assert model.outputs == on
    model.poll(1.5)
    assert model.outputs == {**on, "OUT2": False}
    send(model, SetOutput(OutputPort.ALL_OUTPUTS, OutputLevel.INACTIVE), 1.6)
    model.poll(2.5)
    assert model.outputs == {**on, "OUT1": False, "OUT2": False}


def test_in3_starts_and_in4_stops_the_selected_project() -> None:
    model = ProjectStepperModel()
    program(model, make_project(1, number=2))
    model.set_input(3, True, 1.0)
    assert model.project_running == 2
    assert model.next_event_time() == pytest.approx(2.0)
    model.set_input(3, False, 1.2)
    model.set_input(4, True, 1.5)
    assert not model.running
    assert model.poll(5.0) == []
    assert model.position == pytest.approx(0.5 * PPR)


# -- manual commands, I/O ------------------------------------------------------------------


def test_jog_runs_until_manual_stop() -> None:
    model = ProjectStepperModel()
    program(model, make_project(1, speed_rpm=120))  # project 1 step 1 speed (A0-12)
    send(model, JogForward(), 0.0)
    model.poll(2.0)
    assert model.running
    assert model.position == pytest.approx(4 * PPR)
    send(model, ManualStop(), 3.0)
    assert not model.running
    model.poll(10.0)
    assert model.position == pytest.approx(6 * PPR)
    send(model, JogReverse(), 10.0)
    send(model, ManualStop(), 11.0)
    assert model.position == pytest.approx(4 * PPR)


def test_single_run_uses_project_1_step_1() -> None:
    model = ProjectStepperModel()
    program(model, make_project(1, distance=3 * PPR, direction=RotationDirection.REVERSE))
    send(model, SelectProject(2, 1), 0.0)  # selection does not matter (A0-12)
    send(model, SingleRun(), 0.0)
    assert model.running
    assert model.next_event_time() is None  # no EE DD for manual moves
    model.poll(10.0)
    assert not model.running
    assert model.position == pytest.approx(-3 * PPR)


def test_home_runs_reverse_until_in5() -> None:
    model = ProjectStepperModel()
    program(model, make_project(1))
    send(model, JogForward(), 0.0)
    send(model, ManualStop(), 1.0)
    send(model, Home(), 1.0)
    model.poll(1.5)
    assert model.position == pytest.approx(0.5 * PPR)
    assert model.running
    model.set_input(5, True, 3.0)
    assert not model.running
    assert model.position == 0.0
    assert send(model, ReadInput(5), 3.0) == parse_hex("FF AA 00 0B 05 01")
    assert send(model, ReadInput(4), 3.0) == parse_hex("FF AA 00 0B 04 00")


def test_power_on_homing() -> None:
    model = ProjectStepperModel()
    program(model, make_project(1))
    send(model, SetPowerOnHoming(True), 0.0)
    model.power_cycle(1.0)
    assert not model.running  # not saved: flash still says off
    program(model, make_project(1))
    send(model, SetPowerOnHoming(True), 2.0)
    send(model, SaveProject(1), 2.0)
    model.power_cycle(3.0)
    assert model.running
    model.set_input(5, True, 4.0)
    assert not model.running


def test_set_output_ports_and_leds() -> None:
    model = ProjectStepperModel()
    send(model, SetOutput(OutputPort.LEDS, OutputLevel.ACTIVE), 0.0)
    send(model, SetOutput(OutputPort.OUT2, OutputLevel.ACTIVE), 0.0)
    assert model.outputs == {
        "OUT1": False,
        "OUT2": True,
        "OUT3": False,
        "LED1": True,
        "LED2": True,
    }


def test_model_ignores_other_motors_and_bad_frames() -> None:
    model = ProjectStepperModel(motor=0x05)
    assert model.handle(JogForward().encode(), 0.0) == []  # motor 3
    assert model.handle(JogForward(motor=5).encode(), 0.0) == [parse_hex("FF AA 05 0A 00 00")]
    assert model.handle(AccelAndSpeed(3, 1, 2, motor=5).encode(), 0.0) == [
        parse_hex("FF AA 05 05 00 03")
    ]
    bad_checksum = bytearray(StopProject().encode())
    bad_checksum[-1] ^= 1
    assert model.handle(bytes(bad_checksum), 0.0) == []
    assert model.handle(build_request(bytes((0x05, 0x10, 0, 0, 0, 0, 0, 0))), 0.0) == []
    assert model.handle(build_request(bytes((0x6E, 7, 1, 0, 0, 0, 0, 0))), 0.0) == []


def test_configuration_and_turnaround() -> None:
    assert ProjectStepperModel.family is Family.PROJECT_STEPPER
    rng = random.Random(1)
    assert ProjectStepperModel().turnaround(rng) == DEFAULT_TURNAROUND_S == 1e-3
    jittery = ProjectStepperModel(turnaround_s=2e-3, turnaround_jitter_s=1e-3)
    assert all(2e-3 <= jittery.turnaround(rng) <= 3e-3 for _ in range(20))
    for bad in ({"motor": 0x4E}, {"motor": 0}):
        with pytest.raises(LocalProtocolError, match="motor"):
            ProjectStepperModel(**bad)
    with pytest.raises(LocalProtocolError, match="turnaround_s"):
        ProjectStepperModel(turnaround_s=-1.0)
    with pytest.raises(LocalProtocolError, match="input"):
        ProjectStepperModel().set_input(6, True, 0.0)


def test_move_profile_trapezoid_and_triangle() -> None:
    trapezoid = MoveProfile.plan(10_000, 100, 1100, 10)  # 10 kHz/s: 0.1 s ramps
    assert trapezoid.ramp_time == pytest.approx(0.1)
    assert trapezoid.pulses_at(0.1) == pytest.approx(60)
    assert trapezoid.duration == pytest.approx(0.2 + (10_000 - 120) / 1100)
    assert trapezoid.pulses_at(trapezoid.duration) == 10_000
    triangle = MoveProfile.plan(100, 0, 1000, 10)
    assert triangle.peak_rate == pytest.approx(1000)
    assert triangle.duration == pytest.approx(0.2)
    assert triangle.pulses_at(0.1) == pytest.approx(50)
    assert MoveProfile.plan(0, 50, 100, 1).duration == 0
    assert MoveProfile.plan(5, 50, 0, 1).duration == float("inf")


# -- variants a real controller may differ in ---------------------------------------------------


def test_global_reply_echo_variant_echoes_the_value_byte() -> None:
    printed = ProjectStepperModel()
    echoing = ProjectStepperModel(global_reply_echo="value")
    for cmd, as_printed, echoed in (
        (SetMode4(2), "FF AA 9E 00 00 00", "FF AA 9E 02 00 00"),
        (SetPowerOnHoming(True), "FF AA AE 00 00 00", "FF AA AE 01 00 00"),
        (StopProject(), "FF AA 5E 00 00 00", "FF AA 5E 00 00 00"),
    ):
        assert printed.handle(cmd.encode(), 0.0) == [parse_hex(as_printed)]
        assert echoing.handle(cmd.encode(), 0.0) == [parse_hex(echoed)]


def test_ee_dd_after_stop_variant_sends_it_that_long_after_the_stop() -> None:
    model = ProjectStepperModel(ee_dd_after_stop_s=0.25)
    program(model, make_project(3))
    send(model, StartProject(1), 0.0)
    model.poll(1.5)
    send(model, StopProject(), 1.5)
    assert not model.running
    assert model.next_event_time() == pytest.approx(1.75)
    assert model.poll(1.7) == []
    assert model.poll(1.75) == [PROJECT_FINISHED]
    assert model.next_event_time() is None
    # A stop with nothing running sends nothing.
    send(model, StopProject(), 2.0)
    assert model.next_event_time() is None


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"global_reply_echo": "echo"}, "global_reply_echo"),
        ({"ee_dd_after_stop_s": -0.1}, "ee_dd_after_stop_s"),
        ({"ee_dd_after_stop_s": True}, "ee_dd_after_stop_s"),
        ({"ee_dd_after_stop_s": float("inf")}, "ee_dd_after_stop_s"),
    ],
)
def test_bad_variant_options_are_refused(options: dict[str, Any], field: str) -> None:
    with pytest.raises(LocalProtocolError, match=field) as info:
        ProjectStepperModel(**options)
    assert info.value.field == field
