"""The 11-byte "FF AA" project stepper controller (doc 000, docs/protocols.md part A).

Pure code: no asyncio, no clock, no I/O.

Wire format (A.2): every request is ``FF AA b2 .. b9 CS`` with ``CS = sum8(b0..b9)``;
every reply is ``FF AA r2 r3 r4 r5`` with no checksum, except the 226-byte dump that
answers 0x3E and the bare ``EE DD`` that follows a 0x4E when the project ends.

Three addressing forms share byte 2 (A.2, A0-05): a project/global opcode
(0x1E .. 0xAE), the I/O address 0x00, or a motor number M (default 0x03, A0-02).

Every command of A.4 is a frozen dataclass that validates its fields on construction
(``LocalProtocolError`` naming the field, value and range) and knows the exact shape
of its reply (A.7).  Replies decode to :class:`Ack`, except ``ReadProject`` (a
:class:`ProjectDump`) and ``ReadInput`` (``bool``).

Units (A.3, A0-09): distances are user units (revolutions = distance / distance per
revolution), frequencies Hz, speed RPM, delays ms, the step angle degrees x 100.

The package: ``wire`` (sizes, opcodes, enums, framing, ``Ack``), ``commands``,
``project`` (``StepSpec``, ``Project``, ``ProjectDump`` and the dump codec) and
``decode``; everything is importable from here, as before the split.
"""

from __future__ import annotations

from motorbus.protocol.base import ProjectFinishedMarker as ProjectFinishedMarker
from motorbus.protocol.ff_aa import RotationDirection as RotationDirection
from motorbus.protocol.project_stepper.commands import (
    AccelAndSpeed as AccelAndSpeed,
)
from motorbus.protocol.project_stepper.commands import (
    AckCommand as AckCommand,
)
from motorbus.protocol.project_stepper.commands import (
    ClearProject as ClearProject,
)
from motorbus.protocol.project_stepper.commands import (
    DirectionAndStartFrequency as DirectionAndStartFrequency,
)
from motorbus.protocol.project_stepper.commands import (
    DistancePerRev as DistancePerRev,
)
from motorbus.protocol.project_stepper.commands import (
    Home as Home,
)
from motorbus.protocol.project_stepper.commands import (
    JogForward as JogForward,
)
from motorbus.protocol.project_stepper.commands import (
    JogReverse as JogReverse,
)
from motorbus.protocol.project_stepper.commands import (
    ManualStop as ManualStop,
)
from motorbus.protocol.project_stepper.commands import (
    MotorSetup as MotorSetup,
)
from motorbus.protocol.project_stepper.commands import (
    ProjectStepperCommand as ProjectStepperCommand,
)
from motorbus.protocol.project_stepper.commands import (
    ReadInput as ReadInput,
)
from motorbus.protocol.project_stepper.commands import (
    ReadProject as ReadProject,
)
from motorbus.protocol.project_stepper.commands import (
    RepeatCount as RepeatCount,
)
from motorbus.protocol.project_stepper.commands import (
    RunDistance as RunDistance,
)
from motorbus.protocol.project_stepper.commands import (
    SaveProject as SaveProject,
)
from motorbus.protocol.project_stepper.commands import (
    SelectProject as SelectProject,
)
from motorbus.protocol.project_stepper.commands import (
    SetMode4 as SetMode4,
)
from motorbus.protocol.project_stepper.commands import (
    SetOutput as SetOutput,
)
from motorbus.protocol.project_stepper.commands import (
    SetPowerOnHoming as SetPowerOnHoming,
)
from motorbus.protocol.project_stepper.commands import (
    SingleRun as SingleRun,
)
from motorbus.protocol.project_stepper.commands import (
    StartInput as StartInput,
)
from motorbus.protocol.project_stepper.commands import (
    StartProject as StartProject,
)
from motorbus.protocol.project_stepper.commands import (
    StepDelay as StepDelay,
)
from motorbus.protocol.project_stepper.commands import (
    StepLoop as StepLoop,
)
from motorbus.protocol.project_stepper.commands import (
    StepOutput as StepOutput,
)
from motorbus.protocol.project_stepper.commands import (
    StopInput as StopInput,
)
from motorbus.protocol.project_stepper.commands import (
    StopMode as StopMode,
)
from motorbus.protocol.project_stepper.commands import (
    StopProject as StopProject,
)
from motorbus.protocol.project_stepper.commands import (
    _GatingCommand as _GatingCommand,
)
from motorbus.protocol.project_stepper.commands import (
    _MotorCommand as _MotorCommand,
)
from motorbus.protocol.project_stepper.commands import (
    _ProjectCommand as _ProjectCommand,
)
from motorbus.protocol.project_stepper.commands import (
    _StepCommand as _StepCommand,
)
from motorbus.protocol.project_stepper.commands import (
    project_commands as project_commands,
)
from motorbus.protocol.project_stepper.commands import (
    step_commands as step_commands,
)
from motorbus.protocol.project_stepper.decode import (
    _parse_io as _parse_io,
)
from motorbus.protocol.project_stepper.decode import (
    _parse_motor as _parse_motor,
)
from motorbus.protocol.project_stepper.decode import (
    _parse_project as _parse_project,
)
from motorbus.protocol.project_stepper.decode import (
    _Parser as _Parser,
)
from motorbus.protocol.project_stepper.decode import (
    decode_reply_context_free as decode_reply_context_free,
)
from motorbus.protocol.project_stepper.decode import (
    decode_request as decode_request,
)
from motorbus.protocol.project_stepper.project import (
    BASE_DISTANCE_PER_REV as BASE_DISTANCE_PER_REV,
)
from motorbus.protocol.project_stepper.project import (
    BASE_LOOP_COUNT as BASE_LOOP_COUNT,
)
from motorbus.protocol.project_stepper.project import (
    BASE_LOOP_END as BASE_LOOP_END,
)
from motorbus.protocol.project_stepper.project import (
    BASE_LOOP_START as BASE_LOOP_START,
)
from motorbus.protocol.project_stepper.project import (
    BASE_MODE4 as BASE_MODE4,
)
from motorbus.protocol.project_stepper.project import (
    BASE_NUMBER as BASE_NUMBER,
)
from motorbus.protocol.project_stepper.project import (
    BASE_POWER_ON_HOMING as BASE_POWER_ON_HOMING,
)
from motorbus.protocol.project_stepper.project import (
    BASE_REPEAT as BASE_REPEAT,
)
from motorbus.protocol.project_stepper.project import (
    BASE_RESERVED as BASE_RESERVED,
)
from motorbus.protocol.project_stepper.project import (
    BASE_STEP_ANGLE as BASE_STEP_ANGLE,
)
from motorbus.protocol.project_stepper.project import (
    BASE_STEPS as BASE_STEPS,
)
from motorbus.protocol.project_stepper.project import (
    BASE_STOP_MODE as BASE_STOP_MODE,
)
from motorbus.protocol.project_stepper.project import (
    BASE_SUBDIVISION as BASE_SUBDIVISION,
)
from motorbus.protocol.project_stepper.project import (
    RESERVED_SIZE as RESERVED_SIZE,
)
from motorbus.protocol.project_stepper.project import (
    STEP_ACCEL_HZ as STEP_ACCEL_HZ,
)
from motorbus.protocol.project_stepper.project import (
    STEP_DATA_SIZE as STEP_DATA_SIZE,
)
from motorbus.protocol.project_stepper.project import (
    STEP_DELAY_MS as STEP_DELAY_MS,
)
from motorbus.protocol.project_stepper.project import (
    STEP_DIRECTION as STEP_DIRECTION,
)
from motorbus.protocol.project_stepper.project import (
    STEP_DISTANCE as STEP_DISTANCE,
)
from motorbus.protocol.project_stepper.project import (
    STEP_OUTPUT as STEP_OUTPUT,
)
from motorbus.protocol.project_stepper.project import (
    STEP_RESERVED as STEP_RESERVED,
)
from motorbus.protocol.project_stepper.project import (
    STEP_SPEED_RPM as STEP_SPEED_RPM,
)
from motorbus.protocol.project_stepper.project import (
    STEP_START_HZ as STEP_START_HZ,
)
from motorbus.protocol.project_stepper.project import (
    STEP_START_INPUT as STEP_START_INPUT,
)
from motorbus.protocol.project_stepper.project import (
    STEP_STOP_INPUT as STEP_STOP_INPUT,
)
from motorbus.protocol.project_stepper.project import (
    Project as Project,
)
from motorbus.protocol.project_stepper.project import (
    ProjectDump as ProjectDump,
)
from motorbus.protocol.project_stepper.project import (
    StepSpec as StepSpec,
)
from motorbus.protocol.project_stepper.project import (
    _zero_unused as _zero_unused,
)
from motorbus.protocol.project_stepper.wire import (
    _ANY_PROJECT as _ANY_PROJECT,
)
from motorbus.protocol.project_stepper.wire import (
    _INPUT_STATES as _INPUT_STATES,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_ACCEL_SPEED as CMD_ACCEL_SPEED,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_DIRECTION_START_FREQ as CMD_DIRECTION_START_FREQ,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_DISTANCE_PER_REV as CMD_DISTANCE_PER_REV,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_HOME as CMD_HOME,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_JOG_FORWARD as CMD_JOG_FORWARD,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_JOG_REVERSE as CMD_JOG_REVERSE,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_MANUAL_STOP as CMD_MANUAL_STOP,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_MOTOR_SETUP as CMD_MOTOR_SETUP,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_RUN_DISTANCE as CMD_RUN_DISTANCE,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_SINGLE_RUN as CMD_SINGLE_RUN,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_START_INPUT as CMD_START_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_STEP_DELAY as CMD_STEP_DELAY,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_STEP_OUTPUT as CMD_STEP_OUTPUT,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_STOP_INPUT as CMD_STOP_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    CMD_STOP_MODE as CMD_STOP_MODE,
)
from motorbus.protocol.project_stepper.wire import (
    DEFAULT_MOTOR as DEFAULT_MOTOR,
)
from motorbus.protocol.project_stepper.wire import (
    DUMP_BLOCK_SIZE as DUMP_BLOCK_SIZE,
)
from motorbus.protocol.project_stepper.wire import (
    DUMP_HEADER_SIZE as DUMP_HEADER_SIZE,
)
from motorbus.protocol.project_stepper.wire import (
    DUMP_SIZE as DUMP_SIZE,
)
from motorbus.protocol.project_stepper.wire import (
    GLOBAL_REPLY_OPCODES as GLOBAL_REPLY_OPCODES,
)
from motorbus.protocol.project_stepper.wire import (
    HOME_INPUT as HOME_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    IO_ADDRESS as IO_ADDRESS,
)
from motorbus.protocol.project_stepper.wire import (
    IO_READ_INPUT as IO_READ_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    IO_SET_OUTPUT as IO_SET_OUTPUT,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_INPUT as MAX_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_LOOP_COUNT as MAX_LOOP_COUNT,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_PROJECT as MAX_PROJECT,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_STEP_ANGLE_X100 as MAX_STEP_ANGLE_X100,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_STEPS as MAX_STEPS,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_U16 as MAX_U16,
)
from motorbus.protocol.project_stepper.wire import (
    MAX_U24 as MAX_U24,
)
from motorbus.protocol.project_stepper.wire import (
    MODE4_VALUES as MODE4_VALUES,
)
from motorbus.protocol.project_stepper.wire import (
    MOTOR_COMMANDS as MOTOR_COMMANDS,
)
from motorbus.protocol.project_stepper.wire import (
    OP_CLEAR as OP_CLEAR,
)
from motorbus.protocol.project_stepper.wire import (
    OP_MODE4 as OP_MODE4,
)
from motorbus.protocol.project_stepper.wire import (
    OP_POWER_ON_HOMING as OP_POWER_ON_HOMING,
)
from motorbus.protocol.project_stepper.wire import (
    OP_READ as OP_READ,
)
from motorbus.protocol.project_stepper.wire import (
    OP_REPEAT as OP_REPEAT,
)
from motorbus.protocol.project_stepper.wire import (
    OP_SAVE as OP_SAVE,
)
from motorbus.protocol.project_stepper.wire import (
    OP_SELECT as OP_SELECT,
)
from motorbus.protocol.project_stepper.wire import (
    OP_START as OP_START,
)
from motorbus.protocol.project_stepper.wire import (
    OP_STEP_LOOP as OP_STEP_LOOP,
)
from motorbus.protocol.project_stepper.wire import (
    OP_STOP as OP_STOP,
)
from motorbus.protocol.project_stepper.wire import (
    PAYLOAD_SIZE as PAYLOAD_SIZE,
)
from motorbus.protocol.project_stepper.wire import (
    PROJECT_FINISHED as PROJECT_FINISHED,
)
from motorbus.protocol.project_stepper.wire import (
    PROJECT_OPCODES as PROJECT_OPCODES,
)
from motorbus.protocol.project_stepper.wire import (
    PROJECT_START_INPUT as PROJECT_START_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    PROJECT_STOP_INPUT as PROJECT_STOP_INPUT,
)
from motorbus.protocol.project_stepper.wire import (
    REPEAT_FOREVER as REPEAT_FOREVER,
)
from motorbus.protocol.project_stepper.wire import (
    REPLY_SIZE as REPLY_SIZE,
)
from motorbus.protocol.project_stepper.wire import (
    REQUEST_SIZE as REQUEST_SIZE,
)
from motorbus.protocol.project_stepper.wire import (
    STEP_COMMANDS as STEP_COMMANDS,
)
from motorbus.protocol.project_stepper.wire import (
    Ack as Ack,
)
from motorbus.protocol.project_stepper.wire import (
    GatingInput as GatingInput,
)
from motorbus.protocol.project_stepper.wire import (
    OutputLevel as OutputLevel,
)
from motorbus.protocol.project_stepper.wire import (
    OutputPort as OutputPort,
)
from motorbus.protocol.project_stepper.wire import (
    ReplyKind as ReplyKind,
)
from motorbus.protocol.project_stepper.wire import (
    StepOutputCode as StepOutputCode,
)
from motorbus.protocol.project_stepper.wire import (
    StopBehavior as StopBehavior,
)
from motorbus.protocol.project_stepper.wire import (
    _ack_from as _ack_from,
)
from motorbus.protocol.project_stepper.wire import (
    _check_project as _check_project,
)
from motorbus.protocol.project_stepper.wire import (
    _check_step as _check_step,
)
from motorbus.protocol.project_stepper.wire import (
    _le as _le,
)
from motorbus.protocol.project_stepper.wire import (
    _shape as _shape,
)
from motorbus.protocol.project_stepper.wire import (
    _u16 as _u16,
)
from motorbus.protocol.project_stepper.wire import (
    _u24 as _u24,
)
from motorbus.protocol.project_stepper.wire import (
    build_request as build_request,
)
from motorbus.protocol.project_stepper.wire import (
    check_motor as check_motor,
)
from motorbus.protocol.project_stepper.wire import (
    dump_offset as dump_offset,
)
from motorbus.protocol.project_stepper.wire import (
    request_is_valid as request_is_valid,
)

__all__ = [
    "DEFAULT_MOTOR",
    "DUMP_SIZE",
    "PROJECT_FINISHED",
    "REPLY_SIZE",
    "REQUEST_SIZE",
    "AccelAndSpeed",
    "Ack",
    "AckCommand",
    "ClearProject",
    "DirectionAndStartFrequency",
    "DistancePerRev",
    "GatingInput",
    "Home",
    "JogForward",
    "JogReverse",
    "ManualStop",
    "MotorSetup",
    "OutputLevel",
    "OutputPort",
    "Project",
    "ProjectDump",
    "ProjectFinishedMarker",
    "ProjectStepperCommand",
    "ReadInput",
    "ReadProject",
    "RepeatCount",
    "ReplyKind",
    "RotationDirection",
    "RunDistance",
    "SaveProject",
    "SelectProject",
    "SetMode4",
    "SetOutput",
    "SetPowerOnHoming",
    "SingleRun",
    "StartInput",
    "StartProject",
    "StepDelay",
    "StepLoop",
    "StepOutput",
    "StepOutputCode",
    "StepSpec",
    "StopBehavior",
    "StopInput",
    "StopMode",
    "StopProject",
    "build_request",
    "check_motor",
    "decode_reply_context_free",
    "decode_request",
    "dump_offset",
    "project_commands",
    "request_is_valid",
    "step_commands",
]
