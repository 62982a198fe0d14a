"""Tests of the 11-byte FF AA project stepper protocol (doc 000, docs/protocols.md part A)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import Command, Family, parse_hex, sum8
from motorbus.protocol.project_stepper import (
    DEFAULT_MOTOR,
    DUMP_SIZE,
    PROJECT_FINISHED,
    PROJECT_OPCODES,
    REPLY_SIZE,
    REQUEST_SIZE,
    RESERVED_SIZE,
    STEP_DATA_SIZE,
    AccelAndSpeed,
    Ack,
    ClearProject,
    DirectionAndStartFrequency,
    DistancePerRev,
    GatingInput,
    Home,
    JogForward,
    JogReverse,
    ManualStop,
    MotorSetup,
    OutputLevel,
    OutputPort,
    Project,
    ProjectDump,
    ProjectFinishedMarker,
    ProjectStepperCommand,
    ReadInput,
    ReadProject,
    RepeatCount,
    ReplyKind,
    RotationDirection,
    RunDistance,
    SaveProject,
    SelectProject,
    SetMode4,
    SetOutput,
    SetPowerOnHoming,
    SingleRun,
    StartInput,
    StartProject,
    StepDelay,
    StepLoop,
    StepOutput,
    StepOutputCode,
    StepSpec,
    StopBehavior,
    StopInput,
    StopMode,
    StopProject,
    build_request,
    decode_reply_context_free,
    decode_request,
    dump_offset,
    project_commands,
    request_is_valid,
)
from tests.vectors import load_vectors

KIND = "ffaa11_project_stepper"


def vectors() -> list[dict[str, Any]]:
    """The project stepper vectors (tests/data/vectors.json; a missing file is an error)."""
    return [v for v in load_vectors() if v["device_kind"] == KIND]


def document_vectors() -> list[dict[str, Any]]:
    return [v for v in vectors() if not v["synthesized"]]


def synthesized_dump_vector() -> dict[str, Any]:
    found = [v for v in vectors() if v["synthesized"] and v.get("expected_reply_length") != 6]
    dumps = [v for v in found if len(parse_hex(v["expected_reply_hex"])) == DUMP_SIZE]
    assert len(dumps) == 1
    return dumps[0]


# Every document example, built from the API (A.4); the checksum is the document's.
DOCUMENT_EXAMPLES: list[tuple[Command, str]] = [
    (SelectProject(1, 1), "FF AA 6E 01 01 00 00 00 00 00 19"),
    (MotorSetup(8, 180), "FF AA 03 01 08 00 B4 00 00 00 69"),
    (DistancePerRev(1), "FF AA 03 02 01 00 00 00 00 00 AF"),
    (RunDistance(1, 1), "FF AA 03 03 01 00 00 00 00 01 B1"),
    (
        DirectionAndStartFrequency(1, RotationDirection.REVERSE, 50),
        "FF AA 03 04 01 32 00 00 00 01 E4",
    ),
    (AccelAndSpeed(1, 30, 100), "FF AA 03 05 1E 00 64 00 00 01 34"),
    (StepOutput(1, StepOutputCode.NONE), "FF AA 03 06 00 00 00 00 00 01 B3"),
    (StepDelay(1, 1000), "FF AA 03 07 E8 03 00 00 00 01 9F"),  # V1: 1000 ms, not 2000
    (StartInput(1, GatingInput.NONE), "FF AA 03 08 00 00 00 00 00 01 B5"),
    (StopInput(1, GatingInput.NONE), "FF AA 03 09 00 00 00 00 00 01 B6"),
    (StepLoop(0, 0, 0), "FF AA 7E 00 00 00 00 00 00 00 27"),
    (RepeatCount(0), "FF AA 8E 00 00 00 00 00 00 00 37"),
    (StartProject(1), "FF AA 4E 01 00 00 00 00 00 00 F8"),
    (StopProject(), "FF AA 5E 00 00 00 00 00 00 00 07"),
    (ReadProject(1), "FF AA 3E 01 00 00 00 00 00 00 E8"),
    (SaveProject(1), "FF AA 2E 01 00 00 00 00 00 00 D8"),
    (ClearProject(1), "FF AA 1E 01 00 00 00 00 00 00 C8"),  # V2: C8, not C9
    (JogForward(), "FF AA 03 0A 00 00 00 00 00 00 B6"),
    (JogReverse(), "FF AA 03 0B 00 00 00 00 00 00 B7"),
    (SingleRun(), "FF AA 03 0C 00 00 00 00 00 00 B8"),
    (ManualStop(), "FF AA 03 0D 00 00 00 00 00 00 B9"),
    (StopMode(StopBehavior.SLOW), "FF AA 03 0E 00 00 00 00 00 00 BA"),
    (Home(), "FF AA 03 0F 00 00 00 00 00 00 BB"),
    (SetOutput(OutputPort.OUT1, OutputLevel.INACTIVE), "FF AA 00 0C 01 00 00 00 00 00 B6"),
    (ReadInput(1), "FF AA 00 0B 01 00 00 00 00 00 B5"),
    (SetMode4(0), "FF AA 9E 00 00 00 00 00 00 00 47"),
    (SetPowerOnHoming(False), "FF AA AE 00 00 00 00 00 00 00 57"),
]
BY_HEX = {parse_hex(h): c for c, h in DOCUMENT_EXAMPLES}


# -- document vectors ----------------------------------------------------------------


def test_every_document_vector_has_an_api_example() -> None:
    doc = document_vectors()
    assert len(doc) == 27  # A0-01: 27 commands, whatever the title says
    assert {parse_hex(v["request_hex"]) for v in doc} == set(BY_HEX)


@pytest.mark.parametrize(("cmd", "hex_text"), DOCUMENT_EXAMPLES)
def test_document_examples_encode_byte_exact(cmd: Command, hex_text: str) -> None:
    raw = parse_hex(hex_text)
    assert cmd.encode() == raw
    assert request_is_valid(raw)
    assert decode_request(raw) == cmd
    assert cmd.family is Family.PROJECT_STEPPER


def test_every_document_vector_decodes_and_its_reply_matches() -> None:
    for v in document_vectors():
        raw = parse_hex(v["request_hex"])
        assert v["checksum"]["ok"] is True
        cmd = decode_request(raw)
        assert cmd == BY_HEX[raw]
        assert cmd.encode() == raw
        if v["expected_reply_hex"] is None:
            continue
        reply = parse_hex(v["expected_reply_hex"])
        if isinstance(cmd, ReadProject):
            # The vector gives only the dump header: it must fit the shape as a prefix.
            assert cmd.reply_lengths() == (DUMP_SIZE,)
            assert cmd.reply_shapes()[0].matches(reply)
            assert not cmd.matches_reply(reply)
            continue
        assert cmd.reply_lengths() == (REPLY_SIZE,)
        assert cmd.matches_reply(reply), v["description"]
        ack = cmd.decode_reply(reply)
        assert isinstance(ack, Ack)
        assert ack.raw == reply


@pytest.mark.parametrize(("cmd", "hex_text"), DOCUMENT_EXAMPLES)
def test_reply_with_any_echoed_byte_changed_does_not_match(cmd: Command, hex_text: str) -> None:
    del hex_text
    shape = cmd.reply_shapes()[0]
    good = bytearray(shape.length)
    for i, allowed in enumerate(shape.pattern):
        assert allowed is not None
        good[i] = min(allowed)
    assert cmd.matches_reply(bytes(good))
    for i, allowed in enumerate(shape.pattern):
        assert allowed is not None
        bad = bytearray(good)
        bad[i] = next(b for b in range(256) if b not in allowed)
        assert not cmd.matches_reply(bytes(bad)), (i, bytes(bad).hex(" "))
    assert not cmd.matches_reply(bytes(good)[:-1])
    assert not cmd.matches_reply(bytes(good) + b"\x00")


def test_template_replies_carry_the_current_project_a0_03() -> None:
    for cmd, op in ((StepLoop(3, 5, 2), 0x7E), (RepeatCount(255), 0x8E)):
        for project in (1, 2, 3, 4):
            reply = bytes((0xFF, 0xAA, op, project, 0, 0))
            assert cmd.matches_reply(reply)
            assert cmd.decode_reply(reply) == Ack(ReplyKind.PROJECT, op, project=project, raw=reply)
        for project in (0, 5, 0xFF):
            assert not cmd.matches_reply(bytes((0xFF, 0xAA, op, project, 0, 0)))


def test_read_input_reply_decodes_to_bool() -> None:
    cmd = ReadInput(3)
    assert cmd.decode_reply(parse_hex("FF AA 00 0B 03 01")) is True
    assert cmd.decode_reply(parse_hex("FF AA 00 0B 03 00")) is False
    for bad in ("FF AA 00 0B 03 02", "FF AA 00 0B 01 01", "FF AA 00 0C 03 01"):
        assert not cmd.matches_reply(parse_hex(bad))
        with pytest.raises(RemoteProtocolError):
            cmd.decode_reply(parse_hex(bad))


def test_decoded_acks_per_reply_class() -> None:
    table: list[tuple[Command, str, Ack]] = [
        (SelectProject(2, 5), "FF AA 6E 02 00 00", Ack(ReplyKind.PROJECT, 0x6E, project=2)),
        (StopProject(), "FF AA 5E 00 00 00", Ack(ReplyKind.GLOBAL, 0x5E)),
        (SetMode4(2), "FF AA 9E 00 00 00", Ack(ReplyKind.GLOBAL, 0x9E)),
        (MotorSetup(16, 90, motor=5), "FF AA 05 01 00 00", Ack(ReplyKind.MOTOR, 1, motor=5)),
        (StepDelay(7, 5, motor=9), "FF AA 09 07 00 07", Ack(ReplyKind.STEP, 7, motor=9, step=7)),
        (
            SetOutput(OutputPort.LEDS, OutputLevel.ACTIVE),
            "FF AA 00 0C 05 00",
            Ack(ReplyKind.OUTPUT, 0x0C, port=5),
        ),
    ]
    for cmd, hex_text, expected in table:
        reply = parse_hex(hex_text)
        assert cmd.decode_reply(reply) == replace(expected, raw=reply)
        with pytest.raises(RemoteProtocolError) as info:
            cmd.decode_reply(reply[:5] + bytes(((reply[5] + 1) & 0xFF,)))
        assert info.value.raw[:5] == reply[:5]


# -- the 226-byte dump ---------------------------------------------------------------


def test_synthesized_dump_decodes_to_the_vector_values() -> None:
    v = synthesized_dump_vector()
    raw = parse_hex(v["expected_reply_hex"])
    assert parse_hex(v["request_hex"]) == ReadProject(1).encode()
    assert ReadProject(1).matches_reply(raw)
    assert not ReadProject(2).matches_reply(raw)
    dump = ReadProject(1).decode_reply(raw)
    d = v["decoded"]
    assert (dump.project, dump.stored_number, dump.number_of_steps) == (1, d["project"], d["steps"])
    assert (dump.loop_start, dump.loop_end, dump.loop_count) == (
        d["loop_start"],
        d["loop_end"],
        d["loop_count"],
    )
    assert dump.repeat_count == d["project_loop_count"]
    assert (dump.subdivision, dump.step_angle_x100) == (d["subdivision"], d["step_angle_x100"])
    assert dump.distance_per_rev == d["distance_per_rev"]
    assert (dump.stop_mode, dump.mode4, dump.power_on_homing) == (
        d["stop_mode"],
        d["mode4"],
        d["power_on_homing"],
    )
    assert len(dump.steps) == len(d["steps_detail"]) == 1
    detail = d["steps_detail"][0]
    assert dump_offset(detail["step"], 0) == detail["offset"]
    assert dump.steps[0] == StepSpec(
        run_distance=detail["run_distance"],
        direction=RotationDirection(detail["direction"]),
        start_hz=detail["start_freq_hz"],
        accel_hz=detail["accel_decel_hz"],
        speed_rpm=detail["speed_rpm"],
        output=StepOutputCode(detail["output"]),
        delay_ms=detail["delay_ms"],
        start_input=GatingInput(detail["start_input"]),
        stop_input=GatingInput(detail["stop_input"]),
    )
    assert dump.encode() == raw
    assert decode_reply_context_free(raw) == dump
    # The same project built from the document examples gives the same bytes.
    project = dump.to_project()
    assert ProjectDump.from_project(project).encode() == raw
    assert project_commands(project) == [c for c, _ in DOCUMENT_EXAMPLES[:12]]


def test_dump_offsets_follow_the_formula() -> None:
    assert [dump_offset(0, k) for k in (0, 2, 5, 6, 9, 14, 15, 16)] == [
        6,
        8,
        11,
        12,
        15,
        20,
        21,
        22,
    ]
    assert [dump_offset(1, k) for k in (0, 3, 6, 10, 11, 14, 15)] == [26, 29, 32, 36, 37, 40, 41]
    assert (dump_offset(2, 0), dump_offset(10, 0), dump_offset(10, 19)) == (46, 206, 225)
    with pytest.raises(LocalProtocolError, match="block"):
        dump_offset(11, 0)


def test_dump_keeps_reserved_and_unused_bytes() -> None:
    raw = bytearray(parse_hex(synthesized_dump_vector()["expected_reply_hex"]))
    raw[18], raw[25], raw[26 + 16], raw[225] = 0xA1, 0xA2, 0xA3, 0xA4  # reserved bytes
    raw[46:66] = b"\xff" * 20  # step 2 block: unused (1 step), erased flash
    dump = ProjectDump.decode(bytes(raw))
    assert dump.encode() == bytes(raw)
    assert dump.reserved[0] == 0xA1 and dump.reserved[4] == 0xA2
    assert dump.reserved[5] == 0xA3 and dump.reserved[-1] == 0xA4
    assert dump.unused_steps[:STEP_DATA_SIZE] == b"\xff" * STEP_DATA_SIZE


def test_dump_errors() -> None:
    good = parse_hex(synthesized_dump_vector()["expected_reply_hex"])
    cases = {
        "short": good[:-1],
        "header": b"\xff\xab" + good[2:],
        "opcode": good[:2] + b"\x2e" + good[3:],
        "project 0": good[:3] + b"\x00" + good[4:],
        "byte 5": good[:5] + b"\x01" + good[6:],
        "direction 2 in a used step": good[:29] + b"\x02" + good[30:],
    }
    for name, raw in cases.items():
        with pytest.raises(RemoteProtocolError) as info:
            ProjectDump.decode(raw)
        assert info.value.raw == raw, name


def test_cleared_dump_is_no_project() -> None:
    raw = bytes(parse_hex("FF AA 3E 02 00 00")) + bytes(220)
    dump = ProjectDump.decode(raw)
    assert (dump.project, dump.number_of_steps, dump.steps) == (2, 0, ())
    assert dump.encode() == raw
    with pytest.raises(LocalProtocolError) as info:
        dump.to_project()
    assert info.value.field == "number"


# -- framing, validation ---------------------------------------------------------------


def test_build_request_and_validity() -> None:
    raw = build_request(bytes((0x6E, 1, 1, 0, 0, 0, 0, 0)))
    assert raw == parse_hex("FF AA 6E 01 01 00 00 00 00 00 19")
    assert len(raw) == REQUEST_SIZE
    assert not request_is_valid(raw[:-1] + b"\x18")
    assert not request_is_valid(raw[:-1])
    assert not request_is_valid(b"\xff\xab" + raw[2:])
    with pytest.raises(LocalProtocolError) as info:
        build_request(bytes(7))
    assert info.value.field == "b2_to_b9"


@pytest.mark.parametrize("motor", [0, *sorted(PROJECT_OPCODES), 256, -1])
def test_bad_motor_numbers_are_refused(motor: int) -> None:
    for make in (
        lambda: JogForward(motor=motor),
        lambda: RunDistance(1, 5, motor=motor),
        lambda: MotorSetup(8, 180, motor=motor),
        lambda: StopMode(StopBehavior.IMMEDIATE, motor=motor),
    ):
        with pytest.raises(LocalProtocolError) as info:
            make()
        assert info.value.field == "motor"
        assert "motor" in str(info.value)


def test_motor_is_configurable() -> None:
    cmd = AccelAndSpeed(4, 30, 100, motor=0x01)
    raw = cmd.encode()
    assert raw[2] == 0x01 and raw[9] == 4 and raw[10] == sum8(raw[:10])
    assert cmd.matches_reply(parse_hex("FF AA 01 05 00 04"))
    assert not cmd.matches_reply(parse_hex("FF AA 03 05 00 04"))
    assert JogForward().motor == DEFAULT_MOTOR == 0x03


OUT_OF_RANGE: list[tuple[Callable[[], object], str, str]] = [
    (lambda: SelectProject(0, 1), "project", "1..4"),
    (lambda: SelectProject(5, 1), "project", "1..4"),
    (lambda: SelectProject(1, 11), "total_steps", "1..10"),
    (lambda: SelectProject(1, 0), "total_steps", "1..10"),
    (lambda: StepLoop(0, 0, 1), "start", "1..10"),
    (lambda: StepLoop(5, 3, 1), "end", "5..10"),
    (lambda: StepLoop(1, 11, 1), "end", "1..10"),
    (lambda: StepLoop(1, 2, 255), "count", "1..254"),
    (lambda: StepLoop(1, 2, 0), "count", "1..254"),
    (lambda: RepeatCount(256), "count", "0..255"),
    (lambda: StartProject(5), "project", "1..4"),
    (lambda: ReadProject(0), "project", "1..4"),
    (lambda: SaveProject(9), "project", "1..4"),
    (lambda: ClearProject(-1), "project", "1..4"),
    (lambda: SetMode4(3), "value", "0, 1, 2"),
    (lambda: SetPowerOnHoming(1), "enabled", "bool"),  # type: ignore[arg-type]
    (lambda: MotorSetup(0, 180), "subdivision", "1..65535"),
    (lambda: MotorSetup(65536, 180), "subdivision", "1..65535"),
    (lambda: MotorSetup(8, 256), "step_angle_x100", "1..255"),
    (lambda: MotorSetup(8, 0), "step_angle_x100", "1..255"),
    (lambda: DistancePerRev(0), "value", "1..16777215"),
    (lambda: DistancePerRev(1 << 24), "value", "1..16777215"),
    (lambda: RunDistance(0, 1), "step", "1..10"),
    (lambda: RunDistance(11, 1), "step", "1..10"),
    (lambda: RunDistance(1, 1 << 24), "distance", "0..16777215"),
    (lambda: DirectionAndStartFrequency(1, 2, 50), "direction", "0, 1"),  # type: ignore[arg-type]
    (lambda: DirectionAndStartFrequency(1, 0, 65536), "start_hz", "0..65535"),  # type: ignore[arg-type]
    (lambda: AccelAndSpeed(1, -1, 100), "accel_hz", "0..65535"),
    (lambda: AccelAndSpeed(1, 30, 65536), "speed_rpm", "0..65535"),
    (lambda: StepOutput(1, 9), "code", "0, 1, 2"),  # type: ignore[arg-type]
    (lambda: StepDelay(1, 1 << 24), "delay_ms", "0..16777215"),
    (lambda: StartInput(1, 3), "input_number", "0, 1, 2, 5"),  # type: ignore[arg-type]
    (lambda: StopInput(1, 4), "input_number", "0, 1, 2, 5"),  # type: ignore[arg-type]
    (lambda: StopMode(2), "mode", "0, 1"),  # type: ignore[arg-type]
    (lambda: SetOutput(0, 1), "port", "1, 2, 3, 4, 5"),  # type: ignore[arg-type]
    (lambda: SetOutput(1, 2), "level", "0, 1"),  # type: ignore[arg-type]
    (lambda: ReadInput(6), "input_number", "1..5"),
    (lambda: ReadInput(True), "input_number", "1..5"),
    (lambda: StepSpec(run_distance=-1, speed_rpm=1), "run_distance", "0..16777215"),
    (lambda: StepSpec(run_distance=1, speed_rpm=1, stop_input=3), "stop_input", "0, 1, 2, 5"),  # type: ignore[arg-type]
    (lambda: _project(steps=()), "len(steps)", "1..10"),
    (lambda: _project(loop_start=1, loop_end=3, loop_count=1), "loop_end", "1..2"),
    (lambda: _project(repeat_count=256), "repeat_count", "0..255"),
    (lambda: _project(number=0), "number", "1..4"),
]


def _project(**changes: Any) -> Project:
    fields: dict[str, Any] = {
        "number": 1,
        "subdivision": 8,
        "step_angle_x100": 180,
        "distance_per_rev": 1600,
        "steps": (StepSpec(run_distance=1, speed_rpm=60), StepSpec(run_distance=2, speed_rpm=60)),
    }
    fields.update(changes)
    return Project(**fields)


@pytest.mark.parametrize(("make", "field_name", "allowed"), OUT_OF_RANGE)
def test_out_of_range_values_name_field_and_range(
    make: Callable[[], object], field_name: str, allowed: str
) -> None:
    with pytest.raises(LocalProtocolError) as info:
        make()
    assert info.value.field == field_name
    assert field_name in str(info.value)
    assert allowed in str(info.value)
    assert isinstance(info.value, ValueError)


def test_starts_motion_flags() -> None:
    moving = {type(c).__name__ for c, _ in DOCUMENT_EXAMPLES if c.starts_motion}
    assert moving == {"StartProject", "JogForward", "JogReverse", "SingleRun", "Home"}


# -- decode_request / context-free decode -----------------------------------------------


def test_decode_request_errors() -> None:
    bad = {
        "checksum": parse_hex("FF AA 6E 01 01 00 00 00 00 00 18"),
        "length": parse_hex("FF AA 6E 01 01 00 00 00 00 19"),
        "project 5": build_request(bytes((0x6E, 5, 1, 0, 0, 0, 0, 0))),
        "motor cmd 10": build_request(bytes((0x03, 0x10, 0, 0, 0, 0, 0, 0))),
        "io cmd 0D": build_request(bytes((0x00, 0x0D, 1, 0, 0, 0, 0, 0))),
        "step 0": build_request(bytes((0x03, 0x03, 1, 0, 0, 0, 0, 0))),
        "homing 2": build_request(bytes((0xAE, 2, 0, 0, 0, 0, 0, 0))),
    }
    for name, raw in bad.items():
        with pytest.raises(RemoteProtocolError) as info:
            decode_request(raw)
        assert info.value.raw == raw, name


def test_decode_request_ignores_spare_bytes_a0_18() -> None:
    raw = build_request(bytes((0x5E, 0x01, 0, 0, 0, 0, 0, 0x77)))
    assert decode_request(raw) == StopProject()


CONTEXT_FREE: list[tuple[str, object]] = [
    ("FF AA 6E 03 00 00", Ack(ReplyKind.PROJECT, 0x6E, project=3)),
    ("FF AA AE 00 00 00", Ack(ReplyKind.GLOBAL, 0xAE)),
    ("FF AA 03 02 00 00", Ack(ReplyKind.MOTOR, 0x02, motor=3)),
    ("FF AA 03 09 00 0A", Ack(ReplyKind.STEP, 0x09, motor=3, step=10)),
    ("FF AA 00 0C 04 00", Ack(ReplyKind.OUTPUT, 0x0C, port=4)),
    ("FF AA 00 0B 05 01", Ack(ReplyKind.INPUT, 0x0B, port=5, value=1)),
    ("EE DD", ProjectFinishedMarker()),
]


@pytest.mark.parametrize(("hex_text", "expected"), CONTEXT_FREE)
def test_decode_reply_context_free(hex_text: str, expected: object) -> None:
    raw = parse_hex(hex_text)
    got = decode_reply_context_free(raw)
    assert got == (replace(expected, raw=raw) if isinstance(expected, Ack) else expected)


@pytest.mark.parametrize(
    "hex_text", ["FF AA 03 10 00 00", "FF AA 00 0D 01 00", "FF AB 03 01 00 00", "FF AA 03", "EE"]
)
def test_decode_reply_context_free_refuses(hex_text: str) -> None:
    with pytest.raises(RemoteProtocolError):
        decode_reply_context_free(parse_hex(hex_text))


def test_project_finished_marker() -> None:
    assert PROJECT_FINISHED == b"\xee\xdd"
    assert ProjectFinishedMarker() == ProjectFinishedMarker()


# -- hypothesis --------------------------------------------------------------------------

motors = st.integers(1, 255).filter(lambda m: m not in PROJECT_OPCODES)
steps = st.integers(1, 10)
projects = st.integers(1, 4)
u16 = st.integers(0, 0xFFFF)
u24 = st.integers(0, 0xFFFFFF)
gates = st.sampled_from(list(GatingInput))


@st.composite
def step_loops(draw: st.DrawFn) -> StepLoop:
    if draw(st.booleans()):
        return StepLoop()
    start = draw(steps)
    return StepLoop(start, draw(st.integers(start, 10)), draw(st.integers(1, 254)))


commands: st.SearchStrategy[ProjectStepperCommand] = st.one_of(
    st.builds(SelectProject, projects, steps),
    step_loops(),
    st.builds(RepeatCount, st.integers(0, 255)),
    st.builds(StartProject, projects),
    st.just(StopProject()),
    st.builds(ReadProject, projects),
    st.builds(SaveProject, projects),
    st.builds(ClearProject, projects),
    st.builds(SetMode4, st.integers(0, 2)),
    st.builds(SetPowerOnHoming, st.booleans()),
    st.builds(MotorSetup, st.integers(1, 0xFFFF), st.integers(1, 255), motor=motors),
    st.builds(DistancePerRev, st.integers(1, 0xFFFFFF), motor=motors),
    st.builds(RunDistance, steps, u24, motor=motors),
    st.builds(
        DirectionAndStartFrequency,
        steps,
        st.sampled_from(list(RotationDirection)),
        u16,
        motor=motors,
    ),
    st.builds(AccelAndSpeed, steps, u16, u16, motor=motors),
    st.builds(StepOutput, steps, st.sampled_from(list(StepOutputCode)), motor=motors),
    st.builds(StepDelay, steps, u24, motor=motors),
    st.builds(StartInput, steps, gates, motor=motors),
    st.builds(StopInput, steps, gates, motor=motors),
    st.builds(JogForward, motor=motors),
    st.builds(JogReverse, motor=motors),
    st.builds(SingleRun, motor=motors),
    st.builds(ManualStop, motor=motors),
    st.builds(StopMode, st.sampled_from(list(StopBehavior)), motor=motors),
    st.builds(Home, motor=motors),
    st.builds(SetOutput, st.sampled_from(list(OutputPort)), st.sampled_from(list(OutputLevel))),
    st.builds(ReadInput, st.integers(1, 5)),
)


@given(commands)
def test_every_command_round_trips_through_decode_request(cmd: ProjectStepperCommand) -> None:
    raw = cmd.encode()
    assert len(raw) == REQUEST_SIZE and request_is_valid(raw)
    assert decode_request(raw) == cmd
    assert cmd.reply_lengths() in ((REPLY_SIZE,), (DUMP_SIZE,))
    # The shape's own minimal reply matches, and context-free decoding agrees on b2/b3.
    shape = cmd.reply_shapes()[0]
    reply = bytes(min(a) if a is not None else 0 for a in shape.pattern).ljust(shape.length, b"\0")
    assert cmd.matches_reply(reply)
    if shape.length == REPLY_SIZE:
        ack = decode_reply_context_free(reply)
        assert isinstance(ack, Ack)
        assert ack == cmd.decode_reply(reply) or isinstance(cmd, ReadInput)


step_specs = st.builds(
    StepSpec,
    run_distance=u24,
    direction=st.sampled_from(list(RotationDirection)),
    start_hz=u16,
    accel_hz=u16,
    speed_rpm=u16,
    output=st.sampled_from(list(StepOutputCode)),
    delay_ms=u24,
    start_input=gates,
    stop_input=gates,
)


@st.composite
def project_values(draw: st.DrawFn) -> Project:
    specs = tuple(draw(st.lists(step_specs, min_size=1, max_size=10)))
    n = len(specs)
    loop = (0, 0, 0)
    if draw(st.booleans()):
        start = draw(st.integers(1, n))
        loop = (start, draw(st.integers(start, n)), draw(st.integers(1, 254)))
    return Project(
        number=draw(projects),
        subdivision=draw(st.integers(1, 0xFFFF)),
        step_angle_x100=draw(st.integers(1, 255)),
        distance_per_rev=draw(st.integers(1, 0xFFFFFF)),
        steps=specs,
        loop_start=loop[0],
        loop_end=loop[1],
        loop_count=loop[2],
        repeat_count=draw(st.integers(0, 255)),
    )


@settings(max_examples=150)
@given(
    project_values(),
    st.sampled_from([0, 1]),
    st.sampled_from([0, 1, 2]),
    st.booleans(),
    st.binary(min_size=RESERVED_SIZE, max_size=RESERVED_SIZE),
    st.data(),
)
def test_project_dump_round_trip(
    project: Project, stop_mode: int, mode4: int, homing: bool, reserved: bytes, data: st.DataObject
) -> None:
    unused_size = STEP_DATA_SIZE * (10 - len(project.steps))
    unused = data.draw(st.binary(min_size=unused_size, max_size=unused_size))
    dump = ProjectDump.from_project(project, stop_mode, mode4, homing, reserved, unused)
    raw = dump.encode()
    assert len(raw) == DUMP_SIZE
    again = ReadProject(project.number).decode_reply(raw)
    assert again == dump
    assert again.encode() == raw
    assert again.to_project() == project
    assert (again.stop_mode, again.mode4, again.power_on_homing) == (stop_mode, mode4, int(homing))


@given(project_values())
def test_project_commands_follow_the_typical_session(project: Project) -> None:
    cmds = project_commands(project, motor=0x07)
    n = len(project.steps)
    assert len(cmds) == 3 + 7 * n + 2
    assert cmds[0] == SelectProject(project.number, n)
    assert cmds[1] == MotorSetup(project.subdivision, project.step_angle_x100, motor=0x07)
    assert cmds[2] == DistancePerRev(project.distance_per_rev, motor=0x07)
    for i, spec in enumerate(project.steps, start=1):
        block = cmds[3 + 7 * (i - 1) : 3 + 7 * i]
        assert [c.encode()[3] for c in block] == [3, 4, 5, 6, 7, 8, 9]
        assert all(c.encode()[9] == i and c.encode()[2] == 0x07 for c in block)
        assert block[0] == RunDistance(i, spec.run_distance, motor=0x07)
    assert cmds[-2] == StepLoop(project.loop_start, project.loop_end, project.loop_count)
    assert cmds[-1] == RepeatCount(project.repeat_count)
    assert not any(isinstance(c, SaveProject) for c in cmds)
