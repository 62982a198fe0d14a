"""Decoding requests back into commands, and replies without their request (display)."""

from __future__ import annotations

from collections.abc import Callable

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import FF_AA, ProjectFinishedMarker, check_choice, format_hex
from motorbus.protocol.project_stepper.commands import (
    AccelAndSpeed,
    ClearProject,
    DirectionAndStartFrequency,
    DistancePerRev,
    Home,
    JogForward,
    JogReverse,
    ManualStop,
    MotorSetup,
    ProjectStepperCommand,
    ReadInput,
    ReadProject,
    RepeatCount,
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
    StopInput,
    StopMode,
    StopProject,
)
from motorbus.protocol.project_stepper.project import ProjectDump
from motorbus.protocol.project_stepper.wire import (
    CMD_ACCEL_SPEED,
    CMD_DIRECTION_START_FREQ,
    CMD_DISTANCE_PER_REV,
    CMD_HOME,
    CMD_JOG_FORWARD,
    CMD_JOG_REVERSE,
    CMD_MANUAL_STOP,
    CMD_MOTOR_SETUP,
    CMD_RUN_DISTANCE,
    CMD_SINGLE_RUN,
    CMD_START_INPUT,
    CMD_STEP_DELAY,
    CMD_STEP_OUTPUT,
    CMD_STOP_INPUT,
    CMD_STOP_MODE,
    DUMP_SIZE,
    IO_ADDRESS,
    IO_READ_INPUT,
    IO_SET_OUTPUT,
    OP_CLEAR,
    OP_MODE4,
    OP_POWER_ON_HOMING,
    OP_READ,
    OP_REPEAT,
    OP_SAVE,
    OP_SELECT,
    OP_START,
    OP_STEP_LOOP,
    OP_STOP,
    PROJECT_FINISHED,
    PROJECT_OPCODES,
    REPLY_SIZE,
    Ack,
    _ack_from,
    _le,
    request_is_valid,
)

# -- request and context-free reply decoding ------------------------------------------------

_Parser = Callable[[bytes], ProjectStepperCommand[object]]


def _parse_project(p: bytes) -> ProjectStepperCommand[object]:
    op = p[0]
    if op == OP_SELECT:
        return SelectProject(p[1], p[2])
    if op == OP_STEP_LOOP:
        return StepLoop(p[1], p[2], p[3])
    if op == OP_REPEAT:
        return RepeatCount(p[1])
    if op == OP_STOP:
        return StopProject()
    if op == OP_MODE4:
        return SetMode4(p[1])
    if op == OP_POWER_ON_HOMING:
        check_choice("enabled", p[1], (0, 1), "0 off, 1 on")
        return SetPowerOnHoming(bool(p[1]))
    by_project: dict[int, Callable[[int], ProjectStepperCommand[object]]] = {
        OP_START: StartProject,
        OP_READ: ReadProject,
        OP_SAVE: SaveProject,
        OP_CLEAR: ClearProject,
    }
    return by_project[op](p[1])


def _parse_motor(p: bytes) -> ProjectStepperCommand[object]:
    m, cmd, s = p[0], p[1], p[7]
    parsers: dict[int, _Parser] = {
        CMD_MOTOR_SETUP: lambda q: MotorSetup(_le(q[2:4]), q[4], motor=m),
        CMD_DISTANCE_PER_REV: lambda q: DistancePerRev(_le(q[2:5]), motor=m),
        CMD_RUN_DISTANCE: lambda q: RunDistance(s, _le(q[2:5]), motor=m),
        CMD_DIRECTION_START_FREQ: lambda q: DirectionAndStartFrequency(
            s,
            q[2],  # type: ignore[arg-type]  # validated on init
            _le(q[3:5]),
            motor=m,
        ),
        CMD_ACCEL_SPEED: lambda q: AccelAndSpeed(s, _le(q[2:4]), _le(q[4:6]), motor=m),
        CMD_STEP_OUTPUT: lambda q: StepOutput(s, q[2], motor=m),  # type: ignore[arg-type]
        CMD_STEP_DELAY: lambda q: StepDelay(s, _le(q[2:5]), motor=m),
        CMD_START_INPUT: lambda q: StartInput(s, q[2], motor=m),  # type: ignore[arg-type]
        CMD_STOP_INPUT: lambda q: StopInput(s, q[2], motor=m),  # type: ignore[arg-type]
        CMD_JOG_FORWARD: lambda q: JogForward(motor=m),
        CMD_JOG_REVERSE: lambda q: JogReverse(motor=m),
        CMD_SINGLE_RUN: lambda q: SingleRun(motor=m),
        CMD_MANUAL_STOP: lambda q: ManualStop(motor=m),
        CMD_STOP_MODE: lambda q: StopMode(q[2], motor=m),  # type: ignore[arg-type]
        CMD_HOME: lambda q: Home(motor=m),
    }
    parser = parsers.get(cmd)
    if parser is None:
        raise LocalProtocolError(f"command 0x{cmd:02X} is not 01..0F", field="cmd", value=cmd)
    return parser(p)


def _parse_io(p: bytes) -> ProjectStepperCommand[object]:
    if p[1] == IO_SET_OUTPUT:
        return SetOutput(p[2], p[3])  # type: ignore[arg-type]  # validated on init
    if p[1] == IO_READ_INPUT:
        return ReadInput(p[2])
    raise LocalProtocolError(
        f"I/O command 0x{p[1]:02X} is not 0B or 0C", field="io_command", value=p[1]
    )


def decode_request(raw: bytes) -> ProjectStepperCommand[object]:
    """Decode an 11-byte request into its command (for the simulator and ``motorbus decode``).

    Spare bytes (A0-18) are not checked: a device ignores them, and so does this.

    Raises:
        RemoteProtocolError: wrong length, header or checksum, an unknown command, or a
            field out of range (the cause names the field).
    """
    raw = bytes(raw)
    if not request_is_valid(raw):
        raise RemoteProtocolError(
            f"{format_hex(raw)} is not an 11-byte FF AA request with a valid checksum", raw=raw
        )
    payload = raw[2:-1]
    try:
        if payload[0] in PROJECT_OPCODES:
            return _parse_project(payload)
        if payload[0] == IO_ADDRESS:
            return _parse_io(payload)
        return _parse_motor(payload)
    except LocalProtocolError as err:
        raise RemoteProtocolError(f"{format_hex(raw)}: {err}", raw=raw) from err


def decode_reply_context_free(raw: bytes) -> Ack | ProjectDump | ProjectFinishedMarker:
    """Classify a reply without knowing its request, by value ranges (A0-05). Best effort.

    Accepts a 6-byte reply (-> :class:`Ack`), the 226-byte dump (-> :class:`ProjectDump`)
    or the bare ``EE DD`` (-> :class:`ProjectFinishedMarker`).  Use only for display: a live
    link must match replies against the request sent (A.7).

    Raises:
        RemoteProtocolError: the bytes fit none of the reply classes.
    """
    raw = bytes(raw)
    if raw == PROJECT_FINISHED:
        return ProjectFinishedMarker()
    if len(raw) == DUMP_SIZE:
        return ProjectDump.decode(raw)
    if len(raw) != REPLY_SIZE or raw[:2] != FF_AA:
        raise RemoteProtocolError(
            f"{format_hex(raw)} is not a 6-byte FF AA reply, a dump or EE DD", raw=raw
        )
    return _ack_from(raw)
