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
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol import ff_aa
from motorbus.protocol.base import (
    FF_AA,
    PROJECT_FINISHED_BYTES,
    Command,
    Family,
    FrameShape,
    ProjectFinished,
    ProjectFinishedMarker,
    ReplyT_co,
    check_choice,
    check_int,
    format_hex,
)
from motorbus.protocol.ff_aa import RotationDirection

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
    "ProjectFinished",
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
    "request_is_valid",
]

# -- sizes and limits (doc 000) ----------------------------------------------------------

#: Every request is 11 bytes: FF AA, eight bytes, checksum (A.2).
REQUEST_SIZE = 11
#: Every ordinary reply is 6 bytes ``FF AA r2 r3 r4 r5``, no checksum (A.2).
REPLY_SIZE = ff_aa.REPLY_SIZE
#: The 0x3E reply: 6-byte header + 20-byte base block + 10 x 20-byte step blocks (A.5).
DUMP_SIZE = 226
#: Bytes b2..b9 between the header and the checksum of a request (A.2).
PAYLOAD_SIZE = 8
#: Size of the dump header ``FF AA 3E P 00 00`` (A.5).
DUMP_HEADER_SIZE = 6
#: Size of each dump block: offset = 6 + 20 x + k (A.5).
DUMP_BLOCK_SIZE = 20
#: A project holds 1..10 steps (A.3, 0x6E).
MAX_STEPS = 10
#: Projects are numbered 1..4 (A.3, 0x6E).
MAX_PROJECT = 4
#: Every example addresses motor 0x03; the valid set is undocumented (A0-02).
DEFAULT_MOTOR = 0x03
#: Largest 24-bit field: distances, distance per revolution, delays (A.4 cmds 02/03/07).
MAX_U24 = 0xFFFFFF
#: Largest 16-bit field: subdivision, frequencies, speed (A.4 cmds 01/04/05).
MAX_U16 = 0xFFFF
#: The step angle byte is degrees x 100, so 2.55 degrees is the largest (A0-09).
MAX_STEP_ANGLE_X100 = 255
#: Step-loop count limit "最大设为 254" (A.4 0x7E).
MAX_LOOP_COUNT = 254
#: Project repeat count 255 means "loop forever" (A.4 0x8E).
REPEAT_FOREVER = 255
#: 0x9E accepts 0, 1, 2: "three run modes of mode 4", never defined (A0-13).
MODE4_VALUES = (0, 1, 2)
#: Inputs are IN1..IN5 (A.4 00 0B).
MAX_INPUT = 5
#: IN3 starts the selected project, IN4 stops it (A.3, 0x4E/0x5E notes).
PROJECT_START_INPUT = 3
PROJECT_STOP_INPUT = 4
#: IN5 is the homing sensor of 0x0F (A.4 manual commands).
HOME_INPUT = 5

#: The bare completion marker sent after 0x4E when the project ends (A.2, A0-06).
PROJECT_FINISHED = PROJECT_FINISHED_BYTES

# Project / global opcodes, byte 2 (A.4).
OP_CLEAR = 0x1E
OP_SAVE = 0x2E
OP_READ = 0x3E
OP_START = 0x4E
OP_STOP = 0x5E
OP_SELECT = 0x6E
OP_STEP_LOOP = 0x7E
OP_REPEAT = 0x8E
OP_MODE4 = 0x9E
OP_POWER_ON_HOMING = 0xAE
#: Every byte-2 value that is an opcode; a motor number must avoid them (A0-02, A0-05).
PROJECT_OPCODES = frozenset(
    (
        OP_CLEAR,
        OP_SAVE,
        OP_READ,
        OP_START,
        OP_STOP,
        OP_SELECT,
        OP_STEP_LOOP,
        OP_REPEAT,
        OP_MODE4,
        OP_POWER_ON_HOMING,
    )
)
#: Opcodes whose reply does not echo a project: ``OP 00 00 00`` (A.7, A0-04).
GLOBAL_REPLY_OPCODES = frozenset((OP_STOP, OP_MODE4, OP_POWER_ON_HOMING))

# Motor commands, byte 3 after the motor number (A.4).
CMD_MOTOR_SETUP = 0x01
CMD_DISTANCE_PER_REV = 0x02
CMD_RUN_DISTANCE = 0x03
CMD_DIRECTION_START_FREQ = 0x04
CMD_ACCEL_SPEED = 0x05
CMD_STEP_OUTPUT = 0x06
CMD_STEP_DELAY = 0x07
CMD_START_INPUT = 0x08
CMD_STOP_INPUT = 0x09
CMD_JOG_FORWARD = 0x0A
CMD_JOG_REVERSE = 0x0B
CMD_SINGLE_RUN = 0x0C
CMD_MANUAL_STOP = 0x0D
CMD_STOP_MODE = 0x0E
CMD_HOME = 0x0F
#: Per-step commands carry the step number in b9 and echo it in r5 (A.4, A.7).
STEP_COMMANDS = frozenset(range(CMD_RUN_DISTANCE, CMD_STOP_INPUT + 1))
#: Every motor command byte (A0-05: motor replies have b3 in 01..0F).
MOTOR_COMMANDS = frozenset(range(CMD_MOTOR_SETUP, CMD_HOME + 1))

#: Byte 2 of the I/O commands (A.4 I/O commands).
IO_ADDRESS = 0x00
IO_READ_INPUT = 0x0B
IO_SET_OUTPUT = 0x0C


# -- enums ------------------------------------------------------------------------------


class StepOutputCode(enum.IntEnum):
    """Per-step output action of cmd 06 (A.4, A0-10); not the 00 0C port numbering."""

    NONE = 0
    OUT1_ON = 1
    OUT2_ON = 2
    OUT3_ON = 3
    ALL_ON = 4
    OUT1_OFF = 5
    OUT2_OFF = 6
    OUT3_OFF = 7
    ALL_OFF = 8


class GatingInput(enum.IntEnum):
    """Inputs that may gate the start (cmd 08) or stop (cmd 09) of a step (A.4, A0-11).

    IN3 and IN4 are reserved for project start/stop, so they are not offered.
    """

    NONE = 0
    IN1 = 1
    IN2 = 2
    IN5 = 5


class OutputPort(enum.IntEnum):
    """Port byte of the manual output command 00 0C (A.4, A0-10)."""

    OUT1 = 1
    OUT2 = 2
    OUT3 = 3
    ALL_OUTPUTS = 4
    LEDS = 5


class OutputLevel(enum.IntEnum):
    """Level byte of 00 0C: 1 active (output pulled low, "5 V low level"), 0 inactive (A.4)."""

    INACTIVE = 0
    ACTIVE = 1


class StopBehavior(enum.IntEnum):
    """Value of cmd 0E: 0 slow (decelerate), 1 immediate (A.4, A0-13)."""

    SLOW = 0
    IMMEDIATE = 1


class ReplyKind(enum.Enum):
    """The reply classes of A.7 / A0-04."""

    PROJECT = "project"  # OP P 00 00
    GLOBAL = "global"  # OP 00 00 00 (5E, 9E, AE)
    MOTOR = "motor"  # M CMD 00 00
    STEP = "step"  # M CMD 00 S
    OUTPUT = "output"  # 00 0C Port 00
    INPUT = "input"  # 00 0B In V


# -- framing helpers ----------------------------------------------------------------------


def build_request(b2_to_b9: bytes) -> bytes:
    """Return the 11-byte request ``FF AA b2..b9 CS`` with ``CS = sum8(FF AA b2..b9)`` (A.2).

    Args:
        b2_to_b9: exactly 8 bytes (address/opcode, command, parameters, step or 00).

    Raises:
        LocalProtocolError: ``b2_to_b9`` is not 8 bytes long.
    """
    return ff_aa.frame_request(b2_to_b9, PAYLOAD_SIZE, "b2_to_b9")


def request_is_valid(raw: bytes) -> bool:
    """Return True if ``raw`` is 11 bytes, starts with FF AA and its checksum verifies (A.2)."""
    return ff_aa.request_is_valid(raw, REQUEST_SIZE)


def dump_offset(block: int, k: int) -> int:
    """Return the byte offset of ``[block][k]`` in the 226-byte dump: ``6 + 20 * block + k`` (A.5).

    Args:
        block: 0 for the base block, 1..10 for the steps.
        k: index inside the block, 0..19.

    Raises:
        LocalProtocolError: ``block`` or ``k`` is out of range.
    """
    check_int("block", block, 0, MAX_STEPS)
    check_int("k", k, 0, DUMP_BLOCK_SIZE - 1)
    return DUMP_HEADER_SIZE + DUMP_BLOCK_SIZE * block + k


def _u16(value: int) -> bytes:
    return value.to_bytes(2, "little")


def _u24(value: int) -> bytes:
    return value.to_bytes(3, "little")


def _le(data: bytes) -> int:
    return int.from_bytes(data, "little")


def check_motor(motor: object) -> int:
    """Return ``motor`` if it is a usable motor byte: 1..255 but no opcode 0x1E..0xAE (A0-02).

    Raises:
        LocalProtocolError: naming ``motor``, the value and the allowed range.
    """
    value = check_int("motor", motor, 1, 0xFF)
    if value in PROJECT_OPCODES:
        raise LocalProtocolError(
            f"motor=0x{value:02X} collides with a project opcode: allowed 0x01..0xFF except "
            "0x1E, 0x2E, ..., 0xAE (A0-02)",
            field="motor",
            value=value,
        )
    return value


def _check_project(project: object) -> int:
    return check_int("project", project, 1, MAX_PROJECT)


def _check_step(step: object) -> int:
    return check_int("step", step, 1, MAX_STEPS)


_shape = ff_aa.reply_shape


_ANY_PROJECT = frozenset(range(1, MAX_PROJECT + 1))
_INPUT_STATES = frozenset((0, 1))


# -- decoded replies and events -----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Ack:
    """A decoded 6-byte reply (A.7).

    Attributes:
        kind: which reply class the frame belongs to.
        opcode: the project opcode (b2) for PROJECT/GLOBAL replies, else the motor or
            I/O command byte (b3).
        project: the echoed project P (PROJECT replies; for 0x7E/0x8E the project the
            device considers current, A0-03), else None.
        motor: the echoed motor number M (MOTOR/STEP replies), else None.
        step: the echoed step S (STEP replies), else None.
        port: the echoed output port or input number (OUTPUT/INPUT replies), else None.
        value: the input state 0/1 (INPUT replies), else None.
        raw: the 6 reply bytes.
    """

    kind: ReplyKind
    opcode: int
    project: int | None = None
    motor: int | None = None
    step: int | None = None
    port: int | None = None
    value: int | None = None
    raw: bytes = b""


def _ack_from(raw: bytes) -> Ack:
    """Classify a 6-byte reply by the value ranges of b2/b3 (A0-05); None fields if unknown."""
    b2, b3, b4, b5 = raw[2], raw[3], raw[4], raw[5]
    if b2 in PROJECT_OPCODES:
        if b2 in GLOBAL_REPLY_OPCODES:
            return Ack(ReplyKind.GLOBAL, b2, raw=raw)
        return Ack(ReplyKind.PROJECT, b2, project=b3, raw=raw)
    if b2 == IO_ADDRESS:
        if b3 == IO_SET_OUTPUT:
            return Ack(ReplyKind.OUTPUT, b3, port=b4, raw=raw)
        if b3 == IO_READ_INPUT:
            return Ack(ReplyKind.INPUT, b3, port=b4, value=b5, raw=raw)
        raise RemoteProtocolError(
            f"{format_hex(raw)}: I/O reply with unknown command 0x{b3:02X}", raw=raw
        )
    if b3 in STEP_COMMANDS:
        return Ack(ReplyKind.STEP, b3, motor=b2, step=b5, raw=raw)
    if b3 in MOTOR_COMMANDS:
        return Ack(ReplyKind.MOTOR, b3, motor=b2, raw=raw)
    raise RemoteProtocolError(
        f"{format_hex(raw)}: byte 3 0x{b3:02X} is no motor command (01..0F)", raw=raw
    )


# -- command base classes -----------------------------------------------------------------


class ProjectStepperCommand(Command[ReplyT_co]):
    """Base of every doc-000 command: an 8-byte payload framed by :func:`build_request`.

    Subclasses provide :meth:`payload` and :meth:`reply_shapes`; matching checks the
    exact length and every byte pattern of the shape (A.7).  Most commands are
    acknowledged (:class:`AckCommand`); ``ReadProject`` and ``ReadInput`` decode
    their own replies.
    """

    __slots__ = ()

    family: ClassVar[Family] = Family.PROJECT_STEPPER

    def _validate(self) -> None:
        """Check the fields the addressing base class does not know; raise LocalProtocolError."""

    def body(self) -> bytes:
        """Return bytes b2..b9 of the request (8 bytes, spare bytes 00, A0-18)."""
        raise NotImplementedError

    def encode(self) -> bytes:
        """Return the exact 11-byte request, checksum included (A.2)."""
        return build_request(self.body())

    def payload(self) -> bytes:
        """The old name of :meth:`body` (bytes b2..b9), kept for older callers."""
        return self.body()

    def reply_lengths(self) -> tuple[int, ...]:
        """Return the reply length: 6, or 226 for ReadProject (A.2)."""
        return tuple(shape.length for shape in self.reply_shapes())

    def matches_reply(self, raw: bytes) -> bool:
        """Return True if ``raw`` has the exact length and byte pattern of this reply (A.7)."""
        return any(len(raw) == s.length and s.matches(raw) for s in self.reply_shapes())

    def _ack(self, raw: bytes) -> Ack:
        if not self.matches_reply(raw):
            raise RemoteProtocolError(
                f"{format_hex(raw)} is not a reply to {type(self).__name__}", raw=raw
            )
        return _ack_from(bytes(raw))


class AckCommand(ProjectStepperCommand[Ack]):
    """A command whose reply is an acknowledgement (:class:`Ack`): all but two."""

    __slots__ = ()

    def decode_reply(self, raw: bytes) -> Ack:
        """Decode the acknowledgement (the shape ``reply_shapes`` gives).

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self._ack(raw)


class _ProjectCommand(ProjectStepperCommand[ReplyT_co]):
    """``OP P 00..`` with reply ``OP P 00 00`` (A.4 project commands)."""

    __slots__ = ()
    OPCODE: ClassVar[int]
    project: int

    def __post_init__(self) -> None:
        _check_project(self.project)
        self._validate()

    def body(self) -> bytes:
        """Return ``OP P 00 00 00 00 00 00``."""
        return bytes((self.OPCODE, self.project)) + bytes(6)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return the shape ``FF AA OP P 00 00`` (A.7)."""
        return (_shape(self.OPCODE, self.project, 0, 0),)


class _MotorCommand(AckCommand):
    """``M CMD params 00`` with reply ``M CMD 00 00`` (A.4 motor and manual commands)."""

    __slots__ = ()
    CMD: ClassVar[int]
    motor: int

    def __post_init__(self) -> None:
        self._validate()
        check_motor(self.motor)

    def params(self) -> bytes:
        """Return b4..b9 (6 bytes)."""
        return bytes(6)

    def body(self) -> bytes:
        """Return ``M CMD`` + parameters."""
        return bytes((self.motor, self.CMD)) + self.params()

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return the shape ``FF AA M CMD 00 00`` (A.7)."""
        return (_shape(self.motor, self.CMD, 0, 0),)


class _StepCommand(AckCommand):
    """``M CMD params S`` with reply ``M CMD 00 S`` (A.4 per-step commands)."""

    __slots__ = ()
    CMD: ClassVar[int]
    motor: int
    step: int

    def __post_init__(self) -> None:
        _check_step(self.step)
        self._validate()
        check_motor(self.motor)

    def params(self) -> bytes:
        """Return b4..b8 (5 bytes)."""
        raise NotImplementedError

    def body(self) -> bytes:
        """Return ``M CMD`` + parameters + ``S``."""
        return bytes((self.motor, self.CMD)) + self.params() + bytes((self.step,))

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return the shape ``FF AA M CMD 00 S`` (A.7)."""
        return (_shape(self.motor, self.CMD, 0, self.step),)


# -- project / global commands ------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SelectProject(_ProjectCommand[Ack], AckCommand):
    """0x6E: select project P (1..4) and set its total number of steps (1..10) (A.4).

    Per-step and loop commands act on the project selected last (A0-03).
    """

    OPCODE: ClassVar[int] = OP_SELECT
    project: int
    total_steps: int

    def _validate(self) -> None:
        check_int("total_steps", self.total_steps, 1, MAX_STEPS)

    def body(self) -> bytes:
        """Return ``6E P N 00 00 00 00 00``."""
        return bytes((OP_SELECT, self.project, self.total_steps)) + bytes(5)


@dataclass(frozen=True, slots=True)
class StepLoop(AckCommand):
    """0x7E: repeat steps ``start..end`` ``count`` times in total (A.4, A0-15).

    ``(0, 0, 0)`` disables the loop; otherwise ``1 <= start <= end <= 10`` and
    ``count`` 1..254.  The reply carries the current project, which the request does
    not know: any project 1..4 matches, and :attr:`Ack.project` exposes it (A0-03).
    """

    start: int = 0
    end: int = 0
    count: int = 0

    def __post_init__(self) -> None:
        if (self.start, self.end, self.count) == (0, 0, 0):
            return
        check_int("start", self.start, 1, MAX_STEPS)
        check_int("end", self.end, self.start, MAX_STEPS)
        check_int("count", self.count, 1, MAX_LOOP_COUNT)

    def body(self) -> bytes:
        """Return ``7E start end count 00 00 00 00``."""
        return bytes((OP_STEP_LOOP, self.start, self.end, self.count)) + bytes(4)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA 7E P 00 00`` with P any project 1..4 (A.7)."""
        return (_shape(OP_STEP_LOOP, _ANY_PROJECT, 0, 0),)


@dataclass(frozen=True, slots=True)
class RepeatCount(AckCommand):
    """0x8E: project repeat count 0..254, 255 = forever (A.4).

    The reply carries the current project (see :class:`StepLoop`).
    """

    count: int

    def __post_init__(self) -> None:
        check_int("count", self.count, 0, REPEAT_FOREVER)

    @property
    def forever(self) -> bool:
        """True if the project repeats without end (count 255)."""
        return self.count == REPEAT_FOREVER

    def body(self) -> bytes:
        """Return ``8E C 00 00 00 00 00 00``."""
        return bytes((OP_REPEAT, self.count)) + bytes(6)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA 8E P 00 00`` with P any project 1..4 (A.7)."""
        return (_shape(OP_REPEAT, _ANY_PROJECT, 0, 0),)


@dataclass(frozen=True, slots=True)
class StartProject(_ProjectCommand[Ack], AckCommand):
    """0x4E: start project P (1..4); ``EE DD`` follows when it ends (A.4, A0-06)."""

    OPCODE: ClassVar[int] = OP_START
    starts_motion: ClassVar[bool] = True
    project: int


@dataclass(frozen=True, slots=True)
class StopProject(AckCommand):
    """0x5E: stop the running project; no ``EE DD`` follows (A.4, A0-18)."""

    def body(self) -> bytes:
        """Return ``5E 00 00 00 00 00 00 00``."""
        return bytes((OP_STOP,)) + bytes(7)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA 5E 00 00 00`` (A.7)."""
        return (_shape(OP_STOP, 0, 0, 0),)


@dataclass(frozen=True, slots=True)
class ReadProject(_ProjectCommand["ProjectDump"]):
    """0x3E: read project P; the reply is the 226-byte dump (A.4, A.5)."""

    OPCODE: ClassVar[int] = OP_READ
    project: int

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return the dump shape: 226 bytes starting ``FF AA 3E P 00 00`` (A.5)."""
        return (_shape(OP_READ, self.project, 0, 0, length=DUMP_SIZE),)

    def decode_reply(self, raw: bytes) -> ProjectDump:
        """Decode the 226-byte dump.

        Raises:
            RemoteProtocolError: ``raw`` is not the dump of this project.
        """
        if not self.matches_reply(raw):
            raise RemoteProtocolError(
                f"{len(raw)} bytes starting {format_hex(raw[:6])} are not the dump of "
                f"project {self.project}",
                raw=bytes(raw),
            )
        return ProjectDump.decode(raw)


@dataclass(frozen=True, slots=True)
class SaveProject(_ProjectCommand[Ack], AckCommand):
    """0x2E: save project P to flash (A.4)."""

    OPCODE: ClassVar[int] = OP_SAVE
    project: int


@dataclass(frozen=True, slots=True)
class ClearProject(_ProjectCommand[Ack], AckCommand):
    """0x1E: clear (zero) the parameters of project P (A.4; checksum C8, V2)."""

    OPCODE: ClassVar[int] = OP_CLEAR
    project: int


@dataclass(frozen=True, slots=True)
class SetMode4(AckCommand):
    """0x9E: the undefined "mode 4" setting, raw value 0..2 (A.4, A0-13)."""

    value: int

    def __post_init__(self) -> None:
        check_choice("value", self.value, MODE4_VALUES, "mode 4 run mode, A0-13")

    def body(self) -> bytes:
        """Return ``9E V 00 00 00 00 00 00``."""
        return bytes((OP_MODE4, self.value)) + bytes(6)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA 9E 00 00 00``: the value is not echoed (A.7)."""
        return (_shape(OP_MODE4, 0, 0, 0),)


@dataclass(frozen=True, slots=True)
class SetPowerOnHoming(AckCommand):
    """0xAE: enable or disable homing at power-up (A.4, A0-13)."""

    enabled: bool

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise LocalProtocolError(
                f"enabled must be a bool (False = off, True = on), got {self.enabled!r}",
                field="enabled",
                value=self.enabled,
            )

    def body(self) -> bytes:
        """Return ``AE V 00 00 00 00 00 00``."""
        return bytes((OP_POWER_ON_HOMING, int(self.enabled))) + bytes(6)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA AE 00 00 00`` (A.7)."""
        return (_shape(OP_POWER_ON_HOMING, 0, 0, 0),)


# -- motor configuration -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MotorSetup(_MotorCommand):
    """Cmd 01: subdivision (1..65535) and step angle in degrees x 100 (1..255) (A.4, A0-09)."""

    CMD: ClassVar[int] = CMD_MOTOR_SETUP
    subdivision: int
    step_angle_x100: int
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        check_int("subdivision", self.subdivision, 1, MAX_U16)
        check_int("step_angle_x100", self.step_angle_x100, 1, MAX_STEP_ANGLE_X100)

    def params(self) -> bytes:
        return _u16(self.subdivision) + bytes((self.step_angle_x100,)) + bytes(3)


@dataclass(frozen=True, slots=True)
class DistancePerRev(_MotorCommand):
    """Cmd 02: distance per revolution, the user unit (24-bit, 1..16777215) (A.3, A.4)."""

    CMD: ClassVar[int] = CMD_DISTANCE_PER_REV
    value: int
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        check_int("value", self.value, 1, MAX_U24)

    def params(self) -> bytes:
        return _u24(self.value) + bytes(3)


# -- per-step commands --------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RunDistance(_StepCommand):
    """Cmd 03: run distance of a step, user units, 24-bit unsigned (A.4)."""

    CMD: ClassVar[int] = CMD_RUN_DISTANCE
    step: int
    distance: int
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        check_int("distance", self.distance, 0, MAX_U24)

    def params(self) -> bytes:
        return _u24(self.distance) + bytes(2)


@dataclass(frozen=True, slots=True)
class DirectionAndStartFrequency(_StepCommand):
    """Cmd 04: direction (0 forward, 1 reverse) and start frequency in Hz (A.4)."""

    CMD: ClassVar[int] = CMD_DIRECTION_START_FREQ
    step: int
    direction: RotationDirection
    start_hz: int
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        d = check_choice("direction", self.direction, tuple(RotationDirection), "0 fwd, 1 rev")
        object.__setattr__(self, "direction", RotationDirection(d))
        check_int("start_hz", self.start_hz, 0, MAX_U16)

    def params(self) -> bytes:
        return bytes((self.direction,)) + _u16(self.start_hz) + bytes(2)


@dataclass(frozen=True, slots=True)
class AccelAndSpeed(_StepCommand):
    """Cmd 05: accel/decel frequency in Hz and run speed in RPM (A.4, A0-09)."""

    CMD: ClassVar[int] = CMD_ACCEL_SPEED
    step: int
    accel_hz: int
    speed_rpm: int
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        check_int("accel_hz", self.accel_hz, 0, MAX_U16)
        check_int("speed_rpm", self.speed_rpm, 0, MAX_U16)

    def params(self) -> bytes:
        return _u16(self.accel_hz) + _u16(self.speed_rpm) + bytes(1)


@dataclass(frozen=True, slots=True)
class StepOutput(_StepCommand):
    """Cmd 06: output action switched together with the step's motion (A.4, A0-10)."""

    CMD: ClassVar[int] = CMD_STEP_OUTPUT
    step: int
    code: StepOutputCode
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        c = check_choice("code", self.code, tuple(StepOutputCode), "StepOutputCode, A0-10")
        object.__setattr__(self, "code", StepOutputCode(c))

    def params(self) -> bytes:
        return bytes((self.code,)) + bytes(4)


@dataclass(frozen=True, slots=True)
class StepDelay(_StepCommand):
    """Cmd 07: delay after the step's motion, ms, 24-bit (about 4.66 h max) (A.4, V1)."""

    CMD: ClassVar[int] = CMD_STEP_DELAY
    step: int
    delay_ms: int
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        check_int("delay_ms", self.delay_ms, 0, MAX_U24)

    def params(self) -> bytes:
        return _u24(self.delay_ms) + bytes(2)


class _GatingCommand(_StepCommand):
    """Cmds 08/09: one input number (0 none, 1, 2, 5) in b4 (A.4, A0-11)."""

    __slots__ = ()
    input_number: GatingInput

    def _validate(self) -> None:
        n = check_choice("input_number", self.input_number, tuple(GatingInput), "A0-11")
        object.__setattr__(self, "input_number", GatingInput(n))

    def params(self) -> bytes:
        return bytes((self.input_number,)) + bytes(4)


@dataclass(frozen=True, slots=True)
class StartInput(_GatingCommand):
    """Cmd 08: wait for this input before running the step (0 none, 1, 2, 5) (A.4, A0-11)."""

    CMD: ClassVar[int] = CMD_START_INPUT
    step: int
    input_number: GatingInput
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


@dataclass(frozen=True, slots=True)
class StopInput(_GatingCommand):
    """Cmd 09: this input stops the motor during the step (0 none, 1, 2, 5) (A.4, A0-11)."""

    CMD: ClassVar[int] = CMD_STOP_INPUT
    step: int
    input_number: GatingInput
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


# -- manual commands (use project 1 step 1, A0-12) ---------------------------------------


@dataclass(frozen=True, slots=True)
class JogForward(_MotorCommand):
    """Cmd 0A: turn forward continuously at project 1 step 1 speed until 0D (A.4, A0-12)."""

    CMD: ClassVar[int] = CMD_JOG_FORWARD
    starts_motion: ClassVar[bool] = True
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


@dataclass(frozen=True, slots=True)
class JogReverse(_MotorCommand):
    """Cmd 0B: turn in reverse continuously at project 1 step 1 speed until 0D (A.4)."""

    CMD: ClassVar[int] = CMD_JOG_REVERSE
    starts_motion: ClassVar[bool] = True
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


@dataclass(frozen=True, slots=True)
class SingleRun(_MotorCommand):
    """Cmd 0C: run once with project 1 step 1 distance and speed (A.4, A0-12)."""

    CMD: ClassVar[int] = CMD_SINGLE_RUN
    starts_motion: ClassVar[bool] = True
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


@dataclass(frozen=True, slots=True)
class ManualStop(_MotorCommand):
    """Cmd 0D: stop a manual motion (A.4)."""

    CMD: ClassVar[int] = CMD_MANUAL_STOP
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


@dataclass(frozen=True, slots=True)
class StopMode(_MotorCommand):
    """Cmd 0E: how the motor stops: 0 slow (decelerate), 1 immediate (A.4, A0-13)."""

    CMD: ClassVar[int] = CMD_STOP_MODE
    mode: StopBehavior
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)

    def _validate(self) -> None:
        m = check_choice("mode", self.mode, tuple(StopBehavior), "0 slow, 1 immediate")
        object.__setattr__(self, "mode", StopBehavior(m))

    def params(self) -> bytes:
        return bytes((self.mode,)) + bytes(5)


@dataclass(frozen=True, slots=True)
class Home(_MotorCommand):
    """Cmd 0F: run in reverse at project 1 step 1 speed until IN5 is active (A.4)."""

    CMD: ClassVar[int] = CMD_HOME
    starts_motion: ClassVar[bool] = True
    motor: int = field(default=DEFAULT_MOTOR, kw_only=True)


# -- I/O commands -------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SetOutput(AckCommand):
    """00 0C: drive an output port (1..5) to a level (0 inactive, 1 active) (A.4, A0-10)."""

    port: OutputPort
    level: OutputLevel

    def __post_init__(self) -> None:
        p = check_choice("port", self.port, tuple(OutputPort), "OutputPort, A0-10")
        object.__setattr__(self, "port", OutputPort(p))
        lv = check_choice("level", self.level, tuple(OutputLevel), "0 inactive, 1 active")
        object.__setattr__(self, "level", OutputLevel(lv))

    def body(self) -> bytes:
        """Return ``00 0C Port Level 00 00 00 00``."""
        return bytes((IO_ADDRESS, IO_SET_OUTPUT, self.port, self.level)) + bytes(4)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA 00 0C Port 00`` (A.7)."""
        return (_shape(IO_ADDRESS, IO_SET_OUTPUT, self.port, 0),)


@dataclass(frozen=True, slots=True)
class ReadInput(ProjectStepperCommand[bool]):
    """00 0B: read one input (1..5); the reply ``00 0B In V`` carries V 0/1 (A.4)."""

    input_number: int

    def __post_init__(self) -> None:
        check_int("input_number", self.input_number, 1, MAX_INPUT)

    def body(self) -> bytes:
        """Return ``00 0B In 00 00 00 00 00``."""
        return bytes((IO_ADDRESS, IO_READ_INPUT, self.input_number)) + bytes(5)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Return ``FF AA 00 0B In V`` with V in {0, 1} (A.7)."""
        return (_shape(IO_ADDRESS, IO_READ_INPUT, self.input_number, _INPUT_STATES),)

    def decode_reply(self, raw: bytes) -> bool:
        """Return True if the input is active ("有输入").

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self._ack(raw).value == 1


# -- project values ------------------------------------------------------------------------


#: Offsets inside the base block [0][k] of the dump (A.5).
BASE_NUMBER = 0
BASE_STEPS = 1
BASE_LOOP_START = 2
BASE_LOOP_END = 3
BASE_LOOP_COUNT = 4
BASE_REPEAT = 5
BASE_SUBDIVISION = 6  # 2 bytes
BASE_STEP_ANGLE = 8
BASE_DISTANCE_PER_REV = 9  # 3 bytes
BASE_STOP_MODE = 14
BASE_MODE4 = 15
BASE_POWER_ON_HOMING = 16
#: Base-block bytes the manual does not list (A.5, A0-07).
BASE_RESERVED = (12, 13, 17, 18, 19)

#: Offsets inside a step block [x][k] of the dump (A.5).
STEP_DISTANCE = 0  # 3 bytes
STEP_DIRECTION = 3
STEP_START_HZ = 4  # 2 bytes
STEP_ACCEL_HZ = 6  # 2 bytes
STEP_SPEED_RPM = 8  # 2 bytes
STEP_OUTPUT = 10
STEP_DELAY_MS = 11  # 3 bytes
STEP_START_INPUT = 14
STEP_STOP_INPUT = 15
#: Step-block bytes the manual does not list (A.5, A0-07).
STEP_RESERVED = (16, 17, 18, 19)
#: Data bytes of a step block (all but the reserved tail).
STEP_DATA_SIZE = 16

#: Every reserved byte of the 220-byte dump data, in offset order (5 base + 4 per step).
RESERVED_SIZE = len(BASE_RESERVED) + MAX_STEPS * len(STEP_RESERVED)


@dataclass(frozen=True, slots=True, kw_only=True)
class StepSpec:
    """The parameters of one step (A.4 cmds 03..09).

    Attributes:
        run_distance: user units (revolutions = distance / distance per rev), 24-bit.
        direction: FORWARD or REVERSE.
        start_hz: start frequency, Hz, 0..65535.
        accel_hz: accel/decel frequency, Hz, 0..65535 (the slope unit is unstated, A0-09).
        speed_rpm: run speed, RPM, 0..65535.
        output: output action switched with the motion (A0-10).
        delay_ms: delay after the motion, ms, 24-bit.
        start_input: input that must be active before the step runs (0 = none).
        stop_input: input that stops the motor during the step (0 = none).
    """

    run_distance: int
    direction: RotationDirection = RotationDirection.FORWARD
    start_hz: int = 0
    accel_hz: int = 0
    speed_rpm: int
    output: StepOutputCode = StepOutputCode.NONE
    delay_ms: int = 0
    start_input: GatingInput = GatingInput.NONE
    stop_input: GatingInput = GatingInput.NONE

    def __post_init__(self) -> None:
        check_int("run_distance", self.run_distance, 0, MAX_U24)
        d = check_choice("direction", self.direction, tuple(RotationDirection), "0 fwd, 1 rev")
        object.__setattr__(self, "direction", RotationDirection(d))
        check_int("start_hz", self.start_hz, 0, MAX_U16)
        check_int("accel_hz", self.accel_hz, 0, MAX_U16)
        check_int("speed_rpm", self.speed_rpm, 0, MAX_U16)
        o = check_choice("output", self.output, tuple(StepOutputCode), "A0-10")
        object.__setattr__(self, "output", StepOutputCode(o))
        check_int("delay_ms", self.delay_ms, 0, MAX_U24)
        s = check_choice("start_input", self.start_input, tuple(GatingInput), "A0-11")
        object.__setattr__(self, "start_input", GatingInput(s))
        t = check_choice("stop_input", self.stop_input, tuple(GatingInput), "A0-11")
        object.__setattr__(self, "stop_input", GatingInput(t))

    def commands(
        self, step: int, motor: int = DEFAULT_MOTOR
    ) -> list[ProjectStepperCommand[object]]:
        """Return the seven commands 03..09 that program this step as ``step`` (A.6).

        Raises:
            LocalProtocolError: ``step`` is not 1..10 or ``motor`` is not allowed.
        """
        return [
            RunDistance(step, self.run_distance, motor=motor),
            DirectionAndStartFrequency(step, self.direction, self.start_hz, motor=motor),
            AccelAndSpeed(step, self.accel_hz, self.speed_rpm, motor=motor),
            StepOutput(step, self.output, motor=motor),
            StepDelay(step, self.delay_ms, motor=motor),
            StartInput(step, self.start_input, motor=motor),
            StopInput(step, self.stop_input, motor=motor),
        ]

    def encode_data(self) -> bytes:
        """Return the 16 data bytes of this step's dump block ([x][0..15], A.5)."""
        return (
            _u24(self.run_distance)
            + bytes((self.direction,))
            + _u16(self.start_hz)
            + _u16(self.accel_hz)
            + _u16(self.speed_rpm)
            + bytes((self.output,))
            + _u24(self.delay_ms)
            + bytes((self.start_input, self.stop_input))
        )

    @classmethod
    def decode_data(cls, data: bytes) -> StepSpec:
        """Decode the 16 data bytes of a dump step block ([x][0..15], A.5).

        Raises:
            LocalProtocolError: ``data`` is not 16 bytes or holds an out-of-range code.
        """
        if len(data) != STEP_DATA_SIZE:
            raise LocalProtocolError(
                f"step data must be {STEP_DATA_SIZE} bytes, got {len(data)}",
                field="data",
                value=bytes(data),
            )
        return cls(
            run_distance=_le(data[STEP_DISTANCE : STEP_DISTANCE + 3]),
            direction=data[STEP_DIRECTION],  # type: ignore[arg-type]  # validated on init
            start_hz=_le(data[STEP_START_HZ : STEP_START_HZ + 2]),
            accel_hz=_le(data[STEP_ACCEL_HZ : STEP_ACCEL_HZ + 2]),
            speed_rpm=_le(data[STEP_SPEED_RPM : STEP_SPEED_RPM + 2]),
            output=data[STEP_OUTPUT],  # type: ignore[arg-type]  # validated on init
            delay_ms=_le(data[STEP_DELAY_MS : STEP_DELAY_MS + 3]),
            start_input=data[STEP_START_INPUT],  # type: ignore[arg-type]
            stop_input=data[STEP_STOP_INPUT],  # type: ignore[arg-type]
        )


@dataclass(frozen=True, slots=True)
class Project:
    """A complete project: motor configuration, 1..10 steps, step loop and repeat count.

    Attributes:
        number: project number 1..4.
        subdivision: microstep subdivision, 1..65535.
        step_angle_x100: motor step angle, degrees x 100, 1..255 (A0-09).
        distance_per_rev: user units per revolution, 1..16777215 (A.3).
        steps: 1..10 steps.
        loop_start, loop_end, loop_count: step loop; (0, 0, 0) = none, otherwise
            ``1 <= loop_start <= loop_end <= len(steps)`` and count 1..254, total passes (A0-15).
        repeat_count: project repeat count 0..254, 255 = forever (A.4 0x8E).
    """

    number: int
    subdivision: int
    step_angle_x100: int
    distance_per_rev: int
    steps: tuple[StepSpec, ...]
    loop_start: int = 0
    loop_end: int = 0
    loop_count: int = 0
    repeat_count: int = 0

    def __post_init__(self) -> None:
        check_int("number", self.number, 1, MAX_PROJECT)
        check_int("subdivision", self.subdivision, 1, MAX_U16)
        check_int("step_angle_x100", self.step_angle_x100, 1, MAX_STEP_ANGLE_X100)
        check_int("distance_per_rev", self.distance_per_rev, 1, MAX_U24)
        if not isinstance(self.steps, tuple) or not all(
            isinstance(s, StepSpec) for s in self.steps
        ):
            raise LocalProtocolError(
                f"steps must be a tuple of StepSpec, got {self.steps!r}",
                field="steps",
                value=self.steps,
            )
        check_int("len(steps)", len(self.steps), 1, MAX_STEPS)
        if (self.loop_start, self.loop_end, self.loop_count) != (0, 0, 0):
            check_int("loop_start", self.loop_start, 1, len(self.steps))
            check_int("loop_end", self.loop_end, self.loop_start, len(self.steps))
            check_int("loop_count", self.loop_count, 1, MAX_LOOP_COUNT)
        check_int("repeat_count", self.repeat_count, 0, REPEAT_FOREVER)

    def commands(self, motor: int = DEFAULT_MOTOR) -> list[ProjectStepperCommand[object]]:
        """Return the programming sequence of A.6, without the final SaveProject.

        SelectProject, MotorSetup, DistancePerRev, then 03..09 for each step, then
        StepLoop and RepeatCount (always sent, so stale loop settings are overwritten).

        Raises:
            LocalProtocolError: ``motor`` is not allowed (A0-02).
        """
        out: list[ProjectStepperCommand[object]] = [
            SelectProject(self.number, len(self.steps)),
            MotorSetup(self.subdivision, self.step_angle_x100, motor=motor),
            DistancePerRev(self.distance_per_rev, motor=motor),
        ]
        for i, spec in enumerate(self.steps, start=1):
            out += spec.commands(i, motor)
        out.append(StepLoop(self.loop_start, self.loop_end, self.loop_count))
        out.append(RepeatCount(self.repeat_count))
        return out


def _zero_unused(used: int) -> bytes:
    return bytes(STEP_DATA_SIZE * (MAX_STEPS - used))


@dataclass(frozen=True, slots=True)
class ProjectDump:
    """The 226-byte reply to 0x3E, decoded (A.5, A0-07).

    Base-block fields are the raw stored integers (a cleared project reads zeros).
    ``steps`` holds the used step blocks (the first ``number_of_steps``, at most 10);
    the data bytes of the unused blocks are kept raw in ``unused_steps`` and every
    unlisted byte in ``reserved``, so ``decode(encode())`` is byte-exact.

    Attributes:
        project: P from the header ``FF AA 3E P 00 00`` (1..4).
        number, number_of_steps: [0][0], [0][1].
        loop_start, loop_end, loop_count: [0][2..4].
        repeat_count: [0][5] (255 = forever).
        subdivision: [0][6..7]; step_angle_x100: [0][8]; distance_per_rev: [0][9..11].
        stop_mode: [0][14]; mode4: [0][15]; power_on_homing: [0][16] (raw bytes).
        steps: decoded step blocks 1..min(number_of_steps, 10).
        unused_steps: 16 data bytes for each later block, in order.
        reserved: the 45 unlisted bytes, in offset order ([0][12,13,17..19], then
            [x][16..19] for x = 1..10).
    """

    project: int
    number: int
    number_of_steps: int
    loop_start: int
    loop_end: int
    loop_count: int
    repeat_count: int
    subdivision: int
    step_angle_x100: int
    distance_per_rev: int
    stop_mode: int
    mode4: int
    power_on_homing: int
    steps: tuple[StepSpec, ...]
    unused_steps: bytes = field(default=b"", repr=False)
    reserved: bytes = field(default=bytes(RESERVED_SIZE), repr=False)

    def __post_init__(self) -> None:
        _check_project(self.project)
        for name in (
            "number",
            "number_of_steps",
            "loop_start",
            "loop_end",
            "loop_count",
            "repeat_count",
            "step_angle_x100",
            "stop_mode",
            "mode4",
            "power_on_homing",
        ):
            check_int(name, getattr(self, name), 0, 0xFF)
        check_int("subdivision", self.subdivision, 0, MAX_U16)
        check_int("distance_per_rev", self.distance_per_rev, 0, MAX_U24)
        used = min(self.number_of_steps, MAX_STEPS)
        check_int("len(steps)", len(self.steps), used, used)
        check_int(
            "len(unused_steps)",
            len(self.unused_steps),
            len(_zero_unused(used)),
            len(_zero_unused(used)),
        )
        check_int("len(reserved)", len(self.reserved), RESERVED_SIZE, RESERVED_SIZE)

    @classmethod
    def decode(cls, raw: bytes) -> ProjectDump:
        """Decode a 226-byte 0x3E reply.

        Raises:
            RemoteProtocolError: wrong length, wrong header, or a used step block holds
                an out-of-range code (direction, output, input).
        """
        raw = bytes(raw)
        if len(raw) != DUMP_SIZE:
            raise RemoteProtocolError(f"a dump is {DUMP_SIZE} bytes, got {len(raw)}", raw=raw)
        if raw[:3] != FF_AA + bytes((OP_READ,)) or raw[4:6] != b"\x00\x00":
            raise RemoteProtocolError(
                f"dump header {format_hex(raw[:6])} is not FF AA 3E P 00 00", raw=raw
            )
        if raw[3] not in _ANY_PROJECT:
            raise RemoteProtocolError(f"dump header names project {raw[3]}, not 1..4", raw=raw)

        def base(k: int, n: int = 1) -> int:
            off = dump_offset(0, k)
            return _le(raw[off : off + n])

        reserved = bytes(raw[dump_offset(0, k)] for k in BASE_RESERVED)
        steps: list[StepSpec] = []
        unused = b""
        used = min(base(BASE_STEPS), MAX_STEPS)
        for x in range(1, MAX_STEPS + 1):
            start = dump_offset(x, 0)
            data = raw[start : start + STEP_DATA_SIZE]
            reserved += raw[start + STEP_DATA_SIZE : start + DUMP_BLOCK_SIZE]
            if x > used:
                unused += data
                continue
            try:
                steps.append(StepSpec.decode_data(data))
            except LocalProtocolError as err:
                raise RemoteProtocolError(
                    f"dump step {x} (offset {start}): {err}", raw=raw
                ) from err
        return cls(
            project=raw[3],
            number=base(BASE_NUMBER),
            number_of_steps=base(BASE_STEPS),
            loop_start=base(BASE_LOOP_START),
            loop_end=base(BASE_LOOP_END),
            loop_count=base(BASE_LOOP_COUNT),
            repeat_count=base(BASE_REPEAT),
            subdivision=base(BASE_SUBDIVISION, 2),
            step_angle_x100=base(BASE_STEP_ANGLE),
            distance_per_rev=base(BASE_DISTANCE_PER_REV, 3),
            stop_mode=base(BASE_STOP_MODE),
            mode4=base(BASE_MODE4),
            power_on_homing=base(BASE_POWER_ON_HOMING),
            steps=tuple(steps),
            unused_steps=unused,
            reserved=reserved,
        )

    def encode(self) -> bytes:
        """Return the 226 bytes of this dump, header included (A.5)."""
        out = bytearray(DUMP_SIZE)
        out[:6] = FF_AA + bytes((OP_READ, self.project, 0, 0))

        def put(k: int, data: bytes) -> None:
            off = dump_offset(0, k)
            out[off : off + len(data)] = data

        put(BASE_NUMBER, bytes((self.number, self.number_of_steps)))
        put(BASE_LOOP_START, bytes((self.loop_start, self.loop_end, self.loop_count)))
        put(BASE_REPEAT, bytes((self.repeat_count,)))
        put(BASE_SUBDIVISION, _u16(self.subdivision) + bytes((self.step_angle_x100,)))
        put(BASE_DISTANCE_PER_REV, _u24(self.distance_per_rev))
        put(BASE_STOP_MODE, bytes((self.stop_mode, self.mode4, self.power_on_homing)))
        for i, k in enumerate(BASE_RESERVED):
            out[dump_offset(0, k)] = self.reserved[i]
        datas = [s.encode_data() for s in self.steps]
        datas += [
            self.unused_steps[i : i + STEP_DATA_SIZE]
            for i in range(0, len(self.unused_steps), STEP_DATA_SIZE)
        ]
        tail = self.reserved[len(BASE_RESERVED) :]
        for x, data in enumerate(datas, start=1):
            start = dump_offset(x, 0)
            out[start : start + STEP_DATA_SIZE] = data
            r = (x - 1) * len(STEP_RESERVED)
            out[start + STEP_DATA_SIZE : start + DUMP_BLOCK_SIZE] = tail[r : r + len(STEP_RESERVED)]
        return bytes(out)

    def to_project(self) -> Project:
        """Return the stored project (steps beyond ``number_of_steps`` dropped).

        Raises:
            LocalProtocolError: the stored values do not form a valid project (for
                example a cleared project with 0 steps); the message names the field.
        """
        return Project(
            number=self.number,
            subdivision=self.subdivision,
            step_angle_x100=self.step_angle_x100,
            distance_per_rev=self.distance_per_rev,
            steps=self.steps,
            loop_start=self.loop_start,
            loop_end=self.loop_end,
            loop_count=self.loop_count,
            repeat_count=self.repeat_count,
        )

    @classmethod
    def from_project(
        cls,
        project: Project,
        stop_mode: int = 0,
        mode4: int = 0,
        power_on_homing: bool = False,
        reserved: bytes | None = None,
        unused_steps: bytes | None = None,
    ) -> ProjectDump:
        """Return the dump a device holding ``project`` would send.

        Args:
            project: the project.
            stop_mode: [0][14], 0 slow or 1 immediate.
            mode4: [0][15], 0..2.
            power_on_homing: [0][16].
            reserved: the 45 unlisted bytes (default zeros).
            unused_steps: data bytes of the unused step blocks (default zeros).

        Raises:
            LocalProtocolError: a value is out of range or a byte string has the wrong size.
        """
        check_choice("stop_mode", stop_mode, tuple(StopBehavior), "0 slow, 1 immediate")
        check_choice("mode4", mode4, MODE4_VALUES, "A0-13")
        n = len(project.steps)
        return cls(
            project=project.number,
            number=project.number,
            number_of_steps=n,
            loop_start=project.loop_start,
            loop_end=project.loop_end,
            loop_count=project.loop_count,
            repeat_count=project.repeat_count,
            subdivision=project.subdivision,
            step_angle_x100=project.step_angle_x100,
            distance_per_rev=project.distance_per_rev,
            stop_mode=int(stop_mode),
            mode4=int(mode4),
            power_on_homing=int(bool(power_on_homing)),
            steps=project.steps,
            unused_steps=_zero_unused(n) if unused_steps is None else bytes(unused_steps),
            reserved=bytes(RESERVED_SIZE) if reserved is None else bytes(reserved),
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
