"""The project stepper's commands (doc 000 A.4), one frozen dataclass each.

Which of them write a whole project, and in what order, is in
:mod:`motorbus.protocol.project_stepper.upload`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import (
    Command,
    Family,
    FrameShape,
    ReplyT_co,
    check_choice,
    check_int,
    format_hex,
)
from motorbus.protocol.ff_aa import RotationDirection
from motorbus.protocol.project_stepper.project import ProjectDump
from motorbus.protocol.project_stepper.wire import (
    _ANY_PROJECT,
    _INPUT_STATES,
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
    DEFAULT_MOTOR,
    DUMP_SIZE,
    IO_ADDRESS,
    IO_READ_INPUT,
    IO_SET_OUTPUT,
    MAX_INPUT,
    MAX_LOOP_COUNT,
    MAX_STEP_ANGLE_X100,
    MAX_STEPS,
    MAX_U16,
    MAX_U24,
    MODE4_VALUES,
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
    REPEAT_FOREVER,
    Ack,
    GatingInput,
    OutputLevel,
    OutputPort,
    StepOutputCode,
    StopBehavior,
    _ack_from,
    _check_project,
    _check_step,
    _shape,
    _u16,
    _u24,
    build_request,
    check_motor,
)

# -- command base classes -----------------------------------------------------------------


class ProjectStepperCommand(Command[ReplyT_co]):
    """Base of every doc-000 command: an 8-byte payload framed by :func:`build_request`.

    Subclasses provide :meth:`body` and :meth:`reply_shapes`; matching checks the
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
        """``FF AA 9E 00 00 00`` as printed (A.7: the value is not echoed); a controller
        that echoes the value in byte 3, as the project commands echo theirs, is accepted
        too (accept every reading a real device might send)."""
        return (_shape(OP_MODE4, frozenset((0, self.value)), 0, 0),)


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
        """``FF AA AE 00 00 00`` as printed (A.7), or with the value echoed in byte 3."""
        return (_shape(OP_POWER_ON_HOMING, frozenset((0, int(self.enabled))), 0, 0),)


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
