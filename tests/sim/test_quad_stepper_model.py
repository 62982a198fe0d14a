"""Tests of the simulated 4-axis FF AA stepper controller."""

from __future__ import annotations

import random
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family, parse_hex
from motorbus.protocol.quad_stepper import (
    AccelAndSpeed,
    DirectionAndStartFrequency,
    Home,
    MotorSetup,
    QuadCommand,
    RotationDirection,
    Run,
    RunAll,
    RunPulses,
    Save,
    SetLed,
    Stop,
    StopAll,
    build_request,
    decode_request,
)
from motorbus.sim.quad_stepper import (
    DEFAULT_LED_DELAY_S,
    DEFAULT_TURNAROUND_S,
    MotionProfile,
    MotorParams,
    QuadStepperModel,
)
from tests.vectors import vectors_of

VECTORS = vectors_of("ffaa9_4axis_stepper")

RUN_ACK = parse_hex("FF AA 00 09 00 00")
RUN_DONE = parse_hex("FF AA 00 09 01 00")
FOREVER = 1e9


def send(model: QuadStepperModel, cmd: QuadCommand, now: float = 0.0) -> list[bytes]:
    return model.handle(cmd.encode(), now)


def configure(
    model: QuadStepperModel,
    motor: int,
    pulses: int,
    *,
    rpm: int = 60,
    accel: int = 0,
    start_hz: int = 0,
    direction: RotationDirection = RotationDirection.FORWARD,
) -> None:
    """8 microsteps x 1.8 deg = 1600 pulses/rev, so 60 RPM is 1600 pulses/s."""
    for cmd in (
        MotorSetup(motor, 8, 180),
        RunPulses(motor, pulses),
        DirectionAndStartFrequency(motor, direction, start_hz),
        AccelAndSpeed(motor, accel, rpm),
    ):
        assert len(send(model, cmd)) == 1


# --- vectors ------------------------------------------------------------------------------


@pytest.mark.parametrize("vector", VECTORS, ids=lambda v: v["request_hex"])
def test_vector(vector: dict[str, Any]) -> None:
    model = QuadStepperModel()
    configure(model, 1, 1600)  # a run takes 1 s, so its done reply is really "later"
    request = parse_hex(vector["request_hex"])
    assert model.handle(request, 10.0) == [parse_hex(vector["expected_reply_hex"])]
    completion = vector.get("completion_reply_hex")
    if completion:
        due = model.next_event_time()
        assert due is not None
        assert due > 10.0
        assert model.poll(10.0) == []
        assert model.poll(due) == [parse_hex(completion)]
        assert model.poll(FOREVER) == []
    elif not isinstance(decode_request(request), RunAll):  # run-all: per-motor dones (A1-04)
        assert model.poll(FOREVER) == []


# --- runs ---------------------------------------------------------------------------------


def test_run_without_ramp() -> None:
    model = QuadStepperModel()
    configure(model, 1, 1600)
    assert send(model, Run(1), 2.0) == [RUN_ACK]
    assert model.motors[1].running
    assert model.next_event_time() == pytest.approx(3.0)
    assert model.poll(2.5) == []
    assert model.motors[1].position == 800
    assert model.poll(3.0) == [RUN_DONE]
    assert model.motors[1].position == 1600
    assert not model.motors[1].running
    assert model.next_event_time() is None


def test_run_trapezoid() -> None:
    # 1600 pulses/s cruise, accel 1 -> 1000 Hz/s from 0 Hz: ramps of 1.6 s and 1280 pulses,
    # 3200 - 2 * 1280 = 640 pulses of cruise = 0.4 s.
    model = QuadStepperModel()
    configure(model, 1, 3200, accel=1)
    send(model, Run(1))
    assert model.next_event_time() == pytest.approx(3.6)
    model.poll(1.6)
    assert model.motors[1].position == 1280
    model.poll(2.0)
    assert model.motors[1].position == 1280 + 640
    assert model.poll(3.6) == [RUN_DONE]
    assert model.motors[1].position == 3200


def test_run_triangle() -> None:
    # 1000 pulses never reach 1600 Hz: peak sqrt(1000 Hz/s * 1000) = 1000 Hz after 1 s.
    model = QuadStepperModel()
    configure(model, 1, 1000, accel=1)
    send(model, Run(1))
    assert model.next_event_time() == pytest.approx(2.0)
    model.poll(1.0)
    assert model.motors[1].position == 500


def test_reverse_run_counts_down() -> None:
    model = QuadStepperModel()
    configure(model, 3, 400, direction=RotationDirection.REVERSE)
    send(model, Run(3))
    send(model, Run(3), 1.0)  # after the end: a second run from -400
    assert model.poll(FOREVER) == [RUN_DONE, RUN_DONE]
    assert model.motors[3].position == -800


def test_run_ack_addressed_to_motor() -> None:
    model = QuadStepperModel(run_ack_address="motor")
    configure(model, 2, 16)
    assert send(model, Run(2)) == [parse_hex("FF AA 02 09 00 00")]
    assert model.poll(FOREVER) == [parse_hex("FF AA 02 09 01 00")]


def test_run_while_running_is_acked_and_ignored() -> None:
    model = QuadStepperModel()
    configure(model, 1, 1600)
    send(model, Run(1))
    assert send(model, Run(1), 0.5) == [RUN_ACK]
    assert model.next_event_time() == pytest.approx(1.0)
    assert model.poll(FOREVER) == [RUN_DONE]
    assert model.motors[1].position == 1600


def test_parameter_change_does_not_alter_a_running_move() -> None:
    model = QuadStepperModel()
    configure(model, 1, 1600)
    send(model, Run(1))
    send(model, RunPulses(1, 10), 0.1)
    send(model, AccelAndSpeed(1, 0, 600), 0.1)
    assert model.next_event_time() == pytest.approx(1.0)
    model.poll(FOREVER)
    assert model.motors[1].position == 1600
    assert model.motors[1].params.pulses == 10


def test_stop_suppresses_done() -> None:
    model = QuadStepperModel()
    configure(model, 1, 1600)
    send(model, Run(1))
    assert send(model, Stop(1), 0.5) == [parse_hex("FF AA 01 06 00 00")]
    assert not model.motors[1].running
    assert model.next_event_time() is None
    assert model.poll(FOREVER) == []
    assert model.motors[1].position == 800


def test_stop_after_the_end_keeps_the_done_reply() -> None:
    model = QuadStepperModel()
    configure(model, 1, 1600)
    send(model, Run(1))
    send(model, Stop(1), 2.0)  # the move ended at 1.0; poll was not called yet
    assert model.poll(2.0) == [RUN_DONE]
    assert model.motors[1].position == 1600


def test_run_all_emits_one_done_per_motor() -> None:
    model = QuadStepperModel(run_ack_address="motor")
    for motor, pulses in ((1, 1600), (2, 3200), (3, 800), (4, 0)):
        configure(model, motor, pulses)
    assert send(model, RunAll()) == [parse_hex("FF AA 09 09 00 00")]
    assert all(m.running for m in model.motors.values())
    assert model.poll(0.0) == [parse_hex("FF AA 04 09 01 00")]
    assert model.poll(FOREVER) == [
        parse_hex("FF AA 03 09 01 00"),
        parse_hex("FF AA 01 09 01 00"),
        parse_hex("FF AA 02 09 01 00"),
    ]  # in order of completion
    assert [m.position for m in model.motors.values()] == [1600, 3200, 800, 0]


def test_run_all_default_address_is_zero() -> None:
    model = QuadStepperModel()
    for motor in (1, 2, 3, 4):
        configure(model, motor, 160 * motor)
    send(model, RunAll())
    assert model.poll(FOREVER) == [RUN_DONE] * 4


def test_run_all_done_none_variant_sends_no_done_for_run_all_only() -> None:
    model = QuadStepperModel(run_all_done="none")
    for motor in (1, 2, 3, 4):
        configure(model, motor, 160 * motor)
    assert send(model, RunAll()) == [parse_hex("FF AA 09 09 00 00")]
    assert model.poll(FOREVER) == []
    assert [m.position for m in model.motors.values()] == [160, 320, 480, 640]
    assert not any(m.running for m in model.motors.values())
    # A single run afterwards reports as usual.
    send(model, Run(2), FOREVER)
    assert model.poll(2 * FOREVER) == [RUN_DONE]


def test_run_all_done_must_be_each_or_none() -> None:
    with pytest.raises(LocalProtocolError, match=r"run_all_done='some'.*'each' or 'none'") as info:
        QuadStepperModel(run_all_done="some")  # type: ignore[arg-type]
    assert info.value.field == "run_all_done"


def test_stop_all() -> None:
    model = QuadStepperModel()
    for motor in (1, 2, 3, 4):
        configure(model, motor, 1600)
    send(model, RunAll())
    assert send(model, StopAll(), 0.25) == [parse_hex("FF AA 09 06 00 00")]
    assert model.poll(FOREVER) == []
    assert [m.position for m in model.motors.values()] == [400] * 4
    assert not any(m.running for m in model.motors.values())


# --- homing -------------------------------------------------------------------------------


def test_home_until_stop_input() -> None:
    model = QuadStepperModel()
    configure(model, 1, 0)
    assert send(model, Home(1, 3)) == [parse_hex("FF AA 01 0F 00 00")]
    assert model.motors[1].running
    assert model.next_event_time() is None  # no end in sight
    assert model.poll(5.0) == []
    assert model.motors[1].position == 8000  # 1600 pulses/s
    model.set_input(4, True, 5.5)  # another input: no effect
    assert model.motors[1].running
    model.set_input(3, True, 6.0)
    assert not model.motors[1].running
    assert model.motors[1].position == 0  # the home point
    assert model.poll(FOREVER) == []  # homing has no done reply
    assert model.input_active(3)
    model.set_input(3, False, 7.0)
    assert not model.input_active(3)


def test_home_with_input_already_active_stops_at_once() -> None:
    model = QuadStepperModel()
    configure(model, 2, 0, direction=RotationDirection.REVERSE)
    send(model, Run(2))
    model.poll(1.0)
    model.set_input(13, True, 1.0)
    send(model, Home(2, 13), 1.0)
    assert not model.motors[2].running
    assert model.motors[2].position == 0


def test_home_without_stop_input_runs_until_stopped() -> None:
    model = QuadStepperModel()
    configure(model, 2, 0, direction=RotationDirection.REVERSE)
    send(model, Home(2, 0))
    for n in range(1, 14):
        model.set_input(n, True, 1.0)
    assert model.motors[2].running
    send(model, Stop(2), 2.0)
    assert not model.motors[2].running
    assert model.motors[2].position == -3200
    assert model.poll(FOREVER) == []


# --- LEDs and save ------------------------------------------------------------------------


def test_led_done_after_delay() -> None:
    model = QuadStepperModel()
    assert send(model, SetLed(2, True), 1.0) == [parse_hex("FF AA 00 0C 02 00")]
    assert model.leds == (False, False, False, False)
    due = model.next_event_time()
    assert due == pytest.approx(1.0 + DEFAULT_LED_DELAY_S)
    assert model.poll(1.0) == []
    assert model.poll(1.0 + DEFAULT_LED_DELAY_S) == [parse_hex("FF AA 00 0C 02 01")]
    assert model.leds == (False, True, False, False)
    send(model, SetLed(5, True), 2.0)
    send(model, SetLed(1, False), 2.0)
    assert model.poll(3.0) == [parse_hex("FF AA 00 0C 05 01"), parse_hex("FF AA 00 0C 01 01")]
    assert model.leds == (False, True, True, True)


def test_led_delay_configurable() -> None:
    model = QuadStepperModel(led_delay_s=0.02)
    send(model, SetLed(4, True))
    assert model.next_event_time() == pytest.approx(0.02)


def test_save_and_power_cycle() -> None:
    model = QuadStepperModel()
    send(model, MotorSetup(1, 16, 90))
    assert send(model, Save()) == [parse_hex("FF AA BC 00 00 00")]
    send(model, MotorSetup(1, 32, 90))  # not saved
    send(model, RunPulses(2, 500))  # not saved
    assert model.motors[1].params.subdivision == 32
    assert model.saved_params(1).subdivision == 16
    configure(model, 3, 1600)
    send(model, Run(3))
    send(model, SetLed(1, True))
    model.poll(0.5)
    model.power_cycle(0.6)
    assert model.motors[1].params == MotorParams(subdivision=16, step_angle_x100=90)
    assert model.motors[2].params.pulses == MotorParams().pulses
    assert model.motors[3].position == 0
    assert not model.motors[3].running
    assert model.leds == (False,) * 4
    assert model.next_event_time() is None
    assert model.poll(FOREVER) == []


# --- framing, options ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "raw",
    [
        build_request(parse_hex("01 09 00 00 00 01")),  # nonzero spare byte
        build_request(parse_hex("01 02 00 00 00 00")),  # unknown command
        parse_hex("FF AA 09 06 00 00 00 00 B9"),  # bad checksum
    ],
)
def test_refused_requests_are_ignored(raw: bytes) -> None:
    model = QuadStepperModel()
    assert model.handle(raw, 0.0) == []
    assert model.ignored == 1


def test_turnaround_and_family() -> None:
    assert QuadStepperModel().turnaround(random.Random(1)) == DEFAULT_TURNAROUND_S == 1e-3
    assert QuadStepperModel(turnaround_s=2e-3).turnaround(random.Random(1)) == 2e-3
    assert QuadStepperModel.family is Family.QUAD_STEPPER


@pytest.mark.parametrize(
    "kwargs",
    [{"run_ack_address": "motors"}, {"turnaround_s": -1.0}, {"led_delay_s": float("nan")}],
)
def test_bad_options(kwargs: dict[str, Any]) -> None:
    with pytest.raises(LocalProtocolError):
        QuadStepperModel(**kwargs)


@pytest.mark.parametrize("n", [0, 14])
def test_set_input_range(n: int) -> None:
    with pytest.raises(LocalProtocolError, match=r"1\.\.13"):
        QuadStepperModel().set_input(n, True, 0.0)


# --- properties ---------------------------------------------------------------------------


@given(
    start=st.floats(0, 5000),
    cruise=st.floats(1, 50000),
    accel=st.one_of(st.just(0.0), st.floats(1.0, 1e6)),  # the model's slopes: 0 or >= 1000
    pulses=st.integers(0, 100_000),
)
def test_profile_is_monotone_and_ends_at_the_pulse_count(
    start: float, cruise: float, accel: float, pulses: int
) -> None:
    profile = MotionProfile(min(start, cruise), cruise, accel, pulses)
    duration = profile.duration()
    assert duration >= 0
    assert profile.pulses_at(0.0) == 0
    assert profile.pulses_at(duration) == pulses
    samples = [profile.pulses_at(duration * i / 20) for i in range(21)]
    assert samples == sorted(samples)


@given(
    pulses=st.integers(0, 50_000),
    direction=st.sampled_from(RotationDirection),
    rpm=st.integers(0, 3000),
    accel=st.integers(0, 1000),
    start_hz=st.integers(0, 5000),
    stop_at=st.floats(0, 1),
)
def test_run_ends_where_expected(
    pulses: int,
    direction: RotationDirection,
    rpm: int,
    accel: int,
    start_hz: int,
    stop_at: float,
) -> None:
    model = QuadStepperModel()
    configure(model, 4, pulses, rpm=rpm, accel=accel, start_hz=start_hz, direction=direction)
    send(model, Run(4))
    end = model.next_event_time()
    assert end is not None
    sign = -1 if direction is RotationDirection.REVERSE else 1
    stopped = QuadStepperModel()
    configure(stopped, 4, pulses, rpm=rpm, accel=accel, start_hz=start_hz, direction=direction)
    send(stopped, Run(4))
    send(stopped, Stop(4), end * stop_at)
    assert model.poll(end) == [RUN_DONE]
    assert model.motors[4].position == sign * pulses
    assert 0 <= sign * stopped.motors[4].position <= pulses
