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
``project`` (``StepSpec``, ``Project``, ``ProjectDump`` and the dump codec), ``upload``
(the commands that write a project, A.6) and ``decode``; the public names
(``__all__``) are importable from here; the rest from their modules.  Each public name
loads its module on first use: a program of LA actuators only (a served bus, its
clients, the dashboard) never builds this protocol's command classes (with the quad
stepper's, ~40 ms of start-up: benchmarks/bench_startup.py, ``motorbus serve --help``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from motorbus.protocol.exports import lazy_names

#: The public names and the module each is loaded from on first use.  The one list:
#: ``__all__`` is made from it, and tests/test_public_api.py checks that the
#: ``TYPE_CHECKING`` imports below (which type checkers read) name exactly these.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "motorbus.protocol.project_stepper.wire": (
        "DEFAULT_MOTOR",
        "DUMP_HEADER_SIZE",
        "DUMP_SIZE",
        "GLOBAL_REPLY_OPCODES",
        "HOME_INPUT",
        "MAX_INPUT",
        "MAX_LOOP_COUNT",
        "MAX_PROJECT",
        "MAX_STEP_ANGLE_X100",
        "MAX_STEPS",
        "MAX_U16",
        "MAX_U24",
        "OP_READ",
        "OP_STEP_LOOP",
        "PROJECT_FINISHED",
        "PROJECT_OPCODES",
        "PROJECT_START_INPUT",
        "PROJECT_STOP_INPUT",
        "REPEAT_FOREVER",
        "REPLY_SIZE",
        "REQUEST_SIZE",
        "STEP_COMMANDS",
        "Ack",
        "GatingInput",
        "OutputLevel",
        "OutputPort",
        "ReplyKind",
        "StepOutputCode",
        "StopBehavior",
        "build_request",
        "check_motor",
        "dump_offset",
        "request_is_valid",
    ),
    "motorbus.protocol.project_stepper.project": (
        "BASE_DISTANCE_PER_REV",
        "BASE_LOOP_START",
        "BASE_MODE4",
        "BASE_NUMBER",
        "BASE_POWER_ON_HOMING",
        "BASE_REPEAT",
        "BASE_STOP_MODE",
        "BASE_SUBDIVISION",
        "RESERVED_SIZE",
        "STEP_ACCEL_HZ",
        "STEP_DATA_SIZE",
        "STEP_DELAY_MS",
        "STEP_DIRECTION",
        "STEP_DISTANCE",
        "STEP_OUTPUT",
        "STEP_START_INPUT",
        "STEP_STOP_INPUT",
        "Project",
        "ProjectDump",
        "StepSpec",
    ),
    "motorbus.protocol.project_stepper.commands": (
        "AccelAndSpeed",
        "AckCommand",
        "ClearProject",
        "DirectionAndStartFrequency",
        "DistancePerRev",
        "Home",
        "JogForward",
        "JogReverse",
        "ManualStop",
        "MotorSetup",
        "ProjectStepperCommand",
        "ReadInput",
        "ReadProject",
        "RepeatCount",
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
        "StopInput",
        "StopMode",
        "StopProject",
    ),
    "motorbus.protocol.project_stepper.upload": (
        "project_commands",
        "step_commands",
    ),
    "motorbus.protocol.project_stepper.decode": (
        "decode_reply_context_free",
        "decode_request",
    ),
    "motorbus.protocol.base": ("ProjectFinishedMarker",),
    "motorbus.protocol.ff_aa": ("RotationDirection",),
}

if TYPE_CHECKING:
    from motorbus.protocol.base import ProjectFinishedMarker as ProjectFinishedMarker
    from motorbus.protocol.ff_aa import RotationDirection as RotationDirection
    from motorbus.protocol.project_stepper.commands import AccelAndSpeed as AccelAndSpeed
    from motorbus.protocol.project_stepper.commands import AckCommand as AckCommand
    from motorbus.protocol.project_stepper.commands import ClearProject as ClearProject
    from motorbus.protocol.project_stepper.commands import (
        DirectionAndStartFrequency as DirectionAndStartFrequency,
    )
    from motorbus.protocol.project_stepper.commands import DistancePerRev as DistancePerRev
    from motorbus.protocol.project_stepper.commands import Home as Home
    from motorbus.protocol.project_stepper.commands import JogForward as JogForward
    from motorbus.protocol.project_stepper.commands import JogReverse as JogReverse
    from motorbus.protocol.project_stepper.commands import ManualStop as ManualStop
    from motorbus.protocol.project_stepper.commands import MotorSetup as MotorSetup
    from motorbus.protocol.project_stepper.commands import (
        ProjectStepperCommand as ProjectStepperCommand,
    )
    from motorbus.protocol.project_stepper.commands import ReadInput as ReadInput
    from motorbus.protocol.project_stepper.commands import ReadProject as ReadProject
    from motorbus.protocol.project_stepper.commands import RepeatCount as RepeatCount
    from motorbus.protocol.project_stepper.commands import RunDistance as RunDistance
    from motorbus.protocol.project_stepper.commands import SaveProject as SaveProject
    from motorbus.protocol.project_stepper.commands import SelectProject as SelectProject
    from motorbus.protocol.project_stepper.commands import SetMode4 as SetMode4
    from motorbus.protocol.project_stepper.commands import SetOutput as SetOutput
    from motorbus.protocol.project_stepper.commands import SetPowerOnHoming as SetPowerOnHoming
    from motorbus.protocol.project_stepper.commands import SingleRun as SingleRun
    from motorbus.protocol.project_stepper.commands import StartInput as StartInput
    from motorbus.protocol.project_stepper.commands import StartProject as StartProject
    from motorbus.protocol.project_stepper.commands import StepDelay as StepDelay
    from motorbus.protocol.project_stepper.commands import StepLoop as StepLoop
    from motorbus.protocol.project_stepper.commands import StepOutput as StepOutput
    from motorbus.protocol.project_stepper.commands import StopInput as StopInput
    from motorbus.protocol.project_stepper.commands import StopMode as StopMode
    from motorbus.protocol.project_stepper.commands import StopProject as StopProject
    from motorbus.protocol.project_stepper.decode import (
        decode_reply_context_free as decode_reply_context_free,
    )
    from motorbus.protocol.project_stepper.decode import decode_request as decode_request
    from motorbus.protocol.project_stepper.project import (
        BASE_DISTANCE_PER_REV as BASE_DISTANCE_PER_REV,
    )
    from motorbus.protocol.project_stepper.project import BASE_LOOP_START as BASE_LOOP_START
    from motorbus.protocol.project_stepper.project import BASE_MODE4 as BASE_MODE4
    from motorbus.protocol.project_stepper.project import BASE_NUMBER as BASE_NUMBER
    from motorbus.protocol.project_stepper.project import (
        BASE_POWER_ON_HOMING as BASE_POWER_ON_HOMING,
    )
    from motorbus.protocol.project_stepper.project import BASE_REPEAT as BASE_REPEAT
    from motorbus.protocol.project_stepper.project import BASE_STOP_MODE as BASE_STOP_MODE
    from motorbus.protocol.project_stepper.project import BASE_SUBDIVISION as BASE_SUBDIVISION
    from motorbus.protocol.project_stepper.project import RESERVED_SIZE as RESERVED_SIZE
    from motorbus.protocol.project_stepper.project import STEP_ACCEL_HZ as STEP_ACCEL_HZ
    from motorbus.protocol.project_stepper.project import STEP_DATA_SIZE as STEP_DATA_SIZE
    from motorbus.protocol.project_stepper.project import STEP_DELAY_MS as STEP_DELAY_MS
    from motorbus.protocol.project_stepper.project import STEP_DIRECTION as STEP_DIRECTION
    from motorbus.protocol.project_stepper.project import STEP_DISTANCE as STEP_DISTANCE
    from motorbus.protocol.project_stepper.project import STEP_OUTPUT as STEP_OUTPUT
    from motorbus.protocol.project_stepper.project import STEP_START_INPUT as STEP_START_INPUT
    from motorbus.protocol.project_stepper.project import STEP_STOP_INPUT as STEP_STOP_INPUT
    from motorbus.protocol.project_stepper.project import Project as Project
    from motorbus.protocol.project_stepper.project import ProjectDump as ProjectDump
    from motorbus.protocol.project_stepper.project import StepSpec as StepSpec
    from motorbus.protocol.project_stepper.upload import project_commands as project_commands
    from motorbus.protocol.project_stepper.upload import step_commands as step_commands
    from motorbus.protocol.project_stepper.wire import DEFAULT_MOTOR as DEFAULT_MOTOR
    from motorbus.protocol.project_stepper.wire import DUMP_HEADER_SIZE as DUMP_HEADER_SIZE
    from motorbus.protocol.project_stepper.wire import DUMP_SIZE as DUMP_SIZE
    from motorbus.protocol.project_stepper.wire import GLOBAL_REPLY_OPCODES as GLOBAL_REPLY_OPCODES
    from motorbus.protocol.project_stepper.wire import HOME_INPUT as HOME_INPUT
    from motorbus.protocol.project_stepper.wire import MAX_INPUT as MAX_INPUT
    from motorbus.protocol.project_stepper.wire import MAX_LOOP_COUNT as MAX_LOOP_COUNT
    from motorbus.protocol.project_stepper.wire import MAX_PROJECT as MAX_PROJECT
    from motorbus.protocol.project_stepper.wire import MAX_STEP_ANGLE_X100 as MAX_STEP_ANGLE_X100
    from motorbus.protocol.project_stepper.wire import MAX_STEPS as MAX_STEPS
    from motorbus.protocol.project_stepper.wire import MAX_U16 as MAX_U16
    from motorbus.protocol.project_stepper.wire import MAX_U24 as MAX_U24
    from motorbus.protocol.project_stepper.wire import OP_READ as OP_READ
    from motorbus.protocol.project_stepper.wire import OP_STEP_LOOP as OP_STEP_LOOP
    from motorbus.protocol.project_stepper.wire import PROJECT_FINISHED as PROJECT_FINISHED
    from motorbus.protocol.project_stepper.wire import PROJECT_OPCODES as PROJECT_OPCODES
    from motorbus.protocol.project_stepper.wire import PROJECT_START_INPUT as PROJECT_START_INPUT
    from motorbus.protocol.project_stepper.wire import PROJECT_STOP_INPUT as PROJECT_STOP_INPUT
    from motorbus.protocol.project_stepper.wire import REPEAT_FOREVER as REPEAT_FOREVER
    from motorbus.protocol.project_stepper.wire import REPLY_SIZE as REPLY_SIZE
    from motorbus.protocol.project_stepper.wire import REQUEST_SIZE as REQUEST_SIZE
    from motorbus.protocol.project_stepper.wire import STEP_COMMANDS as STEP_COMMANDS
    from motorbus.protocol.project_stepper.wire import Ack as Ack
    from motorbus.protocol.project_stepper.wire import GatingInput as GatingInput
    from motorbus.protocol.project_stepper.wire import OutputLevel as OutputLevel
    from motorbus.protocol.project_stepper.wire import OutputPort as OutputPort
    from motorbus.protocol.project_stepper.wire import ReplyKind as ReplyKind
    from motorbus.protocol.project_stepper.wire import StepOutputCode as StepOutputCode
    from motorbus.protocol.project_stepper.wire import StopBehavior as StopBehavior
    from motorbus.protocol.project_stepper.wire import build_request as build_request
    from motorbus.protocol.project_stepper.wire import check_motor as check_motor
    from motorbus.protocol.project_stepper.wire import dump_offset as dump_offset
    from motorbus.protocol.project_stepper.wire import request_is_valid as request_is_valid

if not TYPE_CHECKING:  # (type checkers read the imports above: a misspelt name is caught)
    __all__, __getattr__, __dir__ = lazy_names(__name__, _EXPORTS)
