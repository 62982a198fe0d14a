"""Sizes, opcodes, enums, framing helpers and the decoded ``Ack`` of the project stepper
(doc 000 A.2, A.4, A.7)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol import ff_aa
from motorbus.protocol.base import PROJECT_FINISHED_BYTES, check_int, format_hex

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
