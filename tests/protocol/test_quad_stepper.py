"""Tests of the 9-byte FF AA quad stepper protocol (doc 001)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import Command, Family, FrameShape, parse_hex
from motorbus.protocol.quad_stepper import (
    DEFAULT_BAUD,
    REPLY_SIZE,
    REQUEST_SIZE,
    AccelAndSpeed,
    Ack,
    DirectionAndStartFrequency,
    Done,
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
    decode_reply_context_free,
    decode_request,
    is_done_reply,
    request_is_valid,
)
from tests.vectors import vectors_of

DEVICE_KIND = "ffaa9_4axis_stepper"
VECTORS = vectors_of(DEVICE_KIND)


def _fits(shapes: tuple[FrameShape, ...], raw: bytes) -> bool:
    return any(len(raw) == s.length and s.matches(raw) for s in shapes)


# --- the document's examples and the synthesized vectors ----------------------------------

#: Each vector's request, built from the API (not from decode_request).
EXPECTED_COMMANDS: dict[str, QuadCommand] = {
    "FF AA 01 0F 00 00 00 00 B9": Home(1, 0),
    "FF AA 09 09 00 00 00 00 BB": RunAll(),
    "FF AA 09 06 00 00 00 00 B8": StopAll(),
    "FF AA BC 00 00 00 00 00 65": Save(),
    "FF AA 01 01 08 00 B4 00 67": MotorSetup(1, 8, 180),
    "FF AA 01 03 40 06 00 00 F3": RunPulses(1, 1600),
    "FF AA 01 04 01 32 00 00 E1": DirectionAndStartFrequency(1, RotationDirection.REVERSE, 50),
    "FF AA 01 05 1E 00 64 00 31": AccelAndSpeed(1, 30, 100),
    "FF AA 01 09 00 00 00 00 B3": Run(1),
    "FF AA 01 06 00 00 00 00 B0": Stop(1),
    "FF AA 00 0C 01 01 00 00 B7": SetLed(1, True),
}


def test_every_vector_is_in_the_table() -> None:
    assert {v["request_hex"] for v in VECTORS} == set(EXPECTED_COMMANDS)


@pytest.mark.parametrize("vector", VECTORS, ids=lambda v: v["request_hex"])
def test_vector(vector: dict[str, Any]) -> None:
    request = parse_hex(vector["request_hex"])
    cmd = EXPECTED_COMMANDS[vector["request_hex"]]
    assert cmd.encode() == request
    assert request_is_valid(request)
    assert decode_request(request) == cmd
    reply = parse_hex(vector["expected_reply_hex"])
    assert cmd.matches_reply(reply)
    assert _fits(cmd.reply_shapes(), reply)
    assert isinstance(cmd.decode_reply(reply), Ack)
    assert isinstance(decode_reply_context_free(reply), Ack)
    assert not is_done_reply(reply)
    if vector.get("completion_reply_hex"):
        done = parse_hex(vector["completion_reply_hex"])
        assert _fits(cmd.done_shapes(), done)
        assert not cmd.matches_reply(done)
        assert isinstance(cmd.decode_reply(done), Done)
        assert isinstance(decode_reply_context_free(done), Done)
        assert is_done_reply(done)


def test_constants() -> None:
    assert (REQUEST_SIZE, REPLY_SIZE, DEFAULT_BAUD) == (9, 6, 9600)


# --- framing ------------------------------------------------------------------------------


def test_build_request_adds_header_and_checksum() -> None:
    assert build_request(bytes.fromhex("090600000000")) == bytes.fromhex("ffaa090600000000b8")


@pytest.mark.parametrize("size", [0, 5, 7, 9])
def test_build_request_refuses_wrong_size(size: int) -> None:
    with pytest.raises(LocalProtocolError, match="b2_to_b7"):
        build_request(bytes(size))


@pytest.mark.parametrize(
    "raw",
    [
        "FF AA 09 06 00 00 00 00 B9",  # checksum off by one
        "FF AB 09 06 00 00 00 00 B9",  # header
        "FF AA 09 06 00 00 00 B8",  # short
        "FF AA 09 06 00 00 00 00 B8 00",  # long
        "",
    ],
)
def test_invalid_requests(raw: str) -> None:
    data = parse_hex(raw)
    assert not request_is_valid(data)
    with pytest.raises(RemoteProtocolError) as info:
        decode_request(data)
    assert info.value.raw == data


@pytest.mark.parametrize(
    "body",
    [
        "01 02 00 00 00 00",  # motor command 0x02 does not exist in doc 001
        "05 09 00 00 00 00",  # motor 5
        "09 05 00 00 00 00",  # all-motors command other than run/stop
        "00 0B 01 00 00 00",  # I/O command other than LED
        "01 09 00 00 00 01",  # run with a nonzero spare byte
        "01 0F 00 01 00 00",  # homing with a nonzero spare byte
        "BC 00 00 00 01 00",  # save with a nonzero spare byte
        "00 0C 06 01 00 00",  # LED 6
        "00 0C 01 02 00 00",  # LED state 2
        "01 04 02 32 00 00",  # direction 2
        "01 01 00 00 B4 00",  # subdivision 0
        "01 0F 0E 00 00 00",  # stop input 14
        "77 01 00 00 00 00",  # unknown address
    ],
)
def test_decode_request_refuses(body: str) -> None:
    raw = build_request(parse_hex(body))
    with pytest.raises(RemoteProtocolError) as info:
        decode_request(raw)
    assert info.value.raw == raw


# --- replies ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cmd", "ack", "done"),
    [
        (MotorSetup(2, 16, 90), "FF AA 02 01 00 00", None),
        (RunPulses(3, 0xFFFFFF), "FF AA 03 03 00 00", None),
        (DirectionAndStartFrequency(4, RotationDirection.FORWARD, 0), "FF AA 04 04 00 00", None),
        (AccelAndSpeed(2, 0x1234, 600), "FF AA 02 05 00 00", None),
        (Home(3, 13), "FF AA 03 0F 00 00", None),
        (Run(3), "FF AA 00 09 00 00", "FF AA 00 09 01 00"),
        (Run(3), "FF AA 03 09 00 00", "FF AA 03 09 01 00"),  # A1-02: motor address accepted
        (Stop(4), "FF AA 04 06 00 00", None),
        (RunAll(), "FF AA 09 09 00 00", "FF AA 02 09 01 00"),
        (StopAll(), "FF AA 09 06 00 00", None),
        (SetLed(5, False), "FF AA 00 0C 05 00", "FF AA 00 0C 05 01"),
        (Save(), "FF AA BC 00 00 00", None),
    ],
)
def test_reply_matching(cmd: QuadCommand, ack: str, done: str | None) -> None:
    ack_raw = parse_hex(ack)
    assert cmd.matches_reply(ack_raw)
    assert cmd.reply_lengths() == (REPLY_SIZE,)
    assert cmd.expects_reply
    decoded = cmd.decode_reply(ack_raw)
    assert decoded == Ack(ack_raw[2], ack_raw[3], decoded.led, ack_raw)
    assert decode_reply_context_free(ack_raw) == decoded
    for shape in (*cmd.reply_shapes(), *cmd.done_shapes()):
        assert shape.length == REPLY_SIZE
        assert len(shape.pattern) == REPLY_SIZE  # exact patterns: the reassembler relies on it
    if done is None:
        assert cmd.done_shapes() == ()
    else:
        done_raw = parse_hex(done)
        assert cmd.matches_done(done_raw)
        assert not cmd.matches_reply(done_raw)
        assert isinstance(cmd.decode_reply(done_raw), Done)


@pytest.mark.parametrize(
    ("cmd", "reply"),
    [
        (Run(1), "FF AA 02 09 00 00"),  # another motor's run ack
        (Run(1), "FF AA 00 09 01 00"),  # done is not the ack
        (Stop(1), "FF AA 00 06 00 00"),  # stop is addressed to the motor
        (MotorSetup(1, 8, 180), "FF AA 01 01 00 01"),
        (SetLed(1, True), "FF AA 00 0C 02 00"),  # another LED
        (SetLed(1, True), "FF AA 00 0C 01 01"),  # done is not the ack
        (Save(), "FF AA BC 00 00"),  # short
        (Save(), "FF AA BC 00 00 00 00"),  # long
        (RunAll(), "FF AA 09 06 00 00"),
    ],
)
def test_reply_mismatch(cmd: QuadCommand, reply: str) -> None:
    raw = parse_hex(reply)
    assert not cmd.matches_reply(raw)
    if not cmd.matches_done(raw):
        with pytest.raises(RemoteProtocolError) as info:
            cmd.decode_reply(raw)
        assert info.value.raw == raw


def test_run_done_shape_excludes_other_motors() -> None:
    assert not Run(1).matches_done(parse_hex("FF AA 02 09 01 00"))
    assert not Stop(1).done_shapes()


def test_context_free_fields() -> None:
    assert decode_reply_context_free(parse_hex("FF AA 00 0C 03 01")) == Done(
        0x00, 0x0C, 3, parse_hex("FF AA 00 0C 03 01")
    )
    ack = decode_reply_context_free(parse_hex("FF AA 02 05 00 00"))
    assert (type(ack), ack.motor, ack.command, ack.led) == (Ack, 2, 0x05, None)
    run_done = decode_reply_context_free(parse_hex("FF AA 00 09 01 00"))
    assert (type(run_done), run_done.motor) == (Done, None)  # A1-02: not attributable
    assert decode_reply_context_free(parse_hex("FF AA BC 00 00 00")).address == 0xBC


@pytest.mark.parametrize(
    "raw",
    [
        "FF AA 05 01 00 00",  # motor 5
        "FF AA 01 02 00 00",  # no command 0x02
        "FF AA 01 01 01 00",
        "FF AA 00 0C 06 00",  # LED 6
        "FF AA 00 0C 01 02",
        "FF AA 09 09 02 00",
        "FF AA BC 00 00 01",
        "FF AB 01 01 00 00",
        "FF AA 01 01 00",
        "EE DD",
    ],
)
def test_context_free_refuses(raw: str) -> None:
    data = parse_hex(raw)
    assert not is_done_reply(data)
    with pytest.raises(RemoteProtocolError):
        decode_reply_context_free(data)


def test_command_metadata() -> None:
    motion: set[type[QuadCommand]] = {Home, Run, RunAll}
    every: tuple[type[QuadCommand], ...] = (
        MotorSetup,
        RunPulses,
        DirectionAndStartFrequency,
        AccelAndSpeed,
        Home,
        Run,
        Stop,
        RunAll,
        StopAll,
        SetLed,
        Save,
    )
    for cls in every:
        assert cls.starts_motion == (cls in motion)
        assert cls.family is Family.QUAD_STEPPER
    assert issubclass(QuadCommand, Command)


def test_values_are_frozen_and_slotted() -> None:
    cmd = RunPulses(1, 5)
    with pytest.raises(AttributeError):
        cmd.pulses = 6  # type: ignore[misc]
    assert not hasattr(cmd, "__dict__")
    assert not hasattr(Ack(0, 0, None, b""), "__dict__")


def test_direction_accepts_plain_int() -> None:
    cmd = DirectionAndStartFrequency(1, 1, 50)  # type: ignore[arg-type]
    assert cmd.direction is RotationDirection.REVERSE
    assert cmd == DirectionAndStartFrequency(1, RotationDirection.REVERSE, 50)


# --- properties ---------------------------------------------------------------------------

motors = st.integers(1, 4)
u16 = st.integers(0, 0xFFFF)
commands: st.SearchStrategy[QuadCommand] = st.one_of(
    st.builds(MotorSetup, motors, st.integers(1, 0xFFFF), st.integers(1, 255)),
    st.builds(RunPulses, motors, st.integers(0, 0xFFFFFF)),
    st.builds(DirectionAndStartFrequency, motors, st.sampled_from(RotationDirection), u16),
    st.builds(AccelAndSpeed, motors, u16, u16),
    st.builds(Home, motors, st.integers(0, 13)),
    st.builds(Run, motors),
    st.builds(Stop, motors),
    st.just(RunAll()),
    st.just(StopAll()),
    st.builds(SetLed, st.integers(1, 5), st.booleans()),
    st.just(Save()),
)


@given(commands)
def test_round_trip(cmd: QuadCommand) -> None:
    raw = cmd.encode()
    assert len(raw) == REQUEST_SIZE
    assert raw[:2] == b"\xff\xaa"
    assert raw[-1] == sum(raw[:-1]) & 0xFF
    assert request_is_valid(raw)
    assert decode_request(raw) == cmd


@given(commands, st.integers(0, REQUEST_SIZE - 1), st.integers(1, 255))
def test_corrupted_byte_is_refused(cmd: QuadCommand, index: int, delta: int) -> None:
    raw = bytearray(cmd.encode())
    raw[index] = (raw[index] + delta) & 0xFF
    assert not request_is_valid(bytes(raw))


@given(commands, st.binary(min_size=6, max_size=6))
def test_decode_reply_agrees_with_matching(cmd: QuadCommand, tail: bytes) -> None:
    raw = b"\xff\xaa" + tail[:4]
    if cmd.matches_reply(raw):
        assert isinstance(cmd.decode_reply(raw), Ack)
    elif cmd.matches_done(raw):
        assert isinstance(cmd.decode_reply(raw), Done)
        assert is_done_reply(raw)
    else:
        with pytest.raises(RemoteProtocolError):
            cmd.decode_reply(raw)


#: (factory taking one value, field name, lo, hi)
RANGES: list[tuple[Callable[[int], object], str, int, int]] = [
    (lambda v: MotorSetup(v, 8, 180), "motor", 1, 4),
    (lambda v: MotorSetup(1, v, 180), "subdivision", 1, 0xFFFF),
    (lambda v: MotorSetup(1, 8, v), "step_angle_x100", 1, 255),
    (lambda v: RunPulses(1, v), "pulses", 0, 0xFFFFFF),
    (lambda v: RunPulses(v, 0), "motor", 1, 4),
    (lambda v: DirectionAndStartFrequency(1, RotationDirection.FORWARD, v), "start_hz", 0, 0xFFFF),
    (lambda v: AccelAndSpeed(1, v, 100), "accel_hz", 0, 0xFFFF),
    (lambda v: AccelAndSpeed(1, 30, v), "speed_rpm", 0, 0xFFFF),
    (lambda v: Home(1, v), "stop_input", 0, 13),
    (lambda v: Home(v, 0), "motor", 1, 4),
    (lambda v: Run(v), "motor", 1, 4),
    (lambda v: Stop(v), "motor", 1, 4),
    (lambda v: SetLed(v, True), "led", 1, 5),
]


@pytest.mark.parametrize(
    ("factory", "name", "lo", "hi"), RANGES, ids=lambda x: "" if callable(x) else str(x)
)
@given(data=st.data())
def test_out_of_range(
    factory: Callable[[int], object], name: str, lo: int, hi: int, data: st.DataObject
) -> None:
    value = data.draw(st.one_of(st.integers(max_value=lo - 1), st.integers(min_value=hi + 1)))
    with pytest.raises(LocalProtocolError) as info:
        factory(value)
    message = str(info.value)
    assert name in message
    assert f"{lo}..{hi}" in message
    assert str(value) in message
    assert info.value.field == name
    assert isinstance(info.value, ValueError)
    factory(lo)
    factory(hi)


@pytest.mark.parametrize("bad", [True, 1.0, "1", None])
def test_non_int_refused(bad: object) -> None:
    with pytest.raises(LocalProtocolError, match="motor"):
        Run(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [2, -1, None, "reverse"])
def test_bad_direction(bad: object) -> None:
    with pytest.raises(LocalProtocolError, match="direction"):
        DirectionAndStartFrequency(1, bad, 50)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [1, 0, None, "on"])
def test_led_state_must_be_bool(bad: object) -> None:
    with pytest.raises(LocalProtocolError, match="on"):
        SetLed(1, bad)  # type: ignore[arg-type]
